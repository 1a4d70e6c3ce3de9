"""V_l: the twin's consider state and the vial observer."""

from __future__ import annotations

import tomllib
from importlib import resources

import numpy as np
import pytest

from ajtwin._jax import jnp
from ajtwin.estimation import Twin
from ajtwin.estimation.filters import ekf
from ajtwin.estimation.vial import (
    VialObserver,
    VialSettings,
    observe_vial,
    observer_model,
    vial_status,
)
from ajtwin.model import load_parameters
from ajtwin.model.atomizer import net_droplet_generation
from ajtwin.simulation import simulate

PARAMS = load_parameters()


def test_vial_toml_has_provenance_for_every_value():
    with (resources.files("ajtwin") / "data" / "vial.toml").open("rb") as fh:
        raw = tomllib.load(fh)
    for group in ("twin", "observer", "low"):
        for name, entry in raw[group].items():
            assert entry["provenance"].strip(), (group, name)
    settings = VialSettings.load()
    assert settings.vial_low_mL == raw["low"]["vial_low_mL"]["value"]


# --------------------------------------------------------------------------- #
# The twin's V_l as a consider state
# --------------------------------------------------------------------------- #


def test_consider_state_is_never_updated_and_its_variance_is_exact():
    rec = simulate("exp1", seed=2, duration_min=3.0)
    twin = Twin.default(em=False)
    assert twin.config.vial_consider
    init = twin.initial_state(rec.inputs, rec.outputs)
    f = ekf(
        twin.spec,
        init.mean,
        init.covariance,
        rec.inputs,
        rec.outputs,
        np.zeros(5),
        twin.process_cov,
        twin.measurement_var,
    )
    means, pred = np.asarray(f.means), np.asarray(f.predicted_means)
    covs, pred_cov = np.asarray(f.covariances), np.asarray(f.predicted_covariances)
    # the update leaves V_l's mean and variance as predicted ...
    np.testing.assert_array_equal(means[:, 1], pred[:, 1])
    np.testing.assert_allclose(covs[:, 1, 1], pred_cov[:, 1, 1], rtol=1e-12)
    # ... so no data narrow its band: P_VV stays at the fill's σ² (it moves only through
    # the drain's tiny dependence on φ_A and Σ_ξ, ~1e-10 of 9e-6 here)
    np.testing.assert_allclose(covs[:, 1, 1], init.covariance[1, 1], rtol=1e-3)
    # and its mean is the fill minus the modelled drain φ_A Q_c (Euler, θ = 0)
    drain = means[:-1, 4] * rec.inputs[:-1, 1] / 60.0
    np.testing.assert_allclose(np.diff(means[:, 1]), -drain, rtol=1e-9, atol=1e-15)
    # the other states' first update is the unmasked filter's (g does not depend on V_l)
    unmasked = ekf(
        twin.spec._replace(update_mask=None),
        init.mean,
        init.covariance,
        rec.inputs[:1],
        rec.outputs[:1],
        np.zeros(5),
        twin.process_cov,
        twin.measurement_var,
    )
    keep = [0, 2, 3, 4]
    np.testing.assert_allclose(
        np.asarray(unmasked.means)[0, keep], means[0, keep], rtol=1e-12, atol=1e-20
    )
    np.testing.assert_allclose(float(unmasked.nis[0]), float(f.nis[0]), rtol=1e-12)
    # covariances stay symmetric positive definite
    assert (np.linalg.eigvalsh(covs / np.sqrt(np.einsum("kii,kjj->kij", covs, covs))) > 0).all()


