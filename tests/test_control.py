"""Closed-loop control: limits, holding a target, disturbance, safety, targets."""

from __future__ import annotations

import json
from importlib import resources

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ajtwin.apps.planning.mpc import (
    MPC,
    ControlSettings,
    TargetError,
    check_target,
    clip_command,
    mismatch_reasons,
    reachable_linewidth,
)
from ajtwin.estimation import Twin
from ajtwin.model.limits import StateLimits
from ajtwin.model.system import euler_step, output_function

BOUNDS = [(300.0, 440.0), (15.0, 35.0), (30.0, 80.0)]


@pytest.fixture(scope="module")
def twin():
    return Twin.default()


@pytest.fixture(scope="module")
def control_settings():
    return ControlSettings.load()


@pytest.fixture(scope="module")
def mpc(twin, control_settings):
    controller = MPC(twin, control_settings)
    controller.warm_up()
    return controller


def nominal_state(twin, u):
    phi = float(twin.model.steady_aerosol_fraction(np.asarray(u, float), 1.0))
    return np.array([3.5, 1.0, 0.0, 0.0, phi])


# --------------------------------------------------------------------------- #
# Limits and rate limits
# --------------------------------------------------------------------------- #

finite = st.floats(-1e4, 1e4, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    u=st.lists(st.one_of(finite, st.just(np.nan), st.just(np.inf)), min_size=3, max_size=3),
    u_prev=st.lists(st.floats(0.0, 600.0), min_size=3, max_size=3),
    step=st.lists(st.floats(0.01, 50.0), min_size=3, max_size=3),
)
def test_clip_command_never_leaves_limits_or_rate(u, u_prev, step):
    out = clip_command(u, u_prev, BOUNDS, step)
    lo = np.array([b[0] for b in BOUNDS])
    hi = np.array([b[1] for b in BOUNDS])
    u_prev, step = np.asarray(u_prev), np.asarray(step)
    assert np.all(np.isfinite(out))
    assert np.all(np.abs(out - u_prev) <= step * (1 + 1e-12) + 1e-12)
    reachable = (u_prev + step >= lo) & (u_prev - step <= hi)
    assert np.all(~reachable | ((out >= lo) & (out <= hi)))
    # from inside the box the command is always inside
    if np.all((u_prev >= lo) & (u_prev <= hi)):
        assert np.all((out >= lo) & (out <= hi))


@settings(
    max_examples=12,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    droplet=st.floats(0.6, 14.0),
    vial=st.floats(0.05, 2.9),
    nozzle=st.floats(-3.0, 70.0),
    phi=st.floats(0.0, 5e-6),
    log_var=st.floats(-8.0, 2.0),
    z_prev=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3),
    target=st.floats(20.0, 200.0),
)
def test_mpc_respects_limits_under_adversarial_states(
    mpc, droplet, vial, nozzle, phi, log_var, z_prev, target
):
    """Whatever state, covariance and target: every move of the plan is inside the limits
    and within the rate limit of the one before it; the command too."""
    mean = np.array([droplet, vial, 0.0, nozzle, phi])
    cov = np.diag(10.0**log_var * np.array([1.0, 1e-2, 1e-6, 1e-2, 1e-14]))
    u_prev = mpc.lo + np.asarray(z_prev) * mpc.span
    sol = mpc.solve(mean, cov, np.zeros(5), u_prev, target, warm_start=False)
    plan = np.vstack([u_prev, sol.plan])
    max_steps = mpc.rates * mpc.move_gaps[:, None]
    assert np.all(sol.plan >= mpc.lo - 1e-9) and np.all(sol.plan <= mpc.hi + 1e-9)
    assert np.all(np.abs(np.diff(plan, axis=0)) <= max_steps * (1 + 1e-9) + 1e-9)
    assert np.all(np.abs(sol.command - u_prev) <= mpc.rates * mpc.move_gaps[0] + 1e-9)


