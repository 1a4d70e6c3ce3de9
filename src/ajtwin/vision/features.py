"""The 1-D core of the paper's linewidth/overspray definitions (model reference §9, paper App. A).

One grayscale cross-section of the line (a batch mean of image columns, or the brightness
of a true height profile) goes in; the points the paper names come out:

* (i)   the line centre — here the centroid of the dark band (rows darker than half the
        line's contrast), used only to split the profile into a left and a right half;
* (ii)  the two local minima of brightness, one per half (the global minimum of each half):
        the points of maximum slope of the deposit;
* (iii) moving outward from each (ii), the first peak of brightness.  A *peak* must rise
        ``delta`` above the running minimum since (ii) and fall ``delta`` below itself before
        the profile exceeds it again, where ``delta = max(3 x noise, 2 % of the (ii)
        contrast)``; without that, one noisy sample would count as a peak.  When a half has
        no such peak, the first peak of the row standard-deviation profile is used instead
        (the paper's fallback); ragged shoulders make the std peak there;
* linewidth = distance between the two (iii) points;
* overspray edge: from (iii) outward, the first place where brightness has dropped below
  ``threshold x background`` and then returns to at least that level ("returns within 95 %
  of the substrate background"); one-sided overspray = mean of the left and right extents.

Positions are in sample indices with sub-sample refinement (parabolic vertex for peaks,
linear interpolation for the threshold crossing); callers multiply by the sample spacing.
Everything is NumPy on short 1-D arrays so a frame's ~40 batches take well under a
millisecond each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# status strings shared by the extractor and the CLI output
OK = "ok"
STD_FALLBACK = "ok_std_fallback"
NO_LINE = "no_line"
NO_SHOULDER = "no_shoulder"
OVERSPRAY_OUTSIDE = "overspray_outside_frame"

RISE_FRACTION = 0.02  # minimum peak prominence as a fraction of the (ii) contrast
NOISE_MULTIPLE = 3.0  # ... and as a multiple of the noise of the profile
STD_RISE_FRACTION = 0.1  # std fallback: prominence as a fraction of the std range
HOLD_SAMPLES = 3  # the return to background must last this many samples


@dataclass(frozen=True)
class EdgePoints:
    """Feature points of one cross-section, in (fractional) sample indices.

    ``nan`` marks a point that could not be found; ``status`` says why.
    """

    center: float
    minima: tuple[float, float]  # (ii) left, right
    shoulders: tuple[float, float]  # (iii) left, right
    overspray_edges: tuple[float, float]  # left, right outer edges
    used_std: tuple[bool, bool]
    status: str

    @property
    def linewidth(self) -> float:
        """Distance between the (iii) points, in samples."""
        return self.shoulders[1] - self.shoulders[0]

    @property
    def overspray(self) -> float:
        """One-sided overspray (mean of left and right extents), in samples."""
        left = self.shoulders[0] - self.overspray_edges[0]
        right = self.overspray_edges[1] - self.shoulders[1]
        return 0.5 * (left + right)


def _nan_points(center: float, status: str, minima=(np.nan, np.nan)) -> EdgePoints:
    nan2 = (np.nan, np.nan)
    return EdgePoints(float(center), minima, nan2, nan2, (False, False), status)


def _refine_peak(seg: np.ndarray, j: int, parabola: bool = True) -> float:
    """Sub-sample position of the peak at ``j`` (plateau midpoint or parabola vertex)."""
    p = j
    while p > 0 and seg[p - 1] == seg[j]:
        p -= 1
    if p < j:
        return 0.5 * (p + j)
    if parabola and 0 < j < seg.size - 1:
        a, b, c = seg[j - 1], seg[j], seg[j + 1]
        denom = a - 2.0 * b + c
        if denom < 0:
            return j + float(np.clip(0.5 * (a - c) / denom, -0.5, 0.5))
    return float(j)


def first_peak(seg: np.ndarray, delta: float, *, refine: bool = True) -> float:
    """First peak of ``seg`` (index 0 = start, increasing outward) with prominence ``delta``.

    Returns the sub-sample offset, or ``nan`` when there is none.

    Examples
    --------
    >>> first_peak(np.array([0.0, 1.0, 2.0, 1.0, 3.0, 0.0]), 0.5)
    2.0
    """
    if seg.size < 3:
        return np.nan
    d = np.diff(seg)
    candidates = np.flatnonzero((d[:-1] >= 0) & (d[1:] < 0)) + 1
    if candidates.size == 0:
        return np.nan
    running_min = np.minimum.accumulate(seg)
    candidates = candidates[seg[candidates] - running_min[candidates] >= delta]
    for j in candidates.tolist():
        peak = seg[j]
        after = seg[j + 1 :]
        higher = after > peak
        k = int(np.argmax(higher)) if higher.any() else after.size
        if k == 0 or peak - after[:k].min() < delta:
            continue
        return _refine_peak(seg, j, parabola=refine)
    return np.nan


def overspray_end(seg: np.ndarray, thresh: np.ndarray, hold: int = HOLD_SAMPLES) -> float:
    """Offset where ``seg`` (starting at a shoulder) is back at/above ``thresh`` for good.

    From the start, find the first sample below the threshold, then the first sample after
    it from which ``hold`` consecutive samples are at or above the threshold (so one bright
    speck of substrate texture inside the overspray band does not end it); the crossing is
    interpolated linearly.  Returns 0 when the profile never drops below the threshold and
    ``nan`` when it never returns inside ``seg``.

    Examples
    --------
    >>> round(overspray_end(np.array([1.0, 0.8, 0.8, 0.9, 1.0, 1.0]), np.full(6, 0.95), hold=2), 6)
    3.5
    """
    below = seg < thresh
    first_below = int(np.argmax(below))
    if not below[first_below]:
        return 0.0
    above = ~below[first_below:]
    ok = above.copy()
    for shift in range(1, max(1, int(hold))):
        # a run reaching the end of the profile counts even if shorter than ``hold``
        ok[:-shift] &= above[shift:]
    start = int(np.argmax(ok))
    if not ok[start]:
        return np.nan
    b = first_below + start
    lo, hi = seg[b - 1] - thresh[b - 1], seg[b] - thresh[b]
    return (b - 1) + float(-lo / (hi - lo)) if hi != lo else float(b)


def dark_band_center(intensity: np.ndarray, background: np.ndarray | float) -> float:
    """Centroid of the samples darker than half the line's contrast (point (i) proxy)."""
    contrast = np.asarray(background, dtype=float) - intensity
    peak = contrast.max()
    if not np.isfinite(peak) or peak <= 0:
        return np.nan
    weight = np.where(contrast > 0.5 * peak, contrast, 0.0)
    return float(np.dot(np.arange(intensity.size), weight) / weight.sum())


