"""The live twin: streaming engine ≡ batch twin + detectors; sample-order handling."""

from __future__ import annotations

import re

import numpy as np
import pytest

from ajtwin.apps.detection.batch import detect_run
from ajtwin.engine.messages import StepMessage
from ajtwin.engine.stream import TwinStream
from ajtwin.estimation import Twin
from ajtwin.estimation.samples import Sample, clean_sample
from ajtwin.model import STATE_NAMES
from ajtwin.simulation import simulate

# short EM cadence so a few minutes of print cross several EM updates
FAST_EM = {"window_s": 60, "every_s": 30}


@pytest.fixture(scope="module")
def clog_record():
    return simulate(
        "nozzle_clog",
        seed=5,
        duration_min=6.0,
        overrides={"fault": {"onset_min": 3.0, "nozzle_deposition_multiplier": 400.0}},
    )


def _relative(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300))


def _feed_all(stream, record):
    messages = []
    for t, u, y in zip(record.time_s, record.inputs, record.outputs):
        messages += stream.feed(Sample(t, u, y))
    messages += stream.finish()
    return messages


@pytest.mark.parametrize("asynchronous", [False, True])
def test_a_print_fed_a_sample_at_a_time_gives_the_whole_print_result(clog_record, asynchronous):
    rec = clog_record
    batch_twin = Twin.default(**FAST_EM)
    run = batch_twin.run(rec)
    detection = detect_run(run, rec)
    assert len(run.theta_history) >= 5

    stream = TwinStream.new("m", twin_overrides=FAST_EM, asynchronous=asynchronous)
    messages = _feed_all(stream, rec)
    arrays = stream.arrays()
    assert arrays["means"].shape == run.means.shape
    assert _relative(arrays["means"], run.means) < 1e-9
    assert _relative(arrays["covariances"], np.asarray(run.filtered.covariances)) < 1e-9
    assert _relative(arrays["nis"] + 1e-12, np.asarray(run.filtered.nis) + 1e-12) < 1e-9
    assert _relative(arrays["theta_per_step"] + 1e-30, run.theta_per_step + 1e-30) < 1e-9
    assert _relative(stream.theta, batch_twin.theta) < 1e-9
    hist = run.theta_history
    assert np.array_equal(arrays["theta_history_time_s"], hist["time_s"].to_numpy(float))
    events = [e.to_dict() for e in stream.detector.events]
    assert events == [e.to_dict() for e in detection.events]
    assert any(e["cause"] == "nozzle_clog" for e in events)
    # every committed step published once, in order
    steps = [m.step for m in messages if isinstance(m, StepMessage) and not m.provisional]
    assert steps == list(range(len(rec)))
    if asynchronous:
        raised = [e for m in messages if isinstance(m, StepMessage) for e in m.raised()]
        assert raised and raised[0]["detected_s"] == detection.events[0].detected_s


@pytest.mark.parametrize(
    "asynchronous, early, times, starts",
    [
        (False, (10, 25), [9.0, 24.0, 59.0, 89.0], [0.0, 0.0, 0.0, 30.0]),
        # EM in a worker thread is the first test's second case; here once more, slow
        pytest.param(
            True, (10, 25), [9.0, 24.0, 59.0, 89.0], [0.0, 0.0, 0.0, 30.0], marks=pytest.mark.slow
        ),
        # an early step between two multiples of every_s (and one past the window: dropped)
        (True, (45, 70), [44.0, 59.0, 89.0, 119.0], [0.0, 0.0, 30.0, 60.0]),
    ],
)
def test_a_sample_at_a_time_gives_the_whole_print_result_with_early_em(
    clog_record, asynchronous, early, times, starts
):
    """EM also at the early steps, each over the print so far: the same boundaries, θ and
    states in the stream as in the batch twin."""
    overrides = {**FAST_EM, "early_em_s": early}
    batch_twin = Twin.default(**overrides)
    run = batch_twin.run(clog_record)
    hist = run.theta_history
    assert hist["time_s"].to_numpy(float)[:4].tolist() == times
    assert hist["window_start_s"].to_numpy(float)[:4].tolist() == starts
    first = int(times[0]) + 1
    assert _relative(run.theta_per_step[first], run.theta_per_step[first - 1]) > 0  # θ moved
    stream = TwinStream.new("m", twin_overrides=overrides, asynchronous=asynchronous)
    _feed_all(stream, clog_record)
    arrays = stream.arrays()
    assert _relative(arrays["means"], run.means) < 1e-9
    assert _relative(arrays["covariances"], np.asarray(run.filtered.covariances)) < 1e-9
    assert _relative(arrays["theta_per_step"] + 1e-30, run.theta_per_step + 1e-30) < 1e-9
    assert np.array_equal(arrays["theta_history_time_s"], hist["time_s"].to_numpy(float))
    # without the early steps the first update comes only with a full window
    plain = Twin.default(**FAST_EM, early_em_s=()).run(clog_record).theta_history
    assert plain["time_s"].to_numpy(float)[0] == 59.0