def test_step_is_bounded_when_uncertain(mpc, twin):
    """A bounded step: with step_scale 0.25 the command moves at most a quarter rate."""
    u = np.array([375.0, 23.0, 50.0])
    mean = nominal_state(twin, u)
    cov = np.diag([1e-2, 1e-4, 1e-8, 1e-4, 1e-16])
    full = mpc.solve(mean, cov, np.zeros(5), u, 55.0, warm_start=False)
    small = mpc.solve(mean, cov, np.zeros(5), u, 55.0, warm_start=False, step_scale=0.25)
    limit = mpc.rates * mpc.move_gaps[0]
    # the target is 20 µm away: the full step uses its whole rate on Q_c
    assert abs(full.command[1] - u[1]) == pytest.approx(limit[1], rel=1e-6)
    assert np.all(np.abs(small.command - u) <= 0.25 * limit + 1e-9)


# --------------------------------------------------------------------------- #
# Holds a constant target on the nominal model
# --------------------------------------------------------------------------- #


def test_holds_constant_target_on_nominal_model(mpc, twin):
    """The nominal model as the plant (θ = 0, no noise): L_w goes to the target and stays,
    checked with the model's own output function at the plant's state."""
    u = np.array([375.0, 23.0, 50.0])
    x = nominal_state(twin, u)
    cov = np.diag([1e-4, 1e-6, 1e-10, 1e-6, 1e-18])
    params, coeff = twin.model.params, twin.model.coefficient_matrix
    target = 62.0
    mpc.reset()
    linewidths, commands = [], []
    for _ in range(60):  # 10 min
        sol = mpc.solve(x, cov, np.zeros(5), u, target)
        u = sol.command
        commands.append(u)
        for _ in range(mpc.settings.period_s):
            x = np.asarray(euler_step(x, u, np.zeros(5), params))
            linewidths.append(float(output_function(x, u, params, coeff)[0]))
    linewidths = np.array(linewidths)
    assert abs(linewidths[0] - target) > 10.0  # it started far off
    last = linewidths[-300:]  # the last 5 min
    assert np.max(np.abs(last - target)) < 0.05
    # and the inputs settled (no limit cycling)
    assert np.max(np.abs(np.diff(np.array(commands[-20:]), axis=0))) < 0.05


# --------------------------------------------------------------------------- #
# Safety: mismatch and alarms
# --------------------------------------------------------------------------- #


def test_mismatch_reasons(twin, control_settings):
    limits = StateLimits.load(twin.model.params)
    good = np.array([3.5, 1.0, 0.0, 0.03, 4.6e-7])
    assert mismatch_reasons(good, [1.0] * 120, [5] * 120, limits=limits) == []
    bad = good.copy()
    bad[0] = 534.0
    reasons = mismatch_reasons(bad, limits=limits)
    assert reasons and "droplet_diameter_um" in reasons[0]
    # windowed NIS: 5 outputs, NIS 40 per step = 8 per output > 3
    reasons = mismatch_reasons(good, [40.0] * 120, [5] * 120, limits=limits)
    assert len(reasons) == 1 and "windowed NIS 8.0" in reasons[0]
    # too short a window is no evidence
    assert mismatch_reasons(good, [40.0] * 50, [5] * 50, limits=limits) == []
    # an external status (the machine's twin) is honoured, optional
    assert "valve" in mismatch_reasons(good, limits=limits, status=(True, "valve"))[0]
    assert mismatch_reasons(good, limits=limits, status=(False, "")) == []


def test_refuses_to_act_on_a_mismatch(twin, control_settings):
    """The MPC-on-twin strategy, fed a print whose line measurement goes wrong (the camera
    reads 40 % wide from 2 min on): it holds the command in force and says why."""
    from ajtwin.apps.planning.twin_control import MPCTwin
    from ajtwin.engine.stream import TwinStream
    from ajtwin.simulation.stepper import SteppedPrinter

    u0 = np.array([375.0, 23.0, 50.0])
    twin = Twin.default()
    strategy = MPCTwin(
        twin=twin,
        settings=control_settings,
        bounds=BOUNDS,
        u0=u0,
        target=75.0,
        stream=TwinStream("m", twin, asynchronous=False),
    )
    printer = SteppedPrinter("exp1", seed=3, duration_min=6)
    printer.set_setpoints(u0)
    decisions = []
    while not printer.done:
        chunk = printer.advance(10)
        if chunk.time_s[0] >= 120:
            chunk.outputs[:, 0] *= 1.4
        strategy.observe(chunk)
        if chunk.time_s[-1] >= 60:
            decisions.append((chunk.time_s[-1], strategy.decide(chunk.time_s[-1], u0)))
    before = [d for t, d in decisions if t < 120]
    assert before and all(d.status == "act" for d in before)
    late = [d for t, d in decisions if t >= 300]
    assert late and all(d.status == "hold" for d in late)
    assert all(np.array_equal(d.command, u0) for d in late)
    assert all(d.reason for d in late)
    assert any("NIS" in d.reason or "alarm" in d.reason for d in late)


