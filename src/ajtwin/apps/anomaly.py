"""Anomaly detection on the twin's innovations (paper §4 "applications", SPEC §1.3).

Pure functions on arrays. The EKF's one-step innovations ν_k = y_k − ŷ_{k|k−1} with
variances S_k (diagonal) are white and N(0, 1) after normalisation when the twin's
model holds; a fault makes them biased *before* the twin's process noise and EM absorb
it into the states and θ. Three tests:

* **NIS** per step: ε_k = ν_kᵀ S_k⁻¹ ν_k ~ χ²(n_measured) → tail probability.
* **Windowed NIS**: Σ ε over the last ``window_s`` seconds ~ χ²(Σ n_measured).
* **Two-sided CUSUM** per output on e_k = ν_k / √S_k:
  g⁺_k = max(0, g⁺_{k−1} + e_k − drift), g⁻_k = max(0, g⁻_{k−1} − e_k − drift);
  an alarm when g > threshold, the change point estimated as the last time g was 0;
  g restarts at 0 after an alarm. Missing outputs (NaN) leave g unchanged.

Alarms close together are merged into one event; each event gets a likely cause from
the pattern of innovation signs and state corrections (:func:`label_cause`).

Thresholds are not the textbook ones: the twin's innovations are autocorrelated (the
virtual printer is not the twin's model), so ``drift``/``threshold``/``alpha`` were set on
clean prints (``exp1`` seeds 10–13, ``exp2`` and ``exp3`` seed 10: 9 h with input
steps) and the false-alarm rate is measured on ``clean_long`` (a different scenario and
seed), see docs/anomalies.md.

Examples
--------
>>> import numpy as np
>>> e = np.zeros((100, 1)); e[50:, 0] = 1.0          # a 1σ bias from step 50
>>> g_pos, g_neg, alarms = cusum(e, drift=0.5, threshold=5.0)
>>> [(a.step, a.change_step, a.direction) for a in alarms]
[(60, 49, 1)]
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import stats

from ajtwin.model import OUTPUT_NAMES, STATE_NAMES

SHORT_OUTPUT = ("L_w", "L_o", "P_c", "P_s", "Q_m")
#: the CUSUM channels: the five outputs and the common-mode pressure sum
CUSUM_CHANNELS = (*SHORT_OUTPUT, "P_c+P_s")
SHORT_STATE = ("d_a", "V_l", "ΔR_T", "ΔR_N", "φ_A")

#: The likely-cause labels (paper §4; issue 8).
CAUSES = {
    "nozzle_clog": "nozzle clog (both pressures rising, ΔR_N growing)",
    "carrier_leak": (
        "carrier leak, MFC drift or carrier-pressure sensor drift (P_c falling or alone)"
    ),
    "atomizer": "atomizer trouble (Q_m and φ_A falling)",
    "ink_low": "ink running out (V_l low)",
    "unexplained": "unexplained deviation",
    # set by ajtwin.apps.mismatch.relabel_events: the model does not fit the machine
    "model_machine_mismatch": "model–machine mismatch, not a fault (commission the machine)",
}


@dataclass(frozen=True)
class DetectorSettings:
    """Thresholds of the detectors (normalised-innovation units unless said)."""

    cusum_drift: float = 0.35  # allowance k per step [σ]
    cusum_threshold: float = 16.0  # decision interval h [σ] for L_w, L_o, P_c, P_s
    # Q_m (CNN-based, log-normal noise, filter σ a rough 20 %): clean prints reach g ≈ 15–18
    cusum_threshold_material_flow: float = 30.0
    # common-mode pressure channel e_Pc + e_Ps (a nozzle deposit or a carrier change moves
    # both pressures together; their innovations correlate ~0.8 in clean prints)
    cusum_drift_pressure_sum: float = 0.7
    cusum_threshold_pressure_sum: float = 16.0
    nis_window_s: int = 120
    nis_alpha: float = 1e-9  # tail probability of the windowed NIS
    merge_s: float = 600.0  # alarms within this gap belong to one event
    evidence_s: float = 120.0  # seconds after detection used for the cause label
    significance_z: float = 3.0  # |mean e|·√n above this = an output clearly moved
    vial_low_mL: float = 0.5  # the low end of H's Box–Behnken fit (SPEC §4)
    warmup_s: float = 60.0  # ignore the initial transient of the filter


@dataclass
class CusumAlarm:
    step: int  # index where g crossed the threshold
    change_step: int  # estimated change point (last index with g = 0)
    output: int  # column of e
    direction: int  # +1: innovations positive (measured above predicted), −1: below


@dataclass
class AnomalyEvent:
    """One anomaly: when it was detected, when it began (estimate), what it likely is."""

    detected_s: float
    onset_s: float
    cause: str
    description: str
    detectors: list = field(default_factory=list)  # e.g. ["cusum+ P_c", "nis"]
    evidence: dict = field(default_factory=dict)  # mean normalised innovations etc.

    def to_dict(self) -> dict:
        return asdict(self)


# --------------------------------------------------------------------------- #
# Pure tests
# --------------------------------------------------------------------------- #


def normalised_innovations(measurements, predicted_outputs, innovation_variances) -> np.ndarray:
    """e_k = (y_k − ŷ_{k|k−1}) / √S_kk per output; NaN where not measured.

    Parameters
    ----------
    measurements, predicted_outputs : (T, m) arrays, display units
    innovation_variances : (T, m) array, diag of S_k (display units²)
    """
    y = np.asarray(measurements, dtype=float)
    yhat = np.asarray(predicted_outputs, dtype=float)
    var = np.asarray(innovation_variances, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = (y - yhat) / np.sqrt(var)
    e[~np.isfinite(e)] = np.nan
    return e


def nis_tail_probability(nis, n_measured) -> np.ndarray:
    """P(χ²(n) ≥ ε) per step (1 where nothing was measured).

    >>> float(nis_tail_probability([3.84], [1])[0].round(3))
    0.05
    """
    nis = np.asarray(nis, dtype=float)
    dof = np.asarray(n_measured, dtype=float)
    return np.where(dof > 0, stats.chi2.sf(nis, np.maximum(dof, 1)), 1.0)


def windowed_nis(nis, n_measured, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rolling Σε and Σn over the last ``window`` steps, and its χ² tail probability.

    Returns
    -------
    total, dof, p : (T,) arrays; the first ``window − 1`` steps use what exists so far.
    """
    nis = np.nan_to_num(np.asarray(nis, dtype=float))
    dof = np.asarray(n_measured, dtype=float)
    c_nis = np.concatenate([[0.0], np.cumsum(nis)])
    c_dof = np.concatenate([[0.0], np.cumsum(dof)])
    idx = np.arange(1, len(nis) + 1)
    lo = np.maximum(idx - int(window), 0)
    total = c_nis[idx] - c_nis[lo]
    n = c_dof[idx] - c_dof[lo]
    p = np.where(n > 0, stats.chi2.sf(total, np.maximum(n, 1)), 1.0)
    return total, n, p