@pytest.mark.parametrize("asynchronous", [pytest.param(False, marks=pytest.mark.slow), True])
def test_a_sample_at_a_time_gives_the_whole_print_result_with_input_following_droplets(
    clog_record, asynchronous
):
    """The input_following variant reads the input response r as a 4th input: the stream
    carries it sample by sample (model.droplet_dynamics.model_input) through EM
    boundaries and held samples, and equals the batch twin's Twin.model_inputs run."""
    rec = clog_record
    u = rec.inputs.copy()
    u[100:, 1] += 3.0  # carrier steps (r follows with τ_u = 90 s) ...
    u[220:, 0] -= 25.0  # ... and the atomizer current
    overrides = {**FAST_EM, "transition": "input_following"}
    batch_twin = Twin.default(**overrides)
    run = batch_twin.run(inputs=u, measurements=rec.outputs, time_s=rec.time_s)
    # the response is not constant over this record, so the test can tell it apart
    r = batch_twin.model_inputs(u)[:, 3]
    assert np.ptp(r) > 0.05

    stream = TwinStream.new("m", twin_overrides=overrides, asynchronous=asynchronous)
    for t, uk, yk in zip(rec.time_s, u, rec.outputs):
        stream.feed(Sample(t, uk, yk))
    stream.finish()
    arrays = stream.arrays()
    assert np.array_equal(stream.model_inputs()[:, 3], r)
    assert _relative(arrays["means"], run.means) < 1e-9
    assert _relative(arrays["covariances"], np.asarray(run.filtered.covariances)) < 1e-9
    assert _relative(arrays["theta_per_step"] + 1e-30, run.theta_per_step + 1e-30) < 1e-9
    assert _relative(stream.theta, batch_twin.theta) < 1e-9
    # the paper variant on the same inputs differs: the response column is not ignored
    paper = Twin.default(**FAST_EM, transition="paper").run(
        inputs=u, measurements=rec.outputs, time_s=rec.time_s
    )
    assert _relative(paper.means[:, 0], run.means[:, 0]) > 1e-3


def test_gaps_duplicates_and_old_samples(clog_record):
    rec = clog_record.window(0, 120)
    keep = [k for k in range(len(rec)) if k not in (40, 41, 42)]  # a 3 s gap
    stream = TwinStream.new("m", twin_overrides={"em": False}, asynchronous=False)
    for k in keep:
        stream.feed(Sample(rec.time_s[k], rec.inputs[k], rec.outputs[k]))
        if k == 50:
            stream.feed(Sample(rec.time_s[k], rec.inputs[k], rec.outputs[k]))  # duplicate
            stream.feed(Sample(rec.time_s[20], rec.inputs[20], rec.outputs[20]))  # old
    stream.finish()
    assert stream.dropped == {"duplicate": 1, "out_of_order": 1, "bad": 0, "far_future": 0}
    assert stream.missing_inserted == 3
    arrays = stream.arrays()
    assert np.array_equal(arrays["time_s"], rec.time_s)
    # the gap is missing data: batch on the record with NaN outputs there is the same
    y = rec.outputs.copy()
    y[40:43] = np.nan
    u = rec.inputs.copy()
    u[40:43] = u[39]
    run = Twin.default(em=False).run(inputs=u, measurements=y, time_s=rec.time_s)
    assert _relative(arrays["means"], run.means) < 1e-9
    assert np.all(arrays["n_measured"][40:43] == 0)


