"""Which printed trace lies under a point of the part — the trailing camera's question.

The index is a uniform grid (a spatial hash) over the printed segments. Each printed line
or arc is cut into chunks no longer than a grid cell, and each chunk is filed under the
cells its bounding box touches (at most 2 × 2). A query looks up the cells within the
radius around each point, gathers the chunks filed there and computes the *exact* distance
to each (point to line, point to arc), all in NumPy over (point, chunk) pairs, in batches.

Why a grid and not a k-d tree over sampled trace points: distances are exact (no sampling
error to trade against memory), the build is a few array operations, and AJ parts are
dense and fairly uniform (a 19 µm serpentine fill next to sparse fiducials), so a fixed
cell keeps the candidates per query small. The cell defaults to 20 µm (about one AJ
linewidth, so a query of a few µm reads one to four cells of a few traces each, even in the
fills), larger on very long programs so the index keeps about 400 000 chunks at most.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ajtwin.job.geometry import (
    GEOMETRY_FIELDS,
    SEGMENT_FIELDS,
    closest_point,
    point_and_tangent,
    point_at,
    segment_bbox,
)
from ajtwin.job.program import KIND_ARC, KIND_DWELL

__all__ = ["TraceIndex", "TraceHits", "nearest_then_latest"]


_MIN_CELL_MM = 0.02
_MAX_CHUNKS = 400_000
# (point, trace) pairs weighed at once: ~120 bytes each in the temporaries, so a query's
# peak stays near 60 MB; larger batches only cost memory (the camera horizon of a 4-h looped
# public program runs fastest at this size)
_BATCH_PAIRS = 500_000
_TIE_MM = 1e-9


@dataclass(frozen=True)
class TraceHits:
    """Answers of :meth:`TraceIndex.query`, one entry per point asked.

    Attributes
    ----------
    found : ndarray of bool
        A printed trace passes within the radius (and, with ``before_s``, was printed
        before that time).
    stroke, segment, feature, repetition, base_stroke : ndarray of int
        The trace's stroke, segment and feature (-1 where not found).
    s_mm : ndarray
        Arclength along the stroke of the trace's point closest to the query point.
    print_time_s : ndarray
        When the nozzle printed that point.
    ux, uy : ndarray
        Direction of travel of the nozzle there (unit vector).
    distance_mm : ndarray
        From the query point to the trace's centre line.
    x_mm, y_mm : ndarray
        That closest point.
    """

    found: np.ndarray
    stroke: np.ndarray
    segment: np.ndarray
    feature: np.ndarray
    repetition: np.ndarray
    base_stroke: np.ndarray
    s_mm: np.ndarray
    print_time_s: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    distance_mm: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray

    def to_frame(self) -> pd.DataFrame:
        """The hits as a table, one row per query point."""
        return pd.DataFrame({name: getattr(self, name) for name in self.__dataclass_fields__})


class TraceIndex:
    """Uniform-grid index of a job's printed traces (segments with the shutter open).

    Parameters
    ----------
    job : ajtwin.job.Job
    cell_mm : float, optional
        Grid cell and chunk length [mm]; default: 0.02 mm, or the printed length / 400 000
        when larger.

    Examples
    --------
    >>> from ajtwin.job import read_program_text
    >>> prg = "ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),10,0\\nOUT0.0=0"
    >>> job = read_program_text(prg, process_speed_mm_s=2)
    >>> hits = job.locate([5.0, 5.0], [0.01, 3.0], radius_mm=0.05)
    >>> hits.found.tolist(), hits.print_time_s[0].round(6), hits.distance_mm[0].round(6)
    ([True, False], np.float64(2.5), np.float64(0.01))
    """

    def __init__(self, job, cell_mm: float | None = None):
        s = job.segments
        self.job = job
        printed = np.flatnonzero(
            s["shutter_open"] & (s["kind"] != KIND_DWELL) & (s["length_mm"] > 0)
        )
        total = float(s["length_mm"][printed].sum())
        if cell_mm is None:
            cell_mm = max(_MIN_CELL_MM, total / _MAX_CHUNKS)
        if not (cell_mm > 0 and math.isfinite(cell_mm)):
            raise ValueError(f"cell_mm must be a positive length, got {cell_mm}")
        self.cell_mm = float(cell_mm)
        count = np.maximum(1, np.ceil(s["length_mm"][printed] / self.cell_mm)).astype(np.int64)
        parent = np.repeat(printed, count)
        within = np.arange(parent.size) - np.repeat(np.cumsum(count) - count, count)
        n = count.repeat(count)
        self.parent = parent
        self.f_start = within / n
        self.f_end = (within + 1) / n
        g = {k: s[k][parent] for k in GEOMETRY_FIELDS}
        x0, y0 = point_at(*g.values(), self.f_start)
        x1, y1 = point_at(*g.values(), self.f_end)
        arc = g["kind"] == KIND_ARC
        a0 = np.where(arc, g["a0_rad"] + self.f_start * g["sweep_rad"], g["a0_rad"])
        sweep = g["sweep_rad"] * (self.f_end - self.f_start)
        self.chunk = {
            "kind": g["kind"],
            "x0": x0,
            "y0": y0,
            "x1": x1,
            "y1": y1,
            "cx": g["cx_mm"],
            "cy": g["cy_mm"],
            "r": g["radius_mm"],
            "a0": a0,
            "sweep": sweep,
            "length": s["length_mm"][parent] * (self.f_end - self.f_start),
        }
        c = self.chunk
        xmin, ymin, xmax, ymax = segment_bbox(
            c["kind"], x0, y0, x1, y1, c["cx"], c["cy"], c["r"], a0, sweep
        )
        if parent.size == 0:
            self.origin = (0.0, 0.0)
            self.shape = (1, 1)
            self.cell_start = np.zeros(2, dtype=np.int64)
            self.order = np.zeros(0, dtype=np.int64)
            return
        self.origin = (float(xmin.min()), float(ymin.min()))
        nx = int((xmax.max() - self.origin[0]) // self.cell_mm) + 1
        ny = int((ymax.max() - self.origin[1]) // self.cell_mm) + 1
        self.shape = (nx, ny)
        ix0 = ((xmin - self.origin[0]) // self.cell_mm).astype(np.int64)
        ix1 = np.minimum(((xmax - self.origin[0]) // self.cell_mm).astype(np.int64), nx - 1)
        iy0 = ((ymin - self.origin[1]) // self.cell_mm).astype(np.int64)
        iy1 = np.minimum(((ymax - self.origin[1]) // self.cell_mm).astype(np.int64), ny - 1)
        wx, wy = ix1 - ix0 + 1, iy1 - iy0 + 1
        per = wx * wy
        chunk_of = np.repeat(np.arange(parent.size), per)
        k = np.arange(chunk_of.size) - np.repeat(np.cumsum(per) - per, per)
        cell = (ix0[chunk_of] + k // wy[chunk_of]) * ny + iy0[chunk_of] + k % wy[chunk_of]
        order = np.argsort(cell, kind="stable")
        self.order = chunk_of[order]
        self.cell_start = np.searchsorted(cell[order], np.arange(nx * ny + 1))

    def query(self, x_mm, y_mm, radius_mm: float, before_s=None) -> TraceHits:
        """The printed trace nearest to each point, within ``radius_mm``.

        Parameters
        ----------
        x_mm, y_mm : array_like
            Points on the part (broadcast together).
        radius_mm : float
            Search radius around each point (e.g. half the camera's cross-section length).
        before_s : array_like, optional
            Only traces printed before this time (e.g. the frame's time: the camera sees
            what is already printed). Broadcast with the points.

        Returns
        -------
        TraceHits
            The nearest trace; among traces at the same distance (a part printed again on
            itself), the one printed last (before ``before_s``).
        """
        if not (radius_mm >= 0 and math.isfinite(radius_mm)):
            raise ValueError(f"radius_mm must be a non-negative length, got {radius_mm}")
        if before_s is None:
            x, y = np.broadcast_arrays(np.asarray(x_mm, dtype=float), np.asarray(y_mm, dtype=float))
            before = None
        else:
            x, y, before = np.broadcast_arrays(
                np.asarray(x_mm, dtype=float),
                np.asarray(y_mm, dtype=float),
                np.asarray(before_s, dtype=float),
            )
            before = before.ravel()
        shape = x.shape
        x, y = x.ravel(), y.ravel()
        best_chunk = np.full(x.size, -1, dtype=np.int64)
        best_d = np.full(x.size, np.inf)
        best_f = np.zeros(x.size)
        nx, ny = self.shape
        if self.order.size:
            # the cells under each point's square [x - r, x + r] x [y - r, y + r]
            c, (ox, oy) = self.cell_mm, self.origin
            # the cells under the square, cut to the grid: a radius wider than the part asks
            # every cell once, not cells (and arrays) the size of the radius
            lo_x = np.clip(np.floor((x - radius_mm - ox) / c), -1, nx).astype(np.int64)
            hi_x = np.clip(np.floor((x + radius_mm - ox) / c), -1, nx).astype(np.int64)
            lo_y = np.clip(np.floor((y - radius_mm - oy) / c), -1, ny).astype(np.int64)
            hi_y = np.clip(np.floor((y + radius_mm - oy) / c), -1, ny).astype(np.int64)
            lo_x, lo_y = np.maximum(lo_x, 0), np.maximum(lo_y, 0)
            span = int(min(math.ceil(2 * radius_mm / c) + 1, max(nx, ny)))
            per_point = span * span * max(1, int(4 * self.order.size / max(nx * ny, 1)) + 1)
            batch = max(1, _BATCH_PAIRS // per_point)
            for lo in range(0, x.size, batch):
                sel = np.arange(lo, min(x.size, lo + batch))
                self._query_batch(
                    sel,
                    x,
                    y,
                    (lo_x, hi_x, lo_y, hi_y),
                    span,
                    radius_mm,
                    before,
                    best_chunk,
                    best_d,
                    best_f,
                )
        return self._hits(best_chunk, best_d, best_f, x, y, shape)

    def _query_batch(self, points, x, y, box, span, radius, before, best_chunk, best_d, best_f):
        lo_x, hi_x, lo_y, hi_y = (b[points] for b in box)
        nx, ny = self.shape
        k = np.arange(span)
        gx = lo_x[:, None, None] + k[None, :, None]
        gy = lo_y[:, None, None] + k[None, None, :]
        valid = (gx <= hi_x[:, None, None]) & (gy <= hi_y[:, None, None])
        valid &= (gx >= 0) & (gx < nx) & (gy >= 0) & (gy < ny)
        cell = np.where(valid, gx * ny + gy, 0).reshape(points.size, -1)
        start = self.cell_start[cell]
        stop = np.where(valid.reshape(points.size, -1), self.cell_start[cell + 1], start)
        count = (stop - start).ravel()
        total = int(count.sum())
        if total == 0:
            return
        if total > _BATCH_PAIRS and points.size > 1:
            # the batch was sized by the traces' mean density; where they pile up (a job
            # looped over its own part) the pairs would not fit in memory: halve the points
            half = points.size // 2
            for part in (points[:half], points[half:]):
                self._query_batch(part, x, y, box, span, radius, before, best_chunk, best_d,
                                  best_f)  # fmt: skip
            return
        point = np.repeat(np.repeat(points, span * span), count)
        offset = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        chunk = self.order[np.repeat(start.ravel(), count) + offset]
        c = self.chunk
        d, f = closest_point(x[point], y[point], {k: c[k][chunk] for k in SEGMENT_FIELDS})
        keep = d <= radius
        if before is not None:
            s = self.job.segments
            parent = self.parent[chunk]
            f_parent = self.f_start[chunk] + f * (self.f_end[chunk] - self.f_start[chunk])
            t_all = s["t0_s"][parent] + f_parent * (s["t1_s"][parent] - s["t0_s"][parent])
            keep &= t_all < before[point]
        if not keep.any():
            return
        point, chunk, d, f = point[keep], chunk[keep], d[keep], f[keep]
        s = self.job.segments
        parent = self.parent[chunk]
        f_parent = self.f_start[chunk] + f * (self.f_end[chunk] - self.f_start[chunk])
        t = s["t0_s"][parent] + f_parent * (s["t1_s"][parent] - s["t0_s"][parent])

        def position(pairs):
            g = {k: s[k][parent[pairs]] for k in GEOMETRY_FIELDS}
            return point_at(*g.values(), f_parent[pairs])

        first = nearest_then_latest(point, d, t, position)
        p = point[first]
        best_chunk[p], best_d[p], best_f[p] = chunk[first], d[first], f[first]

    def _hits(self, best_chunk, best_d, best_f, x, y, shape) -> TraceHits:
        s = self.job.segments
        found = best_chunk >= 0
        chunk = np.where(found, best_chunk, 0)
        if self.parent.size == 0:
            nan = np.full(x.size, np.nan)
            minus = np.full(x.size, -1, dtype=np.int64)
            return TraceHits(
                found.reshape(shape),
                *(minus.reshape(shape) for _ in range(5)),
                *(nan.reshape(shape) for _ in range(7)),
            )
        parent = self.parent[chunk]
        f = self.f_start[chunk] + best_f * (self.f_end[chunk] - self.f_start[chunk])
        px, py, ux, uy = point_and_tangent(s, parent, f)
        t = s["t0_s"][parent] + f * (s["t1_s"][parent] - s["t0_s"][parent])
        along = s["s0_mm"][parent] + f * s["length_mm"][parent]

        def pick(values, fill):
            return np.where(found, values, fill).reshape(shape)

        return TraceHits(
            found=found.reshape(shape),
            stroke=pick(s["stroke"][parent], -1),
            segment=pick(parent, -1),
            feature=pick(s["feature"][parent], -1),
            repetition=pick(s["repetition"][parent], -1),
            base_stroke=pick(s["base_stroke"][parent], -1),
            s_mm=pick(along, np.nan),
            print_time_s=pick(t, np.nan),
            ux=pick(ux, np.nan),
            uy=pick(uy, np.nan),
            distance_mm=pick(best_d, np.nan),
            x_mm=pick(px, np.nan),
            y_mm=pick(py, np.nan),
        )


def nearest_then_latest(point, d, t, position) -> np.ndarray:
    """The pair chosen for each point among (point, trace) pairs grouped by point, in order.

    The nearest trace wins; traces through the same place (within ``_TIE_MM`` in distance
    and position: a part printed again on itself) are told apart by time, the latest print
    winning.

    Parameters
    ----------
    point : ndarray of int (m,)
        The point of each pair, grouped (equal values next to each other).
    d, t : ndarray (m,)
        Distance [mm] from the point to the trace and when the trace was printed [s].
    position : callable
        ``position(pairs) -> (x_mm, y_mm)`` of the traces' closest points for the pairs
        given (asked only of the pairs as near as the nearest).

    Returns
    -------
    ndarray of int
        One pair index per distinct point, in the points' order.
    """
    starts = np.flatnonzero(np.r_[True, point[1:] != point[:-1]])
    sizes = np.diff(np.r_[starts, point.size])
    d_min = np.repeat(np.minimum.reduceat(d, starts), sizes)
    is_min = np.flatnonzero(d == d_min)
    reference = is_min[np.r_[True, point[is_min][1:] != point[is_min][:-1]]]
    near = np.flatnonzero(d <= d_min + _TIE_MM)
    px, py = position(near)
    ref_of = np.repeat(np.arange(starts.size), sizes)[near]
    at = np.searchsorted(near, reference)
    same = np.hypot(px - px[at][ref_of], py - py[at][ref_of]) <= _TIE_MM
    tied = near[same]
    t_tied = np.full(point.size, -np.inf)
    t_tied[tied] = t[tied]
    t_max = np.repeat(np.maximum.reduceat(t_tied, starts), sizes)
    chosen = np.flatnonzero(t_tied == t_max)
    return chosen[np.r_[True, point[chosen][1:] != point[chosen][:-1]]]
