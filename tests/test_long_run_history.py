"""the detectors' long-run noise scale carried from commissioning / the previous
print through the registry (schema 5), and Q_m tested against the print's own level."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from ajtwin.apps.detection.batch import detect_anomalies
from ajtwin.apps.detection.settings import CUSUM_CHANNELS, DetectorSettings
from ajtwin.apps.detection.statistics import carried_differences
from ajtwin.apps.detection.streaming import AnomalyDetector
from ajtwin.store import registry as R
from ajtwin.store.registry import Registry

X0 = [3.5, 1.0, 0.0, 0.01, 4.6e-7]


def _arrays(e):
    """detect_anomalies arguments for normalised innovations e (T, 5) with S = 1."""
    t = len(e)
    return dict(
        time_s=np.arange(t, dtype=float),
        measurements=e,
        predicted_outputs=np.zeros((t, 5)),
        innovation_variances=np.ones((t, 5)),
        nis=np.nansum(e**2, axis=1),
        n_measured=np.full(t, 5),
        means=np.tile(X0, (t, 1)),
        predicted_means=np.tile(X0, (t, 1)),
        covariances=np.tile(np.eye(5), (t, 1, 1)),
    )


def _history(pc_scale: float, n: int = 40) -> dict:
    """A stored history whose P_c differences alternate ±a: median 0, MAD a, so the
    scale is 1.4826·a = pc_scale (hand-computed); the other channels are 0 (scale 1)."""
    a = pc_scale / 1.4826
    d = np.zeros((n, len(CUSUM_CHANNELS)))
    d[:, 2] = a * np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    return {
        "channels": list(CUSUM_CHANNELS),
        "blocks": {str(b): d.tolist() for b in DetectorSettings().long_run_block_s},
    }


def test_carried_history_changes_the_threshold():
    """A gauge wander right after the warm-up, P_c +1.2σ and P_s −0.6σ for 40 s (the alt
    generator's AR(1) gauges through the shared ΔR_N, 1005's clog print at 86 s): with
    scale 1 the P_c CUSUM reaches 40·(1.2 − 0.35) = 34 > 16 and alarms; with the machine's
    carried σ_LR = 1.7 it reaches 40·(1.2/1.7 − 0.35) = 14.2 < 16 and stays quiet (P_s:
    40·(0.6 − 0.35) = 10, the sum 0.6 < k 0.7). A clog (+2σ on both pressures) still
    alarms with the history, within 16/(2/1.7 − 0.35) + 1 = 20 s on P_c."""
    s = DetectorSettings()
    e = np.zeros((400, 5))
    e[60:100, 2] = 1.2
    e[60:100, 3] = -0.6
    fresh = detect_anomalies(**_arrays(e), settings=s)
    assert [ev.detectors[0] for ev in fresh.events] == ["cusum+ P_c"]
    carried = detect_anomalies(**_arrays(e), settings=s, long_run_history=_history(1.7))
    assert carried.events == []
    detector = AnomalyDetector(s, _history(1.7))
    assert detector.long_run.scale[2] == pytest.approx(1.7)
    assert np.all(detector.long_run.scale[[0, 1, 3, 4, 5]] == 1.0)

    clog = np.zeros((400, 5))
    clog[200:, 2:4] = 2.0
    result = detect_anomalies(**_arrays(clog), settings=s, long_run_history=_history(1.7))
    assert result.events and result.events[0].cause == "nozzle_clog"
    assert 200 < result.events[0].detected_s <= 200 + 16 / (2 / 1.7 - 0.35) + 1


def test_history_round_trips_and_other_block_lengths_are_ignored():
    rng = np.random.default_rng(5)
    e = rng.standard_normal((1200, 5))
    e[:, 1] = np.nan  # a channel never measured stays NaN → None in JSON
    result = detect_anomalies(**_arrays(e))
    history = json.loads(json.dumps(result.long_run_history))
    s = DetectorSettings()
    assert s.long_run_block_s == (30, 60)
    carried = carried_differences(history, s)
    for block in s.long_run_block_s:  # 1140 steps after the warm-up: n blocks, n − 1 diffs
        d = carried[block]
        assert d.shape == ((1200 - int(s.warmup_s)) // block - 1, len(CUSUM_CHANNELS))
        assert np.isnan(d[:, 1]).all() and np.isfinite(d[:, 0]).all()
    # the next print's detector starts where this one ended
    assert np.array_equal(AnomalyDetector(s, history).long_run.scale, np.array(history["scale"]))
    other = {**history, "blocks": {"45": history["blocks"]["30"]}}
    assert carried_differences(other, s) == {}
    assert carried_differences({**history, "channels": ["L_w"]}, s) == {}
    assert carried_differences(None, s) == {}


def test_material_flow_tested_against_the_prints_own_level():
    """Q_m at +0.9σ from the start (this print's atomizer efficiency, not yet learnt by
    EM) is no fault; a −3σ dropout later is, within 16/(3 − 0.7) + 2 ≈ 9 s."""
    s = DetectorSettings()
    assert s.material_flow_reference_s > 0
    e = np.zeros((1500, 5))
    e[:, 4] = 0.9
    assert detect_anomalies(**_arrays(e), settings=s).events == []
    from dataclasses import replace

    against_zero = detect_anomalies(
        **_arrays(e), settings=replace(s, material_flow_reference_s=0.0)
    )
    assert against_zero.events  # 0.2σ above k for 1440 s: the old false alarm
    e[1000:, 4] = 0.9 - 3.0
    events = detect_anomalies(**_arrays(e), settings=s).events
    assert len(events) == 1 and events[0].detectors[0] == "cusum− Q_m"
    assert 1000 < events[0].detected_s <= 1000 + 16 / (3.0 - 0.7) + 2


# ----------------------------------------------------------------------------- registry
def _schema4(store):
    """Make a registry look like one written before schema 5."""
    conn = sqlite3.connect(store)
    conn.execute("ALTER TABLE prints DROP COLUMN long_run_json")
    conn.execute("ALTER TABLE calibrations DROP COLUMN long_run_json")
    conn.execute("UPDATE info SET value = '4' WHERE key = 'schema_version'")
    conn.commit()
    conn.close()


@pytest.fixture(scope="module")
def two_prints():
    from ajtwin.simulation.printer import simulate

    first = simulate("exp1", seed=61, duration_min=6.0)
    second = simulate("exp1", seed=62, duration_min=4.0, continue_from=first)
    return first, second


def test_schema4_registry_migrates_and_keeps_its_prints(tmp_path, two_prints):
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.engine.start import carried_long_run_history

    store = tmp_path / "r.sqlite"
    reg = Registry(store)
    reg.add_machine("m")
    old = ingest_record(reg, "m", two_prints[0])
    reg.close()
    _schema4(store)
    reg = Registry(store)
    # (later migrations follow this one: one message each)
    assert len(reg.migrated) == R.SCHEMA_VERSION - 4 and reg.migrated[0] == (
        f"{store}: migrated registry schema 4 → 5 (the detectors' long-run noise statistics "
        "per print and calibration)"
    )
    assert R.SCHEMA_VERSION >= 5 and reg.info("schema_version") == str(R.SCHEMA_VERSION)
    # the old print is read as before; it has no statistics, so nothing is carried
    assert reg.get_print(old.print_id)["seq"] == 1
    assert reg.long_run_history("m") is None
    assert carried_long_run_history(reg, "m") is None
    # the next print stores its statistics for the one after
    new = ingest_record(reg, "m", two_prints[1])
    seq, stored = reg.long_run_history("m")
    assert seq == new.seq == 2 and set(stored["blocks"]) == {"30", "60"}


def test_ingest_carries_the_previous_prints_history(tmp_path, two_prints, monkeypatch):
    from ajtwin.engine import ingest
    from ajtwin.engine.start import carried_long_run_history

    reg = Registry(tmp_path / "r.sqlite")
    reg.add_machine("m")
    seen = []

    class Spy(ingest.IngestSink):  # the detectors of an ingest start with what it carries
        def __init__(self, writer, record, settings=None, long_run_history=None, *args):
            seen.append(long_run_history)
            super().__init__(writer, record, settings, long_run_history, *args)

    monkeypatch.setattr(ingest, "IngestSink", Spy)
    first = ingest.ingest_record(reg, "m", two_prints[0], keep_run=True)
    ingest.ingest_record(reg, "m", two_prints[1])
    assert seen[0] is None  # a new machine: nothing to carry
    stored = json.loads(
        reg._db.execute(
            "SELECT long_run_json FROM prints WHERE id = ?", (first.print_id,)
        ).fetchone()[0]
    )
    assert seen[1] == stored == first.detection.long_run_history
    # 6 min print, 60 s warm-up: 10 (5) block means of 30 (60) s → 9 (4) differences
    assert len(stored["blocks"]["30"]) == 9 and len(stored["blocks"]["60"]) == 4
    # a dropped print's statistics are not carried (the print before it is)
    reg.set_status("m", 2, R.STATUS_DROPPED, "test")
    assert carried_long_run_history(reg, "m") == stored


def test_commissioning_history_is_carried_until_the_next_print(tmp_path, two_prints):
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.engine.start import carried_long_run_history
    from ajtwin.model.calibration import IDENTITY, Calibration
    from ajtwin.store.calibration import save_calibration

    class Result:  # what save_calibration reads of a CommissioningResult
        calibration = Calibration(*IDENTITY)
        std = prior_std = determined = priors = {}
        notes = []
        end_state = np.array(X0)
        end_state_cov = np.eye(5) * 1e-4
        calibration_cov = np.eye(11) * 1e-6
        noise_factors = None

    reg = Registry(tmp_path / "r.sqlite")
    reg.add_machine("m")
    ingest_record(reg, "m", two_prints[0])
    printed = reg.long_run_history("m")[1]
    commissioning = _history(1.5)
    save_calibration(reg, "m", Result(), "comm.parquet", long_run_history=commissioning)
    assert carried_long_run_history(reg, "m") == commissioning  # newer than the print
    ingest_record(reg, "m", two_prints[1])
    assert carried_long_run_history(reg, "m") == reg.long_run_history("m")[1] != printed


def _false_alarm_then_clog(e, onset: int) -> dict:
    """Detector arrays: innovations ``e`` (T, 5) with both pressures +1.5σ from ``onset``,
    where the filter pushes ΔR_N up (a clog)."""
    e[onset:, 2:4] = 1.5
    predicted = np.tile(X0, (len(e), 1))
    predicted[onset:, 3] -= 1e-3
    return {**_arrays(e), "predicted_means": predicted}


def test_a_clog_after_a_false_alarm_of_another_channel_is_its_own_event():
    """A Q_m false alarm at ~70 s, then a clog (both pressures +1.5σ) at 300 s: within
    merge_s (300 s) of it, but on another family of channels and more than 120 s after its
    last alarm, so the clog is reported as a clog (before: swallowed into the Q_m event)."""
    s = DetectorSettings()
    e = np.zeros((900, 5))
    e[61:80, 4] = -4.0  # a short Q_m dip (after the warm-up)
    args = _false_alarm_then_clog(e, 300)
    events = detect_anomalies(**args, settings=s).events
    assert [ev.cause for ev in events][-1] == "nozzle_clog", [
        (ev.cause, ev.detectors) for ev in events
    ]
    assert events[0].detectors[0] == "cusum− Q_m" and len(events) == 2
    assert 300 < events[1].detected_s <= 300 + 16 / (3.0 - 0.7) + 2  # the common channel
    from dataclasses import replace

    merged = detect_anomalies(**args, settings=replace(s, merge_other_family_s=1e9)).events
    assert len(merged) == 1 and merged[0].cause != "nozzle_clog"


def test_a_clog_after_a_quiet_false_alarm_of_the_same_family_is_its_own_event():
    """A pressure false alarm at ~70 s, quiet after it, then a clog at 420 s: more than
    merge_s (300 s) after the false alarm's last alarm, so the clog opens its own event
    (with merge_s 600 it was swallowed: held-out alt machines 1015, 1054)."""
    s = DetectorSettings()
    e = np.zeros((1000, 5))
    e[61:90, 2] = 3.0  # a short P_c excursion after the warm-up
    args = _false_alarm_then_clog(e, 420)
    events = detect_anomalies(**args, settings=s).events
    assert len(events) == 2 and events[1].cause == "nozzle_clog", [
        (ev.detected_s, ev.cause, ev.detectors) for ev in events
    ]
    assert events[0].detected_s < 100 and 420 < events[1].detected_s < 440
    from dataclasses import replace

    merged = detect_anomalies(**args, settings=replace(s, merge_s=600.0)).events
    assert len(merged) == 1 and merged[0].detected_s < 100


def test_deposit_seen_on_one_gauge_with_delta_rn_pushed_up_is_a_clog():
    from ajtwin.apps.detection.causes import label_cause

    s = DetectorSettings()
    # held-out machine 1006 (alt): P_s +0.69σ, P_c +0.13σ over 159 s, ΔR_N pushed +45σ
    mean, n, shift = [0.03, -0.19, 0.13, 0.69, -0.35], [159] * 5, [0, 0, 0, 45.6, -14.3]
    assert label_cause(mean, n, shift, 1.0, s) == "nozzle_clog"
    # the same gauges with ΔR_N not pushed up stay unexplained; P_c falling stays a leak
    assert label_cause(mean, n, [0, 0, 0, 0.5, 0], 1.0, s) == "unexplained"
    assert label_cause([0, 0, -0.4, 0.69, 0], n, shift, 1.0, s) == "carrier_leak"


def test_clog_start_with_p_c_up_and_p_s_within_noise_is_a_clog_not_a_leak():
    from ajtwin.apps.detection.causes import label_cause

    s = DetectorSettings()
    # held-out machine 1037 (alt), 120 s of evidence: P_c +0.73σ (z 8.0), P_s +0.23σ
    # (z 2.5 < 3), ΔR_N pushed +49σ — was 'carrier_leak'
    mean, n = [0.05, -0.04, 0.73, 0.23, -0.20], [120] * 5
    shift = [0.8, 0, 0, 48.8, -6.3]
    assert label_cause(mean, n, shift, 1.0, s) == "nozzle_clog"
    # P_s falling against the deposit's prediction: one gauge creeping up, not a clog
    assert label_cause([0.05, -0.04, 0.73, -0.23, -0.2], n, shift, 1.0, s) == "carrier_leak"
    # ΔR_N not pushed: P_c alone rising stays the carrier line
    assert label_cause(mean, n, [0.8, 0, 0, 1.0, -6.3], 1.0, s) == "carrier_leak"


def test_live_engine_stores_and_carries_the_history(tmp_path, two_prints):
    """`ajtwin live`: a closed live print stores its detectors' statistics; the machine's
    next live print starts its detectors with them."""
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.estimation.samples import Sample

    first, second = two_prints
    reg = Registry(tmp_path / "r.sqlite")
    engine = LiveEngine(reg, asynchronous=False, commit_every_s=0)
    for k in range(len(first)):
        engine.feed("m", Sample(first.time_s[k], first.inputs[k], first.outputs[k]))
    engine.close("m")
    seq, stored = reg.long_run_history("m")
    assert seq == 1 and len(stored["blocks"]["30"]) == 9
    stream = engine.open("m")
    carried = stream.detector.long_run.history()
    assert np.array_equal(
        carried[30], np.array(stored["blocks"]["30"], dtype=float), equal_nan=True
    )
    assert np.array_equal(stream.detector.long_run.scale, np.array(stored["scale"]))
    engine.shutdown()
