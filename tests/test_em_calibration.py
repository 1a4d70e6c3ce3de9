"""online EM of the line offsets and output noise — never the pressures."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin._jax import jnp
from ajtwin.estimation.em_calibration import output_m_step
from ajtwin.estimation.filters import AJ_EULER, DEFAULT_SCALING, ModelSpec, SmootherResult
from ajtwin.model import DigitalModel, output_function
from ajtwin.model.calibration import CalibratedCoefficients, Calibration


def test_m_step_learns_a_line_offset_step_and_the_noise_but_not_the_pressures():
    model = DigitalModel.default()
    rng = np.random.default_rng(3)
    n = 600
    x = np.tile([3.5, 1.0, 0.0, 0.02, 4.6e-7], (n, 1))
    x[:, 0] += 0.05 * np.sin(np.arange(n) / 50)
    u = np.tile([375.0, 23.0, 50.0], (n, 1))
    commissioned = Calibration(linewidth_offset_um=-30.0, carrier_gauge_offset_Pa=20.0)
    line = jnp.asarray(model.coefficient_matrix)
    spec = ModelSpec(model.params, CalibratedCoefficients(line, commissioned), DEFAULT_SCALING)
    y = np.asarray(output_function(x, u, model.params, spec.coefficients))
    noise_std = np.array([2.0, 3.0, 6.0, 6.0, 1e-9])
    y = y + rng.standard_normal((n, 5)) * noise_std
    y[:, 0] += 4.0  # the camera refocused: L_w reads 4 µm more than at commissioning
    y[:, 2:4] += 50.0  # the pressures rose (a deposit? a gauge?) — must not be learned
    # E-step stand-in: the smoothed states are the truth, known exactly
    smoothed = SmootherResult(jnp.asarray(x), jnp.zeros((n, 5, 5)), jnp.zeros((n - 1, 5, 5)))
    tuned = noise_std**2
    cal, var = output_m_step(
        spec, smoothed, u, y, tuned, commissioned, functions=AJ_EULER, tuned_var=tuned
    )
    # MAP by hand: prior N(−30, 5²), n samples of σ 2 µm with mean −30 + 4 + ε
    mean_shift = np.mean(
        y[:, 0] - np.asarray(output_function(x, u, model.params, spec.coefficients))[:, 0]
    )
    expected = (-30.0 / 25.0 + n * (-30.0 + mean_shift) / 4.0) / (1 / 25.0 + n / 4.0)
    assert cal.linewidth_offset_um == pytest.approx(expected, rel=1e-9)
    assert cal.linewidth_offset_um == pytest.approx(-26.0, abs=0.3)
    assert cal.overspray_offset_um == pytest.approx(0.0, abs=0.5)
    # the pressures and every gain stay as commissioned (model reference §11)
    for name in (
        "carrier_gauge_offset_Pa",
        "sheath_gauge_offset_Pa",
        "carrier_gauge_gain",
        "carrier_line_factor",
        "linewidth_gain",
        "material_flow_gain",
    ):
        assert getattr(cal, name) == getattr(commissioned, name)
    # noise: L_w and L_o variances recovered; the pressures' noise is not learned online
    assert np.sqrt(var[0]) == pytest.approx(2.0, rel=0.1)
    assert np.sqrt(var[1]) == pytest.approx(3.0, rel=0.1)
    assert var[2] == tuned[2] and var[3] == tuned[3]


def test_online_em_keeps_a_clog_a_clog():
    from ajtwin.apps.detection.batch import detect_run
    from ajtwin.estimation.twin import Twin
    from ajtwin.simulation.printer import simulate

    record = simulate(
        "nozzle_clog", seed=31, duration_min=12.0, overrides={"fault": {"onset_min": 5.0}}
    )
    onset = record.meta["fault_onset_s"]
    events = {}
    for learn in (False, True):
        twin = Twin.default(
            calibration=Calibration.identity(),
            learn_line_offsets=learn,
            learn_output_noise=learn,
            every_s=120,
            window_s=240,
        )
        run = twin.run(record)
        events[learn] = [(e.cause, e.detected_s) for e in detect_run(run, record).events]
        if learn:
            assert {"linewidth_offset_um", "noise_std_linewidth_um"} <= set(run.theta_history)
            # nothing about the pressures was learned (model reference §11)
            for name in ("carrier_gauge_offset_Pa", "sheath_gauge_offset_Pa"):
                assert getattr(twin.calibration, name) == 0.0
            assert np.array_equal(twin.measurement_var[2:4], twin.measurement_std[2:4] ** 2)
            truth = record.true_states[-1, 3]
            assert abs(run.means[-1, 3] - truth) < 0.3 * truth  # the deposit is in ΔR_N
    clogs = [t for cause, t in events[True] if cause == "nozzle_clog" and t >= onset]
    assert clogs and clogs[0] - onset <= 60.0, events
    assert events[True] == events[False]  # learning the line side changed no alarm