def test_clean_sample_bad_wire_data():
    ok, problems = clean_sample(3.0, [375, 23, 50], [90, 150, 2000, 1500, 1e-9])
    assert problems == [] and np.all(np.isfinite(ok.outputs))
    s, problems = clean_sample(3.0, [375, 23, 50], [np.nan, -5.0, np.inf, 1500, 1e-9])
    assert np.isnan(s.outputs[:3]).all() and s.outputs[3] == 1500
    assert len(problems) == 2 and "overspray_um" in problems[0]
    s, problems = clean_sample(3.0, [np.nan, 23, 50], [90, 150, 2000, 1500, 1e-9])
    assert np.isnan(s.inputs).all() and "atomizer_current_mA" in problems[0]
    s, problems = clean_sample("x", [375, 23, 50], [90, 150, 2000, 1500, 1e-9])
    assert s is None and "not a number" in problems[0]


@pytest.mark.parametrize(
    "transition", [pytest.param("paper", marks=pytest.mark.slow), "input_following"]
)
def test_engine_many_machines_batched_equals_single(clog_record, transition):
    from ajtwin.engine.fleet import LiveEngine

    rec = clog_record.window(0, 200)
    overrides = {**FAST_EM, "transition": transition}
    engine = LiveEngine(twin_overrides=overrides, asynchronous=False)
    got = []
    engine.subscribe(got.append)
    names = ["a", "b", "c"]
    for k in range(len(rec)):
        # machine c lags by a sample: mixed batches of ordinary steps and boundaries
        items = [(n, Sample(rec.time_s[k], rec.inputs[k], rec.outputs[k])) for n in names[:2]]
        if k > 0:
            items.append(("c", Sample(rec.time_s[k - 1], rec.inputs[k - 1], rec.outputs[k - 1])))
        engine.feed_many(items)
    single = TwinStream.new("s", twin_overrides=overrides, asynchronous=False)
    _feed_all(single, rec)
    for n in names:
        arrays = engine.sessions[n].stream.arrays()
        length = len(arrays["means"])
        assert length == len(rec) - (n == "c")
        assert _relative(arrays["means"], single.arrays()["means"][:length]) < 1e-9
    assert {m.machine for m in got} == set(names)
    engine.shutdown()


def test_a_machines_several_samples_in_one_feed_many_step_one_after_another(clog_record):
    """A burst of one machine's samples handed over in one call: each step starts from the
    carry of the step before it (as fed one at a time), two machines' bursts interleaved."""
    from ajtwin.engine.fleet import LiveEngine

    rec = clog_record.window(0, 200)
    engine = LiveEngine(twin_overrides=FAST_EM, asynchronous=False)
    for first in range(0, len(rec), 25):
        burst = []
        for k in range(first, min(first + 25, len(rec))):
            sample = Sample(rec.time_s[k], rec.inputs[k], rec.outputs[k])
            burst += [("a", sample), ("b", sample)]
        engine.feed_many(burst)
    single = TwinStream.new("s", twin_overrides=FAST_EM, asynchronous=False)
    _feed_all(single, rec)
    expected = single.arrays()["means"]
    for name in ("a", "b"):
        means = engine.sessions[name].stream.arrays()["means"]
        assert len(means) == len(rec)
        assert _relative(means, expected) < 1e-9
    engine.shutdown()


def test_the_steps_a_live_stream_keeps_own_their_numbers(clog_record):
    """No kept step holds a view of the buffer it came from (a device buffer held ~1.7 kB
    for 40-200 bytes of numbers: ~17 kB a step over the hours a stream keeps)."""
    from ajtwin.engine.fleet import LiveEngine

    rec = clog_record.window(0, 120)
    engine = LiveEngine(twin_overrides=FAST_EM, asynchronous=False)
    for k in range(len(rec)):
        sample = Sample(rec.time_s[k], rec.inputs[k], rec.outputs[k])
        engine.feed_many([("a", sample), ("b", sample)])  # the batched step
    single = TwinStream.new("s", twin_overrides=FAST_EM, asynchronous=False)
    _feed_all(single, rec)  # the single step
    for stream in (engine.sessions["a"].stream, single):
        blocks = list(stream._blocks)
        assert sum(len(b) for b in blocks) == len(rec)
        for block in blocks:
            for name, x in zip(block.filtered._fields, block.filtered):
                assert np.asarray(x).base is None, name
    engine.shutdown()