def test_twin_vial_band_holds_the_truth_when_the_atomizer_is_off_the_fit():
    """Generation 12 % below the fit: an updated V_l soaks it up, the consider state not."""
    overrides = {"truth": {"generation_offset_sd": 0.12, "generation_ou_sd": 0.0}}
    rec = simulate("exp1", seed=0, duration_min=12.0, overrides=overrides)
    assert rec.meta["truth_draws"]["generation_offset"] == pytest.approx(-0.1245, abs=1e-3)
    truth = rec.true_states[:, 1]
    run = Twin.default(window_s=300, every_s=150).run(rec)
    inside = np.abs(run.means[:, 1] - truth) <= 2 * run.stds[:, 1]
    assert inside.all()
    # the behaviour this replaces: V_l pulled outside its own ±2σ band (2.6σ in 12 min);
    # without the early EM (θ_φA learns the offset at 120 s and shields V_l from it)
    updated = Twin.default(window_s=300, every_s=150, vial_consider=False, early_em_s=()).run(rec)
    z_old = (updated.means[:, 1] - truth) / updated.stds[:, 1]
    assert np.max(np.abs(z_old)) > 2.0


@pytest.mark.parametrize("fill_error_sigma", [1.0, 3.0])
def test_twin_vial_band_is_the_fill_error_when_the_fill_is_not_the_told_one(fill_error_sigma):
    """Loaded δ off the told fill, the twin's V_l error stays δ and its σ the fill's:
    z = δ/σ_fill all print long, so across prints whose fills are drawn at σ_fill (the
    scenarios' `vial_weighing_sd_mL`) the band covers ~95 %
    (docs/explanation/vial-consider-state.md). Here δ is
    set by hand, so the scenario's own weighing error is switched off."""
    with (resources.files("ajtwin") / "data" / "noise.toml").open("rb") as fh:
        fill_std = tomllib.load(fh)["calibrated"]["initial"]["vial_fill_std_mL"]["value"]
    told = 1.0
    loaded = told - fill_error_sigma * fill_std
    rec = simulate(
        "exp1",
        seed=2,
        duration_min=10.0,
        overrides={"initial": {"vial_volume_mL": loaded}, "truth": {"vial_weighing_sd_mL": 0.0}},
    )
    run = Twin.default(window_s=300, every_s=150, vial_fill_ml=told).run(rec)
    z = (run.means[:, 1] - rec.true_states[:, 1]) / run.stds[:, 1]
    np.testing.assert_allclose(z, fill_error_sigma, atol=0.02)
    inside = np.abs(z) <= 2.0
    assert inside.all() if fill_error_sigma < 2 else not inside.any()


# --------------------------------------------------------------------------- #
# The vial observer
# --------------------------------------------------------------------------- #


def _steady_material_flow(vial_ml, u):
    h = float(net_droplet_generation(u[1], vial_ml, u[0], PARAMS.generation_fit))
    return PARAMS.silver_volume_fraction * h


def test_observer_holds_a_steady_vial_and_streaming_equals_batch():
    u = np.tile([375.0, 23.0, 50.0], (300, 1))
    rng = np.random.default_rng(0)
    q = _steady_material_flow(0.9, u[0]) * np.exp(0.17 * rng.standard_normal(300))
    q[::7] = np.nan  # missing samples: no update
    est = observe_vial(u, q, fill_ml=0.9, fill_std_ml=3e-3)
    assert abs(est.vial_ml[-1] - 0.9) < 0.01
    assert not est.running_low.any()
    live = VialObserver(fill_ml=0.9, fill_std_ml=3e-3)
    for k in range(300):
        status = live.update(u[k], q[k])
    assert status.vial_ml == pytest.approx(est.vial_ml[-1], rel=1e-10)
    assert status.vial_std_ml == pytest.approx(est.vial_std_ml[-1], rel=1e-8)
    assert np.isnan(est.normalised_innovations[::7]).all()
    assert not est.held.any()