def cusum(e, drift: float, threshold: float, start: int = 0):
    """Two-sided CUSUM per column of ``e`` (T, m); NaN entries leave g unchanged.

    Parameters
    ----------
    e : (T, m) array
        Normalised innovations.
    drift : float or (m,) array
        Allowance k per step (half the bias to detect, in σ), per column if an array.
    threshold : float or (m,) array
        Decision interval h (per column if an array).
    start : int
        Steps before ``start`` are not accumulated (filter warm-up).

    Returns
    -------
    g_pos, g_neg : (T, m) arrays
    alarms : list of :class:`CusumAlarm`, in time order
    """
    e = np.asarray(e, dtype=float)
    if e.ndim == 1:
        e = e[:, None]
    n, m = e.shape
    g_pos = np.zeros((n, m))
    g_neg = np.zeros((n, m))
    threshold = np.broadcast_to(np.asarray(threshold, dtype=float), (m,))
    drift = np.broadcast_to(np.asarray(drift, dtype=float), (m,))
    gp = np.zeros(m)
    gn = np.zeros(m)
    zero_p = np.full(m, start - 1)
    zero_n = np.full(m, start - 1)
    alarms = []
    for k in range(start, n):
        ek = e[k]
        ok = np.isfinite(ek)
        gp = np.where(ok, np.maximum(0.0, gp + np.where(ok, ek, 0.0) - drift), gp)
        gn = np.where(ok, np.maximum(0.0, gn - np.where(ok, ek, 0.0) - drift), gn)
        zero_p = np.where(gp == 0.0, k, zero_p)
        zero_n = np.where(gn == 0.0, k, zero_n)
        for j in np.flatnonzero(gp > threshold):
            alarms.append(CusumAlarm(k, int(zero_p[j]), int(j), 1))
            gp[j] = 0.0
            zero_p[j] = k
        for j in np.flatnonzero(gn > threshold):
            alarms.append(CusumAlarm(k, int(zero_n[j]), int(j), -1))
            gn[j] = 0.0
            zero_n[j] = k
        g_pos[k] = gp
        g_neg[k] = gn
    return g_pos, g_neg, alarms