def test_kill_and_resume_from_registry(clog_record, tmp_path):
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.store.live_log import LiveLog
    from ajtwin.store.registry import Registry

    rec = clog_record.window(0, 240)
    registry = Registry(tmp_path / "r.sqlite")
    engine = LiveEngine(registry, twin_overrides=FAST_EM, asynchronous=True, commit_every_s=0)
    for k in range(150):
        engine.feed("m1", Sample(rec.time_s[k], rec.inputs[k], rec.outputs[k]))
    engine.poll_and_publish()
    while engine.sessions["m1"].stream.em_running:  # bounded: EM on 60 samples
        engine.sessions["m1"].stream._em_future.result(timeout=120)
        engine.poll_and_publish()
    committed = engine.sessions["m1"].stream.n_committed
    engine.shutdown()
    del engine  # "killed": the object is gone, only the database remains

    log = LiveLog(registry.path)
    sid = log.open_session_of("m1")["id"]
    assert log.n_steps(sid) == committed
    logged = log.states(sid)  # what the killed process committed
    engine = LiveEngine(registry, twin_overrides=FAST_EM, asynchronous=False, commit_every_s=0)
    published = []
    engine.subscribe(lambda m: published.append(m.to_dict()))
    stream = engine.open("m1")
    assert stream.n_committed == committed
    for k in range(100, len(rec)):  # a re-read from before the kill: old samples dropped
        engine.feed("m1", Sample(rec.time_s[k], rec.inputs[k], rec.outputs[k]))
    # while the session is open, the log holds every committed step (a kill now resumes)
    engine.flush()
    assert log.n_steps(sid) == stream.n_committed > committed
    assert log.states(sid)[:committed] == logged  # nothing committed changed
    print_id = engine.close("m1")
    assert log.open_session_of("m1") is None
    resumed = [m for m in published if "step" in m and not m["provisional"]]
    steps = [m["step"] for m in logged + resumed]
    assert steps == list(range(len(rec)))  # nothing lost, nothing twice
    run = Twin.default(**FAST_EM).run(rec)
    # the published float64 states, before and after the kill, are the batch twin's
    means = np.array([[m["states"][n] for n in STATE_NAMES] for m in logged + resumed])
    assert _relative(means, run.means) < 1e-9
    # closed with its print stored: the per-step rows are gone, the print holds them
    session = log.sessions("m1")[0]
    assert (session["status"], session["print_id"]) == ("closed", print_id)
    assert log.n_steps(sid) == 0 and log.states(sid) == []
    stored = registry.print_arrays(print_id)
    assert np.array_equal(stored["time_s"], rec.time_s)
    assert np.array_equal(stored["inputs"], rec.inputs)
    assert np.array_equal(stored["measurements"], rec.outputs, equal_nan=True)
    assert _relative(stored["means"], run.means) < 1e-6  # float32 by the storage policy
    assert registry.last_print("m1")["seq"] == 1