def test_observer_status_by_hand():
    settings = VialSettings.load()
    model = observer_model(settings, PARAMS)
    u = np.array([375.0, 23.0, 50.0])
    cov = np.diag([1e-4, 0.01**2, 1e-4, 1e-4])
    mean = np.array([0.6, 0.2, 0.0, 0.0])  # 0.2 ± 0.01 mL/h: significant
    status = vial_status(mean, cov, u, model, settings)
    drain = float(net_droplet_generation(23.0, 0.6, 375.0, PARAMS.generation_fit)) * 3600.0
    assert status.drain_ml_per_h == pytest.approx(drain)
    assert status.minutes_to_low == pytest.approx(60.0 * 0.1 / (0.2 + drain))
    assert status.running_low  # 30 min to 0.5 mL is under the 30-min horizon? 29.9 min
    slow = vial_status(np.array([0.6, 0.02, 0.0, 0.0]), cov, u, model, settings)
    assert not slow.running_low and slow.minutes_to_low > settings.horizon_min
    noisy = vial_status(mean, np.diag([1e-4, 0.1**2, 1e-4, 1e-4]), u, model, settings)
    assert not noisy.running_low  # 0.2 ± 0.1 mL/h is not significant (z 2 < 3)
    below = vial_status(np.array([0.45, 0.0, 0.0, 0.0]), cov, u, model, settings)
    assert below.running_low and below.minutes_to_low == 0.0


def test_observer_rejects_bad_fill_and_gain():
    u = np.tile([375.0, 23.0, 50.0], (3, 1))
    q = np.full(3, 1e-8)
    for fill in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="vial fill"):
            observe_vial(u, q, fill_ml=fill)
    with pytest.raises(ValueError, match="material_flow_gain"):
        observe_vial(u, q, material_flow_gain=0.0)
    with pytest.raises(ValueError, match="inputs"):
        observe_vial(u[:, :2], q)


def test_observer_tells_a_falling_vial_from_a_failing_atomizer():
    """Known truth from the virtual printer: the vial evaporating vs a 5-min dropout."""
    low = simulate("ink_running_low", seed=3)
    truth = low.true_states[:, 1]
    est = observe_vial(low.inputs, low.outputs[:, 4], fill_ml=truth[0], fill_std_ml=3e-3)
    z = (est.vial_ml - truth) / est.vial_std_ml
    assert np.mean(np.abs(z) <= 2) > 0.9
    # worst 10.0 % (seed 3), mid-print while the loss rate is being learnt; 2 % at the end
    assert np.max(np.abs(est.vial_ml - truth) / truth) < 0.12
    assert abs(est.vial_ml[-1] - truth[-1]) / truth[-1] < 0.05
    t_low = est.first_running_low_s(low.time_s)
    t_truth = float(low.time_s[np.argmax(truth < 0.5)])
    assert np.isfinite(t_low) and t_low < t_truth  # flagged before the truth crosses 0.5 mL
    assert est.loss_rate_ml_per_h[-1] > 0.1  # the evaporation, 0.15 mL/h
    assert (np.diff(est.running_low.astype(int)) >= 0).all()  # latched: no flicker

    drop = simulate("atomizer_dropout", seed=3)
    est = observe_vial(drop.inputs, drop.outputs[:, 4], fill_ml=1.0, fill_std_ml=3e-3)
    assert not est.running_low.any()
    assert np.max(np.abs(est.vial_ml - drop.true_states[:, 1])) < 0.1
    onset = int(drop.meta["fault_onset_s"])
    # the step holds the observer for the dropout (generation at 40 % for 5 min) and
    # releases it after: the vial does not take the drop
    assert est.held[onset + 10 : onset + 290].mean() > 0.95
    assert not est.held[: onset - 1].any() and not est.held[onset + 400 :].any()
    assert abs(est.vial_ml[onset + 400] - est.vial_ml[onset - 60]) < 0.02


def test_observer_uses_the_calibrations_material_flow_gain():
    u = np.tile([375.0, 23.0, 50.0], (200, 1))
    q = np.full(200, _steady_material_flow(1.0, u[0]) * 1.3)  # a gauge reading 30 % high
    est = observe_vial(u, q, fill_ml=1.0, material_flow_gain=1.3)
    assert est.efficiency[-1] == pytest.approx(1.0, abs=0.02)
    assert jnp.isfinite(est.vial_ml).all()


