"""Registry reliability: hostile/damaged stores (and the security notes), schema
migration, the print chain (impossible end states), the storage policy and
compaction, export/import."""

from __future__ import annotations

import hashlib
import io
import json
import os
import signal
import sqlite3
import tarfile
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.cli.ingest import ingest
from ajtwin.cli.machine import machine
from ajtwin.engine.ingest import detector_inputs
from ajtwin.model.limits import DEFAULT_LIMITS
from ajtwin.store import arrays as A
from ajtwin.store import registry as R
from ajtwin.store.database import open_database
from ajtwin.store.registry import NewPrint, Registry, RegistryError
from store_backends import SLOW_ON_POSTGRES, on_postgres

#: ajtwin 0.1's registry (schema version 1), verbatim: a registry written by it must open.
V1_STATEMENTS = """
CREATE TABLE IF NOT EXISTS info (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS machines (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL UNIQUE,
    created_at TEXT NOT NULL,
    limits_json TEXT NOT NULL,
    notes TEXT NOT NULL DEFAULT ''
);
CREATE TABLE IF NOT EXISTS prints (
    id INTEGER PRIMARY KEY,
    machine_id INTEGER NOT NULL REFERENCES machines(id),
    seq INTEGER NOT NULL,
    content_hash TEXT NOT NULL,
    ingested_at TEXT NOT NULL,
    source TEXT NOT NULL,
    n_samples INTEGER NOT NULL,
    duration_s REAL NOT NULL,
    meta_json TEXT NOT NULL,
    summary_json TEXT NOT NULL,
    start_mean BLOB NOT NULL,
    start_cov BLOB NOT NULL,
    end_mean BLOB NOT NULL,
    end_cov BLOB NOT NULL,
    theta_before BLOB NOT NULL,
    theta_after BLOB NOT NULL,
    UNIQUE (machine_id, seq),
    UNIQUE (machine_id, content_hash)
);
CREATE TABLE IF NOT EXISTS print_arrays (
    print_id INTEGER NOT NULL REFERENCES prints(id),
    name TEXT NOT NULL,
    npy BLOB NOT NULL,
    PRIMARY KEY (print_id, name)
);
CREATE TABLE IF NOT EXISTS anomalies (
    id INTEGER PRIMARY KEY,
    print_id INTEGER NOT NULL REFERENCES prints(id),
    detected_s REAL NOT NULL,
    onset_s REAL NOT NULL,
    cause TEXT NOT NULL,
    description TEXT NOT NULL,
    detectors TEXT NOT NULL,
    evidence_json TEXT NOT NULL
);
"""

#: a physically possible state (d_a µm, V_l mL, ΔR_T µm, ΔR_N µm, φ_A)
GOOD = np.array([3.5, 0.95, 1e-4, 0.03, 4.6e-7])


def run_cli(*args):
    result = CliRunner().invoke(machine, [str(a) for a in args])
    # never a traceback: either success or a ClickException's "Error: ..." line
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result


def _npy(a):
    return R.to_npy(np.asarray(a, dtype=float))


def _write_v1(path, prints=()):
    """A registry as the version-1 code wrote it: raw .npy, full covariance sequence (an
    SQLite file, or the same tables on PostgreSQL)."""
    conn = open_database(path)
    for statement in conn.ddl(V1_STATEMENTS):
        conn.execute(statement)
    if not on_postgres(path):
        conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("INSERT INTO info VALUES ('schema_version', '1')")
    conn.execute(
        "INSERT INTO machines (name, created_at, limits_json) VALUES ('old', "
        "'2025-01-01T00:00:00+00:00', ?)",
        (json.dumps(DEFAULT_LIMITS),),
    )
    rng = np.random.default_rng(0)
    for seq, end in enumerate(prints, start=1):
        n = 600
        means = np.tile(end, (n, 1)) * (1 + 1e-3 * rng.normal(size=(n, 5)))
        cov = np.diag((0.01 * np.abs(end)) ** 2 + 1e-12)
        print_id = conn.execute(
            "INSERT INTO prints (machine_id, seq, content_hash, ingested_at, source, n_samples,"
            " duration_s, meta_json, summary_json, start_mean, start_cov, end_mean, end_cov,"
            " theta_before, theta_after) VALUES (1, ?, ?, ?, 'f', ?,"
            " ?, '{}', '{}', ?, ?, ?, ?, ?, ?) RETURNING id",
            (seq, f"h{seq}", f"2025-01-0{seq}T00:00:00+00:00", n, float(n), _npy(end),
             _npy(cov), _npy(end), _npy(cov),
             _npy(np.zeros(5)), _npy(np.zeros(5))),
        ).fetchone()[0]  # fmt: skip
        arrays = {
            "time_s": np.arange(n, dtype=float),
            "means": means,
            "stds": np.sqrt(np.tile(np.diag(cov), (n, 1))),
            "covariances": np.tile(cov, (n, 1, 1)),
            "predicted_means": means * (1 - 1e-6),
            "measurements": rng.normal(size=(n, 5)),
        }
        conn.executemany(
            "INSERT INTO print_arrays VALUES (?, ?, ?)",
            [(print_id, k, R.to_npy(v)) for k, v in arrays.items()],
        )
        conn.execute(
            "INSERT INTO anomalies (print_id, detected_s, onset_s, cause, description, "
            "detectors, evidence_json) VALUES (?, 300, 250, 'nozzle_clog', 'clog', 'x', '{}')",
            (print_id,),
        )
    conn.close()


