"""Ready to print: the settling detector on known signals and on a virtual start-up."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin.apps.detection.settling import (
    SettlingDetector,
    SettlingSettings,
    rolling_trends,
    settling_time,
)
from ajtwin.simulation.printer import run_virtual_print
from ajtwin.simulation.stepper import SteppedPrinter


def _settling(n=1500, tau=150.0, amplitude=8.0, noise=0.0, seed=0):
    t = np.arange(float(n))
    rng = np.random.default_rng(seed)
    line = 40.0 + amplitude * (1 - np.exp(-t / tau)) + noise * rng.standard_normal(n)
    means = np.column_stack(
        [
            np.full(n, 3.5),
            np.ones(n),
            np.zeros(n),
            np.zeros(n),
            4.6e-7 * (1 - 0.5 * np.exp(-t / tau)),
        ]
    )
    outputs = np.column_stack([line, line / 5, np.zeros(n), np.zeros(n), np.zeros(n)])
    return t, means, outputs


def test_rolling_trend_of_a_line_is_its_slope():
    t = np.arange(50.0)
    y = np.column_stack([3.0 * t + 1.0, -0.5 * t])
    trends = rolling_trends(t, y, 10)
    assert np.isnan(trends[:9]).all()
    np.testing.assert_allclose(trends[9:], [[3.0, -0.5]] * 41)


def test_ready_once_the_change_to_come_is_within_tolerance_and_not_before():
    t, means, outputs = _settling()
    s = SettlingSettings.load()
    r = settling_time(t, means, outputs, s)
    assert r.ready
    # by then the line's slope times the horizon is within the tolerance ...
    k = int(r.ready_at_s)
    slope = 8.0 / 150.0 * np.exp(-(k - s.window_s / 2) / 150.0)
    assert slope * s.horizon_s <= s.tolerances[0] * 1.2
    # ... and the change still to come is below the tolerance
    assert 8.0 * np.exp(-k / 150.0) <= s.tolerances[0]
    assert "linewidth_um" in r.evidence and r.sentence().startswith("ready to print from")


def test_a_line_still_ramping_is_never_ready():
    t = np.arange(1200.0)
    means = np.column_stack(
        [np.full(1200, 3.5), np.ones(1200), np.zeros((1200, 2)), np.full(1200, 4e-7)]
    )
    outputs = np.column_stack([40 + 0.02 * t, np.full(1200, 8.0), np.zeros((1200, 3))])
    r = settling_time(t, means, outputs)
    assert not r.ready and "not settled" in r.sentence()


@pytest.mark.parametrize("chunk", [1, 37, 600])
def test_fed_a_chunk_at_a_time_it_answers_as_on_the_whole_run(chunk):
    t, means, outputs = _settling(noise=0.3, seed=3)
    whole = settling_time(t, means, outputs)
    detector = SettlingDetector()
    for k in range(0, len(t), chunk):
        detector.update(t[k : k + chunk], means[k : k + chunk], outputs[k : k + chunk])
    assert detector.readiness.ready_at_s == whole.ready_at_s
    assert detector.status()["ready"] is True


def test_startup_scenario_settles_and_is_off_by_default():
    off = run_virtual_print("exp1", seed=4, duration_min=20.0)
    on = run_virtual_print("startup", seed=4, duration_min=20.0)
    assert "startup_settling_s" not in off.processes.draws
    settle = on.processes.draws["startup_settling_s"]
    assert 300.0 <= settle <= 900.0
    gen_on, gen_off = on.processes.drivers[:, 0], off.processes.drivers[:, 0]
    ratio = gen_on / gen_off
    assert ratio[0] < 0.65 and abs(ratio[int(settle)] - 0.98) < 1e-4 and ratio[-1] > 0.999
    # the stepped printer draws the same start-up (one implementation)
    stepped = SteppedPrinter("startup", seed=4, duration_min=20.0)
    stepped.advance(1200)
    np.testing.assert_allclose(stepped.true_states, on.states, rtol=1e-12)


def test_the_live_stream_says_ready_to_print_once_settled_and_again_after_an_atomizer_restart():
    """A virtual start-up (the atomizer's run-in) followed live: the committed steps carry
    the verdict — not ready during the run-in, ready once the line has settled, not ready
    while the atomizer is stopped (I_A 0 for 30 s at 10 min) nor after it starts again —
    and the console and the dashboard's samples say it in the words of ``ajtwin
    estimate``."""
    from ajtwin.cli.live import ConsoleReadiness
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.estimation.samples import Sample
    from ajtwin.simulation import simulate
    from ajtwin.web.publisher import LivePublisher

    record = simulate("startup", seed=4, duration_min=14.0)
    inputs = record.inputs.copy()
    inputs[600:630, 0] = 0.0  # the operator stops the atomizer for 30 s
    engine = LiveEngine(None, asynchronous=False)
    messages, lines, publisher = [], [], LivePublisher()
    engine.subscribe(messages.append)
    engine.subscribe(ConsoleReadiness(lines.append))
    engine.subscribe(publisher.publish_engine)
    for t, u, y in zip(record.time_s, inputs, record.outputs):
        engine.feed("m1", Sample(t, u, y))
    engine.close("m1")
    steps = [m for m in messages if getattr(m, "settling", None) and not m.provisional]
    assert [m.time_s for m in steps] == list(record.time_s)
    ready = np.array([m.settling["ready"] for m in steps])
    first = int(np.argmax(ready))
    # not ready through the run-in's first minutes (the window alone is 2 min) ...
    assert not ready[:150].any() and 150 <= first < 600
    # ... ready from the second it says, until the atomizer stops ...
    assert steps[first].settling["ready_at_s"] == steps[first].time_s
    assert ready[first:600].all() and not ready[600:630].any()
    assert steps[610].settling["text"] == "the atomizer is off (below 50 mA): not ready to print"
    # ... and, started again, not ready until the new run-in's window is full
    assert [m.settling["restarts"] for m in steps[629:631]] == [0, 1]
    assert not ready[630 : 630 + 150].any()
    text = steps[first].settling["text"]
    assert text.startswith(f"ready to print from {steps[first].time_s / 60:.1f} min: linewidth ")
    assert lines == [
        "m1: start-up at 0.0 min — waiting for the line to settle",
        f"m1: {text}",
        "m1 at 10.0 min: the atomizer is off (below 50 mA): not ready to print",
        "m1: the atomizer started again at 10.5 min: not ready to print until the line settles",
    ] + [line for line in lines[4:] if line.startswith("m1: ready to print from ")]
    # the dashboard's samples carry it (its "ready to print" card)
    samples = publisher.snapshot("m1")
    assert samples[first]["settling"] == {
        "ready": True,
        "ready_at_s": steps[first].time_s,
        "text": text,
    }
    assert samples[615]["settling"]["ready"] is False
