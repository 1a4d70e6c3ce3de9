"""The detectors after a data gap, beyond the output model's range, and the windowed NIS on
the long-run noise scale (data/detectors.toml [gaps], [nozzle_cleaning], [nis]).

The streams are hand-made normalised innovations (S = 1, so e is the measurement), as in
tests/test_long_run_history.py; the expected counts follow from the CUSUM sums by hand.
"""

from __future__ import annotations

import numpy as np

from ajtwin.apps.detection.batch import detect_anomalies
from ajtwin.apps.detection.settings import CUSUM_CHANNELS, DetectorSettings

X0 = [3.5, 1.0, 0.0, 0.01, 4.6e-7]


def _arrays(e, deposit_um=None, n_measured=None):
    """detect_anomalies arguments for normalised innovations e (T, 5) with S = 1."""
    t = len(e)
    means = np.tile(X0, (t, 1))
    if deposit_um is not None:
        means[:, 3] = deposit_um
    measured = np.isfinite(e).sum(axis=1) if n_measured is None else n_measured
    return dict(
        time_s=np.arange(t, dtype=float),
        measurements=e,
        predicted_outputs=np.zeros((t, 5)),
        innovation_variances=np.ones((t, 5)),
        nis=np.where(measured > 0, np.nansum(e**2, axis=1), np.nan),
        n_measured=measured,
        means=means,
        predicted_means=means.copy(),
        covariances=np.tile(np.eye(5), (t, 1, 1)),
    )


def test_a_data_gap_restarts_the_warm_up_so_re_acquiring_is_no_alarm():
    """30 s without data at 200 s, then the filter pulling L_w back: +3σ for 20 s. The L_w
    CUSUM reaches 20·(3 − 0.35) = 53 > 16, an alarm on a detector that runs on; after the
    restart the 20 s lie in the new 60-s warm-up. A real +3σ shift 100 s after the gap (past
    that warm-up) is still found, within 16/(3 − 0.35) + 1 = 7 s."""
    e = np.zeros((600, 5))
    e[200:230] = np.nan
    e[230:250, 0] = 3.0
    result = detect_anomalies(**_arrays(e))
    assert result.events == [], [(ev.detected_s, ev.cause) for ev in result.events]

    fault = e.copy()
    fault[330:, 0] = 3.0
    found = detect_anomalies(**_arrays(fault)).events
    assert len(found) == 1 and 330 < found[0].detected_s <= 337


def test_a_short_gap_keeps_the_detectors_running():
    """5 s without data (< restart_after_s = 10 s) is a hiccup: a shift right after it is
    found at once, not after a new warm-up."""
    assert DetectorSettings().gap_restart_s == 10.0
    e = np.zeros((600, 5))
    e[200:205] = np.nan
    e[205:, 0] = 3.0
    found = detect_anomalies(**_arrays(e)).events
    assert found and 205 < found[0].detected_s <= 212


def test_a_deposit_beyond_the_models_range_is_one_cleaning_event():
    """The deposit passes 0.5 µm at 1000 s; clog-like pressure excursions (+3σ for 30 s)
    every 700 s (past the 300-s merge gap, so each was its own event) join one event
    'nozzle needs cleaning' whose onset is the first second beyond."""
    n = 4000
    deposit = np.where(np.arange(n) < 1000, 0.45, 0.55)
    e = np.zeros((n, 5))
    for start in range(1200, n - 100, 700):
        e[start : start + 30, 2:4] = 3.0
    events = detect_anomalies(**_arrays(e, deposit_um=deposit)).events
    assert [ev.cause for ev in events] == ["nozzle_cleaning"]
    assert events[0].onset_s == 1000.0

    # the same excursions within the range: a clog (the later excursions, the deposit no
    # thinner than at its detection, join the clog's event), never a cleaning event
    within = detect_anomalies(**_arrays(e, deposit_um=np.full(n, 0.45))).events
    assert [ev.cause for ev in within] == ["nozzle_clog"]
    assert within[0].onset_s < 1210.0


def test_the_windowed_nis_uses_the_channels_long_run_sigma():
    """Every output alternating ±1.22σ (e² = 1.5: the pressures' noise grown with the
    deposit) on a machine whose carried long-run σ is 1.22 on every channel: the CUSUMs see
    ±1σ and stay quiet; the 120-s window sums 120·5·1.5 = 900 against χ²(600), p ≈ 1e-17,
    and raised an event unscaled; scaled by 1.22 it sums 600 (p = 0.5) and raises none."""
    scale = np.sqrt(1.5)
    signs = np.where(np.arange(900) % 2 == 0, 1.0, -1.0)
    e = np.tile(signs[:, None] * scale, (1, 5))
    a = scale / 1.4826  # differences alternating ±a: MAD a, scale 1.4826·a (hand-computed)
    d = a * np.where(np.arange(40) % 2 == 0, 1.0, -1.0)[:, None] * np.ones(len(CUSUM_CHANNELS))
    history = {
        "channels": list(CUSUM_CHANNELS),
        "blocks": {str(b): d.tolist() for b in DetectorSettings().long_run_block_s},
    }
    scaled = detect_anomalies(**_arrays(e), long_run_history=history)
    assert scaled.events == [], [ev.detectors for ev in scaled.events]
    settings = DetectorSettings(nis_long_run_scaled=False)
    unscaled = detect_anomalies(**_arrays(e), settings=settings, long_run_history=history)
    assert unscaled.events and "NIS" in " ".join(unscaled.events[0].detectors)