def _fake_print(reg, name, content_hash, end, expected, status="ok", n=240, alarms=()):
    rng = np.random.default_rng(abs(hash(content_hash)) % 2**32)
    end = np.asarray(end, dtype=float)
    means = np.tile(end, (n, 1)) * (1 + 1e-4 * rng.normal(size=(n, 5)))
    cov = np.diag((0.01 * np.abs(end)) ** 2 + 1e-12)
    covs = np.tile(cov, (n, 1, 1)) * (1 + np.arange(n) / n)[:, None, None]
    return reg.save_print(
        name,
        NewPrint(
            content_hash=content_hash,
            source="test",
            meta={"scenario": "test"},
            summary={},
            n_samples=n,
            duration_s=float(n),
            start_mean=end,
            start_cov=cov,
            end_mean=end,
            end_cov=covs[-1],
            theta_before=np.zeros(5),
            theta_after=np.full(5, 1e-5),
            arrays={
                "time_s": np.arange(n, dtype=float),
                "means": means,
                "stds": np.sqrt(np.diagonal(covs, 0, 1, 2)),
                "covariances": covs,
                "predicted_means": means * (1 - 1e-7),
                "measurements": rng.normal(40, 1, size=(n, 5)),
                "inputs": np.tile([375.0, 23.0, 50.0], (n, 1)),
            },
            anomalies=[
                SimpleNamespace(
                    detected_s=t,
                    onset_s=t - 20,
                    cause="nozzle_clog",
                    description="nozzle clog",
                    detectors=["x"],
                    evidence={},
                )
                for t in alarms
            ],
            status=status,
        ),
        expected_last_seq=expected,
    )