def label_cause(
    mean_innovation, n_samples, state_shift, vial_mL: float, settings: DetectorSettings
) -> str:
    """The likely cause from the pattern of outputs and states (issue 8 rules).

    Parameters
    ----------
    mean_innovation : (5,) mean normalised innovation per output over the evidence window
    n_samples : (5,) number of measured samples behind each mean
    state_shift : (5,) filter corrections Σ(x̂_k − x̂_{k|k−1}) over the window, divided
        by the state's σ at detection (signed: which state the data pushed, and which way)
    vial_mL : latest V_l estimate [mL]

    Returns
    -------
    One key of :data:`CAUSES`.

    Examples
    --------
    >>> s = DetectorSettings()
    >>> label_cause([1, 1, 2, 2, 0], [60] * 5, [0, 0, 0, 5, 0], 1.0, s)
    'nozzle_clog'
    >>> label_cause([0, 0, -2, 0, -1], [60] * 5, [0, 0, 0, 0, -1], 1.0, s)
    'carrier_leak'
    >>> label_cause([-1, 0, 0, 0, -2], [60] * 5, [0, 0, 0, 0, -4], 1.0, s)
    'atomizer'
    """
    m = np.asarray(mean_innovation, dtype=float)
    n = np.asarray(n_samples, dtype=float)
    z = np.nan_to_num(m * np.sqrt(np.maximum(n, 0)))
    shift = np.nan_to_num(np.asarray(state_shift, dtype=float))
    sig = np.abs(z) > settings.significance_z
    lw, lo, pc, ps, qm = range(5)
    if np.isfinite(vial_mL) and vial_mL < settings.vial_low_mL:
        return "ink_low"
    zs = settings.significance_z
    # a physical change in the nozzle moves both pressures the same way (shared
    # (Q_c + Q_s)·R_N term); rising together = deposit
    if z[pc] > zs and z[ps] > zs and (shift[3] > 0 or z[lw] > 0 or z[lo] > 0):
        return "nozzle_clog"
    # less carrier reaching the head lowers P_c (and P_s through the nozzle); a P_c
    # change alone or against P_s is the carrier line or its sensor
    if z[pc] < -zs or (sig[pc] and (not sig[ps] or np.sign(z[pc]) != np.sign(z[ps]))):
        return "carrier_leak"
    if not (sig[pc] or sig[ps]) and (z[qm] < -zs or shift[4] < -zs):
        return "atomizer"
    if z[pc] > zs and z[ps] > zs:
        return "nozzle_clog"
    return "unexplained"