# --------------------------------------------------------------------------- #
# Targets
# --------------------------------------------------------------------------- #


def test_bad_targets_give_clear_errors(twin, mpc):
    u = np.array([375.0, 23.0, 50.0])
    mean = nominal_state(twin, u)
    cov = np.diag([1e-2, 1e-4, 1e-8, 1e-4, 1e-16])
    reach = reachable_linewidth(twin, mean, cov, mpc.bounds)
    # independent check of the range: the box's corners on the model's steady state
    corners = []
    for ia in (300.0, 440.0):
        for qc in (15.0, 35.0):
            for qs in (30.0, 80.0):
                uu = np.array([ia, qc, qs])
                x = nominal_state(twin, uu)
                corners.append(float(twin.model.outputs(x, uu)[0]))
    assert reach[0] == pytest.approx(min(corners), abs=0.2)
    assert reach[1] == pytest.approx(max(corners), abs=0.2)
    text = f"{reach[0]:.1f}–{reach[1]:.1f} µm"
    for bad, fragment in ((float("nan"), "not a finite"), (-5.0, "> 0"), ("wide", "not a number")):
        with pytest.raises(TargetError, match=fragment) as info:
            check_target(bad, reach)
        assert text in str(info.value)
    with pytest.raises(TargetError, match="not reachable") as info:
        check_target(reach[1] + 20.0, reach)
    assert text in str(info.value)
    assert check_target(60.0, reach) == 60.0


def test_settings_file_is_validated(tmp_path):
    s = ControlSettings.load()
    assert s.period_s == 10 and s.move_starts_s == (0, 10, 30)
    bad = tmp_path / "c.toml"
    text = (resources.files("ajtwin") / "data" / "control.toml").read_text()
    bad.write_text(text.replace("move_starts_s = [0, 10, 30]", "move_starts_s = [0, 30, 10]"))
    with pytest.raises(ValueError, match="move_starts_s"):
        ControlSettings.load(bad)


# --------------------------------------------------------------------------- #
# The closed loop and the command line (small instances)
# --------------------------------------------------------------------------- #


