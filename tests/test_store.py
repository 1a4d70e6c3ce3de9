"""Machine registry: schema, idempotency, crash safety, concurrent reads, ingest, CLI."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.engine.ingest import detector_inputs
from ajtwin.model.limits import DEFAULT_LIMITS
from ajtwin.store.registry import (
    TEST_SLEEP_ENV,
    NewPrint,
    Registry,
    RegistryError,
    default_store_path,
    from_npy,
    record_hash,
    to_npy,
)
from store_backends import on_postgres

#: a store test whose PostgreSQL run is long (subprocesses, the twin): `make test-all` runs it
_SLOW_ON_POSTGRES = pytest.param("postgresql", marks=pytest.mark.slow)


def _fake_print(reg, name, content_hash, expected, value=1.0):
    """save_print with small hand-made arrays (no twin needed)."""
    return reg.save_print(
        name,
        NewPrint(
            content_hash=content_hash,
            source="test",
            meta={"scenario": "test"},
            summary={"note": "fake"},
            n_samples=3,
            duration_s=3.0,
            start_mean=np.full(5, value),
            start_cov=np.eye(5),
            end_mean=np.full(5, value + 1),
            end_cov=2 * np.eye(5),
            theta_before=np.zeros(5),
            theta_after=np.full(5, 1e-4),
            arrays={"means": np.arange(15.0).reshape(3, 5)},
            anomalies=[],
        ),
        expected_last_seq=expected,
    )


def test_npy_roundtrip_exact():
    a = np.random.default_rng(0).normal(size=(7, 5, 5))
    assert np.array_equal(from_npy(to_npy(a)), a)


def test_default_path_env(monkeypatch, tmp_path):
    monkeypatch.setenv("AJTWIN_STORE", str(tmp_path / "x.sqlite"))
    assert default_store_path() == tmp_path / "x.sqlite"
    monkeypatch.delenv("AJTWIN_STORE")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    assert default_store_path() == tmp_path / "data" / "ajtwin" / "registry.sqlite"


def test_machines_and_history(store):
    reg = Registry(store)
    m = reg.add_machine("lab1", {"carrier_flow_sccm": [18, 30]})
    assert m["limits"]["carrier_flow_sccm"] == [18.0, 30.0]
    assert m["limits"]["sheath_flow_sccm"] == DEFAULT_LIMITS["sheath_flow_sccm"]
    with pytest.raises(RegistryError, match="already exists"):
        reg.add_machine("lab1")
    with pytest.raises(RegistryError, match="unknown input"):
        reg.add_machine("lab2", {"flow": [1, 2]})
    with pytest.raises(RegistryError, match="no machine 'nope'.*known: lab1"):
        reg.machine("nope")
    assert _fake_print(reg, "lab1", "h1", None) > 0
    assert _fake_print(reg, "lab1", "h2", 1, value=5.0) > 0
    last = reg.last_print("lab1")
    assert last["seq"] == 2
    assert np.array_equal(last["end_mean"], np.full(5, 6.0))
    hist = reg.history("lab1")
    assert list(hist["seq"]) == [1, 2]
    assert list(hist["end_droplet_diameter_um"]) == [2.0, 6.0]
    arrays = reg.print_arrays(last["id"])
    assert np.array_equal(arrays["means"], np.arange(15.0).reshape(3, 5))


def test_duplicate_and_stale_start_rejected(store):
    reg = Registry(store)
    reg.add_machine("m")
    _fake_print(reg, "m", "same", None)
    with pytest.raises(RegistryError, match="got print 1 while this ingest ran from print None"):
        _fake_print(reg, "m", "same", None)
    with pytest.raises(RegistryError, match="already print 1"):
        _fake_print(reg, "m", "same", 1)
    assert reg.machine("m")["n_prints"] == 1


def test_record_hash_sensitive_and_stable(tmp_path):
    from ajtwin.io.records import read_record, write_record
    from ajtwin.simulation import simulate

    rec = simulate("exp1", seed=1, duration_min=1.0)
    h = record_hash(rec)
    write_record(rec, tmp_path / "a.parquet")
    assert record_hash(read_record(tmp_path / "a.parquet")) == h
    rec.data.loc[5, "linewidth_um"] += 1e-9
    assert record_hash(rec) != h


WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    sys.path.insert(0, {tests!r})
    from test_store import _fake_print
    from ajtwin.store.registry import Registry
    reg = Registry({path!r})
    _fake_print(reg, "m", "second", 1, value=9.0)
    print("committed", flush=True)
    """
)