# --------------------------------------------------------------------------- #
# Detection over a run
# --------------------------------------------------------------------------- #


@dataclass
class DetectionResult:
    """Everything the detectors computed over one print."""

    time_s: np.ndarray
    normalised_innovations: np.ndarray  # (T, 5)
    nis_p: np.ndarray  # (T,) per-step χ² tail
    window_nis_p: np.ndarray  # (T,)
    cusum_pos: np.ndarray  # (T, 6): CUSUM_CHANNELS
    cusum_neg: np.ndarray  # (T, 6)
    events: list  # AnomalyEvent
    settings: DetectorSettings

    def events_frame(self):
        import pandas as pd

        rows = [
            {
                "detected_s": ev.detected_s,
                "onset_s": ev.onset_s,
                "cause": ev.cause,
                "description": ev.description,
                "detectors": ", ".join(ev.detectors),
            }
            for ev in self.events
        ]
        return pd.DataFrame(
            rows, columns=["detected_s", "onset_s", "cause", "description", "detectors"]
        )


def detect_anomalies(
    time_s,
    measurements,
    predicted_outputs,
    innovation_variances,
    nis,
    n_measured,
    means,
    predicted_means,
    covariances,
    settings: DetectorSettings | None = None,
) -> DetectionResult:
    """Run NIS, windowed-NIS and CUSUM tests and group alarms into labelled events.

    Parameters
    ----------
    time_s : (T,) seconds
    measurements : (T, 5) measured outputs (NaN = missing)
    predicted_outputs, innovation_variances, nis, n_measured :
        from the EKF (:class:`ajtwin.estimation.filters.FilterResult`)
    means, predicted_means, covariances : (T, 5), (T, 5), (T, 5, 5)
        filtered states x̂_k, predictions x̂_{k|k−1} and P_k (display units)
    settings : DetectorSettings, optional

    Returns
    -------
    DetectionResult
    """
    s = settings or DetectorSettings()
    t = np.asarray(time_s, dtype=float)
    n = len(t)
    e = normalised_innovations(measurements, predicted_outputs, innovation_variances)
    start = int(np.searchsorted(t, t[0] + s.warmup_s))
    p_step = nis_tail_probability(nis, n_measured)
    _, _, p_win = windowed_nis(nis, n_measured, s.nis_window_s)
    channels = np.column_stack([e, e[:, 2] + e[:, 3]])  # + the common-mode pressure channel
    thresholds = np.array(
        [s.cusum_threshold] * 4 + [s.cusum_threshold_material_flow, s.cusum_threshold_pressure_sum]
    )
    drifts = np.array([s.cusum_drift] * 5 + [s.cusum_drift_pressure_sum])
    g_pos, g_neg, alarms = cusum(channels, drifts, thresholds, start=start)

    # raw alarms: (step, change_step, detector label)
    raw = [
        (
            a.step,
            a.change_step,
            f"cusum{'+' if a.direction > 0 else '−'} {CUSUM_CHANNELS[a.output]}",
        )
        for a in alarms
    ]
    win = np.asarray(s.nis_window_s, dtype=int)
    crossing = np.flatnonzero((p_win < s.nis_alpha) & (np.arange(n) >= start + win))
    if crossing.size:
        # only the first step of each run of consecutive windowed-NIS alarms
        firsts = crossing[np.concatenate([[True], np.diff(crossing) > 1])]
        raw += [(int(k), int(max(k - win, 0)), "windowed NIS") for k in firsts]
    means = np.asarray(means, dtype=float)
    predicted_means = np.asarray(predicted_means, dtype=float)
    vial = means[:, 1]
    low = np.flatnonzero((vial < s.vial_low_mL) & (np.arange(n) >= start))
    if low.size:
        raw.append((int(low[0]), int(low[0]), "V_l low"))
    raw.sort()

    events: list[AnomalyEvent] = []
    groups: list[list] = []
    for alarm in raw:
        if groups and t[alarm[0]] - t[groups[-1][-1][0]] <= s.merge_s:
            groups[-1].append(alarm)
        else:
            groups.append([alarm])
    corrections = means - predicted_means
    stds = np.sqrt(np.maximum(np.diagonal(np.asarray(covariances), 0, 1, 2), 1e-300))
    for group in groups:
        k_det = group[0][0]
        # the first alarm's own change point: later alarms may have found older drifts
        k_on = min(k for step, k, _ in group if step == k_det)
        k_end = int(np.searchsorted(t, t[k_det] + s.evidence_s))
        span = slice(max(k_on, 0), min(max(k_end, k_det + 1), n))
        seg = e[span]
        counts = np.isfinite(seg).sum(axis=0)
        with np.errstate(invalid="ignore"):
            mean_e = np.where(counts > 0, np.nansum(seg, axis=0) / np.maximum(counts, 1), 0.0)
        shift = corrections[span].sum(axis=0) / stds[min(span.stop, n) - 1]
        cause = label_cause(mean_e, counts, shift, float(vial[span.stop - 1]), s)
        detectors = []
        for step, _, name in group:
            if step <= k_end and name not in detectors:
                detectors.append(name)
        events.append(
            AnomalyEvent(
                detected_s=float(t[k_det]),
                onset_s=float(t[k_on]),
                cause=cause,
                description=CAUSES[cause],
                detectors=detectors,
                evidence={
                    "mean_normalised_innovation": dict(
                        zip(SHORT_OUTPUT, np.round(mean_e, 3).tolist())
                    ),
                    "state_correction_sigma": dict(zip(SHORT_STATE, np.round(shift, 3).tolist())),
                    "vial_mL": float(vial[span.stop - 1]),
                },
            )
        )
    return DetectionResult(t, e, p_step, p_win, g_pos, g_neg, events, s)


