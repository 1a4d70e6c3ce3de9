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
seed), see docs/anomalies.md. On top (issue 12): innovations are Huber-clipped and each
CUSUM channel is divided by its measured long-run σ (:class:`LongRunScale`).

Examples
--------
>>> import numpy as np
>>> e = np.zeros((100, 1)); e[50:, 0] = 1.0          # a 1σ bias from step 50
>>> g_pos, g_neg, alarms = cusum(e, drift=0.5, threshold=5.0)
>>> [(a.step, a.change_step, a.direction) for a in alarms]
[(60, 49, 1), (71, 60, 1), (82, 71, 1), (93, 82, 1)]
"""

from __future__ import annotations

import warnings
from collections import deque
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import special

from ajtwin import units
from ajtwin.config import packaged_toml
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
    "ink_low": "ink running out (V_l low or falling towards it; vial observer)",
    "unexplained": "unexplained deviation",
    # set by ajtwin.apps.mismatch.relabel_events: the model does not fit the machine
    "model_machine_mismatch": "model–machine mismatch, not a fault (commission the machine)",
}


def load_detector_settings() -> dict:
    """``data/detectors.toml`` (thresholds with their provenance), flattened to
    :class:`DetectorSettings` field names."""
    data = packaged_toml("data/detectors.toml")
    c, n, ev, r, lr, dp = (
        data[k] for k in ("cusum", "nis", "events", "robust", "long_run", "deposit")
    )
    return {
        "cusum_drift": c["drift"],
        "cusum_threshold": c["threshold"],
        "cusum_threshold_pressure": c["threshold_pressure"],
        "cusum_threshold_material_flow": c["threshold_material_flow"],
        "cusum_drift_material_flow": c["drift_material_flow"],
        "cusum_drift_pressure_sum": c["drift_pressure_sum"],
        "cusum_threshold_pressure_sum": c["threshold_pressure_sum"],
        "nis_window_s": n["window_s"],
        "nis_alpha": n["alpha"],
        "merge_s": ev["merge_s"],
        "merge_other_family_s": ev["merge_other_family_s"],
        "evidence_s": ev["evidence_s"],
        "significance_z": ev["significance_z"],
        "vial_low_mL": ev["vial_low_mL"],
        "warmup_s": ev["warmup_s"],
        "innovation_clip_sigma": r["innovation_clip_sigma"],
        "material_flow_reference_s": r["material_flow_reference_s"],
        "long_run_block_s": tuple(int(b) for b in lr["block_s"]),
        "long_run_blocks": lr["blocks"],
        "long_run_min_blocks": lr["min_blocks"],
        "long_run_max_scale": lr["max_scale"],
        "long_run_reference_pressure_sum": lr["reference_pressure_sum"],
        "deposit_window_s": dp["window_s"],
        "deposit_push_nm": dp["push_nm"],
    }


_D = load_detector_settings()


@dataclass(frozen=True)
class DetectorSettings:
    """Thresholds of the detectors (normalised-innovation units unless said).

    Defaults and why each value: ``data/detectors.toml``.
    """

    cusum_drift: float = _D["cusum_drift"]  # allowance k per step [σ]
    cusum_threshold: float = _D["cusum_threshold"]  # h [σ] for L_w, L_o
    # h [σ] for P_c and P_s on their own (their common mode has its own below)
    cusum_threshold_pressure: float = _D["cusum_threshold_pressure"]
    cusum_threshold_material_flow: float = _D["cusum_threshold_material_flow"]
    cusum_drift_material_flow: float = _D["cusum_drift_material_flow"]
    cusum_drift_pressure_sum: float = _D["cusum_drift_pressure_sum"]  # e_Pc + e_Ps
    cusum_threshold_pressure_sum: float = _D["cusum_threshold_pressure_sum"]
    nis_window_s: int = _D["nis_window_s"]
    nis_alpha: float = _D["nis_alpha"]  # tail probability of the windowed NIS
    merge_s: float = _D["merge_s"]  # alarms within this gap belong to one event ...
    merge_other_family_s: float = _D["merge_other_family_s"]  # ... another family: only this
    evidence_s: float = _D["evidence_s"]  # seconds after detection used for the cause label
    significance_z: float = _D["significance_z"]  # |mean e|·√n above this = output moved
    vial_low_mL: float = _D["vial_low_mL"]  # the low end of H's Box–Behnken fit (SPEC §4)
    warmup_s: float = _D["warmup_s"]  # ignore the initial transient of the filter
    innovation_clip_sigma: float = _D["innovation_clip_sigma"]  # Huber clip of e
    # Q_m's CUSUM reference: the print's own level (warm-up mean, then an EWMA with this
    # time constant [s]; 0: e_Qm tested against 0 as before)
    material_flow_reference_s: float = _D["material_flow_reference_s"]
    # each CUSUM channel's increments / its long-run σ (LongRunScale), never by less than 1
    # block lengths [s]: the scale is the largest of their estimates (noise with memory
    # beyond a block looks white to it; a CUSUM integrates over tens of seconds to minutes)
    long_run_block_s: tuple = _D["long_run_block_s"]
    long_run_blocks: int = _D["long_run_blocks"]  # trailing block differences behind it
    long_run_min_blocks: int = _D["long_run_min_blocks"]  # fewer: scale 1
    long_run_max_scale: float = _D["long_run_max_scale"]
    long_run_reference_pressure_sum: float = _D["long_run_reference_pressure_sum"]
    # the filter's push on the nozzle deposit: Σ (x̂_k − x̂_{k|k−1})[ΔR_N] over this window
    # [s] above ``deposit_push_nm`` [nm] = the data keep adding deposit the model does not
    deposit_window_s: int = _D["deposit_window_s"]
    deposit_push_nm: float = _D["deposit_push_nm"]


def cusum_thresholds(settings: DetectorSettings) -> np.ndarray:
    """The CUSUM decision intervals h per channel of :data:`CUSUM_CHANNELS` [σ]."""
    s = settings
    return np.array(
        [s.cusum_threshold] * 2
        + [s.cusum_threshold_pressure] * 2
        + [s.cusum_threshold_material_flow, s.cusum_threshold_pressure_sum]
    )


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
    # chdtrc is what scipy.stats.chi2.sf evaluates, without its per-call overhead (live steps)
    return np.where(dof > 0, special.chdtrc(np.maximum(dof, 1), nis), 1.0)


class WindowedNIS:
    """Rolling Σε and Σn over the last ``window`` steps, one step at a time.

    Keeps running sums C_k = Σ_{j≤k} ε_j (NaN counted as 0) and the last ``window + 1``
    of them, so Σ_{k−w<j≤k} ε_j = C_k − C_{k−w}: the same sums a batch ``cumsum`` gives.

    >>> w = WindowedNIS(2)
    >>> [w.update(x, 1)[0] for x in (1.0, 2.0, 3.0)]
    [1.0, 3.0, 5.0]
    """

    def __init__(self, window: int):
        self.window = int(window)
        self._c_nis = deque([0.0], maxlen=self.window + 1)
        self._c_dof = deque([0.0], maxlen=self.window + 1)

    def update(self, nis: float, n_measured: float) -> tuple[float, float, float]:
        """Add step k; returns (Σε, Σn, χ² tail probability) over the window ending at k."""
        nis = float(nis)
        self._c_nis.append(self._c_nis[-1] + (nis if np.isfinite(nis) else 0.0))
        self._c_dof.append(self._c_dof[-1] + float(n_measured))
        total = self._c_nis[-1] - self._c_nis[0]
        n = self._c_dof[-1] - self._c_dof[0]
        p = float(special.chdtrc(max(n, 1.0), total)) if n > 0 else 1.0
        return total, n, p


def windowed_nis(nis, n_measured, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rolling Σε and Σn over the last ``window`` steps, and its χ² tail probability.

    :class:`WindowedNIS` run over the arrays.

    Returns
    -------
    total, dof, p : (T,) arrays; the first ``window − 1`` steps use what exists so far.
    """
    nis = np.asarray(nis, dtype=float)
    dof = np.asarray(n_measured, dtype=float)
    rolling = WindowedNIS(window)
    out = np.array([rolling.update(a, b) for a, b in zip(nis, dof)]).reshape(-1, 3)
    return out[:, 0], out[:, 1], out[:, 2]