def test_follow_growing_csv(clog_record, tmp_path, caplog):
    import asyncio

    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS
    from ajtwin.live.link import follow_csv
    from ajtwin.store.live_log import LiveLog
    from ajtwin.store.registry import Registry

    rec = clog_record.window(0, 90)
    columns = ["time_s", *INPUT_COLUMNS, *OUTPUT_COLUMNS]
    rows = rec.data[columns].to_numpy(float)
    lines = [",".join(columns)] + [",".join(repr(float(v)) for v in row) for row in rows]
    lines[31] = lines[31].replace(lines[31].split(",")[6], "oops", 1)  # a garbled row
    path = tmp_path / "print.csv"
    path.write_text("\n".join(lines[:41]) + "\n" + lines[41][:10])  # a half-written line
    registry = Registry(tmp_path / "r.sqlite")
    engine = LiveEngine(registry, asynchronous=False, commit_every_s=0)
    published = []
    engine.subscribe(lambda m: published.append(m.to_dict()))

    async def main():
        async def grow():
            await asyncio.sleep(1.0)
            path.write_text("\n".join(lines) + "\n")

        writer = asyncio.create_task(grow())
        print_id = await asyncio.wait_for(
            follow_csv(path, "m1", engine, poll_s=0.1, idle_timeout_s=2.0), 120
        )
        await writer
        return print_id

    print_id = asyncio.run(main())
    arrays = registry.print_arrays(print_id)
    assert np.array_equal(arrays["time_s"], rec.time_s)
    session = max(LiveLog(registry.path).sessions("m1"), key=lambda r: r["id"])
    assert (session["status"], session["print_id"]) == ("closed", print_id)
    assert LiveLog(registry.path).n_steps(session["id"]) == 0  # the print holds them
    states = [m for m in published if "step" in m and not m["provisional"]]
    assert [m["step"] for m in states] == list(range(len(rec)))
    means = np.array([[m["states"][n] for n in STATE_NAMES] for m in states])
    y = rec.outputs.copy()
    u = rec.inputs.copy()
    y[30] = np.nan  # the garbled line: a missing sample (inputs held)
    u[30] = u[29]
    run = Twin.default().run(inputs=u, measurements=y, time_s=rec.time_s)
    assert _relative(means, run.means) < 1e-9
    assert "line 32: not numbers" in caplog.text


def test_live_cli_refuses_an_unknown_transition_variant(tmp_path):
    from click.testing import CliRunner

    from ajtwin.cli import main

    csv = tmp_path / "p.csv"
    csv.write_text("time_s\n")
    result = CliRunner().invoke(
        main,
        ["live", "--machine", "m", "--follow", str(csv), "--transition", "nope"]
        + ["--store", str(tmp_path / "s.sqlite")],
    )
    assert result.exit_code == 2
    assert "no transition variant 'nope'" in result.output and "input_following" in result.output


def test_machine_show_during_a_live_print_shows_the_live_twin_and_its_alarm(clog_record, tmp_path):
    from click.testing import CliRunner

    from ajtwin.cli import main
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.store.registry import Registry

    registry = Registry(tmp_path / "r.sqlite")
    registry.add_machine("m1")
    engine = LiveEngine(registry, twin_overrides=FAST_EM, asynchronous=False, commit_every_s=0)
    published = []
    engine.subscribe(lambda m: published.append(m.to_dict()))
    try:
        for k in range(300):  # the clog starts at 180 s; the print goes on
            engine.feed("m1", Sample(clog_record.time_s[k], clog_record.inputs[k],
                                     clog_record.outputs[k]))  # fmt: skip
        engine.flush()
        raised = [e for m in published for e in m.get("events", []) if e["state"] == "raised"]
        assert raised and raised[0]["cause"] == "nozzle_clog"
        out = CliRunner().invoke(main, ["machine", "show", "m1", "--store", str(registry.path)])
        assert out.exit_code == 0, out.output
        text = out.output
        assert "LIVE print since" in text and "300 samples" in text
        assert "the twin now (5.0 min into the print" in text  # 299 s: print time in minutes
        assert "alarms so far: 1" in text and "nozzle clog" in text
        assert f"alarm at {raised[0]['detected_s'] / 60:.1f} min" in text
        assert re.search(r"φ_A   = 0\.4\d* ± [0-9.]+ ppm", text)  # φ_A in a unit a person reads
        # no stored print yet: the live one is all there is
        assert "no print in the chain" in text
    finally:
        engine.shutdown()
    # after the print is stored, `machine show` shows the stored print and no live one
    engine = LiveEngine(registry, twin_overrides=FAST_EM, asynchronous=False, commit_every_s=0)
    engine.open("m1")
    engine.close("m1")
    out = CliRunner().invoke(main, ["machine", "show", "m1", "--store", str(registry.path)])
    assert "LIVE print" not in out.output and "last stored print: #1" in out.output