def _digest(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


# --------------------------------------------------------------------- hostile stores
def test_t5_prints_table_without_info_is_refused_untouched(tmp_path):
    db = tmp_path / "fp.db"
    conn = sqlite3.connect(db)
    conn.execute("create table prints(x)")
    conn.commit()
    conn.close()
    before = _digest(db)
    res = run_cli("list", "--store", db)
    assert res.exit_code == 1 and "not an ajtwin registry (tables: prints)" in res.output
    assert _digest(db) == before and not os.path.exists(str(db) + "-wal")


@pytest.mark.parametrize(
    ("version", "application", "message"),
    [
        ("abc", None, "not an ajtwin registry"),  # a version that is not a number
        ("abc", R.APPLICATION, "schema_version 'abc' is not a number"),
        ("2", None, "not an ajtwin registry"),  # once printed a sqlite3.Row
        (str(R.SCHEMA_VERSION + 1), R.APPLICATION, "written by a newer ajtwin"),
    ],
)
def test_t6_bad_schema_version(tmp_path, version, application, message):
    db = tmp_path / "bv.db"
    conn = sqlite3.connect(db)
    if application is None:
        conn.execute("create table prints(x)")
        conn.execute("create table info(key, value)")
    else:
        conn.executescript(V1_STATEMENTS)
        conn.execute("insert into info values('application', ?)", (application,))
    conn.execute("insert into info values('schema_version', ?)", (version,))
    conn.commit()
    conn.close()
    res = run_cli("list", "--store", db)
    assert res.exit_code == 1 and message in res.output, res.output
    assert "sqlite3.Row" not in res.output
    with pytest.raises(RegistryError, match=message):
        Registry(db)


def test_t7_fifo_store_is_refused_without_hanging(tmp_path):
    fifo = tmp_path / "ff.sqlite"
    os.mkfifo(fifo)
    signal.alarm(30)  # a regression would block in open(): fail instead of hanging the suite
    try:
        res = run_cli("list", "--store", fifo)
        with pytest.raises(RegistryError, match="not a regular file"):
            Registry(fifo)
    finally:
        signal.alarm(0)
    assert res.exit_code == 1 and "not a regular file" in res.output
    res = run_cli("list", "--store", tmp_path)
    assert res.exit_code != 0 and "Traceback" not in res.output


def test_t8_crafted_blobs_give_a_clear_error_and_never_unpickle(tmp_path, store, monkeypatch):
    monkeypatch.chdir(tmp_path)
    reg = Registry(store)
    reg.add_machine("M")
    _fake_print(reg, "M", "a", GOOD, None)

    class Payload:
        def __reduce__(self):
            return (os.system, ("touch PWNED",))

    buf = io.BytesIO()
    np.save(buf, np.array([Payload()], dtype=object), allow_pickle=True)
    reg._db.execute("UPDATE prints SET end_mean = ?", (buf.getvalue(),))
    for args in (["show", "M"], ["history", "M"]):
        res = run_cli(*args, "--store", store)
        assert res.exit_code == 1, res.output
        assert "registry damaged at print 1 (id 1), column end_mean" in res.output
    from ajtwin.cli.forecast import forecast

    res = CliRunner().invoke(forecast, ["--machine", "M", "--store", str(store)])
    assert res.exit_code == 1 and "registry damaged at print 1" in res.output
    assert not (tmp_path / "PWNED").exists()
    # an array blob that claims an object dtype, one cut short, one that is a zip bomb
    header = json.dumps({"dtype": "|O", "shape": [3]}).encode()
    evil = b"AJZ1" + len(header).to_bytes(2, "little") + header + b"x"
    codec, good = A.encode(np.arange(100.0))
    bomb_header = json.dumps({"dtype": "<f8", "shape": [10]}).encode()
    bomb = b"AJZ1" + len(bomb_header).to_bytes(2, "little") + bomb_header
    bomb += __import__("zlib").compress(b"\0" * 10_000_000)
    for blob, why in ((evil, "not numbers"), (good[:-5], "damaged|bytes"), (bomb, "bytes")):
        with pytest.raises(ValueError, match=why):
            A.decode(blob, codec)
        reg._db.execute("UPDATE print_arrays SET npy = ? WHERE name = 'means'", (blob,))
        with pytest.raises(RegistryError, match="registry damaged at print 1 .* array means"):
            reg.print_arrays(1)


def test_unrelated_database_is_never_taken_over(tmp_path):
    db = tmp_path / "f.db"
    conn = sqlite3.connect(db)
    conn.execute("create table users(n)")
    conn.execute("insert into users values ('alice')")
    conn.commit()
    conn.close()
    before = _digest(db)
    res = run_cli("add", "Z", "--store", db)
    assert res.exit_code == 1 and "not an ajtwin registry (tables: users)" in res.output
    assert "refusing to change it" in res.output
    assert _digest(db) == before
    conn = sqlite3.connect(db)
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
    assert [r[0] for r in conn.execute("select name from sqlite_master")] == ["users"]


def test_read_only_commands_never_create_a_store(tmp_path):
    target = tmp_path / "new" / "dir" / "x.sqlite"
    for args in (["list"], ["show", "M"], ["history", "M"], ["compact", "M"]):
        res = run_cli(*args, "--store", target)
        assert res.exit_code == 1 and "no registry at" in res.output, res.output
    assert not (tmp_path / "new").exists()
    res = CliRunner().invoke(ingest, ["--machine", "M", __file__, "--store", str(target)])
    assert res.exit_code == 1 and not (tmp_path / "new").exists()
    res = run_cli("add", "M", "--store", target)  # a write command may create it
    assert res.exit_code == 0 and target.exists()


def test_names_stripped_and_control_characters_refused(store):
    assert run_cli("add", " lab2 ", "--store", store).exit_code == 0
    for lookup in (" lab2 ", "lab2", "lab2\t"):
        res = run_cli("show", lookup, "--store", store)
        assert res.exit_code == 0 and "machine lab2 " in res.output
    for bad in ("\x1b[31mRED\x1b[0m", "a\nb", "x\u202ey"):
        res = run_cli("add", bad, "--store", store)
        assert res.exit_code == 1 and "control characters" in res.output
        assert "\x1b" not in res.output and "\u202e" not in res.output
    # a name stored by an older version is escaped when printed
    Registry(store)._db.execute(
        "INSERT INTO machines (name, created_at, limits_json) VALUES (?, 'x', '{}')",
        ("\x1b[31mRED\x1b[0m",),
    )
    res = run_cli("list", "--store", store)
    assert res.exit_code == 0 and "\\x1b[31mRED\\x1b[0m" in res.output
    assert "\x1b" not in res.output


# --------------------------------------------------------------------- schema migration
def test_version1_registry_migrates_and_keeps_everything(store):
    impossible = GOOD * np.array([1, -1, 1, 1, 1])  # V_l < 0: an impossible end state
    _write_v1(store, [GOOD, GOOD * 1.01, impossible])
    res = run_cli("show", "old", "--store", store)
    assert res.exit_code == 0, res.output
    assert "migrated registry schema 1 → 2" in res.output
    assert "newest print #3 is excluded" in res.output
    assert "last stored print: #2" in res.output
    reg = Registry(store)
    assert reg.migrated == []  # once only
    assert reg.info("schema_version") == str(R.SCHEMA_VERSION)
    hist = reg.history("old")
    assert hist["status"].tolist() == ["ok", "ok", "excluded"]
    assert "vial_volume_mL" in hist["status_reason"].iloc[2]
    assert np.array_equal(reg.last_print("old")["end_mean"], GOOD * 1.01)
    a = reg.print_arrays(1)  # legacy .npy blobs read as they were
    assert a["covariances"].shape == (600, 5, 5) and a["means"].dtype == np.float64
    # compaction re-encodes them by the policy and shrinks the file
    from ajtwin.store.compaction import compact

    kept = [reg.print_bytes(k) for k in (1, 2, 3)]
    stats = compact(reg, "old", keep_covariances_days=36500)
    assert stats["reencoded"] == 3 and all(
        reg.print_bytes(k) < b / 4 for k, b in zip((1, 2, 3), kept)
    )
    if not on_postgres(store):  # the file shrinks (PostgreSQL reuses the space for new rows)
        assert stats["bytes_after"] < stats["bytes_before"] / 2
    b = reg.print_arrays(1)
    np.testing.assert_allclose(b["means"], a["means"], rtol=1e-7)
    np.testing.assert_allclose(b["predicted_means"], a["predicted_means"], rtol=1e-7)
    assert np.array_equal(b["measurements"], a["measurements"])  # raw samples: exact
    steps = b["covariance_steps"].tolist()
    # every 60 s, the end, and the alarm: detected at 300 s, onset 250 s
    assert steps == [0, 60, 120, 180, 240, 250, 300, 360, 420, 480, 540, 599]
    assert np.array_equal(b["covariance_keyframes"], a["covariances"][steps])


def test_migration_list_is_appendable(store, new_store, monkeypatch):
    """What the other branches do: append (3, ..., function) and old stores follow."""
    reg = Registry(store)
    reg.add_machine("m")
    reg.close()

    def add_tool_changes(db):
        for statement in db.ddl(
            "CREATE TABLE IF NOT EXISTS tool_changes (id INTEGER PRIMARY KEY, "
            "machine_id INTEGER NOT NULL REFERENCES machines(id), value REAL NOT NULL)"
        ):
            db.execute(statement)

    n = R.SCHEMA_VERSION + 1
    monkeypatch.setattr(R, "MIGRATIONS", R.MIGRATIONS + [(n, "tool_changes", add_tool_changes)])
    monkeypatch.setattr(R, "SCHEMA_VERSION", n)
    reg = Registry(store)
    assert reg.migrated == [f"{store}: migrated registry schema {n - 1} → {n} (tool_changes)"]
    assert "tool_changes" in reg._db.tables() and reg.machine("m")["n_prints"] == 0
    fresh = Registry(new_store())
    assert "tool_changes" in fresh._db.tables() and fresh.migrated == []
    assert fresh.info("schema_version") == str(n)


def test_concurrent_first_open_migrates_once(store):
    _write_v1(store, [GOOD])
    first, second = Registry(store), Registry(store)
    # one message per migration from version 1, all by the first opener
    assert len(first.migrated) == R.SCHEMA_VERSION - 1 and second.migrated == []
    assert second.history("old")["status"].tolist() == ["ok"]


# --------------------------------------------------------------------- the chain
def test_chain_skips_excluded_and_dropped_prints(store):
    from ajtwin.engine.chain import chain_start

    reg = Registry(store)
    reg.add_machine("m")
    assert chain_start(reg, "m").start is None
    _fake_print(reg, "m", "p1", GOOD, None)
    _fake_print(reg, "m", "p2", GOOD * 0.9, 1)
    bad = GOOD.copy()
    bad[0] = 534.0  # a 534 µm droplet: impossible
    _fake_print(reg, "m", "p3", bad, 2, status="excluded")
    start = chain_start(reg, "m")
    assert start.from_seq == 2 and start.latest_seq == 3
    assert np.array_equal(start.start[0], GOOD * 0.9) and "print 3: excluded" in start.description
    # a print stored 'ok' with an impossible end (older code) is never a start either
    reg._db.execute("UPDATE prints SET status = 'ok' WHERE seq = 3")
    start = chain_start(reg, "m")
    assert start.from_seq == 2 and "droplet_diameter_um = 534" in start.description
    res = run_cli("drop", "m", "--print", 2, "--reason", "wrong ink", "--store", store)
    assert res.exit_code == 0 and "starts from print #1's end state" in res.output
    assert chain_start(reg, "m").from_seq == 1
    res = run_cli("history", "m", "--store", store)
    assert "#2 dropped: wrong ink" in res.output
    res = run_cli("restore", "m", "--print", 3, "--store", store)
    assert res.exit_code == 1 and "impossible state" in res.output
    assert run_cli("restore", "m", "--print", 2, "--store", store).exit_code == 0
    assert chain_start(reg, "m").from_seq == 2
    res = run_cli("drop", "m", "--print", 9, "--store", store)
    assert res.exit_code == 1 and "has no print #9" in res.output
    assert reg.machine("m")["n_prints"] == 3  # dropping keeps history


@pytest.mark.parametrize("store", ["sqlite", SLOW_ON_POSTGRES], indirect=True)
def test_bad_print_does_not_poison_the_next_one(tmp_path, new_store):
    """An impossible ingest is stored excluded; the next clean print of
    the machine starts from the initial fit, as on a fresh machine."""
    from ajtwin.io.records import write_record
    from ajtwin.simulation import simulate

    ext = simulate("exp1", seed=1, duration_min=4.0)
    # the damaged print also set P_c = 9.9e5 Pa and P_s = 101 Pa: 175x and 1/56 of
    # what the model gives at its inputs, which the input check now refuses before the twin
    # runs (tests/test_bad_inputs.py); L_w/L_o alone still give d_a 534 µm, for the chain
    full = simulate("exp1", seed=1, duration_min=4.0)
    # each with a sensor's scatter: a column of one repeated value is no measurement and is
    # read as missing (tests/test_records_quality.py), which would hide what this pins
    scatter = np.abs(np.random.default_rng(0).normal(0.0, 1.0, len(full.data)))
    for column, value in (
        ("linewidth_um", 4999.0 - 2.0 * scatter),
        ("overspray_um", 0.6 + 0.05 * scatter),
        ("carrier_pressure_Pa", 9.9e5 + 6.0 * scatter),
        ("sheath_pressure_Pa", 101.0 + 6.0 * scatter),
    ):
        full.data[column] = value  # fmt: skip
        if column in ("linewidth_um", "overspray_um"):
            ext.data[column] = value  # fmt: skip
    nxt = simulate("exp1", seed=3, duration_min=4.0)
    for name, rec in (("ext", ext), ("next", nxt), ("full", full)):
        write_record(rec, tmp_path / f"{name}.parquet")
    runner = CliRunner()
    stores = {k: str(new_store()) for k in ("po", "cl")}
    for store in stores.values():
        assert run_cli("add", "M", "--store", store).exit_code == 0
    args = ["--machine", "M", "--no-progress", "--store", stores["po"]]
    res = runner.invoke(ingest, args + [str(tmp_path / "full.parquet")])
    assert res.exit_code == 1 and "column 'carrier_pressure_Pa'" in res.output
    assert Registry(stores["po"]).last_print("M") is None
    res = runner.invoke(ingest, args + [str(tmp_path / "ext.parquet")])
    assert res.exit_code == 0, res.output
    assert "EXCLUDED from the machine's chain" in res.output
    res = runner.invoke(ingest, args + [str(tmp_path / "next.parquet")])
    assert res.exit_code == 0, res.output
    assert "started from initial fit (skipped print 1: excluded)" in res.output
    res = runner.invoke(
        ingest,
        [
            "--machine",
            "M",
            "--no-progress",
            "--store",
            stores["cl"],
            str(tmp_path / "next.parquet"),
        ],
    )
    reg, ref = Registry(stores["po"]), Registry(stores["cl"])
    bad, good = reg.print_by_seq("M", 1), reg.print_by_seq("M", 2)
    assert bad["status"] == "excluded"
    assert "droplet_diameter_um" in bad["status_reason"]
    assert "outside the physical range" in bad["status_reason"]
    assert good["status"] == "ok"
    end = good["end_mean"]
    assert abs(end[1] - 1.0) < 0.05 and abs(end[3] - 0.03) < 0.02  # V_l ≈ 1 mL, ΔR_N ≈ 0.03
    assert not reg.anomalies("M").query("seq == 2")["cause"].str.contains("ink").any()
    np.testing.assert_allclose(end, ref.last_print("M")["end_mean"], rtol=1e-9)
    assert np.array_equal(good["theta_before"], ref.last_print("M")["theta_before"])


# --------------------------------------------------------------------- storage policy
@pytest.mark.parametrize("store", ["sqlite", SLOW_ON_POSTGRES], indirect=True)
def test_storage_policy_compaction_keeps_what_later_commands_need(tmp_path, store):
    """≤ 0.5 MB per print-hour; after compaction forecast, advise, show, history and a
    re-run of the detectors still work, with the same events."""
    import datetime as dt

    from ajtwin.apps.detection.batch import detect_anomalies
    from ajtwin.cli.advise import advise
    from ajtwin.cli.forecast import forecast
    from ajtwin.io.records import write_record
    from ajtwin.simulation import simulate
    from ajtwin.store.compaction import compact

    rec = simulate("nozzle_clog", seed=5, duration_min=12.0,
                   overrides={"fault": {"onset_min": 4.0}})  # fmt: skip
    write_record(rec, tmp_path / "p.parquet")
    assert run_cli("add", "M", "--store", store).exit_code == 0
    reg = Registry(store)
    empty = reg.checkpointed_bytes()
    res = CliRunner().invoke(ingest, ["--machine", "M", "--no-progress", "--store", str(store),
                                      str(tmp_path / "p.parquet")])  # fmt: skip
    assert res.exit_code == 0, res.output
    p = reg.last_print("M")
    per_hour = (reg.checkpointed_bytes() - empty) / (len(rec) / 3600.0)
    if on_postgres(store):
        # the server's tables grow by whole pages and large-value chunks: a 12-min print in
        # an empty database takes 1.2 MB per print-hour of them, the third print 0.53 MB;
        # what the storage policy keeps is the arrays' bytes
        per_hour = reg.print_bytes(p["id"]) / (len(rec) / 3600.0)
    assert per_hour <= 0.5e6, per_hour
    events = reg.anomalies("M")
    assert len(events) >= 1  # the clog is found (so alarm covariances are kept)
    before = reg.print_arrays(p["id"])
    alarm_steps = [int(np.searchsorted(before["time_s"], t)) for t in events["detected_s"]]
    assert set(alarm_steps) <= set(before["covariance_steps"].tolist())

    def later_commands():
        again = detect_anomalies(**detector_inputs(reg, p["id"]))
        assert [e.detected_s for e in again.events] == events["detected_s"].tolist()
        assert [e.cause for e in again.events] == events["cause"].tolist()
        runner = CliRunner()
        out = tmp_path / "f.csv"
        res = runner.invoke(forecast, ["--machine", "M", "--horizon", "5min", "--store",
                                       str(store), "--out", str(out)])  # fmt: skip
        assert res.exit_code == 0, res.output
        # the print clogged: advice on it is refused unless --anyway (both read the store)
        res = runner.invoke(advise, ["--machine", "M", "--target-linewidth", "40",
                                     "--store", str(store)])  # fmt: skip
        assert res.exit_code == 1 and "not advising 'M'" in res.output, res.output
        res = runner.invoke(advise, ["--machine", "M", "--target-linewidth", "40", "--anyway",
                                     "--store", str(store)])  # fmt: skip
        assert res.exit_code in (0, 2), res.output
        assert run_cli("show", "M", "--store", store).exit_code == 0
        assert run_cli("history", "M", "--store", store).exit_code == 0
        return out.read_text(), res.output

    forecast_before, advice_before = later_commands()
    future = dt.datetime.now(dt.UTC) + dt.timedelta(days=31)
    kept = reg.print_bytes(p["id"])
    stats = compact(reg, "M", keep_covariances_days=30, now=future)
    assert stats["thinned"] == 1 and reg.print_bytes(p["id"]) < kept
    if not on_postgres(store):  # the file shrinks (PostgreSQL reuses the space for new rows)
        assert stats["bytes_after"] <= stats["bytes_before"]
    after = reg.print_arrays(p["id"])
    kept = after["covariance_steps"].tolist()
    assert kept == sorted(set(alarm_steps) | {int(s) for s in np.searchsorted(
        before["time_s"], events["onset_s"])} | {len(rec) - 1})  # fmt: skip
    for key in ("means", "stds", "measurements", "inputs", "nis", "predicted_outputs"):
        assert np.array_equal(after[key], before[key]), key
    forecast_after, advice_after = later_commands()
    assert forecast_after == forecast_before and advice_after == advice_before
    res = run_cli("compact", "M", "--keep-covariances-days", "30", "--store", store)
    assert res.exit_code == 0 and "compacted 'M'" in res.output


# --------------------------------------------------------------------- export / import
def test_export_import_roundtrip(tmp_path, store, new_store):
    src = store
    reg = Registry(src)
    reg.add_machine("lab", notes="bay 3")
    _fake_print(reg, "lab", "p1", GOOD, None, alarms=[100.0])
    _fake_print(reg, "lab", "p2", GOOD * 0.9, 1, status="excluded")
    reg.add_machine("other")
    _fake_print(reg, "other", "q1", GOOD, None)
    archive = tmp_path / "lab.tar"
    res = run_cli("export", "lab", "--out", archive, "--store", src)
    assert res.exit_code == 0 and "2 prints" in res.output
    with tarfile.open(archive) as tar:
        assert sorted(tar.getnames()) == ["machine.sqlite", "manifest.json"]
        manifest = json.load(tar.extractfile("manifest.json"))
    assert manifest["schema_version"] == R.SCHEMA_VERSION and manifest["machine"] == "lab"
    dst = new_store()
    for target, name in ((dst, "lab"), (src, "lab-copy")):
        extra = [] if name == "lab" else ["--as", name]
        res = run_cli("import", archive, *extra, "--store", target)
        assert res.exit_code == 0, res.output
        copy = Registry(target)
        a, b = reg.history("lab"), copy.history(name)
        for column in a.columns:
            if column not in ("print_id",):
                assert a[column].tolist() == b[column].tolist(), column
        assert reg.anomalies("lab").equals(copy.anomalies(name))
        for pa, pb in zip(a["print_id"], b["print_id"]):
            x, y = reg.print_arrays(int(pa)), copy.print_arrays(int(pb))
            assert x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)
        assert copy.machine(name)["notes"] == "bay 3"
    assert [m["name"] for m in Registry(dst).machines()] == ["lab"]
    res = run_cli("import", archive, "--store", src)
    assert res.exit_code == 1 and "already exists" in res.output


