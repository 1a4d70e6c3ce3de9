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
    assert "linewidth_um" in r.evidence and r.sentence().startswith("ready at")


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
