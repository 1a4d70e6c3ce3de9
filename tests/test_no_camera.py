"""A machine without a camera, and a camera that drops out.

Truth is the virtual printer (ajtwin.simulation): a print whose L_w, L_o and Q_m columns are
removed must still give finite states, ΔR_N within 5 nm of the truth from the pressures,
and bands of d_a and φ_A that the data do not narrow (they equal the bands of a run that
sees no output at all, and d_a's never falls below its prior σ).
"""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.engine.messages import StepMessage
from ajtwin.estimation import Twin
from ajtwin.io.records import PrintRecord, write_record
from ajtwin.model.parameters import load_noise
from ajtwin.simulation import simulate

LINE_COLUMNS = ["linewidth_um", "overspray_um", "material_flow_mL_s"]
DA, VL, DRT, DRN, PHI = range(5)


def _blind(record, columns, start=None, stop=None) -> PrintRecord:
    data = record.data.copy()
    rows = slice(None) if start is None else (data["time_s"] >= start) & (data["time_s"] < stop)
    data.loc[rows, columns] = np.nan
    return PrintRecord(data, dict(record.meta))


@pytest.fixture(scope="module")
def clog_print():
    """A nozzle clog (ΔR_N grows through the print): the deposit has something to track."""
    return simulate(
        "nozzle_clog", seed=3, duration_min=30.0, overrides={"fault": {"onset_min": 5.0}}
    )


@pytest.fixture(scope="module")
def camera_less_run(clog_print):
    return Twin.default().run(_blind(clog_print, LINE_COLUMNS))


def test_prior_start_values_come_from_the_data_file(clog_print, camera_less_run):
    prior = load_noise(tuning="calibrated")["prior_initial"]
    initial = camera_less_run.initial
    assert initial.states_from_prior == ("droplet_diameter_um", "aerosol_fraction")
    assert initial.mean[DA] == prior["droplet_diameter_mean_um"]
    assert np.sqrt(initial.covariance[DA, DA]) == prior["droplet_diameter_um"]
    twin = Twin.default()
    phi_ss = float(twin.model.steady_aerosol_fraction(clog_print.inputs[0], 1.0))
    assert initial.mean[PHI] == pytest.approx(phi_ss, rel=1e-12)
    assert np.sqrt(initial.covariance[PHI, PHI]) == pytest.approx(
        prior["aerosol_fraction_relative"] * phi_ss, rel=1e-12
    )


def test_camera_less_states_finite_and_nozzle_tracked(clog_print, camera_less_run):
    run = camera_less_run
    assert np.all(np.isfinite(run.means)) and np.all(np.isfinite(run.stds))
    truth = clog_print.true_states
    growth = truth[-1, DRN] - truth[0, DRN]
    assert growth > 0.05  # the clog really moves ΔR_N (> 50 nm): tracking is tested
    after_start = slice(120, None)  # the prior's 50 nm σ settles within the first minutes
    error = np.abs(run.means[after_start, DRN] - truth[after_start, DRN])
    assert error.max() < 5e-3  # within 5 nm of the truth, from the pressures alone


def test_camera_less_bands_stay_at_what_the_model_alone_gives(clog_print, camera_less_run):
    """No output sees d_a or φ_A: their σ equal those of a run that measures nothing."""
    nothing = Twin.default(em=False).run(
        _blind(clog_print, LINE_COLUMNS + ["carrier_pressure_Pa", "sheath_pressure_Pa"])
    )
    pressures_only = Twin.default(em=False).run(_blind(clog_print, LINE_COLUMNS))
    prior_sigma = load_noise(tuning="calibrated")["prior_initial"]["droplet_diameter_um"]
    for run in (pressures_only, camera_less_run):
        assert np.all(run.stds[:, DA] >= prior_sigma * (1 - 1e-9))  # never narrowed by data
    np.testing.assert_allclose(pressures_only.stds[:, DA], nothing.stds[:, DA], rtol=0.02)
    np.testing.assert_allclose(pressures_only.stds[:, PHI], nothing.stds[:, PHI], rtol=0.05)
    # …while the camera, when present, narrows d_a by an order of magnitude
    with_camera = Twin.default(em=False).run(clog_print)
    assert np.median(with_camera.stds[:, DA]) < 0.1 * np.median(pressures_only.stds[:, DA])