def _start_writer(path, sleep_s):
    env = dict(os.environ, **{TEST_SLEEP_ENV: str(sleep_s)})
    script = WRITER.format(tests=os.path.dirname(__file__), path=str(path))
    return subprocess.Popen(
        [sys.executable, "-c", script], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )


def _in_transaction(path) -> bool:
    """Whether another process holds a write transaction open on the registry."""
    if on_postgres(path):
        import psycopg

        with psycopg.connect(str(path), autocommit=True) as conn:
            rows = conn.execute(
                "SELECT 1 FROM pg_stat_activity WHERE application_name = 'ajtwin' "
                "AND state = 'idle in transaction' AND pid != pg_backend_pid()"
            ).fetchall()
        return bool(rows)
    conn = sqlite3.connect(str(path), timeout=0.0, isolation_level=None)
    try:
        conn.execute("BEGIN IMMEDIATE")
        conn.execute("ROLLBACK")
    except sqlite3.OperationalError:
        return True
    finally:
        conn.close()
    return False


def _wait_for_write_lock(path, proc, timeout_s=60.0):
    """Poll until the writer holds its transaction (a second writer would wait)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"writer ended early: {proc.stderr.read().decode()}")
        if _in_transaction(path):
            return
        time.sleep(0.05)
    raise AssertionError("the writer never took its write lock")


def test_killed_ingest_leaves_store_unchanged_and_reads_do_not_block(store):
    path = store
    reg = Registry(path)
    reg.add_machine("m")
    _fake_print(reg, "m", "first", None)
    proc = _start_writer(path, sleep_s=60)
    try:
        _wait_for_write_lock(path, proc)
        # a reader that may not wait at all still sees the committed state
        reader = Registry(path, timeout_s=0.0)
        assert reader.machine("m")["n_prints"] == 1
        assert reader.last_print("m")["seq"] == 1
        assert len(reader.history("m")) == 1
        reader.close()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    reg.close()
    after = Registry(path)
    assert after.machine("m")["n_prints"] == 1
    assert after.find_print("m", "second") is None
    n_arrays = after._db.execute("SELECT COUNT(*) FROM print_arrays").fetchone()[0]
    assert n_arrays == 1  # only the first print's single array
    # and the store still takes the next print
    _fake_print(after, "m", "second", 1)
    assert after.last_print("m")["seq"] == 2


@pytest.mark.parametrize("store", ["sqlite", _SLOW_ON_POSTGRES], indirect=True)
def test_writer_commits_without_hook(store):
    path = store
    reg = Registry(path)
    reg.add_machine("m")
    _fake_print(reg, "m", "first", None)
    proc = _start_writer(path, sleep_s=0)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err.decode()
    assert b"committed" in out
    assert reg.last_print("m")["seq"] == 2


def test_ingest_chain_and_cli(tmp_path, store):
    """Real twin on two short prints: the second starts from the first's end; CLI works."""
    from ajtwin.cli.ingest import ingest
    from ajtwin.cli.machine import machine
    from ajtwin.io.records import write_record
    from ajtwin.simulation import simulate

    first = simulate("exp1", seed=3, duration_min=3.0)
    second = simulate("exp1", seed=4, duration_min=3.0, continue_from=first)
    write_record(first, tmp_path / "p1.parquet")
    write_record(second, tmp_path / "p2.parquet")
    store = str(store)
    runner = CliRunner()
    res = runner.invoke(machine, ["add", "lab", "--carrier", "18,30", "--store", store])
    assert res.exit_code == 0, res.output
    res = runner.invoke(
        ingest,
        ["--machine", "lab", str(tmp_path / "p1.parquet"), "--store", store, "--no-progress"],
    )
    assert res.exit_code == 0, res.output
    assert "print #1" in res.output and "initial fit" in res.output
    res = runner.invoke(
        ingest,
        ["--machine", "lab", str(tmp_path / "p2.parquet"), "--store", store, "--no-progress"],
    )
    assert res.exit_code == 0, res.output
    assert "started from print 1" in res.output
    res = runner.invoke(
        ingest,
        ["--machine", "lab", str(tmp_path / "p1.parquet"), "--store", store, "--no-progress"],
    )
    assert res.exit_code == 0 and "already ingested as print #1" in res.output

    reg = Registry(store)
    p1, p2 = reg.get_print(1), reg.last_print("lab")
    # print 2 started from print 1's end state (fast states' variance widened)
    assert np.array_equal(p2["start_mean"], p1["end_mean"])
    assert np.allclose(p2["start_cov"][1:4, 1:4], p1["end_cov"][1:4, 1:4])
    assert p2["start_cov"][0, 0] > p1["end_cov"][0, 0]
    assert np.array_equal(p2["theta_before"], p1["theta_after"])
    # the twin tracks the truth's nozzle deposit to within 4σ at the end
    truth_end = second.true_states[-1]
    std = np.sqrt(np.diag(p2["end_cov"]))
    assert abs(p2["end_mean"][3] - truth_end[3]) < 4 * std[3]
    assert abs(p2["end_mean"][1] - truth_end[1]) < 0.05

    # the stored arrays are enough to re-run the detectors: same events as stored
    from ajtwin.apps.detection.batch import detect_anomalies

    again = detect_anomalies(**detector_inputs(reg, p2["id"]))
    stored = reg.anomalies("lab")
    stored = stored[stored["seq"] == 2]
    assert len(again.events) == len(stored)
    assert [ev.detected_s for ev in again.events] == stored["detected_s"].tolist()
    assert [ev.description for ev in again.events] == stored["description"].tolist()
    # storage policy: every step's mean and σ, full covariances at key frames (every 60 s,
    # the end, alarms); the last key frame is the stored end covariance, bit for bit
    a = reg.print_arrays(p2["id"])
    assert a["means"].shape == (180, 5) and a["stds"].shape == (180, 5)
    assert {0, 60, 120, 179} <= set(a["covariance_steps"].tolist())
    assert np.array_equal(a["covariance_keyframes"][-1], p2["end_cov"])
    # means are kept as float32 (7 digits); the print row keeps the end state exactly
    np.testing.assert_allclose(a["means"][-1], p2["end_mean"], rtol=1.2e-7, atol=0)

    res = runner.invoke(machine, ["show", "lab", "--store", store])
    assert res.exit_code == 0 and "last stored print: #2" in res.output
    res = runner.invoke(machine, ["history", "lab", "--store", store])
    assert res.exit_code == 0 and res.output.count("\n") >= 3
    res = runner.invoke(machine, ["show", "ghost", "--store", store])
    assert res.exit_code != 0 and "no machine 'ghost'" in res.output
    res = runner.invoke(
        ingest, ["--machine", "ghost", str(tmp_path / "p1.parquet"), "--store", store]
    )
    assert res.exit_code != 0 and "no machine 'ghost'" in res.output


