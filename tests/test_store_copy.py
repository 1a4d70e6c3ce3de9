"""``ajtwin store copy``: a whole registry moved SQLite → PostgreSQL → SQLite; resumable,
checked; ``machine history`` and ``machine show`` print the same on every copy."""

from __future__ import annotations

import re

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.model import STATE_NAMES
from ajtwin.store.copy import COPIED_TABLES, copy_registry
from ajtwin.store.live_log import LiveLog
from ajtwin.store.registry import Registry, RegistryError
from test_store_reliability import GOOD, _fake_print


def _cli(*args):
    res = CliRunner().invoke(main, [str(a) for a in args])
    assert res.exception is None or isinstance(res.exception, SystemExit), res.output
    return res


def _lab(path) -> Registry:
    """A registry with what a lab keeps: two machines, prints with arrays and alarms, one
    excluded, a maintenance event, a live print still running, a reprocessed version."""
    reg = Registry(path)
    reg.add_machine("aj1", notes="bay 1")
    reg.add_machine("aj2")
    _fake_print(reg, "aj1", "p1", GOOD, None, alarms=[100.0])
    _fake_print(reg, "aj1", "p2", GOOD * 0.9, 1, status="excluded")
    _fake_print(reg, "aj1", "p3", GOOD * 1.01, 2)
    _fake_print(reg, "aj2", "q1", GOOD, None)
    _cli("machine", "maintain", "aj2", "--nozzle-cleaned", "--store", path)
    log = LiveLog(path)
    sid = log.open_session("aj2", source="opc.tcp://bay-2:4840", start=None, theta=np.zeros(5))
    states = dict(zip(STATE_NAMES, GOOD.tolist()))
    steps = [(k, float(k), np.ones(3) * k, np.ones(5) * k,
              {"machine": "aj2", "step": k, "time_s": float(k), "status": "ok",
               "states": states, "stds": states}) for k in range(30)]  # fmt: skip
    event = {"detected_s": 12.0, "onset_s": 9.0, "state": "raised", "cause": "x",
             "description": "a clog"}  # fmt: skip
    log.append(sid, steps, [event])
    log.registry.release_machine("aj2")  # the twin stopped, its session open
    log.close()
    version = reg.create_version("test", {})
    reg.save_print_version(version, 1, _version_result(reg.get_print(1)))
    reg.finish_version(version)
    return reg


def _version_result(row):
    from ajtwin.store.registry import NewPrint

    n = 10
    return NewPrint(
        **{
            k: row[k]
            for k in (
                "content_hash",
                "source",
                "meta",
                "summary",
                "n_samples",
                "duration_s",
                "start_mean",
                "start_cov",
                "end_cov",
                "theta_before",
                "theta_after",
            )
        },  # fmt: skip
        end_mean=row["end_mean"] * 1.001,
        arrays={"time_s": np.arange(n, dtype=float), "means": np.ones((n, 5))},
    )


def _shown(path, machine) -> str:
    text = ""
    for args in (("show", machine), ("history", machine), ("history", machine, "--version", 2)):
        res = _cli("machine", *args, "--store", path)
        assert res.exit_code == 0, res.output
        text += res.output.replace(str(path), "REGISTRY")
    return re.sub(r"\(\d+\.\d min ago\)", "(… min ago)", text)


def test_a_registry_copied_to_postgresql_and_back_prints_the_same(tmp_path, pg_store):
    src = tmp_path / "lab.sqlite"
    _lab(src).close()
    res = _cli("store", "copy", src, pg_store, "--no-progress")
    assert res.exit_code == 0, res.output
    assert "copied 2 machine(s), 4 print(s) and 1 live session(s)" in res.output
    assert f"checked: {len(COPIED_TABLES)} tables" in res.output
    back = tmp_path / "back.sqlite"
    res = _cli("store", "copy", pg_store, back, "--no-progress")
    assert res.exit_code == 0, res.output
    for machine in ("aj1", "aj2"):
        assert _shown(src, machine) == _shown(pg_store, machine) == _shown(back, machine)
    a, b = Registry(src), Registry(pg_store)
    for table in COPIED_TABLES:
        assert a.table_digest(table) == b.table_digest(table), table
    assert b.print_arrays(3).keys() == a.print_arrays(3).keys()
    assert all(
        np.array_equal(a.print_arrays(3)[k], b.print_arrays(3)[k]) for k in a.print_arrays(3)
    )
    # the open live print resumes on the new registry: its samples and alarms are there
    session = b.live_session_of("aj2")
    assert b.live_n_steps(session["id"]) == 30 and b.live_events(session["id"])
    # the new registry's own ids go on after the copied ones
    b.add_machine("aj3")
    assert b.machine("aj3")["id"] == 3
    assert _fake_print(b, "aj3", "r1", GOOD, None) == 5


def test_a_stopped_copy_goes_on_where_it_stopped(tmp_path, pg_store):
    src = _lab(tmp_path / "lab.sqlite")
    dst = Registry(pg_store)
    copied = []

    def stop_after_two(table):
        copied.append(table)
        if copied.count("prints") == 2:
            raise KeyboardInterrupt  # the copy killed midway

    with pytest.raises(KeyboardInterrupt):
        copy_registry(src, dst, progress=stop_after_two)
    assert dst.info("copy_state") == "running"
    assert 1 <= len(dst.history("aj1")) < 3
    done = copy_registry(src, dst)
    assert done["resumed"] and done["prints"] == 4
    assert dst.info("copy_state") == "done"
    for table in COPIED_TABLES:
        assert src.table_digest(table) == dst.table_digest(table), table


def test_a_copy_into_a_registry_of_other_machines_is_refused(tmp_path, pg_store):
    src = _lab(tmp_path / "lab.sqlite")
    other = Registry(pg_store)
    other.add_machine("elsewhere")
    with pytest.raises(
        RegistryError, match="already holds machines .elsewhere. that are not a copy"
    ):
        copy_registry(src, other)
    with pytest.raises(RegistryError, match="itself"):
        copy_registry(src, src)