class Cusum:
    """Two-sided CUSUM over m channels, one step at a time (see module docstring).

    Parameters
    ----------
    drift : float or (m,) array
        Allowance k per step [σ].
    threshold : float or (m,) array
        Decision interval h.
    m : int
        Number of channels.
    """

    def __init__(self, drift, threshold, m: int):
        self.drift = np.broadcast_to(np.asarray(drift, dtype=float), (m,)).copy()
        self.threshold = np.broadcast_to(np.asarray(threshold, dtype=float), (m,)).copy()
        self.g_pos = np.zeros(m)
        self.g_neg = np.zeros(m)
        self.zero_pos = np.zeros(m, dtype=int)
        self.zero_neg = np.zeros(m, dtype=int)
        self.started = False

    def update(self, k: int, e_k) -> list[CusumAlarm]:
        """Accumulate step k's normalised innovations (m,); NaN leaves a channel as it was.

        The first call starts the statistics (change points before it: k − 1).
        """
        if not self.started:
            self.zero_pos[:] = k - 1
            self.zero_neg[:] = k - 1
            self.started = True
        ek = np.asarray(e_k, dtype=float)
        ok = np.isfinite(ek)
        e0 = np.where(ok, ek, 0.0)
        gp = np.where(ok, np.maximum(0.0, self.g_pos + e0 - self.drift), self.g_pos)
        gn = np.where(ok, np.maximum(0.0, self.g_neg - e0 - self.drift), self.g_neg)
        self.zero_pos = np.where(gp == 0.0, k, self.zero_pos)
        self.zero_neg = np.where(gn == 0.0, k, self.zero_neg)
        alarms = []
        for j in np.flatnonzero(gp > self.threshold):
            alarms.append(CusumAlarm(k, int(self.zero_pos[j]), int(j), 1))
            gp[j] = 0.0
            self.zero_pos[j] = k
        for j in np.flatnonzero(gn > self.threshold):
            alarms.append(CusumAlarm(k, int(self.zero_neg[j]), int(j), -1))
            gn[j] = 0.0
            self.zero_neg[j] = k
        self.g_pos, self.g_neg = gp, gn
        return alarms


