"""Exact piecewise geometry of a job's segments: points, tangents, distances, boxes.

Every function works on NumPy arrays aligned with a set of segments (lines, arcs and
dwells) and is vectorised: no Python loop over points or segments. An arc is the circle
of centre ``(cx, cy)`` and radius ``r`` from the angle ``a0`` over the signed ``sweep``
(positive counter-clockwise, X towards Y); a line runs from ``(x0, y0)`` to ``(x1, y1)``;
a dwell stays at ``(x0, y0)``.
"""

from __future__ import annotations

import numpy as np

from ajtwin.job.program import KIND_ARC, KIND_DWELL

__all__ = [
    "GEOMETRY_FIELDS",
    "point_at",
    "tangent_at",
    "point_and_tangent",
    "closest_point",
    "segment_bbox",
    "arc_steps",
]

#: The segment arrays that fix a segment's shape, in the order :func:`point_at` and
#: :func:`segment_bbox` take them (before ``f``).
GEOMETRY_FIELDS = (
    "kind",
    "x0_mm",
    "y0_mm",
    "x1_mm",
    "y1_mm",
    "cx_mm",
    "cy_mm",
    "radius_mm",
    "a0_rad",
    "sweep_rad",
)

TWO_PI = 2.0 * np.pi


def point_at(kind, x0, y0, x1, y1, cx, cy, r, a0, sweep, f):
    """Point at fraction ``f`` ∈ [0, 1] of each segment's length.

    Returns
    -------
    x, y : ndarray
        [mm]; a dwell returns its position for every ``f``.

    Examples
    --------
    >>> import numpy as np
    >>> x, y = point_at(np.array([1]), 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0, 0.0, np.pi, 0.5)
    >>> bool(np.allclose([x[0], y[0]], [0.0, 1.0]))
    True
    """
    kind = np.asarray(kind)
    f = np.broadcast_to(np.asarray(f, dtype=float), kind.shape)
    x = np.where(kind == KIND_DWELL, x0, x0 + f * (np.asarray(x1) - x0))
    y = np.where(kind == KIND_DWELL, y0, y0 + f * (np.asarray(y1) - y0))
    arc = kind == KIND_ARC
    if np.any(arc):
        angle = np.asarray(a0 + f * sweep, dtype=float)
        x = np.where(arc, cx + r * np.cos(angle), x)
        y = np.where(arc, cy + r * np.sin(angle), y)
    return np.asarray(x, dtype=float), np.asarray(y, dtype=float)


def tangent_at(kind, x0, y0, x1, y1, a0, sweep, length, f):
    """Unit direction of travel at fraction ``f``; (0, 0) for dwells and zero-length pieces."""
    kind = np.asarray(kind)
    length = np.asarray(length, dtype=float)
    safe = np.where(length > 0, length, 1.0)
    ux = np.where(length > 0, (np.asarray(x1) - x0) / safe, 0.0)
    uy = np.where(length > 0, (np.asarray(y1) - y0) / safe, 0.0)
    arc = kind == KIND_ARC
    if np.any(arc):
        angle = np.asarray(a0 + f * sweep, dtype=float)
        sign = np.sign(sweep)
        ux = np.where(arc, -sign * np.sin(angle), ux)
        uy = np.where(arc, sign * np.cos(angle), uy)
    still = kind == KIND_DWELL
    return np.where(still, 0.0, ux), np.where(still, 0.0, uy)


def point_and_tangent(seg: dict, index, f):
    """Point and unit direction of travel at fraction ``f`` of the segments ``index`` of
    ``seg`` (arrays by :data:`GEOMETRY_FIELDS` and ``length_mm``): :func:`point_at` and
    :func:`tangent_at` together. Returns (x, y, ux, uy) [mm, mm, 1, 1]."""
    g = {k: seg[k][index] for k in GEOMETRY_FIELDS}
    x, y = point_at(*g.values(), f)
    ux, uy = tangent_at(
        g["kind"],
        g["x0_mm"],
        g["y0_mm"],
        g["x1_mm"],
        g["y1_mm"],
        g["a0_rad"],
        g["sweep_rad"],
        seg["length_mm"][index],
        f,
    )
    return x, y, ux, uy


#: the columns of a segment :func:`closest_point` reads: kind, ends, arc centre, radius,
#: start angle, sweep, length
SEGMENT_FIELDS = ("kind", "x0", "y0", "x1", "y1", "cx", "cy", "r", "a0", "sweep", "length")