def find_edges(
    intensity: np.ndarray,
    background: np.ndarray | float,
    *,
    std: np.ndarray | None = None,
    threshold: float = 0.95,
    noise: float = 0.0,
    center: float | None = None,
    refine: bool = True,
) -> EdgePoints:
    """Apply the paper's definitions to one grayscale cross-section.

    Parameters
    ----------
    intensity : (n,) array
        Brightness across the line (batch mean of image rows, or the brightness of a
        height profile), any units.
    background : float or (n,) array
        Substrate background brightness (per sample when illumination is uneven).
    std : (n,) array, optional
        Per-sample standard deviation across the batch (fallback for missing peaks).
    threshold : float
        Overspray ends where ``intensity >= threshold * background``.
    noise : float
        Noise standard deviation of ``intensity`` (sets the minimum peak prominence).
    center : float, optional
        Sample index of the line centre; by default the dark-band centroid.
    refine : bool
        Refine peaks to sub-sample positions with a parabola (right for the smooth peaks of
        a camera image; a noiseless profile's shoulder peak is a cusp, where the parabola
        is biased, so the reference definitions use a fine grid and no refinement).

    Returns
    -------
    EdgePoints
        Sample-index positions of (ii), (iii) and the overspray edges.
    """
    intensity = np.asarray(intensity, dtype=float)
    n = intensity.size
    bg = np.broadcast_to(np.asarray(background, dtype=float), (n,))
    if center is None:
        center = dark_band_center(intensity, bg)
    if not np.isfinite(center) or not (1 <= center <= n - 2):
        return _nan_points(np.nan if center is None else center, NO_LINE)
    c = int(round(center))
    left_min = int(np.argmin(intensity[: c + 1]))
    right_min = c + int(np.argmin(intensity[c:]))
    minima = (float(left_min), float(right_min))
    thresh = threshold * bg

    shoulders, edges, used_std = [], [], []
    for side, start in (("left", left_min), ("right", right_min)):
        if side == "left":
            seg, seg_bg, seg_thr = (
                intensity[start::-1],
                bg[start::-1],
                thresh[start::-1],
            )
            seg_std = None if std is None else std[start::-1]
        else:
            seg, seg_bg, seg_thr = intensity[start:], bg[start:], thresh[start:]
            seg_std = None if std is None else std[start:]
        delta = max(NOISE_MULTIPLE * noise, RISE_FRACTION * (seg_bg[0] - seg[0]))
        offset = first_peak(seg, delta, refine=refine)
        fell_back = False
        if not np.isfinite(offset) and seg_std is not None:
            spread = float(seg_std.max() - seg_std.min())
            offset = first_peak(seg_std, max(STD_RISE_FRACTION * spread, 1e-12), refine=refine)
            fell_back = bool(np.isfinite(offset))
        if not np.isfinite(offset):
            shoulders.append(np.nan)
            edges.append(np.nan)
            used_std.append(False)
            continue
        j = int(np.rint(offset))  # the peak sample itself (the refined vertex is within 0.5)
        extent = overspray_end(seg[j:], seg_thr[j:])
        outer = j + extent if np.isfinite(extent) else np.nan
        outer = max(outer, offset) if np.isfinite(outer) else np.nan
        sign = -1.0 if side == "left" else 1.0
        shoulders.append(start + sign * offset)
        edges.append(start + sign * outer)
        used_std.append(fell_back)

    if not all(np.isfinite(shoulders)):
        status = NO_SHOULDER
    elif not all(np.isfinite(edges)):
        status = OVERSPRAY_OUTSIDE
    elif any(used_std):
        status = STD_FALLBACK
    else:
        status = OK
    return EdgePoints(
        float(center), minima, tuple(shoulders), tuple(edges), tuple(used_std), status
    )


