"""Anomaly detectors, forecast and advice (ajtwin.apps)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import stats

from ajtwin.apps.detection.batch import detect_anomalies
from ajtwin.apps.detection.causes import label_cause
from ajtwin.apps.detection.settings import DetectorSettings
from ajtwin.apps.detection.statistics import (
    cusum,
    nis_tail_probability,
    normalised_innovations,
    windowed_nis,
)
from ajtwin.apps.planning.forecast import (
    Change,
    forecast,
    input_schedule,
    parse_change,
    parse_duration,
)
from ajtwin.studies.detection import detection_delay

# --------------------------------------------------------------------------- detectors


def test_cusum_hand_computed():
    e = np.array([0.0, 2.0, 2.0, -1.0, 3.0, 0.0])
    g_pos, g_neg, alarms = cusum(e, drift=0.5, threshold=4.0)
    # g+: 0, 1.5, 3.0, 1.5, 4.0 (not > 4), 3.5
    assert np.allclose(g_pos[:, 0], [0, 1.5, 3.0, 1.5, 4.0, 3.5])
    # g−: 0, 0, 0, 0.5, 0, 0
    assert np.allclose(g_neg[:, 0], [0, 0, 0, 0.5, 0, 0])
    assert alarms == []
    _, _, alarms = cusum(e, drift=0.5, threshold=3.9)
    assert [(a.step, a.change_step, a.direction) for a in alarms] == [(4, 0, 1)]


def test_cusum_nan_leaves_state_and_restarts_after_alarm():
    e = np.array([[2.0], [np.nan], [2.0], [2.0], [2.0]])
    g_pos, _, alarms = cusum(e, drift=0.0, threshold=3.0)
    assert np.allclose(g_pos[:, 0], [2, 2, 0, 2, 0])  # alarm at 2 and 4, reset to 0
    assert [a.step for a in alarms] == [2, 4]


def test_cusum_delay_matches_theory():
    """A bias b: the alarm comes after ≈ h / (b − k) steps (noise-free)."""
    e = np.zeros((400, 1))
    e[100:] = 1.0
    _, _, alarms = cusum(e, drift=0.35, threshold=16.0)
    assert alarms[0].step - 99 == int(np.floor(16.0 / 0.65)) + 1
    assert alarms[0].change_step == 99


def test_nis_tail_and_window_against_scipy():
    rng = np.random.default_rng(0)
    nis = rng.chisquare(3, size=50)
    n = np.full(50, 3)
    assert np.allclose(nis_tail_probability(nis, n), stats.chi2.sf(nis, 3))
    assert nis_tail_probability([5.0], [0])[0] == 1.0
    total, dof, p = windowed_nis(nis, n, 10)
    assert np.isclose(total[20], nis[11:21].sum())
    assert dof[20] == 30 and dof[3] == 12
    assert np.isclose(p[20], stats.chi2.sf(nis[11:21].sum(), 30))


def test_normalised_innovations():
    e = normalised_innovations([[3.0, np.nan]], [[1.0, 1.0]], [[4.0, 1.0]])
    assert e[0, 0] == 1.0 and np.isnan(e[0, 1])


@pytest.mark.parametrize(
    ("mean", "shift", "vial", "expected"),
    [
        ([0.5, 0.5, 1.0, 1.0, 0.1], [0, 0, 0, 30, 2], 1.0, "nozzle_clog"),
        ([0.0, 0.0, -1.7, -1.5, -0.8], [0, 0, 0, -100, -14], 1.0, "carrier_leak"),
        ([0.0, 0.0, -0.5, 0.5, 0.1], [0, 0, 0, 0, 3], 1.0, "carrier_leak"),  # sensor drift
        ([0.0, 0.0, 0.8, 0.0, 0.0], [0, 0, 0, 0, 0], 1.0, "carrier_leak"),  # P_c alone
        ([-1.3, -0.7, 0.0, 0.0, -2.9], [16, -5, 0, 1, -79], 1.0, "atomizer"),
        ([0.0, 0.0, 0.0, 0.0, 0.0], [0, 0, 0, 0, 0], 0.45, "ink_low"),
        ([0.0, 0.0, 0.0, 0.0, 0.0], [0, 0, 0, 0, 0], 1.0, "unexplained"),
    ],
)
def test_label_rules(mean, shift, vial, expected):
    assert label_cause(mean, [120] * 5, shift, vial, DetectorSettings()) == expected


def _synthetic(bias_from=None, bias=(0, 0, 0, 0, 0), n=3000, seed=0):
    rng = np.random.default_rng(seed)
    s = np.array([3.0, 5.0, 10.0, 10.0, 3e-9])
    y_hat = np.tile([43.0, 29.0, 5661.0, 5641.0, 1.5e-8], (n, 1))
    y = y_hat + rng.normal(size=(n, 5)) * s
    if bias_from is not None:
        y[bias_from:] += np.asarray(bias) * s
    means = np.tile([3.5, 1.0, 0.0, 0.03, 4.6e-7], (n, 1))
    cov = np.tile(np.diag([0.01, 1e-6, 1e-6, 1e-4, 1e-16]), (n, 1, 1))
    e = (y - y_hat) / s
    return dict(
        time_s=np.arange(n, dtype=float),
        measurements=y,
        predicted_outputs=y_hat,
        innovation_variances=np.tile(s**2, (n, 1)),
        nis=(e**2).sum(axis=1),
        n_measured=np.full(n, 5),
        means=means,
        predicted_means=means,
        covariances=cov,
    )


def test_detect_white_noise_no_alarm_and_pressure_step_is_clog():
    clean = detect_anomalies(**_synthetic(seed=1))
    assert clean.events == []
    data = _synthetic(bias_from=2000, bias=(0.5, 0.5, 1.0, 1.0, 0.0), seed=2)
    data["predicted_means"] = data["means"].copy()
    data["predicted_means"][2000:, 3] -= 1e-3  # the filter keeps pushing ΔR_N up
    result = detect_anomalies(**data)
    assert len(result.events) == 1
    ev = result.events[0]
    assert ev.cause == "nozzle_clog"
    assert 2000 < ev.detected_s < 2000 + 16 / 0.65 + 20
    assert 1980 <= ev.onset_s <= ev.detected_s
    d = detection_delay(result, 2000.0)
    assert d["delay_s"] == ev.detected_s - 2000 and d["false_alarms"] == 0
    assert np.isnan(detection_delay(clean, 2000.0)["delay_s"])


def test_one_gauge_wandering_needs_more_evidence_than_both_moving_together():
    """P_c and P_s on their own have a higher CUSUM threshold (24 σ, detectors.toml) than
    their common mode (16 σ): a gauge's slow noise moves one pressure for a minute or so
    (the commonest false alarm on held-out alt machines), a clog moves both. Noise-free
    innovations, so the CUSUMs are hand-computable: +0.7 σ for 60 s gives g = (0.7 − 0.35)
    · 60 = 21 on one gauge (< 24, > 16), and (1.4 − 0.7) · t on the common mode."""
    from dataclasses import replace

    def run(bias, settings=None):
        data = _synthetic(n=600)
        data["measurements"] = data["predicted_outputs"].copy()
        s = np.sqrt(data["innovation_variances"][0])
        data["measurements"][300:360] += np.asarray(bias) * s
        data["nis"] = np.zeros(600)
        return detect_anomalies(**data, settings=settings)

    one_gauge = (0.0, 0.0, 0.7, 0.0, 0.0)
    assert DetectorSettings().cusum_threshold_pressure == 24.0
    assert run(one_gauge).events == []
    at_16 = run(one_gauge, replace(DetectorSettings(), cusum_threshold_pressure=16.0))
    assert [ev.detectors[0] for ev in at_16.events] == ["cusum+ P_c"]
    assert at_16.events[0].detected_s == pytest.approx(300 + 16 / 0.35, abs=1.5)
    both = run((0.0, 0.0, 0.7, 0.7, 0.0))
    assert [ev.detectors[0] for ev in both.events] == ["cusum+ P_c+P_s"]
    assert both.events[0].detected_s == pytest.approx(300 + 16 / 0.7, abs=1.5)


def test_deposit_push_catches_a_clog_the_pressures_hide():
    """The filter's push on ΔR_N, Σ (x̂_k − x̂_{k|k−1}) over 300 s, above 8 nm raises one
    alarm (detectors.toml [deposit]), with the change point where the push began, even
    when no innovation moves: hand-computable on noise-free arrays. 0.045 nm per step from
    step 1000 crosses 8 nm at its 178th step; 0.02 nm per step tops out at 6 nm; a push
    downwards (a leak lowers the pressures) is not a deposit."""

    def run(push_nm_per_step):
        data = _synthetic(n=2000)
        data["measurements"] = data["predicted_outputs"].copy()
        data["nis"] = np.zeros(2000)
        data["predicted_means"] = data["means"].copy()
        data["predicted_means"][1000:, 3] -= push_nm_per_step * 1e-3
        return detect_anomalies(**data)

    s = DetectorSettings()
    assert (s.deposit_window_s, s.deposit_push_nm) == (300, 8.0)
    result = run(0.045)
    assert [ev.detectors for ev in result.events] == [["deposit push ΔR_N"]]
    assert result.events[0].detected_s == 1000 + 177
    assert result.events[0].onset_s == 1000
    assert run(0.02).events == []
    assert run(-0.5).events == []


def test_real_nozzle_clog_detected_quickly():
    """Virtual printer + default twin: a clog from 5 min is caught within 2 min, as a clog."""
    from ajtwin.apps.detection.batch import detect_run
    from ajtwin.estimation import Twin
    from ajtwin.simulation import simulate

    rec = simulate("nozzle_clog", seed=0, duration_min=10, overrides={"fault": {"onset_min": 5}})
    run = Twin.default().run(rec)
    result = detect_run(run, rec)
    d = detection_delay(result, rec.meta["fault_onset_s"])
    assert d["false_alarms"] == 0
    assert d["delay_s"] <= 120
    assert d["cause"] == "nozzle_clog"


# --------------------------------------------------------------------------- forecast


def test_parsers():
    assert parse_change("carrier_flow_sccm=26@+60s") == Change(60.0, 1, 26.0)
    assert parse_change("I_A=400@+2min") == Change(120.0, 0, 400.0)
    assert parse_change("sheath=48") == Change(0.0, 2, 48.0)
    assert parse_duration("1.5h") == 5400.0
    with pytest.raises(ValueError, match="unknown input 'flow'"):
        parse_change("flow=3@+1s")
    with pytest.raises(ValueError, match="cannot read the duration"):
        parse_duration("10 parsecs")
    with pytest.raises(ValueError, match="after the horizon"):
        input_schedule([375, 23, 50], [Change(100.0, 1, 26.0)], 50)
    with pytest.raises(ValueError, match="outside the allowed range"):
        input_schedule([375, 23, 50], [Change(1.0, 1, -5.0)], 50)


@pytest.fixture(scope="module")
def twin_and_state():
    from ajtwin.estimation import Twin

    # the paper's droplet row: its forecasts are checked against the model's own open loop
    # (DigitalModel.simulate); the input-following row's in test_droplet_dynamics
    twin = Twin.default(transition="paper")
    phi = float(twin.model.steady_aerosol_fraction(np.array([375.0, 23.0, 50.0]), 1.0))
    mean = np.array([3.5, 1.0, 1e-4, 0.05, phi])
    cov = np.diag([0.05, 1e-4, 1e-8, 1e-4, (0.05 * phi) ** 2])
    return twin, mean, cov


def test_forecast_mean_is_the_open_loop_model(twin_and_state):
    twin, mean, cov = twin_and_state
    theta = np.array([0.0, 0.0, 0.0, 1e-4, -1e-5])
    u = input_schedule([375, 23, 50], [parse_change("Q_c=26@+30s")], 120)
    fc = forecast(twin, mean, cov, u, theta)
    states = twin.model.simulate(mean, u, theta)  # independent: DigitalModel lax.scan
    assert np.allclose(fc.state_means, states[1:], rtol=1e-10, atol=1e-18)
    y = np.array([twin.model.outputs(states[k + 1], u[k]) for k in (0, 59, 119)])
    assert np.allclose(fc.output_means[[0, 59, 119]], y, rtol=1e-10)


def test_forecast_covariance_matches_monte_carlo(twin_and_state):
    """No process noise: the propagated σ of L_w, P_c ≈ the spread of sampled runs."""
    from ajtwin.estimation import Twin

    _, mean, cov = twin_and_state
    quiet = Twin.default(process_std=(0.0,) * 5, transition="paper")  # as the Monte Carlo
    u = np.tile([375.0, 23.0, 50.0], (60, 1))
    fc = forecast(quiet, mean, cov / 100, u, aerosol_wander_per_sqrt_h=0.0)
    rng = np.random.default_rng(0)
    samples = rng.multivariate_normal(mean, cov / 100, size=400)
    samples[:, 2:4] = np.abs(samples[:, 2:4])
    ys = np.array([quiet.model.outputs(quiet.model.simulate(x, u)[-1], u[-1]) for x in samples])
    mc = ys.std(axis=0)
    assert np.allclose(fc.output_stds[-1, :4], mc[:4], rtol=0.15)
    # with process noise the band only widens
    wide = forecast(twin_and_state[0], mean, cov / 100, u, aerosol_wander_per_sqrt_h=0.0)
    assert np.all(wide.output_stds[-1, :4] >= fc.output_stds[-1, :4])


def test_forecast_aerosol_level_walk_matches_monte_carlo(twin_and_state):
    """θ_φA a random walk over the horizon: the forecast's σ of φ_A, L_o and Q_m ≈ the
    spread of runs whose θ_φA walks with the same per-step variance; the relative σ of the
    steady φ_A grows as w·√(t/h); a vanishing wander gives the plain forecast."""
    from ajtwin._jax import jax, jnp
    from ajtwin.apps.planning.forecast import aerosol_level_variance
    from ajtwin.estimation import Twin
    from ajtwin.model.system import euler_step

    _, mean, _ = twin_and_state
    quiet = Twin.default(process_std=(0.0,) * 5, transition="paper")  # as the Monte Carlo
    tiny = np.diag([1e-6, 1e-8, 1e-12, 1e-10, (1e-6 * mean[4]) ** 2])
    n_steps, wander = 1800, 0.2
    u = np.tile([375.0, 23.0, 50.0], (n_steps, 1))
    fc = forecast(quiet, mean, tiny, u, aerosol_wander_per_sqrt_h=wander)
    q = aerosol_level_variance(quiet, mean, u[0], wander)
    # hand value: Q_c 23 sccm = 0.383 mL/s, head space V_v − V_l, per 3600 steps
    from ajtwin import units

    headspace = float(units.m3_to_ml(quiet.spec.params.vial_volume)) - mean[1]
    assert q == pytest.approx((wander * 23.0 / 60.0 / headspace) ** 2 / 3600.0, rel=1e-9)
    rng = np.random.default_rng(1)
    walks = np.concatenate(
        [np.zeros((400, 1)), np.cumsum(rng.normal(0, np.sqrt(q), (400, n_steps - 1)), axis=1)], 1
    )
    params = quiet.spec.params

    def run(theta_aerosol):
        def body(x, step_input):
            uk, th = step_input
            theta = jnp.zeros(5).at[4].set(th)
            x = euler_step(x, uk, theta, params, 1.0)
            return x, x

        return jax.lax.scan(body, jnp.asarray(mean), (jnp.asarray(u), theta_aerosol))[1][-1]

    ends = np.asarray(jax.jit(jax.vmap(run))(jnp.asarray(walks)))
    ys = np.array([quiet.model.outputs(x, u[-1]) for x in ends])
    assert fc.state_stds[-1, 4] == pytest.approx(ends[:, 4].std(), rel=0.12)
    assert np.allclose(fc.output_stds[-1, [1, 4]], ys[:, [1, 4]].std(axis=0), rtol=0.12)
    # the steady level's relative σ after 30 min: w √(0.5 h), to first order
    assert fc.state_stds[-1, 4] / fc.state_means[-1, 4] == pytest.approx(wander * 0.5**0.5, rel=0.1)
    plain = forecast(quiet, mean, tiny, u, aerosol_wander_per_sqrt_h=0.0)
    barely = forecast(quiet, mean, tiny, u, aerosol_wander_per_sqrt_h=1e-9)
    assert np.allclose(barely.state_stds, plain.state_stds, rtol=1e-9, atol=0)
    # the walk leaves the means alone: the same step, in two programs whose folded parameter
    # constants may round differently in the last bit (measured 5e-16)
    assert np.allclose(barely.state_means, plain.state_means, rtol=1e-14, atol=0)
    with pytest.raises(ValueError, match="aerosol_wander_per_sqrt_h"):
        forecast(quiet, mean, tiny, u, aerosol_wander_per_sqrt_h=-0.1)


def test_forecast_flags_extrapolation(twin_and_state):
    twin, mean, cov = twin_and_state
    fc = forecast(
        twin, mean, cov, np.tile([375.0, 23.0, 50.0], (600, 1)), np.array([0, 0, 0, 0.01, 0])
    )
    assert any("ΔR_N passes" in w for w in fc.warnings)
    ok = forecast(twin, mean, cov, np.tile([375.0, 23.0, 50.0], (60, 1)), np.zeros(5))
    assert ok.warnings == []


# --------------------------------------------------------------------------- advice


def test_advice_reaches_target_with_least_overspray(twin_and_state):
    from ajtwin.apps.planning.advice import advise

    twin, mean, cov = twin_and_state
    twin.theta = np.zeros(5)
    # 10 µm below the nominal line (75 µm with the CFD-fitted output model), inside the limits
    target = 65.0
    limits = {
        "atomizer_current_mA": [300, 440],
        "carrier_flow_sccm": [15, 35],
        "sheath_flow_sccm": [30, 80],
    }
    adv = advise(twin, mean, cov, [375, 23, 50], target, limits=limits, settle_s=60)
    assert adv.reachable and "on the target 65 µm" in adv.message and "(2σ)" in adv.message
    # independent check: the model run open loop with the advised inputs
    u = np.tile(adv.inputs, (60, 1))
    y = twin.model.outputs(twin.model.simulate(mean, u)[-1], adv.inputs)
    assert abs(y[0] - target) < 0.06
    assert np.all(adv.inputs >= [300, 15, 30]) and np.all(adv.inputs <= [440, 35, 80])
    # no grid point that reaches 40 ± 0.5 µm has clearly less overspray
    best = np.inf
    for ia in np.linspace(300, 440, 5):
        for qc in np.linspace(15, 35, 9):
            for qs in np.linspace(30, 80, 11):
                uu = np.array([ia, qc, qs])
                yy = twin.model.outputs(twin.model.simulate(mean, np.tile(uu, (60, 1)))[-1], uu)
                if abs(yy[0] - target) < 0.5:
                    best = min(best, yy[1] - (yy[0] - target) * 0.7)
    assert adv.predicted["overspray_um"][0] <= best + 0.5


def test_advice_unreachable(twin_and_state):
    from ajtwin.apps.planning.advice import advise

    twin, mean, cov = twin_and_state
    adv = advise(twin, mean, cov, [375, 23, 50], 5.0, settle_s=30)
    assert not adv.reachable and "not reachable" in adv.message
    # the closest setting sits on the search range's bounds, and says so
    assert adv.at_limits and "on a search limit" in adv.limit_note()
    for name, side in adv.at_limits.items():
        low, high = adv.bounds[("atomizer_current_mA", "carrier_flow_sccm",
                                "sheath_flow_sccm").index(name)]  # fmt: skip
        value = adv.inputs[("atomizer_current_mA", "carrier_flow_sccm",
                            "sheath_flow_sccm").index(name)]  # fmt: skip
        assert value == pytest.approx(low if side == "lower" else high, abs=1e-3 * (high - low))


def test_forecast_and_advise_cli(tmp_path):
    from ajtwin.cli.advise import advise
    from ajtwin.cli.forecast import forecast
    from ajtwin.store.registry import NewPrint, Registry

    store = tmp_path / "r.sqlite"
    reg = Registry(store)
    reg.add_machine("m")
    runner = CliRunner()
    res = runner.invoke(forecast, ["--machine", "m", "--store", str(store)])
    assert res.exit_code != 0 and "no prints yet" in res.output
    from ajtwin.estimation import Twin

    twin = Twin.default()
    phi = float(twin.model.steady_aerosol_fraction(np.array([375.0, 23.0, 50.0]), 1.0))
    end = np.array([3.5, 1.0, 1e-4, 0.04, phi])
    reg.save_print(
        "m",
        NewPrint(
            content_hash="x",
            source="t",
            meta={},
            summary={},
            n_samples=2,
            duration_s=2.0,
            start_mean=end,
            start_cov=np.eye(5) * 1e-6,
            end_mean=end,
            end_cov=np.diag([1e-3, 1e-6, 1e-10, 1e-6, (0.02 * phi) ** 2]),
            theta_before=np.zeros(5),
            theta_after=np.zeros(5),
            arrays={"inputs": np.tile([375.0, 23.0, 50.0], (2, 1))},
            anomalies=[],
        ),
        expected_last_seq=None,
    )
    out = tmp_path / "f.csv"
    res = runner.invoke(
        forecast,
        [
            "--machine", "m", "--set", "Q_c=26@+60s", "--horizon", "5min", "--store", str(store),
            "--out", str(out),
        ],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    # without --plot the figure lands beside the CSV, not in the working directory
    assert (tmp_path / "f.png").stat().st_size > 10_000
    import pandas as pd

    frame = pd.read_csv(out)
    assert len(frame) == 300 and frame["carrier_flow_sccm"].iloc[59] == 23.0
    assert frame["carrier_flow_sccm"].iloc[60] == 26.0
    assert (tmp_path / "f.png").stat().st_size > 1000
    res = runner.invoke(forecast, ["--machine", "m", "--set", "Q_x=1", "--store", str(store)])
    assert res.exit_code != 0 and "unknown input" in res.output
    res = runner.invoke(
        advise, ["--machine", "m", "--target-linewidth", "45", "--store", str(store)]
    )
    assert res.exit_code == 0, res.output
    assert "on the target 45 µm" in res.output and "target reached" not in res.output
    # a print that clogged: no advice until the nozzle is cleaned (or --anyway)
    from ajtwin.apps.detection.streaming import AnomalyEvent
    from ajtwin.cli.machine import machine

    clog = AnomalyEvent(3600.0, 3540.0, "nozzle_clog", "nozzle clog", ["cusum+ P_c+P_s"])
    last = reg.last_print("m")
    reg.save_print("m", NewPrint(**{**{k: last[k] for k in ("start_mean", "start_cov", "end_mean",
                   "end_cov", "theta_before", "theta_after")}, "content_hash": "y", "source": "u",
                   "meta": {}, "summary": {}, "n_samples": 2, "duration_s": 2.0,
                   "arrays": {"inputs": np.tile([375.0, 23.0, 50.0], (2, 1))},
                   "anomalies": [clog]}), expected_last_seq=1)  # fmt: skip
    args = ["--machine", "m", "--target-linewidth", "45", "--store", str(store)]
    res = runner.invoke(advise, args)
    assert res.exit_code == 1 and "not advising 'm': its print #2" in res.output
    assert (
        "nozzle clogging since 59.0 min: clean the nozzle, then `ajtwin machine maintain m "
        "--nozzle-cleaned`"
        in res.output
        and "--anyway" in res.output
    )
    res = runner.invoke(advise, [*args, "--anyway"])
    assert res.exit_code == 0 and "WARNING advised --anyway" in res.output, res.output
    # the history names the fault (not `ok`), says what to do, and fits 110 columns
    res = runner.invoke(machine, ["history", "m", "--store", str(store)])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert max(len(line) for line in lines) <= 110, res.output
    assert re.search(r"^\s+2\s.*\sclog\s", res.output, re.M) and "φ_A ppm" in lines[0]
    assert re.search(r"^\s+1\s.*\sok\s", res.output, re.M)
    assert "#2 open fault: nozzle clogging since 59.0 min: clean the nozzle" in res.output
    shown = runner.invoke(machine, ["show", "m", "--store", str(store)])
    assert "print #2: alarm at 60.0 min" in shown.output, shown.output
    assert "what to do: clean the nozzle" in shown.output and "closed:" not in shown.output
    done = runner.invoke(machine, ["maintain", "m", "--nozzle-cleaned", "--store", str(store)])
    assert done.exit_code == 0 and "m: nozzle cleaned (" in done.output, done.output
    res = runner.invoke(advise, args)
    assert res.exit_code == 0 and "WARNING" not in res.output, res.output
    # the fixed clog is shown closed by the cleaning, not with the action again
    shown = runner.invoke(machine, ["show", "m", "--store", str(store)])
    assert "closed: nozzle cleaned after print #2 (" in shown.output, shown.output
    assert "what to do: clean the nozzle" not in shown.output
    # a print the model did not fit is a mismatch, not ok
    reg.save_print("m", NewPrint(**{**{k: last[k] for k in ("start_mean", "start_cov", "end_mean",
                   "end_cov", "theta_before", "theta_after")}, "content_hash": "z", "source": "v",
                   "meta": {}, "summary": {"mismatch": {"mismatch": True, "message": "x"}},
                   "n_samples": 2, "duration_s": 2.0,
                   "arrays": {"inputs": np.tile([375.0, 23.0, 50.0], (2, 1))}}),
                   expected_last_seq=2)  # fmt: skip
    res = runner.invoke(machine, ["history", "m", "--store", str(store)])
    assert re.search(r"^\s+3\s.*\smismatch\s", res.output, re.M) and "open fault" not in res.output


def test_long_run_scale_sees_coloured_noise_not_a_fault_step():
    """AR(1) noise: σ_LR = σ_w/(1 − φ) (hand-computed); a step bias must not inflate it."""
    from ajtwin.apps.detection.statistics import LongRunScale

    rng = np.random.default_rng(3)
    n, phi = 12000, 0.8
    w = rng.standard_normal(n)
    x = np.zeros(n)
    for k in range(1, n):
        x[k] = phi * x[k - 1] + w[k]
    white = rng.standard_normal(n)
    stepped = white.copy()
    stepped[n // 2 :] += 3.0  # a fault: a 3σ step
    scale = LongRunScale(3, block=60, blocks=200, min_blocks=5, max_scale=50.0)
    for row in np.column_stack([x, white, stepped]):
        s = scale.update(row)
    assert abs(s[0] - 1.0 / (1.0 - phi)) < 0.2 * 5.0  # σ_LR = 5
    assert s[1] < 1.2 and s[2] < 1.2  # white: 1 (floored); the step moves one d_j only


def test_clipped_outlier_does_not_alarm_but_a_bias_does():
    """One 30σ camera outlier (heavy-tailed line noise) is clipped; a 1σ bias still alarms."""
    rng = np.random.default_rng(4)
    t = 1200
    e = rng.standard_normal((t, 5)) * 0.5
    e[600, 0] = 30.0
    args = dict(
        time_s=np.arange(t, dtype=float),
        predicted_outputs=np.zeros((t, 5)),
        innovation_variances=np.ones((t, 5)),
        n_measured=np.full(t, 5),
        means=np.tile([3.5, 1.0, 0.0, 0.01, 4.6e-7], (t, 1)),
        predicted_means=np.tile([3.5, 1.0, 0.0, 0.01, 4.6e-7], (t, 1)),
        covariances=np.tile(np.eye(5), (t, 1, 1)),
    )
    quiet = detect_anomalies(measurements=e, nis=np.sum(e**2, axis=1), **args)
    assert quiet.events == []
    biased = e.copy()
    biased[800:, 0] += 1.0
    loud = detect_anomalies(measurements=biased, nis=np.sum(biased**2, axis=1), **args)
    assert loud.events and "cusum+ L_w" in loud.events[0].detectors
