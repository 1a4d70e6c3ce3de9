"""A print's arrays written in parts while the twin runs (an ingest, a live print) read back
as the same arrays as the print written whole; a registry from before the parts (schema 6)
opens, keeps its prints and takes new ones in parts; a draft left by a killed process goes."""

from __future__ import annotations

import functools
import os

import numpy as np
import pytest

from ajtwin.engine import ingest
from ajtwin.engine.ingest import TwinOutcome, ingest_record, run_arrays, save_print
from ajtwin.engine.parts import PrintWriter
from ajtwin.estimation import Twin
from ajtwin.simulation import simulate
from ajtwin.store import registry as R
from ajtwin.store.registry import Registry, record_hash


@pytest.fixture(scope="module")
def record():
    return simulate("exp1", seed=3, duration_min=20)  # 1200 s: EM chunks of 120-300 s


def _save_whole(reg, machine, record, events=()):
    """The print as a store without parts kept it: the whole run's arrays in the print's
    one transaction."""
    twin = Twin.default()
    theta_before = twin.theta.copy()
    run = twin.run(record)
    outcome = TwinOutcome(
        arrays=run_arrays(run, record),
        events=list(events),
        start=(run.start_mean, run.start_cov),
        end=(run.end_mean, run.end_cov),
        theta_before=theta_before,
        theta_after=twin.theta,
        started_from="initial fit",
        status="ok",
        status_reason="",
    )
    print_id, _ = save_print(
        reg, machine, record, outcome, digest=record_hash(record), source="whole",
        expected_last_seq=None,
    )  # fmt: skip
    return print_id


def test_a_print_written_in_parts_reads_back_as_the_print_written_whole(
    store, new_store, record, monkeypatch
):
    monkeypatch.setattr(ingest, "PrintWriter", functools.partial(PrintWriter, part_steps=250))
    reg = Registry(store)
    reg.add_machine("m")
    done = ingest_record(reg, "m", record, source="parts")
    n_parts = reg._db.execute(
        "SELECT COUNT(DISTINCT part) FROM print_array_parts WHERE print_id = ? AND name = 'means'",
        (done.print_id,),
    ).fetchone()[0]
    # the filter's chunks (EM at 120, 300, 600, 900 s) gathered to >= 250 steps: 4 × 300
    assert n_parts == 4
    assert reg._db.execute("SELECT COUNT(*) FROM array_drafts").fetchone()[0] == 0
    parts = reg.print_arrays(done.print_id)

    whole_reg = Registry(new_store())
    whole_reg.add_machine("m")
    whole = whole_reg.print_arrays(_save_whole(whole_reg, "m", record, done.events))
    assert sorted(parts) == sorted(whole)
    for name in whole:
        np.testing.assert_allclose(parts[name], whole[name], rtol=1e-12, atol=0, err_msg=name)
    assert len(parts["time_s"]) == len(record)
    # one array alone (the fleet page's trends, the reported band) reads the parts too
    for name in ("means", "stds", "time_s"):
        np.testing.assert_array_equal(reg.print_array(done.print_id, name), parts[name])
    assert reg.print_array(done.print_id, "no such array") is None


def test_a_registry_from_before_the_parts_opens_and_keeps_its_prints(
    store, new_store, record, monkeypatch
):
    with monkeypatch.context() as old:
        old.setattr(R, "MIGRATIONS", [m for m in R.MIGRATIONS if m[0] <= 6])
        old.setattr(R, "SCHEMA_VERSION", 6)
        reg = Registry(store)
        reg.add_machine("m")
        first = _save_whole(reg, "m", record)
        assert not {"array_drafts", "print_array_parts"} & reg._db.tables()
        reg.close()
    reg = Registry(store)
    assert reg.migrated[0] == (
        f"{store}: migrated registry schema 6 → 7 (print arrays written in parts while a print "
        "runs)"
    )
    assert len(reg.migrated) == R.SCHEMA_VERSION - 6
    assert reg.info("schema_version") == str(R.SCHEMA_VERSION)
    after = reg.print_arrays(first)
    now = Registry(new_store())  # the same print stored whole by this schema
    now.add_machine("m")
    before = now.print_arrays(_save_whole(now, "m", record))
    assert sorted(after) == sorted(before)
    for name in before:
        np.testing.assert_array_equal(after[name], before[name], err_msg=name)
    # the chain goes on from the old print, the new one written in parts
    second = ingest_record(reg, "m", simulate("exp1", seed=4, duration_min=5), source="new")
    assert second.seq == 2 and second.summary["started_from"] == "print 1"
    assert len(reg.print_arrays(second.print_id)["time_s"]) == 300


def test_a_draft_left_by_a_killed_process_is_removed_by_the_next_writer(store):
    reg = Registry(store)
    reg.add_machine("m")
    writer = PrintWriter(reg, "m", "ingest of a.csv", part_steps=10)
    n = 25
    writer.add(
        {
            "time_s": np.arange(n, dtype=float),
            "means": np.ones((n, 5)),
            "covariances": np.tile(np.eye(5), (n, 1, 1)),
            "nis": np.ones(n),
            "reinitialised": np.zeros(n, bool),
            "inputs": np.ones((n, 3)),
            "measurements": np.ones((n, 5)),
        }
    )
    assert reg._db.execute("SELECT COUNT(*) FROM print_array_parts").fetchone()[0] > 0
    # the process that wrote it is gone: a pid that no process has
    reg._db.execute("UPDATE array_drafts SET pid = ?", (2**22 + 12345,))
    assert not os.path.exists(f"/proc/{2**22 + 12345}")
    PrintWriter(reg, "m", "ingest of b.csv").discard()
    assert reg._db.execute("SELECT COUNT(*) FROM print_array_parts").fetchone()[0] == 0
    assert reg._db.execute("SELECT COUNT(*) FROM array_drafts").fetchone()[0] == 0