def _tar(path, members):
    with tarfile.open(path, "w") as tar:
        for name, data, kind in members:
            info = tarfile.TarInfo(name)
            info.type = kind
            if kind == tarfile.SYMTYPE:
                info.linkname = data.decode()
                tar.addfile(info)
            else:
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))


def test_import_refuses_damaged_or_foreign_archives(tmp_path, store, new_store):
    src = store
    reg = Registry(src)
    reg.add_machine("lab")
    _fake_print(reg, "lab", "p1", GOOD, None)
    archive = tmp_path / "lab.tar"
    from ajtwin.store.archive import export_machine

    manifest = export_machine(reg, "lab", archive)
    with tarfile.open(archive) as tar:
        db = tar.extractfile("machine.sqlite").read()
    good_manifest = json.dumps(manifest).encode()
    newer = json.dumps({**manifest, "schema_version": R.SCHEMA_VERSION + 1}).encode()
    reg_file = tarfile.REGTYPE
    cases = {
        "not a tar": None,
        "traversal": [("manifest.json", good_manifest, reg_file), ("../evil.sqlite", db, reg_file)],
        "absolute": [
            ("manifest.json", good_manifest, reg_file),
            ("/tmp/x/machine.sqlite", db, reg_file),
        ],  # fmt: skip
        "symlink": [
            ("manifest.json", good_manifest, reg_file),
            ("machine.sqlite", b"/etc/passwd", tarfile.SYMTYPE),
        ],  # fmt: skip
        "checksum": [
            ("manifest.json", good_manifest, reg_file),
            ("machine.sqlite", db[:-100] + b"\0" * 100, reg_file),
        ],  # fmt: skip
        "newer": [("manifest.json", newer, reg_file), ("machine.sqlite", db, reg_file)],
        "foreign manifest": [
            ("manifest.json", b'{"a": 1}', reg_file),
            ("machine.sqlite", db, reg_file),
        ],  # fmt: skip
    }
    messages = {
        "not a tar": "not a tar archive",
        "traversal": "expected exactly",
        "absolute": "expected exactly",
        "symlink": "not a regular file",
        "checksum": "SHA-256",
        "newer": "written by a newer ajtwin",
        "foreign manifest": "not an ajtwin machine manifest",
    }
    dst = new_store()
    Registry(dst).close()
    before = Registry(dst).table_digest("machines")
    work = tmp_path / "work"
    work.mkdir()
    for case, members in cases.items():
        bad = work / f"{case}.tar"
        if members is None:
            bad.write_bytes(b"\x00garbage" * 200)
        else:
            _tar(bad, members)
        res = run_cli("import", bad, "--store", dst)
        assert res.exit_code == 1 and messages[case] in res.output, (case, res.output)
        assert Registry(dst).table_digest("machines") == before
        assert Registry(dst).machines() == []
    assert not (tmp_path / "evil.sqlite").exists() and not os.path.exists("/tmp/x/machine.sqlite")
    assert sorted(p.name for p in work.iterdir()) == sorted(f"{c}.tar" for c in cases)