LOOKAHEAD_SAMPLES = 16  # batch version: how far past a peak its fall is looked for


@dataclass(frozen=True)
class BatchEdges:
    """Feature points of many cross-sections at once (columns of a batch-mean image)."""

    center: np.ndarray  # (B,)
    shoulders: np.ndarray  # (B, 2) left, right (iii), sample index
    overspray_edges: np.ndarray  # (B, 2)
    status: list[str]

    @property
    def linewidth(self) -> np.ndarray:
        """Linewidth per batch: shoulder to shoulder [µm]."""
        return self.shoulders[:, 1] - self.shoulders[:, 0]

    @property
    def overspray(self) -> np.ndarray:
        """One-sided overspray per batch: the mean of the two shoulders' distances to their edges
        [µm]."""
        left = self.shoulders[:, 0] - self.overspray_edges[:, 0]
        right = self.overspray_edges[:, 1] - self.shoulders[:, 1]
        return 0.5 * (left + right)


def _gather(values: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """values[rows[k, b], b] with NaN where ``rows`` falls outside the array."""
    inside = (rows >= 0) & (rows < values.shape[0])
    picked = np.take_along_axis(values, np.clip(rows, 0, values.shape[0] - 1), axis=0)
    return np.where(inside, picked, np.nan)


def _side_batches(mean, thresh, start, direction, delta, lookahead, hold):
    """Vectorised first peak outward from ``start`` and overspray end, per column."""
    n_rows, n_cols = mean.shape
    # steps that stay inside the array for some column (further ones are all NaN, which no
    # test below can pass, so leaving them out changes nothing and halves the work)
    n_steps = int(start.max()) + 1 if direction < 0 else n_rows - int(start.min())
    n_steps = max(n_steps, 2)
    steps = np.arange(n_steps)[:, None]
    seg = _gather(mean, start[None, :] + direction * steps)
    with np.errstate(invalid="ignore"):
        d = np.diff(seg, axis=0)
        local_max = np.zeros_like(seg, dtype=bool)
        local_max[1:-1] = (d[:-1] >= 0) & (d[1:] < 0)
        running_min = np.fmin.accumulate(seg, axis=0)
        rise_ok = seg - running_min >= delta
    # the fall after the peak (below peak - delta before anything exceeds the peak), tested
    # only at the few candidates that pass the first two tests
    kk, bb = np.nonzero(local_max & rise_ok)
    level = seg[kk, bb]
    need = np.broadcast_to(delta, seg.shape)[kk, bb]
    # all ``lookahead`` samples after every candidate at once, (lookahead, candidates):
    # "alive" until a sample exceeds the peak; the fall counts only while alive
    idx = kk[None, :] + np.arange(1, lookahead + 1)[:, None]
    ahead = np.where(idx < n_steps, seg[np.minimum(idx, n_steps - 1), bb[None, :]], np.nan)
    with np.errstate(invalid="ignore"):
        alive = np.logical_and.accumulate(~(ahead > level), axis=0)
        fall_ok = (alive & (ahead <= level - need)).any(axis=0)
    # np.nonzero lists candidates row by row, so a column's first hit is its nearest peak
    first = np.full(n_cols, n_steps, dtype=np.int64)
    hit_cols, first_hit = np.unique(bb[fall_ok], return_index=True)
    first[hit_cols] = kk[fall_ok][first_hit]
    found = first < n_steps
    k = np.where(found, first, 0)
    cols = np.arange(n_cols)
    km1 = seg[np.maximum(k - 1, 0), cols]
    k0 = seg[k, cols]
    kp1 = seg[np.minimum(k + 1, n_steps - 1), cols]
    denom = km1 - 2.0 * k0 + kp1
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.where(denom < 0, np.clip(0.5 * (km1 - kp1) / denom, -0.5, 0.5), 0.0)
    offset = np.where(found, k + shift, np.nan)

    # overspray: from the peak sample outward, below threshold, then back for ``hold``
    rows_out = start[None, :] + direction * (k[None, :] + steps)
    tail = _gather(mean, rows_out)
    tail_thr = _gather(thresh, rows_out)
    with np.errstate(invalid="ignore"):
        below = tail < tail_thr
    has_below = below.any(axis=0)
    after_first = np.logical_or.accumulate(below, axis=0)
    back = ~below  # NaN beyond the frame counts as "back" only to finish a run
    ok = back & ~np.isnan(tail) & after_first
    for s in range(1, max(1, hold)):
        ok[:-s] &= back[s:]
    returned = ok.any(axis=0)
    b = np.maximum(np.argmax(ok, axis=0), 1)
    lo = tail[b - 1, cols] - tail_thr[b - 1, cols]
    hi = tail[b, cols] - tail_thr[b, cols]
    with np.errstate(invalid="ignore", divide="ignore"):
        cross = np.where(hi != lo, (b - 1) + (-lo) / (hi - lo), b)
    extent = np.where(has_below, np.where(returned, cross, np.nan), 0.0)
    outer = np.fmax(k + extent, offset)
    outer = np.where(np.isfinite(extent) & found, outer, np.nan)
    return start + direction * offset, start + direction * outer, found


def find_edges_batches(
    mean: np.ndarray,
    background: np.ndarray,
    *,
    std: np.ndarray | None = None,
    threshold: float = 0.95,
    noise: np.ndarray | float = 0.0,
    lookahead: int = LOOKAHEAD_SAMPLES,
    hold: int = HOLD_SAMPLES,
    center: np.ndarray | None = None,
) -> BatchEdges:
    """:func:`find_edges` for every column of ``mean`` at once (NumPy-vectorised).

    Identical definitions, with one bound: a peak's fall (prominence on the outer side)
    must show within ``lookahead`` samples.  Columns without a brightness peak fall back to
    :func:`find_edges` with the std profile, column by column.

    Parameters
    ----------
    mean, background : (rows, B) arrays
        Batch-mean brightness and substrate background per row.
    std : (rows, B) array, optional
        Per-row standard deviation of each batch.
    threshold : float
    noise : float or (B,) array
        Noise sigma of each column of ``mean``.
    center : (B,) array, optional
        Row index of each column's line centre (i); by default the dark-band centroid.
    """
    mean = np.asarray(mean, dtype=float)
    n_rows, n_cols = mean.shape
    background = np.broadcast_to(np.asarray(background, dtype=float), mean.shape)
    noise = np.broadcast_to(np.asarray(noise, dtype=float), (n_cols,))
    rows = np.arange(n_rows, dtype=float)[:, None]
    contrast = background - mean
    peak = contrast.max(axis=0)
    if center is None:
        weight = np.where(contrast > 0.5 * peak, contrast, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            center = (rows * weight).sum(axis=0) / weight.sum(axis=0)
    center = np.asarray(center, dtype=float)
    valid = (peak > 0) & np.isfinite(center) & (center >= 1) & (center <= n_rows - 2)
    ci = np.where(valid, np.rint(np.nan_to_num(center)), 1).astype(np.int64)
    left_min = np.argmin(np.where(rows <= ci, mean, np.inf), axis=0)
    right_min = np.argmin(np.where(rows >= ci, mean, np.inf), axis=0)
    cols = np.arange(n_cols)
    thresh = threshold * background
    shoulders = np.full((n_cols, 2), np.nan)
    edges = np.full((n_cols, 2), np.nan)
    found = np.zeros((n_cols, 2), dtype=bool)
    for side, (start, direction) in enumerate(((left_min, -1), (right_min, 1))):
        depth = background[start, cols] - mean[start, cols]
        delta = np.maximum(NOISE_MULTIPLE * noise, RISE_FRACTION * depth)
        shoulder, edge, ok = _side_batches(
            mean, thresh, start, direction, delta[None, :], lookahead, hold
        )
        shoulders[:, side], edges[:, side], found[:, side] = shoulder, edge, ok
    both = found.all(axis=1)
    finite = np.isfinite(edges).all(axis=1)
    status = np.where(
        ~valid, NO_LINE, np.where(~both, NO_SHOULDER, np.where(finite, OK, OVERSPRAY_OUTSIDE))
    )
    status = status.astype(object)
    shoulders[~valid] = np.nan
    edges[~valid] = np.nan
    if std is not None:
        for b in np.flatnonzero(valid & ~both):  # rare: the std fallback, column by column
            pts = find_edges(
                mean[:, b],
                background[:, b],
                std=std[:, b],
                threshold=threshold,
                noise=float(noise[b]),
                center=float(center[b]),
            )
            shoulders[b], edges[b] = pts.shoulders, pts.overspray_edges
            status[b] = pts.status
    status = status.tolist()
    return BatchEdges(center, shoulders, edges, status)