def test_not_a_registry(tmp_path):
    bad = tmp_path / "bad.sqlite"
    bad.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(RegistryError, match="not a usable ajtwin registry"):
        Registry(bad)


def test_ingest_with_video_cli(tmp_path):
    """--video fills L_w/L_o from the camera (ajtwin.vision) before the twin runs."""
    from ajtwin.cli.ingest import ingest
    from ajtwin.cli.machine import machine
    from ajtwin.cli.vision import render
    from ajtwin.io.records import write_record
    from ajtwin.simulation import simulate

    rec = simulate("exp1", seed=7, duration_min=1.0)
    write_record(rec, tmp_path / "p.parquet")
    video = tmp_path / "cam.avi"
    render.main(
        [str(tmp_path / "p.parquet"), "--out", str(video), "--fps", "0.5", "--size", "640x400"],
        standalone_mode=False,
    )
    store = str(tmp_path / "r.sqlite")
    runner = CliRunner()
    assert runner.invoke(machine, ["add", "cam", "--store", store]).exit_code == 0
    res = runner.invoke(ingest, ["--machine", "cam", str(tmp_path / "p.parquet"), "--video",
                                 str(video), "--store", store, "--no-progress"])  # fmt: skip
    assert res.exit_code != 0 and "--um-per-px" in res.output
    res = runner.invoke(ingest, ["--machine", "cam", str(tmp_path / "p.parquet"), "--video",
                                 str(video), "--um-per-px", "0.75", "--store", store,
                                 "--no-progress"])  # fmt: skip
    assert res.exit_code == 0, res.output
    reg = Registry(store)
    p = reg.last_print("cam")
    assert p["meta"]["vision"]["seconds_filled"] == 30
    lw = reg.print_arrays(p["id"])["measurements"][:, 0]
    assert np.isfinite(lw).sum() == 30  # one frame every 2 s
    logged = rec.outputs[:, 0]
    ok = np.isfinite(lw)
    assert np.median(np.abs(lw[ok] - logged[ok])) < 1.5  # vision within ~1 µm of the line
    res = runner.invoke(machine, ["list", "--store", store])
    assert "cam  (1 prints" in res.output