def test_import_refuses_an_archive_with_damaged_blobs(tmp_path):
    src = Registry(tmp_path / "a.sqlite")
    src.add_machine("lab")
    _fake_print(src, "lab", "p1", GOOD, None)
    src._db.execute("UPDATE print_arrays SET npy = x'00' WHERE name = 'means'")
    db = tmp_path / "crafted.sqlite"
    src._db.execute("VACUUM INTO ?", (str(db),))
    data = db.read_bytes()
    manifest = {"format": "ajtwin-machine-export", "format_version": 1, "schema_version": 2,
                "machine": "lab", "database_sha256": hashlib.sha256(data).hexdigest()}  # fmt: skip
    archive = tmp_path / "crafted.tar"
    _tar(archive, [("manifest.json", json.dumps(manifest).encode(), tarfile.REGTYPE),
                   ("machine.sqlite", data, tarfile.REGTYPE)])  # fmt: skip
    dst = tmp_path / "b.sqlite"
    res = run_cli("import", archive, "--store", dst)
    assert res.exit_code == 1 and "registry damaged at print 1" in res.output
    assert "array means" in res.output and Registry(dst).machines() == []


def test_exported_version1_machine_is_migrated_on_import(tmp_path):
    old = tmp_path / "v1.sqlite"
    _write_v1(old, [GOOD])
    # an archive as a version-1 export would hold: the old registry file itself
    db = old.read_bytes()
    manifest = {"format": "ajtwin-machine-export", "format_version": 1, "schema_version": 1,
                "machine": "old", "database_sha256": hashlib.sha256(db).hexdigest()}  # fmt: skip
    archive = tmp_path / "old.tar"
    _tar(archive, [("manifest.json", json.dumps(manifest).encode(), tarfile.REGTYPE),
                   ("machine.sqlite", db, tarfile.REGTYPE)])  # fmt: skip
    res = run_cli("import", archive, "--store", tmp_path / "new.sqlite")
    assert res.exit_code == 0, res.output
    assert "archive: " in res.output and "schema 1 → 2" in res.output
    new = Registry(tmp_path / "new.sqlite")
    assert new.print_arrays(new.last_print("old")["id"])["covariances"].shape == (600, 5, 5)


