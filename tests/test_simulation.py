"""The virtual printer: determinism, truth vs nominal model, faults, ink balance, CLI."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.io import read_record
from ajtwin.model import DigitalModel, load_parameters
from ajtwin.simulation import list_scenarios, load_scenario, run_virtual_print, simulate

PACKAGED = [
    "exp1",
    "exp2",
    "exp3",
    "nozzle_clog",
    "carrier_leak",
    "pressure_sensor_drift",
    "atomizer_dropout",
    "ink_running_low",
    "clean_long",
    "commissioning",
    "startup",
]

# Every mismatch and noise switched off: the truth must collapse onto the nominal model.
NO_MISMATCH = {
    "initial": {"nozzle_deposition_um": 0.0},
    "truth": {
        "droplet_offset_sd_um": 0.0,
        "droplet_ou_sd_um": 0.0,
        "droplet_trend_sd_um_per_h": 0.0,
        "droplet_carrier_um_per_sccm": 0.0,
        "droplet_current_um_per_mA": 0.0,
        "generation_offset_sd": 0.0,
        "generation_ou_sd": 0.0,
        "tube_deposition_factor": 1.0,
        "nozzle_deposition_factor": 1.0,
        "line_coefficient_sd": 0.0,
    },
    "measurement": {
        "carrier_flow_jitter_sccm": 0.0,
        "sheath_flow_jitter_sccm": 0.0,
        "atomizer_current_jitter_mA": 0.0,
        "flow_sensor_noise_sccm": 0.0,
        "current_sensor_noise_mA": 0.0,
        "pressure_noise_Pa": 0.0,
        "linewidth_log_sd": 0.0,
        "overspray_log_sd": 0.0,
        "material_flow_log_sd": 0.0,
    },
}


@pytest.fixture(scope="module")
def exp1():
    return run_virtual_print("exp1", seed=3)


@pytest.fixture(scope="module")
def fault_prints():
    return {name: run_virtual_print(name, seed=3) for name in PACKAGED[3:8]}


def test_packaged_scenarios_load_and_are_listed():
    assert sorted(PACKAGED) == list_scenarios()
    durations = {name: load_scenario(name).duration_s for name in PACKAGED}
    assert durations["clean_long"] == 8 * 3600
    assert durations["commissioning"] == 20 * 60  # model reference §11: a short print
    assert durations["startup"] == 30 * 60
    short = ("clean_long", "commissioning", "startup")
    assert all(d == 5400 for n, d in durations.items() if n not in short)


def test_schedules_match_spec_section_10():
    u = load_scenario("exp3").setpoints()
    step_qc, step_qs = int(37.6 * 60), int(68.5 * 60)
    assert (u[:step_qc, 1] == 24).all() and (u[step_qc:, 1] == 26).all()
    assert (u[:step_qs, 2] == 51).all() and (u[step_qs:, 2] == 48).all()
    assert (u[:, 0] == 375).all()
    u2 = load_scenario("exp2").setpoints()
    assert u2[0].tolist() == [330, 20, 53] and u2[-1].tolist() == [375, 23, 53]
    u1 = load_scenario("exp1").setpoints()
    assert (u1 == [375, 23, 50]).all()


def test_user_scenario_file_and_typo(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text(
        "[scenario]\nduration_min = 3.0\n[inputs]\ncarrier_flow_sccm = [[0.0, 21.0], [1.0, 25.0]]\n"
        '[fault]\nkind = "nozzle_clog"\nonset_min = 2.0\nnozzle_deposition_multiplier = 10.0\n'
    )
    record = simulate(path, seed=2)
    assert len(record) == 180 and record.meta["scenario"] == "mine"
    assert record.meta["fault_kind"] == "nozzle_clog" and record.meta["fault_onset_s"] == 120.0
    assert abs(record.data["carrier_flow_sccm"].iloc[30:60].mean() - 21.0) < 0.2
    assert abs(record.data["carrier_flow_sccm"].iloc[90:].mean() - 25.0) < 0.2
    path.write_text("[truth]\nnozzle_deposition_factr = 2.0\n")
    with pytest.raises(ValueError, match="unknown key 'truth.nozzle_deposition_factr'"):
        load_scenario(path)
    with pytest.raises(ValueError, match="unknown scenario 'exp9'"):
        load_scenario("exp9")
    with pytest.raises(ValueError, match="needs onset_min"):
        load_scenario({"fault": {"kind": "carrier_leak", "leak_fraction": 0.1, "ramp_min": 1}})


def test_same_seed_same_record_other_seed_differs():
    a = simulate("exp3", seed=7, duration_min=5)
    b = simulate("exp3", seed=7, duration_min=5)
    c = simulate("exp3", seed=8, duration_min=5)
    assert a.data.equals(b.data)
    assert not np.allclose(a.outputs, c.outputs)
    assert a.meta == b.meta and a.meta["seed"] == 7


def test_a_weighed_fill_and_a_cleaned_nozzle_are_not_exactly_what_is_stated():
    """Commissioning: the vial holds 1.0 mL + N(0, 3 µL); the cleaned nozzle |N(0, 2 nm)|."""
    starts = np.array(
        [simulate("commissioning", seed=s, duration_min=1).true_states[0] for s in range(40)]
    )
    fills, residues = starts[:, 1] - 1.0, starts[:, 3]
    # 40 draws: the sample sd (rms for the half-normal) lies within ±35 % (chi-square, p > 0.999)
    assert 0.65 * 3e-3 < np.std(fills) < 1.35 * 3e-3
    assert abs(np.mean(fills)) < 4 * 3e-3 / np.sqrt(40)
    assert np.all(residues >= 0.0)
    assert 0.65 * 2e-3 < np.sqrt(np.mean(residues**2)) < 1.35 * 2e-3
    stated = {"truth": {"vial_weighing_sd_mL": 0.0, "nozzle_residue_sd_um": 0.0}}
    drawn = simulate("commissioning", seed=3, duration_min=1)
    exact = simulate("commissioning", seed=3, duration_min=1, overrides=stated)
    assert exact.true_states[0, 1] == 1.0 != drawn.true_states[0, 1]
    assert exact.true_states[0, 3] == 0.0 < drawn.true_states[0, 3]
    # their own streams: every other draw of the print is unchanged
    np.testing.assert_array_equal(drawn.inputs, exact.inputs)
    np.testing.assert_array_equal(drawn.true_states[:, 0], exact.true_states[:, 0])
    # a print that continues the machine keeps the vial and nozzle it was left
    again = simulate("commissioning", seed=4, duration_min=1, continue_from=drawn)
    np.testing.assert_array_equal(again.true_states[0, 1:4], drawn.true_states[-1, 1:4])


def test_without_mismatch_truth_is_the_nominal_model():
    vp = run_virtual_print("exp3", seed=1, duration_min=45, overrides=NO_MISMATCH)
    model = DigitalModel.default()
    x = vp.states
    u = vp.record.inputs
    # the model's own RK4 at 1 s from the same start, driven by the same inputs
    nominal = model.simulate(x[0], u[:-1], method="rk4")
    np.testing.assert_allclose(x[:, [0, 1]], nominal[:, [0, 1]], rtol=1e-12)
    np.testing.assert_allclose(x[:, 2:4], nominal[:, 2:4], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(x[:, 4], nominal[:, 4], rtol=1e-9)
    np.testing.assert_allclose(vp.record.outputs, model.outputs(x, u), rtol=1e-12)


def test_droplet_size_drifts_like_the_paper():
    changes, starts = [], []
    for seed in range(8):
        vp = run_virtual_print("exp1", seed=seed)
        d = vp.states[:, 0]
        starts.append(d[0])
        changes.append(d[3000] - d[0])
    changes = np.abs(changes)
    # the paper's measured d_a moved ~0.25 µm in 50 min; ours: ~0.1–0.3 µm typical
    assert 0.05 < np.sqrt(np.mean(changes**2)) < 0.35
    assert changes.max() < 0.6
    # starts differ from 3.5 µm by a seeded amount (sd 0.15 µm)
    assert 0.03 < np.std(starts) < 0.35 and np.ptp(starts) > 0.1


def test_droplet_size_follows_carrier_step_with_lag():
    overrides = {"truth": {**NO_MISMATCH["truth"], "droplet_carrier_um_per_sccm": 0.05}}
    overrides["measurement"] = NO_MISMATCH["measurement"]
    vp = run_virtual_print("exp3", seed=0, duration_min=40, overrides=overrides)
    d = vp.states[:, 0]
    step = int(37.6 * 60)
    before = d[step - 1]
    assert before == pytest.approx(3.5 + 0.05 * (24 - 23))
    # first-order lag, τ = 60 s: 1 − e^{−1} of the 0.1 µm shift one minute after the step
    assert d[step + 60] - before == pytest.approx(0.1 * (1 - np.exp(-1)), rel=0.03)
    assert d[-1] - before == pytest.approx(0.1 * (1 - np.exp(-(len(d) - 1 - step) / 60)), rel=0.03)


def hand_pressures(carrier_sccm, sheath_sccm, tube_um, nozzle_um):
    """P_c, P_s from model reference §5/§6 written out independently of ajtwin.model."""
    qc = carrier_sccm / 60 * 1e-6
    qs = sheath_sccm / 60 * 1e-6
    r_tube = 8 * 1.76e-5 * 0.4572 / (np.pi * (7.89e-4 - tube_um * 1e-6) ** 4)
    a = [4.57e9, 2.75e9, -7.96e8, 9.73e7, -5.81e6, 1.83e5, -2.92e3, 18.67]
    r_tip = sum(ai * nozzle_um**i for i, ai in enumerate(a))
    r_nozzle = 5.36e6 + 6.07e7 + r_tip
    p_c = qc * (r_tube + 1.1972e4 + 5.6305e4 + 6.9590e5) + (qc + qs) * r_nozzle
    p_s = qs * (2.185e5 + 175.66 + 1.28e6) / 2 + (qc + qs) * r_nozzle
    return p_c, p_s


def test_pressures_follow_the_resistance_network_at_true_states(exp1):
    x = exp1.states
    flows = exp1.processes.head_inputs
    p_c, p_s = hand_pressures(flows[:, 1], flows[:, 2], x[:, 2], x[:, 3])
    measured = exp1.record.data
    noise = exp1.scenario.config["measurement"]["pressure_noise_Pa"]
    for measured_p, hand in (
        (measured["carrier_pressure_Pa"], p_c),
        (measured["sheath_pressure_Pa"], p_s),
    ):
        residual = measured_p.to_numpy() - hand
        assert abs(residual.mean()) < 0.3
        assert residual.std() == pytest.approx(noise, rel=0.05)
    # the 30 nm starting deposit shows: ~3.3e3 Pa/µm above the clean nozzle
    clean_c, _ = hand_pressures(23.0, 50.0, 0.0, 0.0)
    assert clean_c == pytest.approx(5661, abs=1)
    start = measured["carrier_pressure_Pa"].iloc[:60].mean()
    expected = np.mean(hand_pressures(flows[:60, 1], flows[:60, 2], 0.0, 0.03)[0])
    assert start == pytest.approx(expected, abs=2)
    assert start - clean_c > 60


def test_line_noise_is_lognormal_around_the_true_line(exp1):
    meas = exp1.scenario.config["measurement"]
    y = exp1.record.outputs
    log_ratio = np.log(y / exp1.outputs_true)
    assert abs(log_ratio[:, 0].mean()) < 0.003
    assert log_ratio[:, 0].std() == pytest.approx(meas["linewidth_log_sd"], rel=0.05)
    assert log_ratio[:, 1].std() == pytest.approx(meas["overspray_log_sd"], rel=0.05)
    assert log_ratio[:, 4].std() == pytest.approx(meas["material_flow_log_sd"], rel=0.05)
    # the true line model is not the twin's: sensitivities differ by a few percent
    factors = np.array(exp1.record.meta["truth_draws"]["line_coefficient_factors"])
    assert 0.005 < np.abs(factors - 1).mean() < 0.1


def test_inputs_jitter_and_the_twin_sees_measured_inputs(exp1):
    u_meas = exp1.record.inputs
    u_true = exp1.processes.mfc_inputs
    set_points = exp1.processes.setpoints
    meas = exp1.scenario.config["measurement"]
    assert (u_true[:, 1] - set_points[:, 1]).std() == pytest.approx(
        meas["carrier_flow_jitter_sccm"], rel=0.25
    )
    assert (u_meas[:, 1] - u_true[:, 1]).std() == pytest.approx(
        meas["flow_sensor_noise_sccm"], rel=0.05
    )
    assert (u_true[:, 0] - set_points[:, 0]).std() == pytest.approx(
        meas["atomizer_current_jitter_mA"], rel=0.05
    )


def test_aerosol_generation_differs_from_nominal_by_a_few_percent(exp1):
    params = load_parameters()
    model = DigitalModel.default()
    nominal = np.array(
        [
            model.steady_aerosol_fraction(u, v)
            for u, v in zip(exp1.processes.head_inputs[::300], exp1.states[::300, 1], strict=True)
        ]
    )
    ratio = exp1.states[::300, 4] / nominal
    offset = exp1.record.meta["truth_draws"]["generation_offset"]
    assert abs(np.median(ratio) - 1 - offset) < 0.05
    assert 0.005 < np.std(ratio) < 0.1  # the slow wander of the generation
    assert params.vial_volume > 0


def ink_balance(vp):
    params = load_parameters()
    x = vp.states
    lt, rt = params.tube_length, params.tube_radius
    ln, rn = params.nozzle_length, params.nozzle_radius

    def annulus_ml(radius, length, deposit_um):
        inner = radius - deposit_um * 1e-6
        return np.pi * (radius**2 - inner**2) * length * 1e6

    tube = annulus_ml(rt, lt, x[-1, 2]) - annulus_ml(rt, lt, x[0, 2])
    nozzle = annulus_ml(rn, ln, x[-1, 3]) - annulus_ml(rn, ln, x[0, 3])
    evaporated = vp.processes.drivers[:-1, 3].sum()
    vial_loss = x[0, 1] - x[-1, 1]
    return vial_loss - evaporated, tube, nozzle, vp.substrate_ink_mL[-1]


@pytest.mark.parametrize("name", ["exp1", "ink_running_low"])
def test_ink_is_conserved(exp1, fault_prints, name):
    vp = exp1 if name == "exp1" else fault_prints[name]
    drawn, tube, nozzle, substrate = ink_balance(vp)
    assert drawn > 0 and tube > 0 and nozzle > 0 and substrate > 0
    assert tube + nozzle + substrate == pytest.approx(drawn, rel=1e-6)
    # and the substrate share agrees with the material flow the truth implies
    phi_m = load_parameters().silver_volume_fraction
    drawn_by_qm = np.trapezoid(vp.outputs_true[:, 4] / phi_m)
    assert drawn_by_qm == pytest.approx(drawn, rel=2e-3)
    # per second, against the model's own ink accounting (ajtwin.model.ink_flows, trapezoid
    # over the second): the nozzle deposit grows by factor × the model's flow into it, and
    # the substrate gains what leaves the vial minus both deposits
    from ajtwin.model import ink_flows

    params = load_parameters()
    k = np.arange(100, len(vp.states) - 1, 700)
    u = vp.processes.head_inputs[k]
    flows = [np.asarray(ink_flows(vp.states[j], u, params)) for j in (k, k + 1)]
    out, into_tube, into_nozzle = (0.5 * (flows[0][i] + flows[1][i]) for i in range(3))
    factors = vp.processes.drivers[k]
    nozzle_gain = (
        np.pi
        * params.nozzle_length
        * 1e6
        * (
            (params.nozzle_radius - vp.states[k, 3] * 1e-6) ** 2
            - (params.nozzle_radius - vp.states[k + 1, 3] * 1e-6) ** 2
        )
    )
    np.testing.assert_allclose(nozzle_gain, factors[:, 2] * into_nozzle, rtol=1e-3)
    expected = out - factors[:, 1] * into_tube - factors[:, 2] * into_nozzle
    gained = vp.substrate_ink_mL[k + 1] - vp.substrate_ink_mL[k]
    np.testing.assert_allclose(gained, expected, rtol=1e-3)


def test_deposition_is_faster_than_the_model(exp1):
    model = DigitalModel.default()
    x = exp1.states
    u = exp1.processes.head_inputs
    nominal_rate = np.array([model.derivative(x[k], u[k])[3] for k in range(0, 5400, 600)])
    true_rate = np.gradient(x[:, 3])[::600]
    factor = exp1.scenario.config["truth"]["nozzle_deposition_factor"]
    np.testing.assert_allclose(true_rate / nominal_rate, factor, rtol=0.02)


def test_nozzle_clog(exp1, fault_prints):
    vp = fault_prints["nozzle_clog"]
    onset = int(vp.record.meta["fault_onset_s"])
    assert onset == 3600 and vp.record.meta["fault_kind"] == "nozzle_clog"
    rn = vp.states[:, 3]
    np.testing.assert_array_equal(rn[:onset], exp1.states[:onset, 3])
    before = (rn[onset] - rn[onset - 600]) / 600
    after = (rn[onset + 600] - rn[onset]) / 600
    assert 40 < after / before < 60
    pc = vp.record.data["carrier_pressure_Pa"]
    assert pc.iloc[-60:].mean() - pc.iloc[onset - 60 : onset].mean() > 500


def test_carrier_leak(exp1, fault_prints):
    vp = fault_prints["carrier_leak"]
    onset = int(vp.record.meta["fault_onset_s"])
    d, d0 = vp.record.data, exp1.record.data
    # the MFC still reports its set flow; the head gets 15 % less; P_c and Q_m drop
    np.testing.assert_array_equal(d["carrier_flow_sccm"], d0["carrier_flow_sccm"])
    late = slice(onset + 300, None)
    drop = d0["carrier_pressure_Pa"].iloc[late].mean() - d["carrier_pressure_Pa"].iloc[late].mean()
    p_full, _ = hand_pressures(23.0, 50.0, 0.0, 0.05)
    p_leak, _ = hand_pressures(23.0 * 0.85, 50.0, 0.0, 0.05)
    assert drop == pytest.approx(p_full - p_leak, rel=0.1)
    q_ratio = vp.outputs_true[late, 4].mean() / exp1.outputs_true[late, 4].mean()
    assert q_ratio < 0.8


def test_pressure_sensor_drift(exp1, fault_prints):
    vp = fault_prints["pressure_sensor_drift"]
    onset = int(vp.record.meta["fault_onset_s"])
    np.testing.assert_array_equal(vp.states, exp1.states)  # the physics is untouched
    offset = vp.record.data["carrier_pressure_Pa"] - exp1.record.data["carrier_pressure_Pa"]
    assert (offset.iloc[:onset] == 0).all()
    assert offset.iloc[-1] == pytest.approx(-40.0 * (5399 - onset) / 3600)
    assert (vp.record.data["sheath_pressure_Pa"] == exp1.record.data["sheath_pressure_Pa"]).all()


def test_atomizer_dropout(exp1, fault_prints):
    vp = fault_prints["atomizer_dropout"]
    onset = int(vp.record.meta["fault_onset_s"])
    ratio = vp.states[:, 4] / exp1.states[:, 4]
    assert ratio[:onset] == pytest.approx(1.0)
    # φ_A settles to 40 % within a few head-space time constants (~5 s)
    assert ratio[onset + 60 : onset + 300] == pytest.approx(0.4, rel=0.01)
    assert ratio[onset + 600 :] == pytest.approx(1.0, rel=0.01)


def test_ink_running_low(fault_prints):
    vp = fault_prints["ink_running_low"]
    v = vp.states[:, 1]
    assert v[0] == pytest.approx(0.70, abs=5 * 3e-3)  # the stated 0.70 mL, weighed (3 µL)
    assert v[0] - v[-1] == pytest.approx(0.15 * 1.5, rel=0.02)
    assert v[-1] < 0.5  # below the generation fit's validity
    q = vp.outputs_true[:, 4]
    assert q[-1] < 0.8 * q[0]


def test_missing_samples_in_exp2_survive_a_round_trip(tmp_path):
    record = simulate("exp2", seed=4, duration_min=20)
    missing = record.data["linewidth_um"].isna()
    assert 0.003 < missing.mean() < 0.03
    assert (record.data["overspray_um"].isna() == missing).all()
    path = tmp_path / "exp2.csv"
    from ajtwin.io import write_record

    write_record(record, path)
    back = read_record(path)
    assert (back.data["linewidth_um"].isna() == missing).all()


def test_cli_simulate_and_plot(tmp_path):
    from ajtwin.cli import main

    runner = CliRunner()
    out = tmp_path / "p.parquet"
    result = runner.invoke(
        main,
        [
            "simulate",
            "--scenario",
            "carrier_leak",
            "--seed",
            "2",
            "--out",
            str(out),
            "--duration-min",
            "50",
        ],
    )
    assert result.exit_code == 0, result.output
    record = read_record(out)
    assert record.meta["fault_onset_s"] == 2700.0 and len(record) == 3000
    png = tmp_path / "p.png"
    result = runner.invoke(main, ["plot", str(out), "-o", str(png)])
    assert result.exit_code == 0, result.output
    import matplotlib.image as mpimg

    image = mpimg.imread(png)
    assert png.stat().st_size > 50_000
    assert image.shape[0] > 800 and image.shape[1] > 1000
    assert image[..., :3].std() > 0.05  # not a blank canvas
    result = runner.invoke(main, ["simulate", "--scenario", "nope", "--out", str(out)])
    assert result.exit_code != 0 and "unknown scenario 'nope'" in result.output


@pytest.mark.slow
def test_clean_long_eight_hours():
    vp = run_virtual_print("clean_long", seed=5)
    x = vp.states
    assert len(x) == 28_800 and vp.record.meta["fault_kind"] == "none"
    assert 2.5 < x[:, 0].min() and x[:, 0].max() < 4.5  # d_a stays physical for 8 h
    drawn, tube, nozzle, substrate = ink_balance(vp)
    assert tube + nozzle + substrate == pytest.approx(drawn, rel=1e-6)


def test_a_second_print_continues_the_machine(tmp_path):
    first = simulate("exp1", seed=1, duration_min=20)
    second = simulate("exp3", seed=2, duration_min=5, continue_from=first)
    last, start = first.true_states[-1], second.true_states[0]
    np.testing.assert_array_equal(start[1:4], last[1:4])
    assert second.meta["machine_id"] == first.meta["machine_id"]
    # the CLI does the same from a file
    from ajtwin.cli import main
    from ajtwin.io import write_record

    write_record(first, tmp_path / "first.parquet")
    out = tmp_path / "second.parquet"
    result = CliRunner().invoke(
        main,
        [
            "simulate",
            "-s",
            "exp3",
            "-n",
            "2",
            "--duration-min",
            "5",
            "--out",
            str(out),
            "--continue-from",
            str(tmp_path / "first.parquet"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert read_record(out).data.equals(second.data)
    with pytest.raises(ValueError, match="needs a record with truth"):
        simulate("exp1", continue_from=first.__class__(first.data.iloc[:, :9], {}))
