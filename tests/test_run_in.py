"""The atomizer's run-in after switch-on is a known phase, not a fault nor a misfit.

A print that begins as the atomizer is switched on (the virtual ``startup``: the mist builds
up over 5-15 min) moves Q_m and the line away from a twin tuned for steady prints: the
detectors and the mismatch guard must say "run-in", while a clog or a leak (the pressures,
which a mist building up does not move) keeps its label and its time.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.causes import open_faults
from ajtwin.apps.detection.settling import RunIn
from ajtwin.engine.chain import open_registry
from ajtwin.engine.estimate import estimate_to_csv
from ajtwin.engine.ingest import ingest_record
from ajtwin.engine.reprocess import FIRST, reprocess_print
from ajtwin.estimation import Twin
from ajtwin.io.records import PrintRecord
from ajtwin.simulation import simulate


def test_a_short_start_up_print_raises_no_fault_and_no_mismatch(tmp_path):
    """Start-up seed 3, 12 min: before, 'atomizer trouble' at 1.8 min (a fault) and a Q_m
    mismatch from 7 min, in ingest and estimate alike; now the event is the run-in's."""
    record = simulate("startup", seed=3, duration_min=12.0)
    assert record.meta["atomizer_switched_on_s"] == 0.0
    registry = open_registry(tmp_path / "r.sqlite")
    registry.add_machine("m1")
    ingested = ingest_record(registry, "m1", record)
    causes = [ev.cause for ev in ingested.events]
    assert "run_in" in causes  # the detectors did see the mist building up ...
    assert open_faults(ingested.events, []) == []  # ... and call none of it a fault
    assert ingested.summary["mismatch"]["mismatch"] is False
    done = estimate_to_csv(Twin.default(), record, tmp_path / "states.csv")
    assert done.mismatch.mismatch is False
    assert not np.asarray(done.mismatch.flags).any()
    # reprocessed from the registry (its stored metadata keeps the switch-on): the same
    version = registry.create_version("test", {})
    reprocess_print(registry, version, "m1", ingested.print_id, FIRST)
    again = registry.history("m1", version=version)
    assert again["causes"].tolist() == ["run_in"] and not again["mismatch"].any()


@pytest.mark.parametrize("fault", ["nozzle_clog", "carrier_leak"])
def test_a_clog_or_leak_keeps_its_label_and_time_with_or_without_a_run_in(fault):
    """A clog or a leak 2 min into a print (inside the not-yet-ready minutes every print has)
    is found when and as it was, whether or not the print began with a switch-on: a run-in
    explains no pressure alarm."""
    overrides = {"fault": {"onset_min": 2.0}}
    record = simulate(fault, seed=0, duration_min=6.0, overrides=overrides)
    run = Twin.default().run(record)
    steady = detect_run(run, record).events
    switched_on = PrintRecord(record.data, {**record.meta, "atomizer_switched_on_s": 0.0})
    as_start_up = detect_run(run, switched_on).events
    found = [
        [(ev.detected_s, ev.onset_s, ev.cause) for ev in events if ev.detected_s >= 120.0]
        for events in (steady, as_start_up)
    ]
    assert found[0] and found[0][0][2] == fault and found[0][0][0] - 120.0 < 60.0
    assert found[1] == found[0]


def test_a_switch_on_in_the_atomizer_current_begins_a_run_in_until_ready():
    """Live, the switch-on shows in the current (below 50 mA, then above): a run-in from
    that second; a record that does not show one has none."""
    run_in = RunIn()
    for t, current in enumerate([0.0, 0.0, 375.0, 375.0, np.nan, 0.0, 380.0]):
        run_in.update(float(t), current, np.zeros(5), np.zeros(5))
    assert [start for start, _ in run_in.spans] == [2.0, 6.0]
    assert run_in.covers(3.0) and not run_in.covers(1.0)
    steady = RunIn()
    for t in range(5):
        steady.update(float(t), 375.0, np.zeros(5), np.zeros(5))
    assert steady.spans == [] and not steady.covers(3.0)


def test_the_live_twin_labels_the_run_in_of_an_atomizer_it_sees_switched_on():
    """Live, with no record metadata: the atomizer current rising through 50 mA at 3 s is the
    switch-on, and the mist building up after it is the run-in's event, not a fault."""
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.estimation.samples import Sample

    record = simulate("startup", seed=3, duration_min=3.0)
    inputs = record.inputs.copy()
    inputs[:3, 0] = 0.0  # switched on at 3 s
    engine = LiveEngine(None, asynchronous=False)
    messages = []
    engine.subscribe(messages.append)
    for t, u, y in zip(record.time_s, inputs, record.outputs, strict=True):
        engine.feed("m1", Sample(t, u, y))
    engine.close("m1")
    events = [e for m in messages for e in (getattr(m, "events", None) or ())]
    assert events and {e["cause"] for e in events} == {"run_in"}
    assert open_faults(events, []) == []


def test_a_log_that_does_not_say_its_switch_on_is_told_on_the_command_line(tmp_path):
    """A machine's log carries no switch-on time: `--switched-on 0` on `estimate` and
    `ingest` makes its run-in the known phase the record's own metadata would."""
    from click.testing import CliRunner

    from ajtwin.cli import main
    from ajtwin.io.records import write_record

    start_up = simulate("startup", seed=3, duration_min=12.0)
    meta = {k: v for k, v in start_up.meta.items() if k != "atomizer_switched_on_s"}
    path = write_record(PrintRecord(start_up.data, meta), tmp_path / "log.parquet")
    runner = CliRunner()
    for told in ([], ["--switched-on", "0"]):
        store = ["--store", str(tmp_path / f"r{len(told)}.sqlite")]
        assert runner.invoke(main, ["machine", "add", "m1", *store]).exit_code == 0
        for args in (["estimate", str(path), "--out", str(tmp_path / "s.csv")],
                     ["ingest", "--machine", "m1", str(path), *store]):  # fmt: skip
            result = runner.invoke(main, [*args, *told])
            assert result.exit_code == 0, result.output
            assert args[0] == "estimate" or "ingested" in result.output
            said = result.output
            if args[0] == "estimate":  # the log alone: the run-in's seconds read as a misfit
                flagged = pd.read_csv(tmp_path / "s.csv")["mismatch"].sum()
                assert (flagged > 0) == (not told), (flagged, said)
            else:  # ... and, ingested, as atomizer trouble (a fault)
                assert ("atomizer trouble" in said) == (not told), said
                assert ("running in" in said) == bool(told), said
            assert "WARNING model–machine mismatch" not in said or not told
