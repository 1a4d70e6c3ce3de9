"""The detectors' statistics on the twin's innovations: pure functions and small
one-step-at-a-time states.

The EKF's one-step innovations ν_k = y_k − ŷ_{k|k−1} with variances S_k (diagonal) are
white and N(0, 1) after normalisation when the twin's model holds; a fault makes them
biased *before* the twin's process noise and EM absorb it into the states and θ. Three
tests:

* **NIS** per step: ε_k = ν_kᵀ S_k⁻¹ ν_k ~ χ²(n_measured) → tail probability.
* **Windowed NIS**: Σ ε over the last ``window_s`` seconds ~ χ²(Σ n_measured).
* **Two-sided CUSUM** per output on e_k = ν_k / √S_k:
  g⁺_k = max(0, g⁺_{k−1} + e_k − drift), g⁻_k = max(0, g⁻_{k−1} − e_k − drift);
  an alarm when g > threshold, the change point estimated as the last time g was 0;
  g restarts at 0 after an alarm. Missing outputs (NaN) leave g unchanged.

Each CUSUM channel is divided by its measured long-run σ (:class:`LongRunScale`, at
several block lengths: :class:`MultiScaleLongRun`).

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
from dataclasses import dataclass

import numpy as np

from ajtwin.apps.detection.settings import CUSUM_CHANNELS, DetectorSettings


@dataclass
class CusumAlarm:
    """One CUSUM alarm.

    Attributes
    ----------
    step : int
        Index where g crossed the threshold.
    change_step : int
        Estimated change point (the last index with g = 0).
    output : int
        Column of the normalised innovations e.
    direction : int
        +1: innovations positive (measured above predicted), −1: below.
    """

    step: int  # index where g crossed the threshold
    change_step: int  # estimated change point (last index with g = 0)
    output: int  # column of e
    direction: int  # +1: innovations positive (measured above predicted), −1: below


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
    return np.where(dof > 0, _chi2_tail(np.maximum(dof, 1), nis), 1.0)


def _chi2_tail(dof, x):
    """P(χ²(dof) ≥ x); scipy.special is imported on first use (0.1 s that ``estimate``, which
    imports this module for the guard but never calls it, does not pay)."""
    from scipy.special import chdtrc

    return chdtrc(dof, x)


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
        p = float(_chi2_tail(max(n, 1.0), total)) if n > 0 else 1.0
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
