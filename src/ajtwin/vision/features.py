"""The 1-D core of the paper's linewidth/overspray definitions (SPEC §9, paper App. A).

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
    for j in candidates:
        peak = seg[j]
        if peak - running_min[j] < delta:
            continue
        after = seg[j + 1 :]
        higher = np.flatnonzero(after > peak)
        k = higher[0] if higher.size else after.size
        if k == 0 or peak - after[:k].min() < delta:
            continue
        return _refine_peak(seg, int(j), parabola=refine)
    return np.nan


def overspray_end(seg: np.ndarray, thresh: np.ndarray) -> float:
    """Offset where ``seg`` (starting at a shoulder) is back at/above ``thresh`` for good.

    From the start, find the first sample below the threshold, then the first sample at or
    above it after that; the crossing is interpolated linearly.  Returns 0 when the profile
    never drops below the threshold and ``nan`` when it never returns inside ``seg``.
    """
    below = seg < thresh
    first_below = np.argmax(below)
    if not below[first_below]:
        return 0.0
    back = np.flatnonzero(~below[first_below:])
    if back.size == 0:
        return np.nan
    b = first_below + int(back[0])
    if b == 0:
        return 0.0
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
        j = int(np.floor(offset))
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