def test_camera_less_run_says_which_states_it_cannot_see(camera_less_run):
    seen = camera_less_run.seen
    assert not seen[:, DA].any() and not seen[:, PHI].any() and not seen[:, VL].any()
    assert seen[:, DRN].all() and seen[:, DRT].all()
    frame = camera_less_run.to_frame()
    assert (frame["seen_droplet_diameter_um"] == 0).all()
    assert (frame["seen_nozzle_deposition_um"] == 1).all()
    n = len(frame)
    assert camera_less_run.unseen_summary() == {"droplet_diameter_um": n, "aerosol_fraction": n}


def test_camera_dropout_keeps_states_finite_and_widens_the_bands():
    record = simulate("exp1", seed=4, duration_min=20.0)
    start, stop = 300.0, 600.0  # the camera is gone for 5 minutes
    run = Twin.default().run(_blind(record, LINE_COLUMNS, start, stop))
    assert np.all(np.isfinite(run.means)) and np.all(np.isfinite(run.stds))
    k0, k1 = int(start), int(stop)
    before, during = run.stds[k0 - 1, DA], run.stds[k1 - 1, DA]
    # nothing sees d_a in the gap: its variance grows by the process noise, q² per second
    q = Twin.default().config.process_std[DA]
    assert during == pytest.approx(np.sqrt(before**2 + (k1 - k0) * q**2), rel=0.02)
    assert during > 2 * before  # the band widens while nothing sees d_a …
    assert run.stds[k1 + 60, DA] < 0.5 * during  # … and closes again when the camera returns
    assert not run.seen[k0:k1, DA].any() and run.seen[:k0, DA].all() and run.seen[k1:, DA].all()
    truth = record.true_states
    assert np.abs(run.means[:, DRN] - truth[:, DRN])[120:].max() < 5e-3
    z = np.abs(run.means[k0:k1, DA] - truth[k0:k1, DA]) / run.stds[k0:k1, DA]
    assert np.mean(z < 2) > 0.9  # the widened band still holds the truth


def test_estimate_cli_on_a_camera_less_record(tmp_path, clog_print):
    from ajtwin.cli.estimate import estimate

    record = _blind(clog_print.window(0, 300), LINE_COLUMNS)
    data = record.data.drop(columns=LINE_COLUMNS)  # the columns removed, not only NaN
    path = write_record(PrintRecord(data, record.meta), tmp_path / "nocam.csv")
    result = CliRunner().invoke(estimate, [str(path), "--out", str(tmp_path / "s.csv")])
    assert result.exit_code == 0, result.output
    assert "start from their priors" in result.output
    assert "cannot see them" in result.output and "droplet_diameter_um" in result.output
    import pandas as pd

    frame = pd.read_csv(tmp_path / "s.csv")
    assert frame.filter(like="droplet").notna().all().all()
    assert (frame["seen_droplet_diameter_um"] == 0).all()


