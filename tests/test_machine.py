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
