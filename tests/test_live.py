"""The live twin: streaming engine ≡ batch twin + detectors; sample-order handling."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin.apps.anomaly import detect_run
from ajtwin.estimation import Twin
from ajtwin.live.engine import Sample, TwinStream, clean_sample
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
def test_stream_equals_batch(clog_record, asynchronous):
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
    steps = [m["step"] for m in messages if "step" in m and not m["provisional"]]
    assert steps == list(range(len(rec)))
    if asynchronous:
        raised = [e for m in messages for e in m.get("events", []) if e["state"] == "raised"]
        assert raised and raised[0]["detected_s"] == detection.events[0].detected_s


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
    assert stream.dropped == {"duplicate": 1, "out_of_order": 1, "bad": 0}
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