def closest_point(px, py, segments):
    """Closest point of each segment to each point (arrays aligned pairwise).

    ``segments``: a mapping of the columns :data:`SEGMENT_FIELDS` (arrays aligned with
    ``px``, ``py``).

    Returns
    -------
    distance : ndarray
        [mm], exact for lines and arcs.
    f : ndarray
        Fraction of the segment's length at the closest point.
    """
    kind, x0, y0, x1, y1, cx, cy, r, a0, sweep, length = (segments[k] for k in SEGMENT_FIELDS)
    kind = np.asarray(kind)
    dx, dy = x1 - x0, y1 - y0
    len2 = dx * dx + dy * dy
    f = np.clip(((px - x0) * dx + (py - y0) * dy) / np.where(len2 > 0, len2, 1.0), 0.0, 1.0)
    f = np.where(len2 > 0, f, 0.0)
    qx, qy = x0 + f * dx, y0 + f * dy
    d = np.hypot(px - qx, py - qy)
    arc = kind == KIND_ARC
    if np.any(arc):
        ia = np.flatnonzero(arc)
        sa, aa, ra = sweep[ia], a0[ia], r[ia]
        vx, vy = px[ia] - cx[ia], py[ia] - cy[ia]
        theta = np.arctan2(vy, vx)
        # angle travelled from the start to the point's direction, in the sweep's sense
        u = np.mod((theta - aa) * np.sign(sa), TWO_PI)
        inside = u <= np.abs(sa)
        d_inside = np.abs(np.hypot(vx, vy) - ra)
        ex = cx[ia] + ra * np.cos(aa + sa)
        ey = cy[ia] + ra * np.sin(aa + sa)
        d_start = np.hypot(px[ia] - x0[ia], py[ia] - y0[ia])
        d_end = np.hypot(px[ia] - ex, py[ia] - ey)
        f_arc = np.where(inside, u / np.abs(sa), np.where(d_start <= d_end, 0.0, 1.0))
        d_arc = np.where(inside, d_inside, np.minimum(d_start, d_end))
        d[ia] = d_arc
        f[ia] = f_arc
    return d, f


def segment_bbox(kind, x0, y0, x1, y1, cx, cy, r, a0, sweep):
    """Exact bounding box of each segment (an arc's extreme points included).

    Returns
    -------
    xmin, ymin, xmax, ymax : ndarray
    """
    kind = np.asarray(kind)
    xmin, xmax = np.minimum(x0, x1), np.maximum(x0, x1)
    ymin, ymax = np.minimum(y0, y1), np.maximum(y0, y1)
    arc = kind == KIND_ARC
    if np.any(arc):
        ia = np.flatnonzero(arc)
        sa, aa = sweep[ia], a0[ia]
        for angle, which in (
            (0.0, "xmax"),
            (np.pi / 2, "ymax"),
            (np.pi, "xmin"),
            (1.5 * np.pi, "ymin"),
        ):
            reached = np.mod((angle - aa) * np.sign(sa), TWO_PI) <= np.abs(sa)
            hit = ia[reached]
            if which == "xmax":
                xmax[hit] = cx[hit] + r[hit]
            elif which == "ymax":
                ymax[hit] = cy[hit] + r[hit]
            elif which == "xmin":
                xmin[hit] = cx[hit] - r[hit]
            else:
                ymin[hit] = cy[hit] - r[hit]
    return xmin, ymin, xmax, ymax


def arc_steps(kind, r, sweep, max_step_rad: float, chord_tolerance_mm: float):
    """Number of chords per segment: 1 for lines and dwells; for arcs enough that every
    chord spans at most ``max_step_rad`` and strays at most ``chord_tolerance_mm`` from
    the arc (sagitta r·(1 − cos(Δ/2)))."""
    kind = np.asarray(kind)
    n = np.ones(kind.shape, dtype=np.int64)
    arc = kind == KIND_ARC
    if np.any(arc):
        ra = r[arc]
        ratio = np.clip(1.0 - chord_tolerance_mm / ra, -1.0, 1.0)
        step = np.minimum(max_step_rad, 2.0 * np.arccos(ratio))
        n[arc] = np.maximum(1, np.ceil(np.abs(sweep[arc]) / np.maximum(step, 1e-9) - 1e-9)).astype(
            np.int64
        )
    return n