class LongRunScale:
    """Long-run σ of m innovation channels from trailing block means, one step at a time.

    A CUSUM assumes white, unit-variance increments; its false-alarm rate at (k, h) is set
    by the *long-run* variance σ²_LR = lim n·Var(mean of n steps), which autocorrelated
    noise the filter does not model (an AR(1) gauge wander) makes larger than 1. Per
    channel, block means m_j over ``block`` steps (n_j measured samples) give
    d_j = (m_j − m_{j−1}) / √(1/n_j + 1/n_{j−1}), N(0, σ²_LR) for stationary noise; a step
    or a ramp (a fault) moves one d_j or all of them by a constant, so the robust scale
    σ̂_LR = 1.4826 · median|d_j − median(d)| over the last ``blocks`` differences ignores
    it. The scale returned is clip(σ̂_LR, 1, max_scale) (1 until ``min_blocks`` exist).

    ``history`` (n, m): the d_j of earlier prints of the machine (:meth:`history`, kept in
    the registry): they fill the window at the start, so the scale is the machine's from
    the first step instead of 1 for the print's first minutes (when a CUSUM meets the most
    coloured noise with the least data); the print's own blocks push them out.

    >>> rng = np.random.default_rng(0)
    >>> x = np.zeros(6000); w = rng.standard_normal(6000)
    >>> for k in range(1, 6000): x[k] = 0.9 * x[k - 1] + w[k]       # AR(1), σ²_LR = 100
    >>> s = LongRunScale(1, block=60, blocks=100, min_blocks=5, max_scale=20.0)
    >>> for v in x: scale = s.update([v])
    >>> 7.0 < float(scale[0]) < 13.0
    True
    >>> t = LongRunScale(1, block=60, blocks=100, min_blocks=5, max_scale=20.0,
    ...                  history=s.history())
    >>> bool(t.update([0.0])[0] == s.scale[0])       # the machine's scale from step one
    True
    """

    def __init__(
        self, m: int, block: int, blocks: int, min_blocks: int, max_scale: float, history=None
    ):
        self.block, self.min_blocks, self.max_scale = int(block), int(min_blocks), max_scale
        self.m = int(m)
        self.sums = np.zeros(m)
        self.counts = np.zeros(m)
        self.steps = 0
        self.last_mean = None  # (m,) the previous block's mean and count
        self.last_n = None
        self.diffs: deque = deque(maxlen=int(blocks))
        self.scale = np.ones(m)
        if history is not None:
            carried = np.asarray(history, dtype=float).reshape(-1, m)
            for row in carried[-int(blocks) :]:
                self.diffs.append(row.copy())
            self._estimate()

    def history(self) -> np.ndarray:
        """(n, m) the block differences d_j behind the current scale (carried ones too)."""
        return np.array(self.diffs, dtype=float).reshape(-1, self.m)

    def _estimate(self) -> None:
        if len(self.diffs) < self.min_blocks:
            return
        d = np.array(self.diffs)
        with warnings.catch_warnings():  # all-NaN channel (never measured): scale 1
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(d, axis=0)
            mad = 1.4826 * np.nanmedian(np.abs(d - med), axis=0)
        self.scale = np.clip(np.nan_to_num(mad, nan=1.0), 1.0, self.max_scale)

    def update(self, e_k) -> np.ndarray:
        """Add step k (NaN = not measured); the scale to use at step k (from past blocks)."""
        scale = self.scale.copy()
        ek = np.asarray(e_k, dtype=float)
        ok = np.isfinite(ek)
        self.sums += np.where(ok, ek, 0.0)
        self.counts += ok
        self.steps += 1
        if self.steps == self.block:
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.where(self.counts > 0, self.sums / self.counts, np.nan)
                if self.last_mean is not None:
                    self.diffs.append(
                        (mean - self.last_mean) / np.sqrt(1.0 / self.counts + 1.0 / self.last_n)
                    )
            self.last_mean, self.last_n = mean, self.counts.copy()
            self.sums = np.zeros(self.m)
            self.counts = np.zeros(self.m)
            self.steps = 0
            self._estimate()
        return scale