def test_ingest_cli_on_a_camera_less_record(tmp_path, clog_print):
    from ajtwin.cli.ingest import ingest
    from ajtwin.cli.machine import machine

    record = _blind(clog_print.window(0, 300), LINE_COLUMNS)
    path = write_record(record, tmp_path / "nocam.parquet")
    store = str(tmp_path / "r.sqlite")
    runner = CliRunner()
    assert runner.invoke(machine, ["add", "M", "--store", store]).exit_code == 0
    result = runner.invoke(ingest, ["--machine", "M", "--store", store, str(path), "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "start from their priors" in result.output and "cannot see them" in result.output


def test_never_seen_states_keep_the_prior_relative_width(clog_print, camera_less_run):
    """φ_A relaxes to the generation model's steady state within seconds, which alone
    contracts its variance to the process noise's (a few %): a band the data never earned.
    A state taken from its prior and never seen keeps the prior's relative width."""
    run = camera_less_run
    prior = run.initial
    for i in (DA, PHI):
        relative = np.sqrt(prior.covariance[i, i]) / prior.mean[i]
        assert np.all(run.stds[:, i] >= relative * np.abs(run.means[:, i]) * (1 - 1e-12))
    model_only = np.sqrt(np.asarray(run.filtered.covariances)[:, PHI, PHI])
    assert np.median(model_only / run.means[:, PHI]) < 0.1  # what the band was before
    np.testing.assert_allclose(run.stds[:, PHI] / run.means[:, PHI], 0.5, rtol=1e-9)
    # the deposits, which the pressures see, are untouched by the floor
    deposit = np.sqrt(np.asarray(run.filtered.covariances)[:, DRN, DRN])
    np.testing.assert_array_equal(run.stds[:, DRN], deposit)
    # the CSV and the registry take the same σ
    assert np.array_equal(run.to_frame(smoothed=False)["aerosol_fraction_std"], run.stds[:, PHI])


def test_a_camera_that_saw_the_start_gets_no_prior_floor():
    """States fitted from data (camera at the start) keep the filter's bands, also in a
    later dropout (the floor is for what the data never constrained)."""
    record = simulate("exp1", seed=4, duration_min=6.0)
    run = Twin.default(em=False).run(_blind(record, LINE_COLUMNS, 120.0, 240.0))
    assert run.prior_floor is None and not run.initial.states_from_prior
    covariances = np.asarray(run.filtered.covariances)
    np.testing.assert_array_equal(run.stds, np.sqrt(np.einsum("tii->ti", covariances)))


@pytest.mark.parametrize("truth_generator", ["model", "alt"])
def test_camera_less_aerosol_band_holds_the_truth(truth_generator):
    """On both truth generators (alt: a generation efficiency that drifts as a sinusoid
    and a trend, not the model's wander) the camera-less φ_A band holds the truth at
    every second; the model's own band (before) missed it a third of the time on seed 1."""
    record = simulate("exp1", seed=1, duration_min=12.0, truth_generator=truth_generator)
    run = Twin.default().run(_blind(record, LINE_COLUMNS))
    truth = record.true_states[:, PHI]
    z = np.abs(run.means[:, PHI] - truth) / run.stds[:, PHI]
    assert np.all(z < 2)
    model_only = np.sqrt(np.asarray(run.filtered.covariances)[:, PHI, PHI])
    z_model = np.abs(run.means[60:, PHI] - truth[60:]) / model_only[60:]
    if truth_generator == "model":
        assert np.mean(z_model < 2) < 0.9


def test_live_stream_reports_the_same_camera_less_bands_as_the_batch_twin(clog_print):
    """One math path: the live twin's published σ and stored arrays carry the same floor."""
    from ajtwin.engine.stream import TwinStream
    from ajtwin.estimation.samples import Sample

    record = _blind(clog_print.window(0, 180), LINE_COLUMNS)
    run = Twin.default(em=False).run(record)
    stream = TwinStream.new("m", twin_overrides={"em": False}, asynchronous=False)
    messages = []
    for t, u, y in zip(record.time_s, record.inputs, record.outputs, strict=True):
        messages += stream.feed(Sample(t, u, y))
    messages += stream.finish()
    stds = stream.arrays()["stds"]
    np.testing.assert_allclose(stds, run.stds, rtol=1e-9)
    published = [m.to_dict() for m in messages if isinstance(m, StepMessage) and not m.provisional]
    phi = np.array([m["stds"]["aerosol_fraction"] for m in published])
    np.testing.assert_allclose(phi, run.stds[:, PHI], rtol=1e-9)
    assert np.all(stds[:, PHI] >= 0.49 * stream.arrays()["means"][:, PHI])
