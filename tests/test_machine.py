"""virtual machines, per-machine calibration, commissioning (model reference §11)."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin.estimation.commission import CommissioningError, commission, parse_known
from ajtwin.estimation.twin import Twin
from ajtwin.model import DigitalModel, output_function
from ajtwin.model.calibration import (
    CALIBRATION_NAMES,
    CalibratedCoefficients,
    Calibration,
    read_calibration_file,
    write_calibration_file,
)
from ajtwin.simulation.machine import draw_machine, load_machine_variation, named_machine
from ajtwin.simulation.printer import run_virtual_print, simulate


@pytest.fixture(scope="module")
def model():
    return DigitalModel.default()


@pytest.fixture(scope="module")
def commissioned():
    """A commissioning print on machine seed 3 and the calibration fitted from it."""
    vp = run_virtual_print("commissioning", seed=11, machine_seed=3)
    return vp, commission(vp.record)


def test_identity_calibration_gives_the_nominal_outputs_exactly(model):
    rng = np.random.default_rng(0)
    x = np.column_stack(
        [
            rng.uniform(2.5, 4, 20),
            rng.uniform(0.5, 1.5, 20),
            rng.uniform(0, 1e-3, 20),
            rng.uniform(0, 0.1, 20),
            rng.uniform(1e-7, 1e-6, 20),
        ]
    )
    u = np.column_stack(
        [rng.uniform(300, 440, 20), rng.uniform(15, 35, 20), rng.uniform(40, 60, 20)]
    )
    matrix = model.coefficient_matrix
    plain = np.asarray(output_function(x, u, model.params, matrix))
    calibrated = np.asarray(
        output_function(x, u, model.params, CalibratedCoefficients(matrix, Calibration.identity()))
    )
    assert np.array_equal(plain, calibrated)


def test_calibration_equations_by_hand(model):
    p = model.params
    x = np.array([3.5, 1.0, 0.0, 0.0, 4.6e-7])
    u = np.array([375.0, 23.0, 50.0])
    cal = Calibration(
        linewidth_gain=0.5,
        linewidth_offset_um=-10.0,
        overspray_gain=2.0,
        overspray_offset_um=3.0,
        carrier_line_factor=1.2,
        carrier_gauge_gain=1.08,
        carrier_gauge_offset_Pa=40.0,
        sheath_line_factor=0.9,
        sheath_gauge_gain=0.95,
        sheath_gauge_offset_Pa=-20.0,
        material_flow_gain=1.3,
    )
    nominal = np.asarray(output_function(x, u, p, model.coefficient_matrix))
    y = np.asarray(output_function(x, u, p, CalibratedCoefficients(model.coefficient_matrix, cal)))
    qc, qs = 23.0 / 60 * 1e-6, 50.0 / 60 * 1e-6  # m³/s
    tube = 8 * p.gas_viscosity * p.tube_length / (np.pi * p.tube_radius**4)
    carrier_line = qc * (tube + p.carrier_inlet_r1 + p.carrier_inlet_r2 + p.carrier_inlet_r3)
    sheath_line = qs * 0.5 * (p.sheath_inlet_r1 + p.sheath_inlet_r2 + p.sheath_inlet_r3)
    assert y[0] == pytest.approx(0.5 * nominal[0] - 10.0, rel=1e-12)
    assert y[1] == pytest.approx(2.0 * nominal[1] + 3.0, rel=1e-12)
    assert y[2] == pytest.approx(1.08 * (nominal[2] + 0.2 * carrier_line) + 40.0, rel=1e-12)
    assert y[3] == pytest.approx(0.95 * (nominal[3] - 0.1 * sheath_line) - 20.0, rel=1e-12)
    assert y[4] == pytest.approx(1.3 * nominal[4], rel=1e-12)


def test_default_machine_is_nominal_and_drawn_machines_stay_in_their_ranges():
    plain = simulate("exp1", seed=2, duration_min=1.0)
    named = simulate("exp1", seed=2, duration_min=1.0, machine="nominal")
    assert plain.data.equals(named.data)
    assert "machine" not in plain.meta
    sizes = load_machine_variation()["machine_variation"]
    for seed in range(6):
        m = draw_machine(seed)
        assert m == draw_machine(seed)  # reproducible
        assert abs(m.carrier_line_factor - 1) <= sizes["carrier_line_factor"]
        assert abs(m.sheath_gauge_offset_Pa) <= sizes["sheath_gauge_offset_Pa"]
        assert abs(m.linewidth_gain - 1) <= sizes["linewidth_gain"]
    assert draw_machine(0) != draw_machine(1)


def test_machine_changes_only_the_outputs_and_is_recorded():
    nominal = run_virtual_print("exp1", seed=4, duration_min=1.0)
    varied = run_virtual_print("exp1", seed=4, duration_min=1.0, machine_seed=7)
    # same hidden states (the machine is the plumbing/sensors/line model, not the ink)
    assert np.array_equal(nominal.states, varied.states)
    assert not np.allclose(nominal.record.outputs[:, 2], varied.record.outputs[:, 2])
    meta = varied.record.meta["machine"]
    assert meta["name"] == "seed-7"
    assert set(meta["equivalent_calibration"]) == set(CALIBRATION_NAMES)
    # the next print of the same machine keeps it
    nxt = run_virtual_print("exp1", seed=5, duration_min=1.0, continue_from=varied.record)
    assert nxt.machine == varied.machine


def test_paper_machine_prints_the_papers_lines():
    rec = simulate("exp1", seed=1, duration_min=3.0, machine="paper")
    droplet = rec.data["true_droplet_diameter_um"].to_numpy()
    lw = rec.data["linewidth_um"].to_numpy()
    lo = rec.data["overspray_um"].to_numpy()
    # the paper machine is anchored at d_a = 3.5 µm; correct for this seed's droplet size
    alpha = DigitalModel.default().coefficient_matrix[:, 0]
    assert np.mean(lw - alpha[0] * (droplet - 3.5)) == pytest.approx(43.0, abs=1.5)
    assert np.mean(lo - alpha[1] * (droplet - 3.5)) == pytest.approx(29.0, abs=1.5)
    with pytest.raises(ValueError, match="unknown named machine"):
        named_machine("nonesuch")


def test_commissioning_recovers_the_machine_within_its_standard_errors(commissioned):
    vp, result = commissioned
    truth = vp.machine.calibration()._asdict()
    for row in result.table():
        name = row["parameter"]
        if not row["determined"]:
            continue
        z = (row["value"] - truth[name]) / row["std_error"]
        assert abs(z) < 3.0, (name, row["value"], truth[name], row["std_error"])
    # the sheath lines carry < 1 Pa of the sheath pressure: honestly not determined
    assert not result.determined["sheath_line_factor"]
    for name in ("linewidth_gain", "linewidth_offset_um", "carrier_gauge_gain"):
        assert result.determined[name]
    # the deviations were real: the nominal model was far off
    assert abs(truth["linewidth_offset_um"]) > 5 * result.std["linewidth_offset_um"]


def test_calibration_file_round_trip(tmp_path, commissioned):
    _, result = commissioned
    path = write_calibration_file(
        tmp_path / "cal.toml", result.calibration, result.std, {"print": "x.parquet"}
    )
    cal, data = read_calibration_file(path)
    assert cal == result.calibration
    assert data["provenance"]["print"] == "x.parquet"
    (tmp_path / "bad.toml").write_text("[calibration]\nlinewidth_gain = -1\n")
    with pytest.raises(ValueError, match="must be positive"):
        read_calibration_file(tmp_path / "bad.toml")


def test_bad_commissioning_prints_are_refused_clearly():
    short = simulate("commissioning", seed=1, duration_min=3.0)
    with pytest.raises(CommissioningError, match="at least 300 s"):
        commission(short)
    flat = simulate("exp1", seed=1, duration_min=6.0)
    with pytest.raises(CommissioningError, match="carrier flow varies only"):
        commission(flat)
    rec = simulate("commissioning", seed=1, duration_min=8.0)
    rec.data["linewidth_um"] = np.nan
    rec.data["overspray_um"] = np.nan
    with pytest.raises(CommissioningError, match="camera"):
        commission(rec)


def test_parse_known():
    assert parse_known(["droplet_diameter_um=3.5±0.2"]) == {"droplet_diameter_um": (3.5, 0.2)}
    assert parse_known(["aerosol_fraction=4.6e-7+-1e-8"]) == {"aerosol_fraction": (4.6e-7, 1e-8)}
    with pytest.raises(ValueError, match="unknown state"):
        parse_known(["droplet=3.5±0.2"])
    with pytest.raises(ValueError, match="positive uncertainty"):
        parse_known(["droplet_diameter_um=3.5"])


def test_second_truth_generator_is_different_reproducible_and_conserves_ink():
    from ajtwin.model import load_parameters

    alt = run_virtual_print("exp1", seed=9, duration_min=20.0, truth_generator="alt")
    again = run_virtual_print("exp1", seed=9, duration_min=20.0, truth_generator="alt")
    first = run_virtual_print("exp1", seed=9, duration_min=20.0)
    assert alt.record.data.equals(again.record.data)
    assert alt.record.meta["truth_generator"] == "alt"
    assert not np.allclose(alt.states[:, 0], first.states[:, 0])
    # ink balance: what left the vial is in the tube, in the nozzle or on the substrate
    p = load_parameters()
    s = alt.states
    r_t, r_n = p.tube_radius, p.nozzle_radius
    tube = np.pi * p.tube_length * (r_t**2 - (r_t - s[:, 2] * 1e-6) ** 2) * 1e6  # mL
    nozzle = np.pi * p.nozzle_length * (r_n**2 - (r_n - s[:, 3] * 1e-6) ** 2) * 1e6
    left_vial = s[0, 1] - s[:, 1]
    balance = left_vial - tube - nozzle - alt.substrate_ink_mL
    assert np.max(np.abs(balance)) < 1e-3 * left_vial[-1]
    with pytest.raises(ValueError, match="truth generator"):
        run_virtual_print("exp1", seed=9, duration_min=1.0, truth_generator="other")


def test_calibration_uncertainty_widens_the_bands_by_the_hand_computed_amount():
    record = simulate("exp1", seed=12, duration_min=3.0)
    cov = np.zeros((len(CALIBRATION_NAMES), len(CALIBRATION_NAMES)))
    i = CALIBRATION_NAMES.index("linewidth_offset_um")
    cov[i, i] = 2.0**2  # the L_w offset known to ±2 µm, nothing else uncertain
    plain = Twin.default(calibration=Calibration.identity()).run(record)
    banded = Twin.default(calibration=Calibration.identity(), calibration_cov=cov).run(record)
    assert np.array_equal(plain.means, banded.means)  # the estimate itself is unchanged
    extra = banded.calibration_covariances[-60:]
    alpha_da = DigitalModel.default().coefficient_matrix[0, 0]  # ∂L_w/∂d_a, µm/µm
    # L_w carries ~99 % of the d_a information: δd_a ≈ δo / α^da
    assert np.sqrt(extra[:, 0, 0]).mean() == pytest.approx(2.0 / alpha_da, rel=0.15)
    # the pressures pin ΔR_N and the vial is not seen by L_w: no extra width there
    assert np.sqrt(extra[:, 3, 3]).max() < 1e-3
    assert np.sqrt(extra[:, 1, 1]).max() < 1e-6
    assert np.all(banded.stds[:, 0] >= plain.stds[:, 0])


def test_commissioning_fits_the_machines_output_noise_and_files_keep_it(tmp_path, commissioned):
    from ajtwin.model import OUTPUT_NAMES

    vp, result = commissioned
    # seed 3 prints 1.37× wider lines: the camera's relative noise is larger in µm; the
    # fitted factor is the camera's noise on this print over the tuned σ of L_w
    assert vp.machine.calibration().linewidth_gain > 1.3
    measured = np.isfinite(vp.record.outputs[:, 0])
    camera = np.std(vp.record.outputs[measured, 0] - vp.outputs_true[measured, 0])
    tuned = Twin.default().config.measurement_std[0]
    assert camera > 1.05 * tuned
    assert result.noise_factors[0] == pytest.approx(camera / tuned, rel=0.1)
    assert 0.5 <= result.noise_factors[2] <= 1.5  # same gauges' noise as the tuning
    path = write_calibration_file(
        tmp_path / "cal.toml",
        result.calibration,
        result.std,
        covariance=result.calibration_cov,
        noise_factors=dict(zip(OUTPUT_NAMES, result.noise_factors.tolist())),
    )
    _, data = read_calibration_file(path)
    assert np.allclose(data["covariance"]["matrix"], result.calibration_cov, rtol=1e-12)
    assert data["noise_factor"]["linewidth_um"] == pytest.approx(result.noise_factors[0])


# --- φ_A's level: an atomizer that is not the generation model (model reference §11) ---


@pytest.fixture(scope="module")
def off_model_machine():
    """Held-out machine 1203 with an atomizer at 0.77 × the generation model."""
    from ajtwin.simulation.truth_alt import off_model_atomizer_machine

    return off_model_atomizer_machine(1203)


def test_off_model_atomizer_is_drawn_per_machine_and_only_on_the_second_generator(
    off_model_machine,
):
    from dataclasses import replace

    from ajtwin.simulation.truth_alt import off_model_atomizer_machine

    outputs = [off_model_atomizer_machine(seed).atomizer_output for seed in range(1201, 1221)]
    assert all(0.7 <= v <= 1.3 for v in outputs) and np.ptp(outputs) > 0.3
    assert off_model_atomizer_machine(1203) == off_model_machine  # reproducible
    # everything but the atomizer is the machine of the same seed
    assert replace(off_model_machine, name="seed-1203", atomizer_output=1.0,
                   atomizer_wander_per_h=0.0) == draw_machine(1203)  # fmt: skip
    with pytest.raises(ValueError, match="second truth generator"):
        run_virtual_print("exp1", seed=1, duration_min=1.0, machine=off_model_machine)
    plain = run_virtual_print(
        "exp1", seed=3, duration_min=10.0, machine_seed=1203, truth_generator="alt"
    )
    off = run_virtual_print(
        "exp1", seed=3, duration_min=10.0, machine=off_model_machine, truth_generator="alt"
    )
    # the aerosol follows the atomizer's factor (and its per-print trend) within seconds
    draws = off.record.meta["truth_draws"]
    hours = np.arange(len(off.states)) / 3600.0
    expected = off_model_machine.atomizer_output * (1.0 + draws["atomizer_trend_per_h"] * hours)
    ratio = off.states[:, 4] / plain.states[:, 4]
    assert np.allclose(ratio[30:], expected[30:], rtol=2e-3)
    assert abs(draws["atomizer_trend_per_h"]) <= 0.12
    # the next print of the machine keeps its atomizer
    nxt = run_virtual_print(
        "exp1", seed=4, duration_min=1.0, continue_from=off.record, truth_generator="alt"
    )
    assert nxt.machine.atomizer_output == off_model_machine.atomizer_output


def test_aerosol_level_posterior_by_hand():
    from ajtwin.estimation.commission import aerosol_level_posterior

    # no pin: the level stays at the prior and the gain takes the whole product
    mean, cov = aerosol_level_posterior(0.8, 0.02, 0.35)
    assert mean == pytest.approx([np.log(0.8), 0.0], abs=1e-12)
    assert np.sqrt(cov[0, 0]) == pytest.approx(np.hypot(0.02, 0.35), rel=1e-9)
    # a weighed level ρ ± r combines with the prior as two measurements of b
    mean, cov = aerosol_level_posterior(0.8, 0.02, 0.35, ink_used=(0.75, 0.05))
    w = (1 / 0.05**2) / (1 / 0.05**2 + 1 / 0.35**2)
    assert mean[1] == pytest.approx(w * np.log(0.75), rel=1e-9)
    assert cov[1, 1] == pytest.approx(1 / (1 / 0.05**2 + 1 / 0.35**2), rel=1e-9)
    assert mean[0] + mean[1] == pytest.approx(np.log(0.8), abs=1e-3)  # the product holds
    # a known gain m: b = ln p − ln m with variance r_p² + r_m², then the prior
    mean, cov = aerosol_level_posterior(0.8, 0.02, 0.35, gain=(1.0, 0.03))
    v = 0.02**2 + 0.03**2
    assert cov[1, 1] == pytest.approx(1 / (1 / v + 1 / 0.35**2), rel=1e-9)
    assert mean[1] == pytest.approx(np.log(0.8) * (1 / v) / (1 / v + 1 / 0.35**2), rel=1e-9)


@pytest.fixture(scope="module")
def pinned_commissionings(off_model_machine):
    """The same commissioning print of the off-model machine, commissioned without a pin,
    with a profilometer-calibrated gain and with the vial weighed."""
    from ajtwin.studies.machine import commission_virtual_machine

    out = {}
    for pin in ("none", "gain", "vial"):
        comm, done, _ = commission_virtual_machine(
            4001, "alt", off_model_machine, learn_noise_scale=False, pin=pin
        )
        out[pin] = done.result
    return comm, out


def test_a_pin_moves_phi_and_the_gain_apart(pinned_commissionings):
    comm, results = pinned_commissionings
    true_gain = comm.machine.calibration().material_flow_gain
    atomizer = comm.machine.atomizer_output
    free = results["none"]
    # without a pin the gain takes the atomizer's deficit, and says it rests on the prior
    assert free.calibration.material_flow_gain == pytest.approx(true_gain * atomizer, rel=0.08)
    assert abs(free.calibration.material_flow_gain - true_gain) > 0.15
    assert free.aerosol_level["pinned_by"] == []
    assert free.aerosol_level["relative_std"] == pytest.approx(0.35)
    assert free.std["material_flow_gain"] > 0.3 * free.calibration.material_flow_gain
    assert "known only relative to the generation model" in free.notes[-1]
    for pin, name in (("gain", "material_flow_gain"), ("vial", "vial weighing")):
        r = results[pin]
        gain, std = r.calibration.material_flow_gain, r.std["material_flow_gain"]
        assert abs(gain - true_gain) < 0.06 and abs(gain - true_gain) < 2.5 * std, pin
        assert r.aerosol_level["pinned_by"] == [name]
        assert r.aerosol_level["relative"] == pytest.approx(atomizer, rel=0.1), pin
        assert r.aerosol_level["relative_std"] < 0.1
        # the machine ends the print with φ_A at the atomizer's level, not the model's
        assert r.end_state[4] == pytest.approx(comm.states[-1, 4], rel=0.1), pin
        assert r.aerosol_level["theta_per_s"] < 0.0  # θ_φA holds a deficit
    assert free.end_state[4] > 1.2 * comm.states[-1, 4]


def test_phi_band_without_a_pin_is_as_wide_as_the_generation_prior(pinned_commissionings):
    from ajtwin.engine.commissioning import calibrated_twin, commissioned_start

    comm, results = pinned_commissionings
    nxt = run_virtual_print(
        "exp1", seed=4002, duration_min=20.0, continue_from=comm.record, truth_generator="alt"
    )
    truth = nxt.states[:, 4]
    for pin in ("none", "gain"):
        result = results[pin]
        run = calibrated_twin(result).run(nxt.record, start=commissioned_start(result))
        z = (run.means[:, 4] - truth) / run.stds[:, 4]
        late = slice(300, None)  # after the first EM updates
        if pin == "none":
            # the band holds the level's prior: 0.35 of φ_A at least, and the truth
            assert np.all(run.stds[late, 4] >= 0.35 * run.means[late, 4] * 0.999)
            assert np.mean(np.abs(z[late]) <= 2.0) >= 0.85
            assert np.median(np.abs(run.means[late, 4] / truth[late] - 1)) > 0.15  # honestly far
        else:
            assert np.max(np.abs(run.means[late, 4] / truth[late] - 1)) < 0.10
            assert np.mean(np.abs(z[late]) <= 2.0) >= 0.85
            assert np.median(run.stds[late, 4] / run.means[late, 4]) < 0.1


def test_calibration_file_keeps_the_aerosol_level(tmp_path, pinned_commissionings):
    from ajtwin.engine.commissioning import write_calibration

    _, results = pinned_commissionings
    path = write_calibration(tmp_path / "cal.toml", results["vial"], {"print": "c.parquet"})
    _, data = read_calibration_file(path)
    level = data["aerosol_level"]
    assert level["pinned_by"] == ["vial weighing"]
    assert level["relative"] == pytest.approx(results["vial"].aerosol_level["relative"])


def test_bad_level_pins_are_refused_clearly():
    from ajtwin.estimation.commission import parse_amount

    rec = simulate("commissioning", seed=5, duration_min=6.0)
    with pytest.raises(CommissioningError, match="check the weighing"):
        commission(rec, vial_used_ml=(0.2, 0.01))  # 0.2 mL: ~2000× the model's draw
    with pytest.raises(ValueError, match="positive uncertainty"):
        parse_amount("1e-4", "--vial-used-ml")
    assert parse_known(["material_flow_gain=1.00±0.03"]) == {"material_flow_gain": (1.0, 0.03)}


def test_estimate_says_phi_is_relative_to_the_generation_model(tmp_path, pinned_commissionings):
    import pandas as pd
    from click.testing import CliRunner

    from ajtwin.cli import main
    from ajtwin.engine.commissioning import write_calibration
    from ajtwin.io.records import write_record

    comm, results = pinned_commissionings
    record = tmp_path / "next.parquet"
    nxt = simulate("exp1", seed=4003, duration_min=4.0, continue_from=comm.record,
                   truth_generator="alt")  # fmt: skip
    write_record(nxt, record)
    runner = CliRunner()
    for pin, says in (
        ("none", "known only relative to the generation model (±35%)"),
        ("vial", "φ_A pinned by vial weighing"),
    ):
        cal = write_calibration(tmp_path / f"{pin}.toml", results[pin], {"print": "c"})
        out = tmp_path / f"{pin}.csv"
        res = runner.invoke(
            main, ["estimate", str(record), "--calibration", str(cal), "--out", str(out)]
        )
        assert res.exit_code == 0, res.output
        assert says in res.output
        frame = pd.read_csv(out)
        relative = frame["aerosol_fraction_std"] / frame["aerosol_fraction"]
        if pin == "none":
            assert relative.min() >= 0.35 * 0.999  # the band is the prior's, at least
        else:
            assert relative.median() < 0.1
    res = runner.invoke(main, ["estimate", str(record), "--out", str(tmp_path / "n.csv")])
    assert "takes the nominal Q_m scale as exact" in res.output


def test_machine_show_and_the_dashboard_say_how_well_phi_is_known(tmp_path, pinned_commissionings):
    """Never commissioned, commissioned without a pin, and with the vial weighed: `machine
    show` and the machine page's care fields each say which, in words a user reads."""
    from click.testing import CliRunner

    from ajtwin.cli import main
    from ajtwin.engine.commissioning import Commissioning, save_commissioning
    from ajtwin.engine.views import care_fields
    from ajtwin.store.registry import Registry

    _, results = pinned_commissionings
    store = tmp_path / "r.sqlite"
    with Registry(store) as reg:
        for name in ("bare", "free", "weighed"):
            reg.add_machine(name)
        save_commissioning(reg, "free", Commissioning(results["none"], None), "c.parquet")
        save_commissioning(reg, "weighed", Commissioning(results["vial"], None), "c.parquet")
        care = {
            name: care_fields(reg, name)["aerosol_level"] for name in ("bare", "free", "weighed")
        }
    level = results["vial"].aerosol_level
    says = {
        "bare": "not commissioned",
        "free": "known only relative to the generation model (±35%)",
        "weighed": f"φ_A pinned by vial weighing: the atomizer delivers {level['relative']:.2f}",
    }
    runner = CliRunner()
    for name, text in says.items():
        res = runner.invoke(main, ["machine", "show", name, "--store", str(store)])
        assert res.exit_code == 0, res.output
        assert text in res.output, name
        assert text in care[name]["note"], name
    assert care["free"]["pinned_by"] == [] and care["free"]["relative_std"] == pytest.approx(0.35)
    assert care["weighed"]["pinned_by"] == ["vial weighing"]
    assert care["weighed"]["relative_std"] < 0.1


def test_the_off_model_atomizer_study_runs_a_small_real_instance():
    """`python -m ajtwin.studies.machine --atomizer-variant --pin gain` on one machine and a
    30-min print (its first check): the study's own path (commission with the pin, the next
    print, the table)."""
    from ajtwin.studies.machine import _atomizer_lines, evaluate_machine

    m = evaluate_machine(machine_seed=1203, print_seed=4001, minutes=30.0, clog=False,
                         atomizer_variant=True, pin="gain")  # fmt: skip
    assert m["machine"] == "seed-1203-atomizer" and m["atomizer_output"] < 0.8
    assert m["aerosol_level"]["pinned_by"] == ["material_flow_gain"]
    assert m["aerosol_level"]["relative"] == pytest.approx(m["atomizer_output"], rel=0.1)
    gain = m["calibration_recovery"]["material_flow_gain"]
    assert abs(gain["z"]) < 3 and gain["determined"]
    assert m["after"]["coverage"]["φ_A"] >= 0.85
    assert m["after"]["errors"]["30min"]["phi_A_rel"] < 0.10
    table = _atomizer_lines({"pin": "gain", "machines": [m]})
    assert f"| seed-1203-atomizer | {m['atomizer_output']:.3f} |" in table