def cusum(e, drift: float, threshold: float, start: int = 0):
    """Two-sided CUSUM per column of ``e`` (T, m): :class:`Cusum` run over the array.

    Parameters
    ----------
    e : (T, m) array
        Normalised innovations; NaN entries leave g unchanged.
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
    detector = Cusum(drift, threshold, m)
    alarms = []
    for k in range(start, n):
        alarms += detector.update(k, e[k])
        g_pos[k] = detector.g_pos
        g_neg[k] = detector.g_neg
    return g_pos, g_neg, alarms


def label_cause(
    mean_innovation,
    n_samples,
    state_shift,
    vial_mL: float,
    settings: DetectorSettings,
    vial_running_low: bool | None = None,
) -> str:
    """The likely cause from the pattern of outputs and states (issue 8 rules).

    Parameters
    ----------
    mean_innovation : (5,) mean normalised innovation per output over the evidence window
    n_samples : (5,) number of measured samples behind each mean
    state_shift : (5,) filter corrections Σ(x̂_k − x̂_{k|k−1}) over the window, divided
        by the state's σ at detection (signed: which state the data pushed, and which way)
    vial_mL : latest V_l estimate [mL] (the twin's; used when there is no observer)
    vial_running_low : the vial observer's flag (:mod:`ajtwin.estimation.vial`) at the
        end of the evidence window, or None without one. The twin's own V_l is a
        consider state (it follows the fill and the modelled draw), so with the observer
        it decides 'ink running out'; a Q_m deficit it does not read as the vial is
        left to the other rules (atomizer …).

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
    >>> label_cause([-1, 0, 0, 0, -2], [60] * 5, [0, 0, 0, 0, -4], 1.0, s, True)
    'ink_low'
    """
    if vial_running_low is not None:
        # the vial observer (issue 18) sees the vial apart from the atomizer: it decides
        if vial_running_low:
            return "ink_low"
        vial_mL = np.nan
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
    # both pressures up, the filter reading them as a growing nozzle deposit (ΔR_N pushed
    # up by many σ), though P_s's rise is still within its noise in the evidence window: a
    # clog's start, not the carrier line (a leak LOWERS P_c; a gauge creeping up alone
    # pushes ΔR_N while P_s falls below the deposit's prediction). Held-out alt machines
    # 1037/1042: P_c +0.73/+0.77σ, P_s +0.23/+0.20σ, ΔR_N +49/+58σ were labelled carrier
    # leak by the rule below (set 2026-11-25, issue 12)
    if shift[3] > zs and z[pc] > zs and z[ps] > 0:
        return "nozzle_clog"
    # less carrier reaching the head lowers P_c (and P_s through the nozzle); a P_c
    # change alone or against P_s is the carrier line or its sensor
    if z[pc] < -zs or (sig[pc] and (not sig[ps] or np.sign(z[pc]) != np.sign(z[ps]))):
        return "carrier_leak"
    if not (sig[pc] or sig[ps]) and (z[qm] < -zs or shift[4] < -zs):
        return "atomizer"
    if z[pc] > zs and z[ps] > zs:
        return "nozzle_clog"
    # the filter reads the pressures as a growing nozzle deposit (ΔR_N pushed up by many σ)
    # and together they rose, though one gauge's mean stayed within its noise (alt
    # generator, held-out machines 1006/1013: P_s +0.7σ, P_c +0.15σ, ΔR_N +37…46σ)
    if shift[3] > zs and min(z[pc], z[ps]) > -zs and z[pc] + z[ps] > zs:
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
    # the long-run statistics to carry to the machine's next print (AnomalyDetector)
    long_run_history: dict | None = None

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


@dataclass
class DetectorStep:
    """What the detectors say after one step (one row of :class:`DetectionResult`)."""

    step: int
    time_s: float
    normalised_innovation: np.ndarray  # (5,)
    nis_p: float
    window_nis_p: float
    cusum_pos: np.ndarray  # (6,)
    cusum_neg: np.ndarray  # (6,)
    alarms: list  # detector labels that fired at this step
    raised: list  # AnomalyEvent opened at this step (label from the evidence so far)
    finalised: list  # AnomalyEvent whose evidence window closed at this step (final label)


#: channel families for event grouping (AnomalyDetector._joins)
_FAMILIES = {"L_w": "line", "L_o": "line", "P_c": "pressure", "P_s": "pressure", "Q_m": "material"}


def _family(detector: str) -> str | None:
    """'cusum+ P_c' → 'pressure', 'V_l low' → 'vial', 'windowed NIS' → None (any)."""
    if detector.startswith("cusum"):
        return _FAMILIES[detector.split(" ", 1)[1].split("+")[0]]
    if detector.startswith("deposit"):
        return "pressure"  # a deposit is seen through the pressures
    return "vial" if detector.startswith("V_l") else None


def carried_differences(history: dict | None, settings: DetectorSettings) -> dict:
    """{block length: (n, 6) block differences} of a stored long-run history for the block
    lengths of ``settings`` (a block length it does not hold, or other channels: left out;
    it says nothing about this detector's blocks)."""
    if not history or list(history.get("channels", [])) != list(CUSUM_CHANNELS):
        return {}
    out = {}
    blocks = history.get("blocks") or {}
    for block in settings.long_run_block_s:
        rows = blocks.get(str(int(block)))
        if rows:
            d = np.array([[np.nan if v is None else float(v) for v in r] for r in rows], float)
            out[int(block)] = d.reshape(-1, len(CUSUM_CHANNELS))
    return out


class MultiScaleLongRun:
    """:class:`LongRunScale` at several block lengths; the scale is their largest.

    Why the largest: σ_LR estimated from blocks of B seconds misses the part of the noise
    whose memory is longer than B (the alt generator's pressure innovations: block-mean
    variance × B grows from 1.9 at 30 s to 2.3 at 60 s and 3.1 at 120 s), while a CUSUM
    at k = 0.35, h = 16 sums over 20–150 s; the largest estimate is the conservative one.
    """

    def __init__(self, m: int, settings: DetectorSettings, history: dict | None = None):
        self.scales = {
            int(b): LongRunScale(
                m,
                int(b),
                settings.long_run_blocks,
                settings.long_run_min_blocks,
                settings.long_run_max_scale,
                history=(history or {}).get(int(b)),
            )
            for b in settings.long_run_block_s
        }
        self.scale = self._combined()

    def _combined(self) -> np.ndarray:
        return np.max([ls.scale for ls in self.scales.values()], axis=0)

    def update(self, e_k) -> np.ndarray:
        """Add step k; the scale to use at step k (from past blocks, largest estimate)."""
        scale = np.max([ls.update(e_k) for ls in self.scales.values()], axis=0)
        self.scale = self._combined()
        return scale

    def history(self) -> dict:
        """{block length: (n, m) differences} behind the current scales (carried ones too)."""
        return {b: ls.history() for b, ls in self.scales.items()}


class AnomalyDetector:
    """NIS, windowed-NIS and CUSUM tests, one EKF step at a time, alarms → labelled events.

    The batch :func:`detect_anomalies` runs this over arrays, so a live twin and a finished
    print give the same events. An event is *raised* at its first alarm with the cause
    read from the evidence so far and *finalised* once ``evidence_s`` seconds after the
    detection have been seen (or at :meth:`finish`), with the batch label.

    Parameters
    ----------
    settings : DetectorSettings, optional
    long_run_history : dict, optional
        :meth:`long_run_history` of the machine's previous print (or of its commissioning
        print): the CUSUMs start with the machine's long-run noise scale instead of 1.
        Ignored when it was taken with another block length or other channels.
    """

    def __init__(
        self, settings: DetectorSettings | None = None, long_run_history: dict | None = None
    ):
        s = self.settings = settings or DetectorSettings()
        thresholds = cusum_thresholds(s)
        drifts = np.array(
            [s.cusum_drift] * 4 + [s.cusum_drift_material_flow, s.cusum_drift_pressure_sum]
        )
        self.cusum = Cusum(drifts, thresholds, len(CUSUM_CHANNELS))
        self.window = WindowedNIS(s.nis_window_s)
        self.long_run = MultiScaleLongRun(
            len(CUSUM_CHANNELS), s, carried_differences(long_run_history, s)
        )
        self._q_sum, self._q_n, self._q_ref = 0.0, 0, None  # Q_m's reference level
        self.long_run_reference = np.array([1.0] * 5 + [s.long_run_reference_pressure_sum])
        self.window_steps = int(np.asarray(s.nis_window_s, dtype=int))
        # the last deposit_window_s corrections of ΔR_N [nm] and whether the push is over
        self._deposit_push = deque(maxlen=int(s.deposit_window_s))
        self._deposit_crossing = False
        self.k = -1
        self.start = None  # first step past the warm-up
        self.t0 = None
        self.time: list[float] = []
        self.e: list[np.ndarray] = []
        self.corrections: list[np.ndarray] = []
        self.stds: list[np.ndarray] = []
        self.vial: list[float] = []
        self.groups: list[list] = []  # raw alarms (step, change_step, label) per event
        self.events: list[AnomalyEvent] = []  # one per group
        self.final: list[bool] = []
        self._crossing = False
        self._vial_low = False
        self.vial_observer = None  # started at the first step that brings the inputs
        self.vial_running_low: list[bool | None] = []
        self._observer_vial: list[float] = []
        self.vial_status = None  # the observer's latest VialStatus (None: no observer)

    def update(
        self,
        time_s,
        measurement,
        predicted_output,
        innovation_variance,
        nis,
        n_measured,
        mean,
        predicted_mean,
        covariance,
        inputs=None,
    ) -> DetectorStep:
        """Step k: the EKF outputs of one sample (display units; see :func:`detect_anomalies`).

        With ``inputs`` (3,) the vial observer runs too (:mod:`ajtwin.estimation.vial`):
        started from the twin's V_l and σ at the first such step (the fill, or the
        previous print's end), it raises 'V_l low' and decides the 'ink running out'
        label. Without it the twin's V_l below ``vial_low_mL`` does (as before).
        """
        s = self.settings
        self.k += 1
        k = self.k
        t = float(time_s)
        if self.t0 is None:
            self.t0 = t
        if self.start is None and t >= self.t0 + s.warmup_s:
            self.start = k
        e = normalised_innovations(
            np.asarray(measurement, dtype=float)[None],
            np.asarray(predicted_output, dtype=float)[None],
            np.asarray(innovation_variance, dtype=float)[None],
        )[0]
        mean = np.asarray(mean, dtype=float)
        self.time.append(t)
        self.e.append(e)
        self.corrections.append(mean - np.asarray(predicted_mean, dtype=float))
        self.stds.append(np.sqrt(np.maximum(np.diag(np.asarray(covariance, dtype=float)), 1e-300)))
        self.vial.append(float(mean[1]))
        running_low = None
        if inputs is not None:
            if self.vial_observer is None:
                from ajtwin.estimation.vial import VialObserver

                sd = float(np.sqrt(max(float(np.asarray(covariance)[1, 1]), 1e-12)))
                self.vial_observer = VialObserver(fill_ml=float(mean[1]), fill_std_ml=sd)
            self.vial_status = self.vial_observer.update(inputs, float(measurement[4]))
            running_low = self.vial_status.running_low
        self.vial_running_low.append(running_low)
        self._observer_vial.append(np.nan if running_low is None else self.vial_status.vial_ml)
        p_step = float(nis_tail_probability([nis], [n_measured])[0])
        # Huber-clipped innovations: a heavy-tailed outlier counts as a ±clip σ one
        c = s.innovation_clip_sigma
        e_clip = np.clip(e, -c, c)
        nis_robust = float(nis)
        if np.isfinite(nis_robust) and np.nansum(e**2) > 0:
            nis_robust *= np.nansum(e_clip**2) / np.nansum(e**2)
        _, _, p_win = self.window.update(nis_robust, n_measured)

        raw = []
        q = e_clip[4]
        tau = float(s.material_flow_reference_s)
        if self.start is None and np.isfinite(q):  # warm-up: the print's Q_m level so far
            self._q_sum += q
            self._q_n += 1
        if self.start is not None:
            # + the common-mode pressure channel; each divided by its long-run σ
            channels = np.append(e_clip, e_clip[2] + e_clip[3])
            if tau > 0:
                # Q_m tested against the print's own level (DetectorSettings): a change
                # during the print is a fault, the level it started at is this print's
                # atomizer efficiency, which the twin learns by EM only after minutes
                if self._q_ref is None:
                    self._q_ref = self._q_sum / self._q_n if self._q_n else 0.0
                channels[4] = q - self._q_ref
                if np.isfinite(q):
                    self._q_ref += (q - self._q_ref) / tau
            channels = channels / self.long_run.update(channels / self.long_run_reference)
            for a in self.cusum.update(k, channels):
                sign = "+" if a.direction > 0 else "−"
                raw.append((a.step, a.change_step, f"cusum{sign} {CUSUM_CHANNELS[a.output]}"))
        crossing = (
            self.start is not None and p_win < s.nis_alpha and k >= self.start + self.window_steps
        )
        if crossing and not self._crossing:  # the first step of a run of crossings
            raw.append((k, max(k - self.window_steps, 0), "windowed NIS"))
        self._crossing = crossing
        raw.extend(self._deposit_alarm(k))
        vial_low = mean[1] < s.vial_low_mL if running_low is None else running_low
        if self.start is not None and not self._vial_low and vial_low:
            self._vial_low = True
            raw.append((k, k, "V_l low"))
        raw.sort()

        raised = []
        for alarm in raw:
            last = self.groups[-1][-1][0] if self.groups else None
            if last is not None and t - self.time[last] <= s.merge_s and self._joins(alarm):
                self.groups[-1].append(alarm)
            else:
                self.groups.append([alarm])
                self.events.append(None)
                self.final.append(False)
                raised.append(len(self.groups) - 1)
        finalised = []
        for i, group in enumerate(self.groups):
            if self.final[i]:
                continue
            k_end = self._evidence_end(group[0][0])
            if k_end is not None:
                self.final[i] = True
                finalised.append(i)
            self.events[i] = self._event(group, k_end)
        return DetectorStep(
            k,
            t,
            e,
            p_step,
            p_win,
            self.cusum.g_pos.copy() if self.cusum.started else np.zeros(len(CUSUM_CHANNELS)),
            self.cusum.g_neg.copy() if self.cusum.started else np.zeros(len(CUSUM_CHANNELS)),
            [name for _, _, name in raw],
            [self.events[i] for i in raised],
            [self.events[i] for i in finalised],
        )

    def _deposit_alarm(self, k: int) -> list:
        """The filter's push on the nozzle deposit over the last ``deposit_window_s``.

        P = Σ_j (x̂_j − x̂_{j|j−1})[ΔR_N] is what the data added to the deposit beyond the
        model's own growth (and θ_RN's, once EM has learnt one). A clog whose pressures the
        filter follows closely (innovations +0.2…+0.6 σ, below every CUSUM) still keeps
        pushing ΔR_N up: held-out alt machine 1168, +76 nm in 10 min. Only after the
        warm-up and with a full window; one alarm per run of crossings.
        """
        s = self.settings
        correction = float(units.um_to_nm(self.corrections[-1][3]))
        self._deposit_push.append(correction if np.isfinite(correction) else 0.0)
        full = len(self._deposit_push) == self._deposit_push.maxlen
        if self.start is None or k < self.start + len(self._deposit_push) or not full:
            return []
        over = sum(self._deposit_push) > s.deposit_push_nm
        alarms = []
        if over and not self._deposit_crossing:
            # change point: the last step where a CUSUM of the window's corrections with
            # allowance κ = push_nm / window (the slowest push that crosses in one window)
            # was 0; the plain cumulative sum's last minimum wanders minutes early on noise
            allowance = s.deposit_push_nm / len(self._deposit_push)
            g, last_zero = 0.0, -1
            for i, c in enumerate(self._deposit_push):
                g = max(0.0, g + c - allowance)
                if g == 0.0:
                    last_zero = i
            # entry i of the window is step k − len + 1 + i
            onset = min(k - len(self._deposit_push) + 2 + last_zero, k)
            alarms.append((k, onset, "deposit push ΔR_N"))
        self._deposit_crossing = over
        return alarms

    def finish(self) -> list[AnomalyEvent]:
        """End of the print: finalise the open events with the data there is; all events."""
        for i, group in enumerate(self.groups):
            if not self.final[i]:
                self.events[i] = self._event(group, self.k + 1)
                self.final[i] = True
        return list(self.events)

    def _joins(self, alarm) -> bool:
        """Whether an alarm belongs to the newest event (within ``merge_s`` of its last
        alarm): yes on a family of channels the event already has (line, pressure, Q_m;
        windowed NIS joins any), or while the event is active (its last alarm, or its
        detection, less than ``merge_other_family_s`` ago). Else a new event: a clog 4 min
        after the last alarm of a Q_m false alarm is a clog, not part of it."""
        group = self.groups[-1]
        family = _family(alarm[2])
        if family is None or family in {_family(name) for _, _, name in group}:
            return True
        last = max(step for step, _, _ in group)
        return self.time[alarm[0]] - self.time[last] <= self.settings.merge_other_family_s

    def long_run_history(self) -> dict:
        """The long-run statistics to carry to the machine's next print (JSON-able): the
        block differences d_j behind the current scale (NaN → None), with the block length
        and channels they were taken with."""
        return {
            "channels": list(CUSUM_CHANNELS),
            "blocks": {
                str(b): [[None if not np.isfinite(v) else float(v) for v in row] for row in d]
                for b, d in self.long_run.history().items()
            },
            "scale": self.long_run.scale.tolist(),
        }

    def _evidence_end(self, k_det: int) -> int | None:
        """First step at or after detection + evidence_s, if it has been seen."""
        target = self.time[k_det] + self.settings.evidence_s
        if self.time[-1] < target:
            return None
        return int(np.searchsorted(np.asarray(self.time), target))

    def _event(self, group: list, k_end: int | None) -> AnomalyEvent:
        """The event of a group of alarms, from the evidence up to ``k_end`` (None: so far)."""
        s = self.settings
        n = self.k + 1
        if k_end is None:
            k_end = n
        k_det = group[0][0]
        # the first alarm's own change point: later alarms may have found older drifts
        k_on = min(k for step, k, _ in group if step == k_det)
        span = slice(max(k_on, 0), min(max(k_end, k_det + 1), n))
        seg = np.asarray(self.e[span])
        counts = np.isfinite(seg).sum(axis=0)
        with np.errstate(invalid="ignore"):
            mean_e = np.where(counts > 0, np.nansum(seg, axis=0) / np.maximum(counts, 1), 0.0)
        shift = np.asarray(self.corrections[span]).sum(axis=0) / self.stds[span.stop - 1]
        vial = self.vial[span.stop - 1]
        running_low = self.vial_running_low[span.stop - 1]
        cause = label_cause(mean_e, counts, shift, vial, s, running_low)
        detectors = []
        for step, _, name in group:
            if step <= k_end and name not in detectors:
                detectors.append(name)
        return AnomalyEvent(
            detected_s=self.time[k_det],
            onset_s=self.time[k_on],
            cause=cause,
            description=CAUSES[cause],
            detectors=detectors,
            evidence={
                "mean_normalised_innovation": dict(zip(SHORT_OUTPUT, np.round(mean_e, 3).tolist())),
                "state_correction_sigma": dict(zip(SHORT_STATE, np.round(shift, 3).tolist())),
                "vial_mL": float(vial),
                **(
                    {}
                    if running_low is None
                    else {
                        "vial_observer_running_low": bool(running_low),
                        "vial_observer_mL": float(self._observer_vial[span.stop - 1]),
                    }
                ),
            },
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
    inputs=None,
    long_run_history: dict | None = None,
) -> DetectionResult:
    """Run NIS, windowed-NIS and CUSUM tests and group alarms into labelled events.

    :class:`AnomalyDetector` run over the arrays, step by step.

    Parameters
    ----------
    time_s : (T,) seconds
    measurements : (T, 5) measured outputs (NaN = missing)
    predicted_outputs, innovation_variances, nis, n_measured :
        from the EKF (:class:`ajtwin.estimation.filters.FilterResult`)
    means, predicted_means, covariances : (T, 5), (T, 5), (T, 5, 5)
        filtered states x̂_k, predictions x̂_{k|k−1} and P_k (display units)
    settings : DetectorSettings, optional
    inputs : (T, 3), optional
        [mA, sccm, sccm]: runs the vial observer (see :meth:`AnomalyDetector.update`).
    long_run_history : dict, optional
        The machine's carried long-run statistics (see :class:`AnomalyDetector`).

    Returns
    -------
    DetectionResult (its ``long_run_history``: what to carry to the next print)
    """
    detector = AnomalyDetector(settings, long_run_history)
    t = np.asarray(time_s, dtype=float)
    columns = (
        measurements,
        predicted_outputs,
        innovation_variances,
        nis,
        n_measured,
        means,
        predicted_means,
        covariances,
    )
    columns = [np.asarray(c, dtype=float) for c in columns]
    u = None if inputs is None else np.asarray(inputs, dtype=float)
    rows = [
        detector.update(t[k], *(c[k] for c in columns), inputs=None if u is None else u[k])
        for k in range(len(t))
    ]
    events = detector.finish()
    n_channels = len(CUSUM_CHANNELS)

    def stack(name, shape):
        return np.array([getattr(r, name) for r in rows]).reshape(shape)

    return DetectionResult(
        t,
        stack("normalised_innovation", (len(t), 5)),
        stack("nis_p", (len(t),)),
        stack("window_nis_p", (len(t),)),
        stack("cusum_pos", (len(t), n_channels)),
        stack("cusum_neg", (len(t), n_channels)),
        events,
        detector.settings,
        detector.long_run_history(),
    )


def detect_run(
    run, record, settings: DetectorSettings | None = None, long_run_history: dict | None = None
) -> DetectionResult:
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
        inputs=record.inputs,
        long_run_history=long_run_history,
    )


def commissioning_long_run_history(record, result, settings: DetectorSettings | None = None):
    """The detectors' long-run statistics of a machine from its commissioning print.

    The commissioned twin (``result``: a
    :class:`~ajtwin.estimation.commission.CommissioningResult`) runs over the print it was
    fitted from, as it will run over the next one, and the detectors' block differences
    are returned (:meth:`AnomalyDetector.long_run_history`): the first print after
    commissioning starts with the machine's noise scale (its gauges' wander, its camera)
    instead of 1. The input steps of a commissioning print move single block means, which
    the robust scale ignores.
    """
    from ajtwin.estimation.twin import Twin

    twin = Twin.default(
        calibration=result.calibration,
        calibration_cov=result.calibration_cov,
        noise_factors=result.noise_factors,
    )
    return detect_run(twin.run(record), record, settings).long_run_history


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
    "AnomalyDetector",
    "AnomalyEvent",
    "Cusum",
    "LongRunScale",
    "MultiScaleLongRun",
    "DetectorStep",
    "WindowedNIS",
    "CusumAlarm",
    "DetectionResult",
    "DetectorSettings",
    "carried_differences",
    "commissioning_long_run_history",
    "cusum",
    "detect_anomalies",
    "load_detector_settings",
    "detect_run",
    "detection_delay",
    "label_cause",
    "nis_tail_probability",
    "normalised_innovations",
    "windowed_nis",
    "OUTPUT_NAMES",
    "STATE_NAMES",
]