# --------------------------------------------------------------------------- #
# The detectors: 'V_l low' and the ink_low label from the observer
# --------------------------------------------------------------------------- #


def test_label_cause_defers_to_the_vial_observer():
    from ajtwin.apps.detection.causes import label_cause
    from ajtwin.apps.detection.settings import DetectorSettings

    s = DetectorSettings()
    qm_deficit = ([-1, 0, 0, 0, -2], [60] * 5, [0, 0, 0, 0, -4])
    assert label_cause(*qm_deficit, 1.0, s) == "atomizer"
    assert label_cause(*qm_deficit, 1.0, s, True) == "ink_low"
    # the twin's V_l is a consider state: with an observer it no longer decides
    assert label_cause(*qm_deficit, 0.3, s, False) == "atomizer"
    assert label_cause(*qm_deficit, 0.3, s) == "ink_low"


def _detector_arrays(vial_truth, n):
    """A print the twin explains perfectly (e = 0) but whose Q_m follows a vial V(t)."""
    u = np.tile([375.0, 23.0, 50.0], (n, 1))
    h = np.array(
        [float(net_droplet_generation(23.0, v, 375.0, PARAMS.generation_fit)) for v in vial_truth]
    )
    y = np.tile([45.0, 30.0, 5661.0, 5641.0, 0.0], (n, 1))
    y[:, 4] = PARAMS.silver_volume_fraction * h
    means = np.tile([3.5, vial_truth[0], 0.0, 0.03, 4.6e-7], (n, 1))
    cov = np.tile(np.diag([1e-2, 9e-6, 1e-6, 1e-4, 1e-16]), (n, 1, 1))
    return dict(
        time_s=np.arange(n, dtype=float),
        measurements=y,
        predicted_outputs=y.copy(),
        innovation_variances=np.tile([4.0, 9.0, 36.0, 36.0, (0.17 * y[0, 4]) ** 2], (n, 1)),
        nis=np.zeros(n),
        n_measured=np.full(n, 5.0),
        means=means,
        predicted_means=means.copy(),
        covariances=cov,
        inputs=u,
    )


def test_detectors_raise_vial_low_from_the_observer_and_label_it():
    from ajtwin.apps.detection.batch import detect_anomalies

    n = 5400
    falling = 0.7 - 0.25 * np.arange(n) / n  # 0.70 → 0.45 mL in 90 min (0.17 mL/h)
    result = detect_anomalies(**_detector_arrays(falling, n))
    assert len(result.events) == 1
    event = result.events[0]
    assert event.cause == "ink_low" and event.detectors == ["V_l low"]
    assert event.evidence["vial_observer_running_low"]
    # raised before the vial reaches 0.5 mL (the horizon: 30 min at the learnt loss)
    assert event.detected_s < float(np.argmax(falling < 0.5))
    steady = detect_anomalies(**_detector_arrays(np.full(n, 0.7), n))
    assert steady.events == []
    # without the inputs (an old stored print) the twin's V_l decides, as before
    old = _detector_arrays(falling, n)
    old.pop("inputs")
    assert detect_anomalies(**old).events == []


def test_twin_run_carries_the_observer_and_writes_its_columns():
    rec = simulate("exp1", seed=1, duration_min=3.0)
    run = Twin.default(em=False).run(rec)
    direct = observe_vial(rec.inputs, rec.outputs[:, 4], 1.0, 3e-3)
    np.testing.assert_allclose(run.vial.vial_ml, direct.vial_ml, rtol=1e-12)
    frame = run.to_frame()
    np.testing.assert_allclose(frame["vial_observed_mL"], direct.vial_ml, rtol=1e-12)
    assert not frame["vial_running_low"].any()
    no_qm = rec.outputs.copy()
    no_qm[:, 4] = np.nan
    bare = Twin.default(em=False).run(inputs=rec.inputs, measurements=no_qm)
    assert bare.vial is None and "vial_observed_mL" not in bare.to_frame()