def test_cli_simulate_small(tmp_path):
    from ajtwin.cli import main
    from ajtwin.io.records import read_record

    out = tmp_path / "ctl"
    result = CliRunner().invoke(
        main,
        [
            "control",
            "simulate",
            "--scenario",
            "exp1",
            "--target-linewidth",
            "65",
            "--out",
            str(out),
            "--duration-min",
            "3",
            "--strategies",
            "open_loop,pi",
            "--no-progress",
        ],
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    block = metrics["scenarios"]["exp1"]["per_seed"]["1"]
    assert set(block) == {"open_loop", "pi"}
    for m in block.values():
        assert m["inside_limits"] and m["rate_limits_respected"]
    rec = read_record(out / "exp1" / "seed1" / "pi.parquet")
    assert len(rec) == 180 and rec.has_truth
    assert rec.meta["control"]["strategy"] == "pi"
    assert (out / "exp1.png").stat().st_size > 10_000
    # open loop held its start inputs: the reported carrier flow sits at the start set-point
    ol = read_record(out / "exp1" / "seed1" / "open_loop.parquet")
    assert np.median(ol.inputs[:, 1]) == pytest.approx(metrics["start_inputs"][1], abs=0.05)


def test_cli_unreachable_target(tmp_path):
    from ajtwin.cli import main

    result = CliRunner().invoke(
        main,
        [
            "control",
            "simulate",
            "--scenario",
            "exp1",
            "--target-linewidth",
            "300",
            "--out",
            str(tmp_path),
            "--duration-min",
            "1",
            "--no-progress",
        ],
    )
    assert result.exit_code != 0
    assert "not reachable" in result.output and "reachable now: 41." in result.output


def test_converges_after_a_step_disturbance(control_settings):
    """Virtual print, the atomizer's generation steps to 70 % at 3 min (permanent): the
    open loop's line narrows and stays off; the MPC on the twin brings it back (the
    atomizer alarm does not hold it: not a fault of the inputs)."""
    from ajtwin.studies.closed_loop import ClosedLoopPlan, simulate_strategy

    settings = control_settings
    u0 = np.array([300.0, 24.116, 80.0])
    step = {
        "fault": {
            "kind": "atomizer_dropout",
            "onset_min": 3.0,
            "generation_fraction": 0.7,
            "duration_min": 0.0,
        }
    }
    runs = {
        strategy: simulate_strategy(
            ClosedLoopPlan(
                "exp1", 2, 65.0, duration_min=10, u0=u0, overrides=step, settings=settings
            ),
            strategy,
        )
        for strategy in ("open_loop", "mpc_twin")
    }
    open_lw = runs["open_loop"].true_outputs[:, 0]
    twin_lw = runs["mpc_twin"].true_outputs[:, 0]
    # the disturbance is real: the open loop loses > 2 µm of line after the step (2.5 µm)
    assert np.mean(open_lw[120:180]) - np.mean(open_lw[-180:]) > 2.0
    # the loop converged: the last 3 min within 0.75 µm of the target on average
    assert abs(np.mean(twin_lw[-180:]) - 65.0) < 0.75
    # a sudden 30 % loss of generation is the atomizer, not the vial: no ink stop
    assert runs["mpc_twin"].metrics["ink_stop_s"] is None
    assert runs["mpc_twin"].metrics["inside_limits"]
    assert runs["mpc_twin"].metrics["rate_limits_respected"]


@pytest.mark.slow
def test_full_comparison_exp1(tmp_path):
    """The comparison on exp1, seeds 1–5 (~10 min on 2 idle cores): the MPC on the twin is
    ≥ 3× below the open loop in RMS error and inside every limit. (The issue's second aim,
    ≥ 1.5× below PI, is not met — docs/howto/closed-loop-control.md says why — so it is not
    asserted.)"""
    from ajtwin.studies.control import ComparisonGrid, compare

    results = compare(ComparisonGrid(["exp1"], range(1, 6), 65.0), tmp_path, log=lambda _: None)
    summary = results["scenarios"]["exp1"]["summary"]
    assert summary["ratio_rms_open_loop_over_mpc_twin"] >= 3.0
    for strategy in ("open_loop", "pi", "mpc_nominal", "mpc_twin"):
        assert summary[strategy]["all_inside_limits"]
        assert summary[strategy]["all_rate_limits_respected"]
    assert summary["mpc_twin"]["within_2um_fraction_mean"] > 0.95


# --------------------------------------------------------------------------- #
# Ink supply: the vial running dry is detected, not chased
# --------------------------------------------------------------------------- #


def _vial(level, minutes=float("inf"), running_low=False):
    from ajtwin.estimation.vial import VialStatus

    return VialStatus(level, 0.01, 0.3, 0.05, 0.0, 1.0, 0.05, minutes, running_low)


def test_ink_balance_and_supply_status(twin, control_settings):
    from ajtwin.apps.planning.mpc import ink_supply_status, vial_level_from_material_flow

    params = twin.model.params
    # 1 h of Q_m that carries 0.1 mL of ink (φ_m of it silver), a few samples missing
    per_s = 0.1 / 3600.0 * params.silver_volume_fraction
    q = np.full(3600, per_s)
    q[::100] = np.nan
    level = vial_level_from_material_flow(q, 0.7, params=params)
    assert level == pytest.approx(0.7 - 0.1 * 3564 / 3600, rel=1e-9)
    # a Q_m gain of 2 (calibration): the same flow is half the ink
    assert vial_level_from_material_flow(q, 0.7, 2.0, params) == pytest.approx(
        0.7 - 0.05 * 3564 / 3600, rel=1e-9
    )
    with pytest.raises(ValueError, match="fill"):
        vial_level_from_material_flow(q, float("nan"))
    s = control_settings
    assert s.ink_stop_vial_ml == 0.5 and s.ink_stop_lead_min == 10.0
    assert ink_supply_status(0.8, None, s).status == "ok"
    assert ink_supply_status(0.8, _vial(0.8), s).status == "ok"
    # the balance alone: below the fit's low end
    stop = ink_supply_status(0.45, _vial(0.8), s)
    assert stop.status == "stop" and stop.reason.startswith("ink_low") and "balance" in stop.reason
    # the observer's level, and its projection within the lead time
    assert "observer" in ink_supply_status(0.8, _vial(0.49), s).reason
    assert ink_supply_status(0.8, _vial(0.52, 8.0, True), s).status == "stop"
    # 'running low' further out: a warning, the controller keeps steering
    low = ink_supply_status(0.8, _vial(0.6, 25.0, True), s)
    assert low.status == "low" and "refill" in low.reason


def test_vial_running_dry_stops_the_mpc_for_good(control_settings):
    """A vial filled to 0.53 mL that loses 1 mL/h (0.5 mL crossed at ~2 min): the MPC on
    the twin stops (reason ink_low), holds the inputs in force and never resumes — even
    when the ink rule would clear — while on a clean print it never stops."""
    from ajtwin.studies.closed_loop import ClosedLoopPlan, simulate_strategy

    u0 = np.array([300.0, 24.116, 80.0])
    dry = {"initial": {"vial_volume_mL": 0.53}, "truth": {"vial_evaporation_mL_per_h": 1.0}}
    plan = ClosedLoopPlan(
        "exp1", 1, 65.0, duration_min=8, overrides=dry, u0=u0, settings=control_settings
    )
    run = simulate_strategy(plan, "mpc_twin")
    c = run.commands
    stopped = np.flatnonzero(c["status"].to_numpy() == "stop")
    assert len(stopped), c["status"].value_counts()
    first = stopped[0]
    # detected within 3 min of the true crossing, after the controller had steered
    true_vial = run.record.data["true_vial_volume_mL"].to_numpy()
    crossing = float(np.argmax(true_vial < 0.5))
    assert crossing < c["time_s"].iloc[first] < crossing + 180
    assert (c["status"].iloc[:first] == "act").any()
    # latched: every later period is a stop with the same reason and unchanged set-points
    assert (c["status"].iloc[first:] == "stop").all()
    assert c["reason"].iloc[first].startswith("ink_low")
    assert c["reason"].iloc[first:].nunique() == 1
    held = c[["atomizer_current_mA", "carrier_flow_sccm", "sheath_flow_sccm"]].iloc[first - 1 :]
    assert (held.diff().abs().fillna(0.0).to_numpy() == 0.0).all()
    k = int(c["time_s"].iloc[first])
    assert (np.abs(np.diff(run.setpoints[k:], axis=0)) == 0).all()
    assert run.metrics["ink_stop_s"] == c["time_s"].iloc[first]
    assert run.metrics["inside_limits"] and run.metrics["rate_limits_respected"]


def test_ink_stop_latch_ignores_a_later_all_clear(twin, control_settings):
    from ajtwin.apps.planning.twin_control import MPCTwin
    from ajtwin.engine.stream import TwinStream
    from ajtwin.simulation.stepper import SteppedPrinter

    u0 = np.array([375.0, 23.0, 50.0])
    twin = Twin.default(vial_fill_ml=0.45)
    strategy = MPCTwin(
        twin=twin,
        settings=control_settings,
        bounds=BOUNDS,
        u0=u0,
        target=75.0,
        stream=TwinStream("m", twin, asynchronous=False),
    )
    printer = SteppedPrinter("exp1", seed=2, duration_min=2)
    printer.set_setpoints(u0)
    for _ in range(8):
        strategy.observe(printer.advance(10))
    first = strategy.decide(80.0, u0)
    assert first.status == "stop" and "balance" in first.reason  # told 0.45 mL: below 0.5
    strategy.vial_fill_ml = 1.0  # the balance would now say ok: still stopped
    strategy.observe(printer.advance(10))
    again = strategy.decide(90.0, u0 + np.array([5.0, 0.0, 0.0]))
    assert again.status == "stop" and again.reason == first.reason
    np.testing.assert_array_equal(again.command, u0 + np.array([5.0, 0.0, 0.0]))


@pytest.mark.parametrize("variant", ["mean_reverting", "input_following"])
def test_mpc_plans_with_the_twins_transition_variant(variant, control_settings):
    """The MPC's prediction is the twin's own forecast (its transition variant, the one
    θ was learned on), not the paper's step: the plan's L̂_w equals ``forecast`` under the
    planned inputs."""
    from ajtwin.apps.planning.forecast import forecast

    tw = Twin.default(transition=variant)
    controller = MPC(tw, control_settings)
    u = np.array([375.0, 23.0, 50.0])
    mean = np.array([3.3, 1.0, 0.0, 0.0, float(tw.model.steady_aerosol_fraction(u, 1.0))])
    cov = np.diag([1e-2, 1e-4, 1e-8, 1e-4, (0.05 * mean[4]) ** 2])
    sol = controller.solve(mean, cov, np.zeros(5), u, 70.0, warm_start=False)
    inputs = sol.plan[controller.block_index]
    expected = forecast(tw, mean, cov, inputs, np.zeros(5))
    np.testing.assert_allclose(sol.predicted_linewidth, expected.output_means[:, 0], rtol=1e-9)
    # and it differs from the paper's step (d_a relaxes / follows the inputs here)
    paper = forecast(Twin.default(transition="paper"), mean, cov, inputs, np.zeros(5))
    assert np.max(np.abs(paper.output_means[:, 0] - expected.output_means[:, 0])) > 1e-3


def test_cli_merge_runs_and_truth_alt(tmp_path):
    """Per-seed runs (one on the second truth generator) merge into one table; runs that
    are not one table (another target, the same print differing) are refused."""
    from ajtwin.cli import main

    def run(name, seed, *extra):
        out = tmp_path / name
        result = CliRunner().invoke(
            main,
            [
                "control",
                "simulate",
                "--scenario",
                "exp1",
                "--target-linewidth",
                "65",
                "--out",
                str(out),
                "--duration-min",
                "2",
                "--seeds",
                str(seed),
                "--strategies",
                "open_loop,pi",
                "--no-progress",
                *extra,
            ],
        )
        assert result.exit_code == 0, result.output
        return out

    a, b, alt = run("a", 1), run("b", 2), run("alt", 1, "--truth", "alt")
    out = tmp_path / "merged"
    result = CliRunner().invoke(
        main, ["control", "merge", str(a), str(b), str(alt), "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    merged = json.loads((out / "metrics.json").read_text())
    assert set(merged["scenarios"]) == {"exp1", "exp1@alt"}
    exp1 = merged["scenarios"]["exp1"]
    assert list(exp1["per_seed"]) == ["1", "2"]
    rms = [exp1["per_seed"][s]["pi"]["rms_error_um"] for s in ("1", "2")]
    assert exp1["summary"]["pi"]["rms_error_um_mean"] == pytest.approx(np.mean(rms))
    # the alt print is another print: not the first generator's seed 1
    alt_rms = merged["scenarios"]["exp1@alt"]["per_seed"]["1"]["open_loop"]["rms_error_um"]
    assert alt_rms != exp1["per_seed"]["1"]["open_loop"]["rms_error_um"]
    table = (out / "metrics.md").read_text()
    assert "| exp1@alt | 1 |" in table and "| exp1 | 1,2 |" in table
    # a conflicting re-run of the same print, and another target, are refused
    bad = json.loads((b / "metrics.json").read_text())
    bad["scenarios"]["exp1"]["per_seed"]["2"]["pi"]["rms_error_um"] += 1.0
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "metrics.json").write_text(json.dumps(bad))
    result = CliRunner().invoke(
        main, ["control", "merge", str(b), str(tmp_path / "c"), "--out", str(out)]
    )
    assert result.exit_code != 0 and "seed 2 pi differs" in result.output
    bad = json.loads((b / "metrics.json").read_text())
    bad["target_linewidth_um"] = 60.0
    (tmp_path / "c" / "metrics.json").write_text(json.dumps(bad))
    result = CliRunner().invoke(
        main, ["control", "merge", str(a), str(tmp_path / "c"), "--out", str(out)]
    )
    assert result.exit_code != 0 and "target_linewidth_um" in result.output
    result = CliRunner().invoke(
        main, ["control", "merge", str(tmp_path / "nothing"), "--out", str(out)]
    )
    assert result.exit_code != 0


def test_live_link_takes_the_vial_fill():
    from ajtwin.apps.planning.supervisor import ControlTarget
    from ajtwin.live.control_link import ControlLink

    link = ControlLink("opc.tcp://127.0.0.1:4840", "m", ControlTarget(65.0, vial_fill_ml=0.7))
    assert link.print.target.vial_fill_ml == 0.7
    link.prepare()
    assert link.controller.twin.config.vial_fill_ml == 0.7
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="vial fill"):
            ControlLink("opc.tcp://127.0.0.1:4840", "m", ControlTarget(65.0, vial_fill_ml=bad))


def test_only_alarms_that_make_acting_unsafe_hold_the_mpc(control_settings):
    """An alarm that is not a fault of the inputs (atomizer trouble, an unexplained
    deviation, a clog: changes the twin follows in its states) does not hold the MPC, and
    the decision names the alarm it acts through; a fault of the inputs (carrier leak / MFC
    drift), a model–machine mismatch, a deposit beyond the model's range, or any alarm the
    filter's own consistency test raised (a sensor or the model off the data) still hold,
    the reason saying why. 'Ink running out' is the ink rule's (it steers while the vial is in
    H's fit and stops for good before it leaves it): no on/off holds."""
    from ajtwin.apps.planning.twin_control import MPCTwin
    from ajtwin.engine.stream import TwinStream
    from ajtwin.simulation.stepper import SteppedPrinter

    u0 = np.array([375.0, 23.0, 50.0])
    twin = Twin.default()
    stream = TwinStream("m", twin, asynchronous=False)
    strategy = MPCTwin(
        twin=twin, settings=control_settings, bounds=BOUNDS, u0=u0, target=75.0, stream=stream
    )
    printer = SteppedPrinter("exp1", seed=2, duration_min=2)
    printer.set_setpoints(u0)
    for _ in range(9):
        strategy.observe(printer.advance(10))
    assert strategy.safety() == []
    strategy.stream.status = lambda: ("alarm", "ink_low")
    assert strategy.safety() == []
    for cause in ("atomizer", "unexplained", "nozzle_clog"):
        strategy.stream.status = lambda cause=cause: ("alarm", cause)
        assert strategy.safety() == [], cause
    decision = strategy.decide(90.0, u0)
    assert decision.status == "act"
    assert "acting through the alarm nozzle clog" in decision.reason
    for cause, words in (
        ("carrier_leak", "carrier leak, MFC drift"),
        ("model_machine_mismatch", "model–machine mismatch"),
        ("nozzle_cleaning", "nozzle needs cleaning"),
    ):
        strategy.stream.status = lambda cause=cause: ("alarm", cause)
        (reason,) = strategy.safety()
        assert reason.startswith("alarm that makes acting unsafe") and words in reason
    decision = strategy.decide(100.0, u0)
    assert decision.status == "hold" and "nozzle needs cleaning" in decision.reason
    # whatever its cause, an alarm the filter's own consistency test raised holds: the data
    # are off the twin's predictions by far more than their noise (a sensor or the model)
    from ajtwin.apps.detection.streaming import AnomalyEvent

    strategy.stream.status = lambda: ("alarm", "unexplained")
    strategy.stream.detector.events.append(
        AnomalyEvent(100.0, 80.0, "unexplained", "", ["cusum+ L_w", "windowed NIS"])
    )
    (reason,) = strategy.safety()
    assert "unexplained deviation" in reason and "consistency test (windowed NIS)" in reason


def test_stop_time_that_has_passed_today_means_tomorrow():
    """``--stop-at 01:00`` given at 22:00 stops after midnight, not at once; a later time
    today stays today."""
    from datetime import UTC, datetime

    from ajtwin.studies.control import next_utc_time

    now = datetime(2026, 3, 1, 22, 0, tzinfo=UTC)
    assert next_utc_time("01:00", now) == datetime(2026, 3, 2, 1, 0, tzinfo=UTC).timestamp()
    assert next_utc_time("23:15", now) == datetime(2026, 3, 1, 23, 15, tzinfo=UTC).timestamp()
    assert next_utc_time("22:00", now) == datetime(2026, 3, 2, 22, 0, tzinfo=UTC).timestamp()
