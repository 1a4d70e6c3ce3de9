"""the model–machine mismatch guard, commissioned clogs, maintenance events."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.mismatch import MISMATCH_CAUSE, assess, assess_run, relabel_events
from ajtwin.estimation.commission import commission
from ajtwin.estimation.twin import Twin
from ajtwin.simulation.machine import MachineDeviation
from ajtwin.simulation.printer import simulate

LINE_OFFSET = MachineDeviation(name="line-30", linewidth_offset_um=-30.0)
GAUGE_GAIN = MachineDeviation(name="gauge+8%", carrier_gauge_gain=1.08, sheath_gauge_gain=1.08)


def _guard(record, twin=None, start=None):
    run = (twin or Twin.default()).run(record, start=start)
    return run, assess_run(run, record)


def test_guard_unit_bias_and_range():
    n = 400
    t = np.arange(float(n))
    x = np.tile([3.5, 1.0, 0.0, 0.01, 4.6e-7], (n, 1))
    e = np.random.default_rng(0).standard_normal((n, 5)) * 0.3
    quiet = assess(t, x, e, np.full(n, 5.0), np.full(n, 5))
    assert not quiet.mismatch and quiet.first_s is None
    biased = e.copy()
    biased[200:, 1] += 2.0  # overspray 2 σ above the model from 200 s
    status = assess(t, x, biased, np.full(n, 5.0), np.full(n, 5))
    assert status.mismatch and status.outputs == ["overspray_um"]
    assert 200 <= status.first_s <= 200 + 300  # needs its window of evidence
    bad = x.copy()
    bad[100:, 1] = -2.35  # the negative vial
    status = assess(t, bad, e, np.full(n, 5.0), np.full(n, 5))
    assert status.states == ["vial_volume_mL"] and status.first_s == 100.0


def test_guard_judges_q_m_level_only_once_em_could_learn_it():
    """Q_m's level (the print's atomizer efficiency) is θ_φA's to learn: an offset before
    the first EM update is not a misfit, the same offset after it is; other outputs are
    judged from the warm-up as before."""
    n = 1500
    t = 100.0 + np.arange(float(n))  # a clock that does not start at 0
    x = np.tile([3.5, 1.0, 0.0, 0.01, 4.6e-7], (n, 1))
    e = np.random.default_rng(1).standard_normal((n, 5)) * 0.3
    level = e.copy()
    level[:600, 4] += 1.0  # Q_m 1 σ high until EM (first update at t = 700) absorbs it
    args = (np.full(n, 5.0), np.full(n, 5))
    assert assess(t, x, level, *args).outputs == ["material_flow_mL_s"]  # no EM: a misfit
    assert not assess(t, x, level, *args, level_learned_s=700.0).mismatch
    late = e.copy()
    late[900:, 4] += 1.0  # still off after EM's update: the model does not fit
    status = assess(t, x, late, *args, level_learned_s=700.0)
    assert status.outputs == ["material_flow_mL_s"] and 900 - 100 <= status.first_s <= 1200
    # a part window right after the update is no evidence (θ's own transient): a whole one
    spike = e.copy()
    spike[600:640, 4] += 3.0  # a 40-s transient: 3 σ on a part window, 0.4 σ on a whole
    assert not assess(t, x, spike, *args, level_learned_s=700.0).mismatch
    line = e.copy()
    line[:, 1] += 1.0  # overspray off alone (Q_m on the model): a line misfit from the warm-up
    status = assess(t, x, line, *args, level_learned_s=700.0)
    assert status.outputs == ["overspray_um"] and status.first_s == 60.0  # 60 s of evidence
    # overspray and Q_m off the same way in the first minutes: the atomizer level (1061/1087)
    both = e.copy()
    both[:200, 1] += 1.0
    both[:200, 4] += 1.2
    assert not assess(t, x, both, *args, level_learned_s=150.0).mismatch
    # ... but not without EM, nor when Q_m moves the other way, nor once the level is learned
    assert assess(t, x, both, *args).outputs == ["overspray_um", "material_flow_mL_s"]
    against = both.copy()
    against[:200, 4] -= 2.4
    assert assess(t, x, against, *args, level_learned_s=150.0).outputs == ["overspray_um"]
    late = e.copy()
    late[900:, 1] += 1.0
    late[900:, 4] += 1.2
    assert assess(t, x, late, *args, level_learned_s=150.0).outputs == [
        "overspray_um",
        "material_flow_mL_s",
    ]


def test_guard_flags_a_deposit_below_zero_beyond_its_noise():
    """Uncommissioned alt machines 1029/1135: ΔR_N −42/−76 nm at σ 0.6 nm, nothing else off."""
    n = 400
    t = np.arange(float(n))
    x = np.tile([3.5, 1.0, 0.0, 0.0, 4.6e-7], (n, 1))
    e = np.random.default_rng(2).standard_normal((n, 5)) * 0.3
    sd = np.tile([0.03, 0.003, 1e-3, 6e-4, 1e-8], (n, 1))
    args = (np.full(n, 5.0), np.full(n, 5))
    x[:, 3] = np.where(t < 100, 0.0, -0.076)
    status = assess(t, x, e, *args, stds=sd)
    assert status.states == ["nozzle_deposition_um"] and status.first_s == 100.0
    assert "cannot be negative" in status.reasons[0] and "-76.0 nm" in status.reasons[0]
    assert not assess(t, x, e, *args).mismatch  # without σ the test cannot run
    # within the floor + 3σ (5 nm + 1.8 nm): a clean nozzle's estimate dipping in its noise
    x[:, 3] = -0.0065
    assert not assess(t, x, e, *args, stds=sd).mismatch
    x[:, 3] = -0.0070
    assert assess(t, x, e, *args, stds=sd).states == ["nozzle_deposition_um"]
    # a wide σ (an unseen deposit) excuses the same value
    wide = sd.copy()
    wide[:, 3] = 0.05
    assert not assess(t, x, e, *args, stds=wide).mismatch


@pytest.mark.parametrize(
    "machine, expect_output, expect_state",
    [
        (LINE_OFFSET, "overspray_um", "droplet_diameter_um"),
        (GAUGE_GAIN, None, "nozzle_deposition_um"),
    ],
    ids=["line_offset_-30um", "pressure_gain_+8%"],
)
def test_guard_fires_on_an_offset_line_and_a_gauge_gain_within_5_min(
    machine, expect_output, expect_state
):
    record = simulate("exp1", seed=301, duration_min=6.0, machine=machine)
    _, status = _guard(record)
    assert status.mismatch
    assert status.first_s <= 300.0
    assert expect_state in status.states
    if expect_output:
        assert expect_output in status.outputs
    assert "commission" in status.message


def test_guard_is_silent_on_the_nominal_machine():
    record = simulate("exp1", seed=301, duration_min=12.0)
    _, status = _guard(record)
    assert not status.mismatch, status.message
    assert not status.flags.any()


def test_clog_on_a_commissioned_machine_is_detected_and_labelled():
    # commission machine seed 3, then print on it with a clog 5 min into the print
    commissioning = simulate("commissioning", seed=21, machine_seed=3)
    result = commission(commissioning, known={"droplet_diameter_um": (3.45, 0.2)})
    clog = simulate(
        "nozzle_clog",
        seed=22,
        duration_min=12.0,
        continue_from=commissioning,
        overrides={"fault": {"onset_min": 5.0}},
    )
    assert clog.meta["machine"]["name"] == "seed-3"  # the same machine prints again
    twin = Twin.default(calibration=result.calibration)
    run, status = _guard(clog, twin, start=(result.end_state, result.end_state_cov))
    events = relabel_events(detect_run(run, clog).events, status)
    onset = clog.meta["fault_onset_s"]
    clogs = [ev for ev in events if ev.cause == "nozzle_clog"]
    assert clogs, [(ev.cause, ev.detected_s) for ev in events]
    assert clogs[0].detected_s - onset <= 60.0
    assert not [ev for ev in events if ev.detected_s < onset]  # nothing before the clog
    # the same print read with the nominal model: the guard says mismatch instead
    _, uncommissioned = _guard(clog)
    assert uncommissioned.mismatch and uncommissioned.first_s <= 300.0


def test_mismatch_relabels_start_events_but_not_later_faults():
    from ajtwin.apps.detection.mismatch import MismatchStatus
    from ajtwin.apps.detection.streaming import AnomalyEvent

    status = MismatchStatus(True, 40.0, ["overspray_um"], [], ["r"], ["f"], "m", np.ones(10, bool))
    early = AnomalyEvent(75.0, 20.0, "nozzle_clog", "clog")
    late = AnomalyEvent(3000.0, 2950.0, "nozzle_clog", "clog")
    out = relabel_events([early, late], status)
    assert out[0].cause == MISMATCH_CAUSE and out[0].evidence["relabelled_from"] == "nozzle_clog"
    assert out[1].cause == "nozzle_clog"
    later = MismatchStatus(True, 4000.0, [], [], ["r"], ["f"], "m", np.ones(10, bool))
    assert relabel_events([AnomalyEvent(3000.0, 2950.0, "nozzle_clog", "c")], later)[0].cause == (
        "nozzle_clog"
    )


def test_maintenance_resets_what_it_names(tmp_path):
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.engine.start import apply_maintenance
    from ajtwin.store.calibration import maintenance_history, record_maintenance
    from ajtwin.store.registry import Registry

    mean = np.array([3.4, 0.7, 1e-4, 0.09, 4.5e-7])
    cov = np.full((5, 5), 1e-6) + np.diag([1e-2, 1e-4, 1e-8, 1e-4, 1e-16])
    theta = np.array([1e-5, 0.0, 1e-4, 2e-3, 1e-2])
    m2, c2, t2 = apply_maintenance(mean, cov, theta, [{"nozzle_cleaned": True}])
    assert m2[3] == 0.0 and t2[3] == 0.0 and c2[3, 3] == pytest.approx(2e-3**2)
    assert np.all(c2[3, [0, 1, 2, 4]] == 0.0) and m2[1] == 0.7 and t2[4] == 1e-2
    m3, c3, t3 = apply_maintenance(
        mean, cov, theta, [{"vial_refilled_ml": 1.2, "reset_theta": True}]
    )
    assert m3[1] == 1.2 and m3[3] == 0.09 and np.all(t3 == 0.0)

    reg = Registry(tmp_path / "r.sqlite")
    reg.add_machine("aj")
    with pytest.raises(ValueError, match="must name what was done"):
        record_maintenance(reg, "aj")
    first = simulate("exp1", seed=5, duration_min=2.0)
    ingest_record(reg, "aj", first)
    record_maintenance(reg, "aj", nozzle_cleaned=True, vial_refilled_ml=1.1, reset_theta=True)
    second = simulate("exp1", seed=6, duration_min=2.0, continue_from=first)
    result = ingest_record(reg, "aj", second)
    stored = reg.get_print(result.print_id)
    assert stored["start_mean"][3] == 0.0 and stored["start_mean"][1] == 1.1
    assert np.all(stored["theta_before"] == 0.0)
    assert "maintenance" in result.summary["started_from"]
    # the event stays in the history but is not applied twice
    assert len(maintenance_history(reg, "aj")) == 1
    third = ingest_record(reg, "aj", simulate("exp1", seed=7, duration_min=2.0))
    assert third.summary["maintenance"] == []


def test_cli_commission_refuses_and_maintain_needs_an_action(tmp_path):
    from ajtwin.cli import main
    from ajtwin.io.records import write_record

    path = tmp_path / "flat.parquet"
    write_record(simulate("exp1", seed=1, duration_min=6.0), path)
    store = str(tmp_path / "r.sqlite")
    runner = CliRunner()
    assert runner.invoke(main, ["machine", "add", "aj", "--store", store]).exit_code == 0
    out = runner.invoke(main, ["machine", "commission", "aj", str(path), "--store", store])
    assert out.exit_code != 0 and "carrier flow varies only" in out.output
    out = runner.invoke(main, ["machine", "maintain", "aj", "--store", store])
    assert out.exit_code != 0 and "must name what was done" in out.output
    out = runner.invoke(
        main, ["machine", "commission", "aj", str(path), "--known", "d=1", "--store", store]
    )
    assert out.exit_code != 0 and "unknown state" in out.output


def test_registry_calibration_reaches_ingest_forecast_and_history(tmp_path):
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.engine.start import machine_twin
    from ajtwin.store.calibration import calibration_history, save_calibration
    from ajtwin.store.registry import Registry

    reg = Registry(tmp_path / "r.sqlite")
    reg.add_machine("m3")
    commissioning = simulate("commissioning", seed=41, duration_min=8.0, machine_seed=3)
    first = commission(commissioning)
    save_calibration(reg, "m3", first, "comm1.parquet")
    second = commission(commissioning, known={"droplet_diameter_um": (3.4, 0.1)})
    save_calibration(reg, "m3", second, "comm2.parquet")  # re-commissioning keeps history
    assert calibration_history(reg, "m3")["source"].tolist() == ["comm1.parquet", "comm2.parquet"]
    nxt = simulate("exp1", seed=42, duration_min=3.0, continue_from=commissioning)
    result = ingest_record(reg, "m3", nxt)
    assert result.summary["calibration_id"] == 2
    assert result.summary["started_from"] == "commissioning 2"
    assert np.allclose(reg.get_print(result.print_id)["start_mean"][:4], second.end_state[:4])
    assert result.summary["mismatch"]["mismatch"] is False
    twin, *_ = machine_twin(reg, "m3")
    assert twin.calibration == second.calibration


def test_start_surprise_explains_start_alarms_only():
    """A deposit that jumped at the start names P_c/P_s, but a clog on P_c/P_s an hour later
    is a clog; a deposit out of range is a misfit for the whole print."""
    from ajtwin.apps.detection.mismatch import MismatchStatus
    from ajtwin.apps.detection.streaming import AnomalyEvent

    def clog(detected_s, onset_s):
        return AnomalyEvent(detected_s, onset_s, "nozzle_clog", "clog", detectors=["cusum+ P_c"])

    nozzle = ["nozzle_deposition_um"]
    start = MismatchStatus(True, 37.0, [], nozzle, ["r"], ["f"], "m", np.ones(10, bool), nozzle)
    early, late = relabel_events([clog(80.0, 60.0), clog(3660.0, 3600.0)], start)
    assert early.cause == MISMATCH_CAUSE
    assert late.cause == "nozzle_clog"
    ranged = MismatchStatus(True, 37.0, [], nozzle, ["r"], ["f"], "m", np.ones(10, bool))
    assert relabel_events([clog(3660.0, 3600.0)], ranged)[0].cause == MISMATCH_CAUSE


def test_carried_over_print_keeps_its_clog_label(tmp_path):
    """The demo's chain: a clean print, then a print of the same machine that clogs at
    20 min. The filter's re-convergence at the second print's start moves ΔR_N by ~1.6 nm
    (2.8 σ of the carried-over prior): that is no mismatch, and the clog is a clog."""
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.store.registry import Registry

    registry = Registry(tmp_path / "r.sqlite")
    registry.add_machine("M")
    clean = simulate("exp1", seed=1, duration_min=15.0)
    faulty = simulate(
        "nozzle_clog",
        seed=2,
        duration_min=22.0,
        continue_from=clean,
        overrides={"fault": {"onset_min": 20.0}},
    )
    ingest_record(registry, "M", clean)
    second = ingest_record(registry, "M", faulty)
    assert second.summary["mismatch"]["mismatch"] is False, second.summary["mismatch"]
    causes = [(ev.cause, ev.detected_s) for ev in second.events]
    onset = faulty.meta["fault_onset_s"]
    assert [c for c, _ in causes] == ["nozzle_clog"], causes
    assert 0 <= causes[0][1] - onset <= 60.0