def detect_run(run, record, settings: DetectorSettings | None = None) -> DetectionResult:
    """:func:`detect_anomalies` on a :class:`~ajtwin.estimation.twin.TwinRun` and its record."""
    f = run.filtered
    return detect_anomalies(
        run.time_s,
        record.outputs,
        np.asarray(f.predicted_outputs),
        np.asarray(f.innovation_variances),
        np.asarray(f.nis),
        np.asarray(f.n_measured),
        np.asarray(f.means),
        np.asarray(f.predicted_means),
        np.asarray(f.covariances),
        settings,
    )


def detection_delay(result: DetectionResult, fault_onset_s: float | None) -> dict:
    """Delay of the first event at or after the fault onset, and false alarms before it.

    Returns
    -------
    dict with ``delay_s`` (NaN when missed), ``cause`` of that event, ``false_alarms``
    (events detected before the onset; all events for a clean print).
    """
    if fault_onset_s is None or not np.isfinite(fault_onset_s):
        return {"delay_s": float("nan"), "cause": None, "false_alarms": len(result.events)}
    before = [ev for ev in result.events if ev.detected_s < fault_onset_s]
    after = [ev for ev in result.events if ev.detected_s >= fault_onset_s]
    if not after:
        return {"delay_s": float("nan"), "cause": None, "false_alarms": len(before)}
    return {
        "delay_s": after[0].detected_s - fault_onset_s,
        "cause": after[0].cause,
        "false_alarms": len(before),
    }


__all__ = [
    "CAUSES",
    "AnomalyEvent",
    "CusumAlarm",
    "DetectionResult",
    "DetectorSettings",
    "cusum",
    "detect_anomalies",
    "detect_run",
    "detection_delay",
    "label_cause",
    "nis_tail_probability",
    "normalised_innovations",
    "windowed_nis",
    "OUTPUT_NAMES",
    "STATE_NAMES",
]