def test_guard_firings_are_counted_and_stored(store):
    """One absurd linewidth sample (1e300 µm, an in-memory record no reader checked):
    the divergence guard resets the filter there; the ingest counts the firing in the
    summary and stores it per step."""
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.simulation import simulate

    reg = Registry(store)
    reg.add_machine("M")
    rec = simulate("exp1", seed=1, duration_min=3.0)
    rec.data.iloc[100, rec.data.columns.get_loc("linewidth_um")] = 1e300
    result = ingest_record(reg, "M", rec)
    fired = reg.print_arrays(result.print_id)["reinitialised"]
    assert fired.dtype == bool and fired.shape == (180,)
    steps = np.flatnonzero(fired)
    assert result.summary["guard_reinitialisations"] == len(steps) >= 1
    assert 100 <= steps[0] <= 102
    # what float32 cannot hold is stored as float64, not as inf
    stored = reg.print_arrays(result.print_id)
    assert stored["measurements"][100, 0] == 1e300
    run = result.run
    for key, exact in (
        ("predicted_outputs", run.filtered.predicted_outputs),
        ("innovation_variances", run.filtered.innovation_variances),
    ):
        exact = np.asarray(exact)
        assert np.array_equal(np.isfinite(stored[key]), np.isfinite(exact)), key
        np.testing.assert_allclose(stored[key], exact, rtol=1.2e-7)
