"""Linewidth and overspray of the traces of a part, guided by the program.

The paper's algorithm (:mod:`ajtwin.vision.extract`) looks for one straight line per frame.
On a part the program already says where every trace is: from the job
(:class:`ajtwin.job.Job`), the camera's geometry (:class:`ajtwin.vision.camera.Camera`) and
the frame's time, the strokes inside each frame, their direction and their print times are
known. This module measures them there.

**Windows.** Every stroke is cut into windows of ``batch`` cross-sections one pixel apart
(the paper's batch of n = 50 columns, turned to follow the stroke). A cross-section is a
line of samples perpendicular to the stroke's local direction — on a curve too — from
``−(reach + background)`` to ``+(reach + background)`` µm, one pixel apart. The frame is
resampled along all the cross-sections of the windows in view at once (:func:`cv2.remap`,
bilinear), each window's cross-sections are averaged into one profile, and the paper's
definitions are applied to every window at once
(:func:`ajtwin.vision.features.find_edges_batches`, the line's centre (i) being the centroid
of what is darker than 70 % of its depth): the two minima (ii), the first peak outward of
each (iii) (the first peak of the per-sample standard deviation over the window's
cross-sections where there is none), linewidth between
the (iii) points, overspray from each (iii) out to where brightness is back within 95 % of
the substrate, one-sided = mean of both sides. The substrate is measured on the
``background`` µm beyond the reach on each side and taken linear across the trace.

**What is not measured, and why.** A reading must be one trace's, on bare substrate, away
from anything that changes its profile. A window is skipped, with the reason counted per
frame, when (first reason that applies):

* ``border`` — a cross-section leaves the frame (or comes within ``margin_px`` of its edge);
* ``fiducial`` — a fiducial mark lies within reach of the window;
* ``stroke_end`` — within ``reach`` of a stroke's start or end, or of the nozzle while the
  stroke is being printed (the deposit there is a cap, not a line);
* ``corner`` — within ``reach + background`` (along the stroke) of a change of direction
  larger than ``corner_deg``, of a bend tighter than ``min_radius_factor × (reach +
  background)``, or where the stroke comes back near itself;
* ``crossing`` — another trace crosses the window's deposit;
* ``overprint`` — another trace runs on the same path (a layer printed on a layer);
* ``fill`` — another trace runs side by side closer than ``reach`` (the deposits merge: a
  filled area, e.g. a serpentine at 19 µm pitch);
* ``neighbour`` — another trace comes within ``reach`` of the window's cross-sections.

The other traces count only once printed: a window is measurable until its first neighbour
is printed (the first leg of a fill, seen by a trailing camera before the next leg comes).
Windows in view that were measured but gave no reading fail with the image's reason:
``no_line`` (no dark band where the program puts the trace), ``off_program`` (the line's
centre further than ``position_tolerance_um`` from the program's path: a wrong camera
geometry or clock), ``no_shoulder``, ``overspray_outside`` / ``beyond_reach`` (the
overspray does not end within ``reach``: widen it). No reading is ever a mix of two traces.

**Where the program prints nothing.** Each frame with light is also searched for lines
farther than ``reach`` from every trace printed by then
(:func:`ajtwin.vision.program_match.lines_off_program`): a video filmed over another
program, or with its clock off, shows them (``PartFrame.foreign``).

**Output per reading:** frame and its time, stroke, arclength of the window's middle,
print time of that spot, linewidth, overspray, and quality figures: ``linewidth_se_um``
(half the difference between the two halves of the window, an estimate of the reading's
own error), ``offset_um`` (line centre minus the program's path), ``snr`` (line depth over
the profile's noise).
"""

from __future__ import annotations

import functools
import math
from collections import Counter
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ajtwin.config import packaged_toml, settings_from_table
from ajtwin.job.geometry import tangent_at
from ajtwin.job.program import KIND_ARC, KIND_DWELL
from ajtwin.vision import features as F
from ajtwin.vision.camera import Camera
from ajtwin.vision.extract import (
    DARK_MEAN_GRAY,
    MIN_LINE_CONTRAST,
    VisionInputError,
    _StageClock,
    to_gray,
)
from ajtwin.vision.program_match import MatchSettings, lines_off_program

__all__ = [
    "PartSettings",
    "PartExtractor",
    "PartFrame",
    "SKIP_REASONS",
    "FAIL_REASONS",
    "READING_COLUMNS",
    "FRAME_COLUMNS",
]

#: Why a window in view is not measured, in the order they are tested (a window counts once).
SKIP_REASONS = (
    "border",
    "fiducial",
    "stroke_end",
    "corner",
    "crossing",
    "overprint",
    "fill",
    "neighbour",
)
#: Static reasons (from the program alone), in priority order; their bit in the masks.
_STATIC = ("fiducial", "stroke_end", "corner", "crossing", "overprint", "fill", "neighbour")
#: Why a measured window gave no reading (the image did not show what the program says).
FAIL_REASONS = (
    "no_line",
    "off_program",
    "no_shoulder",
    "overspray_outside",
    "beyond_reach",
)
READING_COLUMNS = (
    "frame",
    "time_s",
    "stroke",
    "base_stroke",
    "repetition",
    "s_mm",
    "print_time_s",
    "x_mm",
    "y_mm",
    "linewidth_um",
    "overspray_um",
    "linewidth_se_um",
    "offset_um",
    "snr",
    "status",
)
FRAME_COLUMNS = (
    "frame",
    "time_s",
    "view_x_mm",
    "view_y_mm",
    "windows_in_view",
    "readings",
    *(f"skip_{r}" for r in SKIP_REASONS),
    *(f"fail_{r}" for r in FAIL_REASONS),
    "foreign_line_um",
    "status",
)
#: Frame statuses.
FRAME_OK = "ok"
NO_STROKE = "no_stroke_in_view"
NOTHING_MEASURABLE = "nothing_measurable"
TRACES_NOT_FOUND = "traces_not_found"


@functools.cache
def _defaults() -> dict:
    return packaged_toml("vision/part.toml")["part"]


@dataclass(frozen=True)
class PartSettings:
    """Settings of program-guided extraction (defaults: ``vision/part.toml``, with reasons).

    Attributes
    ----------
    batch : int
        Cross-sections (one pixel apart along the stroke) averaged per reading.
    reach_um : float
        Distance from a trace's centre line within which its deposit ends, µm.
    background_um : float
        Substrate sampled beyond the reach on each side, µm.
    min_radius_factor : float
        Smallest radius measured, as a multiple of ``reach_um + background_um``.
    corner_deg, parallel_deg : float
        Direction change that makes a corner; angle under which two traces run side by side.
    overprint_um : float
        A parallel trace closer than this to the centre line is printed on the same path.
    position_tolerance_um : float
        Largest distance between the line's centre and the program's path.
    fiducial_radius_um : float
        Extent of a fiducial mark when none is given.
    margin_px : int
        Cross-sections keep this far from the frame's border.
    threshold : float
        Overspray ends where brightness is back at ``threshold`` x substrate.
    """

    batch: int = 50
    reach_um: float = 75.0
    background_um: float = 20.0
    min_radius_factor: float = 1.25
    corner_deg: float = 2.0
    parallel_deg: float = 20.0
    overprint_um: float = 10.0
    position_tolerance_um: float = 10.0
    fiducial_radius_um: float = 100.0
    margin_px: int = 3
    threshold: float = 0.95

    @classmethod
    def from_defaults(cls, **overrides) -> PartSettings:
        """Settings from ``part.toml`` with keyword overrides (``None`` values ignored)."""
        settings = settings_from_table(cls, _defaults(), overrides, "part")
        settings.validate()
        return settings

    def validate(self) -> None:
        """Refuse settings no measurement can use (the message names the field)."""
        if int(self.batch) < 2:
            raise VisionInputError(f"batch must be >= 2 cross-sections, got {self.batch}")
        for name in ("reach_um", "background_um", "min_radius_factor", "fiducial_radius_um"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise VisionInputError(f"{name} must be > 0, got {value}")
        if not 0 < self.threshold < 1:
            raise VisionInputError(f"threshold must be in (0, 1), got {self.threshold}")
        if not (0 < self.parallel_deg < 90 and 0 < self.corner_deg < 90):
            raise VisionInputError("parallel_deg and corner_deg must lie in (0, 90) degrees")

    @property
    def half_length_um(self) -> float:
        """Half-length of a cross-section: reach plus the substrate beyond it, µm."""
        return self.reach_um + self.background_um

    @property
    def min_radius_um(self) -> float:
        """Smallest radius of curvature measured, µm."""
        return self.min_radius_factor * self.half_length_um


@dataclass
class PartFrame:
    """What one frame gave: readings, and the windows in view that gave none (with why).

    ``readings`` maps each column of :data:`READING_COLUMNS` to an array (one entry per
    reading); ``skipped``/``failed`` count the windows per reason; ``status`` is ``ok`` (at
    least one reading), ``no_stroke_in_view``, ``nothing_measurable`` (all skipped) or
    ``traces_not_found`` (measured, none found where the program says).
    """

    frame: int
    time_s: float
    view_mm: tuple[float, float]
    windows_in_view: int = 0
    readings: dict = field(default_factory=dict)
    skipped: Counter = field(default_factory=Counter)
    failed: Counter = field(default_factory=Counter)
    status: str = NO_STROKE
    # for drawing: window ids in view and their outcome (reason or "ok"), and the
    # cross-sections measured (pixel positions, feature points)
    drawn: list = field(default_factory=list)
    geometry: dict | None = None
    # compared with the program: the frame had light, and the lines it shows where the
    # program prints nothing (ajtwin.vision.program_match.ForeignLine, longest first)
    lit: bool = False
    foreign: list = field(default_factory=list)

    @property
    def n_readings(self) -> int:
        """Readings of the frame."""
        return int(len(self.readings.get("linewidth_um", ())))

    def row(self) -> dict:
        """The frame table's row (:data:`FRAME_COLUMNS`)."""
        out = {
            "frame": self.frame,
            "time_s": self.time_s,
            "view_x_mm": self.view_mm[0],
            "view_y_mm": self.view_mm[1],
            "windows_in_view": self.windows_in_view,
            "readings": self.n_readings,
        }
        out.update({f"skip_{r}": self.skipped.get(r, 0) for r in SKIP_REASONS})
        out.update({f"fail_{r}": self.failed.get(r, 0) for r in FAIL_REASONS})
        out["foreign_line_um"] = self.foreign[0].length_um if self.foreign else 0.0
        out["status"] = self.status
        return out


class Windows:
    """Every stroke cut into measurement windows, with what the program alone says of each.

    Arrays (one entry per window): ``stroke``, ``s_from``/``s_to``/``s_mid`` (mm along the
    stroke), ``x``/``y``/``ux``/``uy`` (middle point and direction of travel), ``t_from``/
    ``t_to``/``t_mid`` (print times), ``static`` (bit mask of static reasons that hold
    whenever the window is printed: fiducial, stroke end, corner) and ``conflict_t`` (one
    column per reason of :data:`_STATIC`: the earliest time at which another trace that
    spoils the window exists; ``inf``: never).
    """

    def __init__(self, job, camera: Camera, settings: PartSettings, fiducials=()):
        self.job = job
        self.settings = settings
        self.length_mm = settings.batch * camera.um_per_px * 1e-3
        self._build(job)
        self.conflict_t = np.full((self.n, len(_STATIC)), np.inf)
        self._static_reasons(job)
        self._fiducials(fiducials)
        self._neighbours()
        self._grid()

    @property
    def n(self) -> int:
        """Number of windows."""
        return int(self.stroke.size)

    # -- geometry of the windows --------------------------------------------------------
    def _build(self, job) -> None:
        table = job.strokes
        lengths = table["length_mm"].to_numpy(float)
        count = np.floor(lengths / self.length_mm + 1e-9).astype(np.int64)
        stroke = np.repeat(np.arange(lengths.size), count)
        within = np.arange(stroke.size) - np.repeat(np.cumsum(count) - count, count)
        start = 0.5 * (lengths - count * self.length_mm)  # centred: leftovers at both ends
        s_from = start[stroke] + within * self.length_mm
        self.stroke = stroke.astype(np.int64)
        self.stroke_length = lengths
        self.s_from = s_from
        self.s_to = s_from + self.length_mm
        self.s_mid = s_from + 0.5 * self.length_mm
        mid = job.point_at(stroke, self.s_mid)
        a = job.point_at(stroke, self.s_from)
        b = job.point_at(stroke, self.s_to)
        self.x, self.y, self.ux, self.uy = mid.x_mm, mid.y_mm, mid.ux, mid.uy
        self.x_from, self.y_from, self.x_to, self.y_to = a.x_mm, a.y_mm, b.x_mm, b.y_mm
        self.t_from, self.t_to, self.t_mid = a.time_s, b.time_s, mid.time_s
        self.base_stroke = table["base_stroke"].to_numpy(np.int64)[stroke]
        self.repetition = table["repetition"].to_numpy(np.int64)[stroke]
        self._pieces(job, lengths, count, start)

    def _pieces(self, job, lengths, count, start) -> None:
        """The printed traces as pieces that may spoil a window: the windows, and the ends
        of strokes no window covers (a stroke shorter than a window is one piece: a dot
        beside a line spoils it as much as a long trace)."""
        strokes = np.arange(lengths.size)
        has = count > 0
        first_end = np.where(has, start, lengths)  # [0, first_end) before the first window
        last_start = np.where(has, start + count * self.length_mm, lengths)
        lo = np.concatenate([np.zeros(lengths.size), last_start[has]])
        hi = np.concatenate([first_end, lengths[has]])
        st = np.concatenate([strokes, strokes[has]])
        keep = hi - lo > 1e-9
        lo, hi, st = lo[keep], hi[keep], st[keep]
        a, b = job.point_at(st, lo), job.point_at(st, hi)
        mid = job.point_at(st, 0.5 * (lo + hi))

        def both(window_values, stub_values):
            return np.concatenate([window_values, stub_values])

        self.piece = {
            "stroke": both(self.stroke, st),
            "s_mid": both(self.s_mid, 0.5 * (lo + hi)),
            "x": both(self.x, mid.x_mm),
            "y": both(self.y, mid.y_mm),
            "ux": both(self.ux, mid.ux),
            "uy": both(self.uy, mid.uy),
            "x_from": both(self.x_from, a.x_mm),
            "y_from": both(self.y_from, a.y_mm),
            "x_to": both(self.x_to, b.x_mm),
            "y_to": both(self.y_to, b.y_mm),
            "t_from": both(self.t_from, a.time_s),
        }

    def _static_reasons(self, job) -> None:
        """Stroke ends, corners and tight bends, from the job's segments."""
        cfg = self.settings
        reach = cfg.reach_um * 1e-3
        zone = cfg.half_length_um * 1e-3
        ends = (self.s_from < reach) | (self.s_to > self.stroke_length[self.stroke] - reach)
        self.conflict_t[ends, _STATIC.index("stroke_end")] = -np.inf
        s = job.segments
        moving = np.flatnonzero(
            s["shutter_open"] & (s["kind"] != KIND_DWELL) & (s["length_mm"] > 0)
        )
        args = lambda f: tangent_at(  # noqa: E731
            s["kind"][moving],
            s["x0_mm"][moving],
            s["y0_mm"][moving],
            s["x1_mm"][moving],
            s["y1_mm"][moving],
            s["a0_rad"][moving],
            s["sweep_rad"][moving],
            s["length_mm"][moving],
            f,
        )
        ux0, uy0 = args(0.0)
        ux1, uy1 = args(1.0)
        stroke = s["stroke"][moving]
        same = stroke[1:] == stroke[:-1]
        cos = np.clip(ux1[:-1] * ux0[1:] + uy1[:-1] * uy0[1:], -1.0, 1.0)
        kink = same & (np.degrees(np.arccos(cos)) > cfg.corner_deg)
        spots = [(stroke[1:][kink], s["s0_mm"][moving][1:][kink], s["s0_mm"][moving][1:][kink])]
        tight = (s["kind"][moving] == KIND_ARC) & (s["radius_mm"][moving] * 1e3 < cfg.min_radius_um)
        s0 = s["s0_mm"][moving][tight]
        spots.append((stroke[tight], s0, s0 + s["length_mm"][moving][tight]))
        corner = np.zeros(self.n, dtype=bool)
        for st, lo, hi in spots:
            for k, a, b in zip(st.tolist(), lo.tolist(), hi.tolist()):
                first = np.searchsorted(self.stroke, k, side="left")
                last = np.searchsorted(self.stroke, k, side="right")
                sel = slice(first, last)
                corner[sel] |= (self.s_to[sel] > a - zone) & (self.s_from[sel] < b + zone)
        self.conflict_t[corner, _STATIC.index("corner")] = -np.inf

    def _fiducials(self, fiducials) -> None:
        """Windows within reach of a fiducial mark (x, y[, radius]) [mm]."""
        cfg = self.settings
        for item in fiducials:
            fx, fy = float(item[0]), float(item[1])
            radius = float(item[2]) if len(item) > 2 else cfg.fiducial_radius_um * 1e-3
            distance = self._distance_to_region(fx, fy)
            near = distance < radius + cfg.reach_um * 1e-3
            self.conflict_t[near, _STATIC.index("fiducial")] = -np.inf

    def _distance_to_region(self, px, py, index=None) -> np.ndarray:
        """Distance [mm] of points to each window's cross-section rectangle."""
        sel = slice(None) if index is None else index
        dx, dy = px - self.x[sel], py - self.y[sel]
        along = dx * self.ux[sel] + dy * self.uy[sel]
        across = -dx * self.uy[sel] + dy * self.ux[sel]
        half_a = 0.5 * self.length_mm
        half_n = self.settings.half_length_um * 1e-3
        return np.hypot(
            np.maximum(np.abs(along) - half_a, 0.0), np.maximum(np.abs(across) - half_n, 0.0)
        )

    def _neighbours(self) -> None:
        """Other traces that spoil a window, and the earliest time each kind exists.

        Two passes over pairs of windows (a k-d tree of their middles): first the windows
        right beside each other (within one window length: overprinted layers, the legs of
        a fill), which settles every window of a dense area; then, for the windows still
        measurable at some time, everything within reach of their cross-sections. A window
        of a filled area therefore counts as ``fill`` (or ``overprint``) even where another
        trace also crosses it.
        """
        cfg = self.settings
        if self.n < 2:
            return
        reach = cfg.reach_um * 1e-3
        half_n = cfg.half_length_um * 1e-3
        half_a = 0.5 * self.length_mm
        pieces = self.piece
        tree = cKDTree(np.column_stack([pieces["x"], pieces["y"]]))
        close = tree.query_pairs(2 * half_a, output_type="ndarray")
        if close.size:
            close = np.concatenate([close, close[:, ::-1]])
            self._classify(close[close[:, 0] < self.n])  # (window, piece)
        # windows that something may still spoil later (or never)
        open_ = np.flatnonzero(self.conflict_t.min(axis=1) > self.t_from)
        if open_.size == 0:
            return
        radius = math.hypot(half_a, half_n) + reach + 2 * half_a
        lists = tree.query_ball_point(np.column_stack([self.x[open_], self.y[open_]]), radius)
        counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=open_.size)
        if counts.sum():
            v = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])
            w = np.repeat(open_, counts)
            keep = w != v
            self._classify(np.column_stack([w[keep], v[keep]]))

    def _classify(self, pairs: np.ndarray) -> None:
        """For pairs (w, v): does trace piece v spoil window w, how, and from when."""
        P = self.piece
        cfg = self.settings
        reach = cfg.reach_um * 1e-3
        half_n = cfg.half_length_um * 1e-3
        half_a = 0.5 * self.length_mm
        cos_parallel = math.cos(math.radians(cfg.parallel_deg))
        turn_zone = 2.0 * (half_n + reach)
        step = 1_000_000
        for lo in range(0, pairs.shape[0], step):
            w, v = pairs[lo : lo + step, 0], pairs[lo : lo + step, 1]
            same = self.stroke[w] == P["stroke"][v]
            ds = np.abs(self.s_mid[w] - P["s_mid"][v])
            gap = np.hypot(self.x[w] - P["x"][v], self.y[w] - P["y"][v])
            # the stroke's own continuation: the path between them has not turned back
            own = same & (gap >= 0.9 * ds - 1e-9)
            keep = ~own
            w, v, same, ds = w[keep], v[keep], same[keep], ds[keep]
            # v's chord sampled at 5 points, in w's frame (along, across)
            t = np.linspace(0.0, 1.0, 5)[:, None]
            px = P["x_from"][v] + t * (P["x_to"][v] - P["x_from"][v])
            py = P["y_from"][v] + t * (P["y_to"][v] - P["y_from"][v])
            dx, dy = px - self.x[w], py - self.y[w]
            along = dx * self.ux[w] + dy * self.uy[w]
            across = -dx * self.uy[w] + dy * self.ux[w]
            slack = 0.125 * self.length_mm  # between samples of a chord
            outside_a = np.maximum(np.abs(along) - half_a, 0.0)
            to_region = np.hypot(outside_a, np.maximum(np.abs(across) - half_n, 0.0)).min(0)
            spoils = to_region < reach + slack
            if not spoils.any():
                continue
            w, v, same, ds = w[spoils], v[spoils], same[spoils], ds[spoils]
            along, across, outside_a = along[:, spoils], across[:, spoils], outside_a[:, spoils]
            parallel = np.abs(self.ux[w] * P["ux"][v] + self.uy[w] * P["uy"][v]) >= cos_parallel
            lateral = np.abs(across).min(0)
            # distance to w's centre line: a crossing trace passes through it
            to_centre = np.hypot(outside_a, across).min(0)
            kind = np.full(w.size, _STATIC.index("neighbour"))
            kind[parallel & (lateral < reach)] = _STATIC.index("fill")
            kind[parallel & (np.abs(across).max(0) < cfg.overprint_um * 1e-3)] = _STATIC.index(
                "overprint"
            )
            kind[~parallel & (to_centre < reach + slack)] = _STATIC.index("crossing")
            kind[same & (ds < turn_zone)] = _STATIC.index("corner")
            np.minimum.at(self.conflict_t, (w, kind), P["t_from"][v])

    def _grid(self) -> None:
        """Windows filed by their middle in square cells, for the frames' look-ups."""
        if self.n == 0:
            self.cell_mm, self.origin, self.shape = 1.0, (0.0, 0.0), (1, 1)
            self.order = np.zeros(0, dtype=np.int64)
            self.cell_start = np.zeros(2, dtype=np.int64)
            return
        self.cell_mm = max(0.1, 4 * self.length_mm)
        self.origin = (float(self.x.min()), float(self.y.min()))
        ix = ((self.x - self.origin[0]) // self.cell_mm).astype(np.int64)
        iy = ((self.y - self.origin[1]) // self.cell_mm).astype(np.int64)
        nx, ny = int(ix.max()) + 1, int(iy.max()) + 1
        self.shape = (nx, ny)
        cell = ix * ny + iy
        self.order = np.argsort(cell, kind="stable")
        self.cell_start = np.searchsorted(cell[self.order], np.arange(nx * ny + 1))

    def usable(self, stroke, s_mm, time_s) -> np.ndarray:
        """Whether points of traces (stroke, arclength) lie in a window with nothing that
        spoils it at ``time_s`` (no end, corner, crossing, fill, neighbour...)."""
        stroke = np.asarray(stroke, dtype=np.int64)
        s_mm = np.asarray(s_mm, dtype=float)
        if self.n == 0:
            return np.zeros(stroke.shape, dtype=bool)
        key = self.stroke * 1e6 + self.s_from  # windows are in stroke, then arclength order
        i = np.clip(np.searchsorted(key, stroke * 1e6 + s_mm, side="right") - 1, 0, self.n - 1)
        inside = (self.stroke[i] == stroke) & (s_mm >= self.s_from[i]) & (s_mm <= self.s_to[i])
        times = np.broadcast_to(np.asarray(time_s, dtype=float), stroke.shape)
        return inside & np.all(self.conflict_t[i] >= times[..., None], axis=-1)

    def near(self, x_mm: float, y_mm: float, radius_mm: float) -> np.ndarray:
        """Windows whose middle may lie within ``radius_mm`` of a point (a superset)."""
        nx, ny = self.shape
        c, (ox, oy) = self.cell_mm, self.origin
        x0 = max(0, int((x_mm - radius_mm - ox) // c))
        x1 = min(nx - 1, int((x_mm + radius_mm - ox) // c))
        y0 = max(0, int((y_mm - radius_mm - oy) // c))
        y1 = min(ny - 1, int((y_mm + radius_mm - oy) // c))
        if x1 < x0 or y1 < y0:
            return np.zeros(0, dtype=np.int64)
        starts = self.cell_start[np.arange(x0, x1 + 1)[:, None] * ny + np.arange(y0, y1 + 1)]
        stops = self.cell_start[np.arange(x0, x1 + 1)[:, None] * ny + np.arange(y0, y1 + 1) + 1]
        parts = [self.order[a:b] for a, b in zip(starts.ravel().tolist(), stops.ravel().tolist())]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


class PartExtractor:
    """Program-guided linewidth/overspray of the traces in each frame of a job's video.

    Parameters
    ----------
    job : ajtwin.job.Job
        The program the machine ran (looped with :meth:`~ajtwin.job.Job.repeat` if it was).
    camera : Camera
        The camera's geometry; frames must be ``width_px x height_px``.
    settings : PartSettings, optional
        Defaults from ``vision/part.toml``.
    fiducials : sequence of (x_mm, y_mm[, radius_mm]), optional
        Marks on the part whose surroundings are not measured.
    match : MatchSettings, optional
        How each frame is compared with the program
        (:func:`ajtwin.vision.program_match.lines_off_program`); ``vision/part.toml [match]``.

    Examples
    --------
    >>> from ajtwin.job import read_program_text
    >>> from ajtwin.vision.part_render import PartRenderer, PrintTruth
    >>> job = read_program_text("ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),1,0\\nOUT0.0=0\\n"
    ...                         "ptp/e (X,Y),0,0", process_speed_mm_s=2)
    >>> cam = Camera(um_per_px=0.75, width_px=480, height_px=360)
    >>> frame = PartRenderer(job, cam, PrintTruth.constant(2, 43, 29)).frame(0.75)
    >>> result = PartExtractor(job, cam).process(frame, time_s=0.75)
    >>> result.status, bool(abs(np.median(result.readings["linewidth_um"]) - 43) < 1.5)
    ('ok', True)
    """

    CACHE_WINDOWS = 4096

    def __init__(
        self,
        job,
        camera: Camera,
        settings: PartSettings | None = None,
        fiducials=(),
        match: MatchSettings | None = None,
    ):
        self.job = job
        self.camera = camera
        self.settings = PartSettings.from_defaults() if settings is None else settings
        self.settings.validate()
        cfg = self.settings
        px = camera.um_per_px
        frame_um = 1e3 * camera.half_diagonal_mm
        if cfg.half_length_um > frame_um:
            # the cross-sections (and their arrays) would reach far beyond what any frame shows
            raise VisionInputError(
                f"reach_um + background_um = {cfg.half_length_um:g} µm either side of a trace is "
                f"more than the camera's frame shows ({camera.width_px} x {camera.height_px} px "
                f"at {px:g} µm/px: {frame_um:.0f} µm from its centre to a corner); give a "
                "reach within the frame"
            )
        self.half_samples = int(math.ceil(cfg.half_length_um / px))
        self.n_across = 2 * self.half_samples + 1
        self.zone = max(3, int(round(cfg.background_um / px)))
        self.windows = Windows(job, camera, cfg, fiducials)
        self.fiducials = [
            (float(f[0]), float(f[1]), float(f[2]) if len(f) > 2 else cfg.fiducial_radius_um * 1e-3)
            for f in fiducials
        ]
        self.match = MatchSettings.from_defaults() if match is None else match
        # cross-section lines of recently used windows: a ring of CACHE_WINDOWS slots
        self._store = np.zeros((self.CACHE_WINDOWS, cfg.batch, 4))
        self._slot_of = np.full(self.windows.n, -1, dtype=np.int64)
        self._window_in = np.full(self.CACHE_WINDOWS, -1, dtype=np.int64)
        self._next_slot = 0
        self._offsets = (np.arange(self.n_across) - self.half_samples).astype(np.float32)
        self.stage_seconds: dict[str, float] = {}

    # -- sampling geometry ------------------------------------------------------------
    def _lines(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre points [mm] and left normals of the cross-sections of windows ``ids``.

        Returns (len(ids), batch, 2) arrays; exact on lines and arcs (the job's geometry),
        kept for the last ``CACHE_WINDOWS`` windows computed (a trailing camera sees each
        window in many frames).
        """
        if ids.size > self.CACHE_WINDOWS:  # more than the ring holds: no caching
            pts = self._points(ids)
            return pts[..., :2], pts[..., 2:]
        slots = self._slot_of[ids]
        missing = np.flatnonzero(slots < 0)
        if missing.size:
            idx = ids[missing]
            free = (self._next_slot + np.arange(idx.size)) % self.CACHE_WINDOWS
            self._next_slot = int((self._next_slot + idx.size) % self.CACHE_WINDOWS)
            evicted = self._window_in[free]
            self._slot_of[evicted[evicted >= 0]] = -1
            self._window_in[free] = idx
            self._slot_of[idx] = free
            self._store[free] = self._points(idx)
            slots = self._slot_of[ids]
        lines = self._store[slots]
        return lines[..., :2], lines[..., 2:]

    def _points(self, idx: np.ndarray) -> np.ndarray:
        """(len(idx), batch, 4): x, y [mm] and left normal of each cross-section's centre."""
        w = self.windows
        n = self.settings.batch
        s = w.s_from[idx, None] + (np.arange(n) + 0.5)[None, :] * (w.length_mm / n)
        pts = self.job.point_at(np.repeat(w.stroke[idx, None], n, axis=1), s)
        return np.stack([pts.x_mm, pts.y_mm, -pts.uy, pts.ux], axis=-1)

    # -- columns across the strokes (the height-profile CNN's input) ----------------------
    def columns(
        self, result: PartFrame, n_pixels: int = 200, um_per_sample: float | None = None
    ) -> np.ndarray:
        """Window-mean columns across the stroke of each reading of a processed frame.

        The height-profile CNN's input on a part: each reading's 50 cross-sections (taken
        perpendicular to the stroke, on arcs too) averaged, ``n_pixels`` samples
        ``um_per_sample`` apart (default: the camera's pixel) centred on the line's dark
        band, by linear interpolation — as :func:`ajtwin.profile_cnn.frames.frame_columns`
        cuts them across a straight line.

        Returns
        -------
        (n_readings, n_pixels) array, rows in the order of ``result.readings``.

        Raises
        ------
        ValueError
            A column longer than the cross-sections (raise the reach).
        """
        if result.geometry is None or result.n_readings == 0:
            return np.zeros((0, n_pixels))
        step = (um_per_sample or self.camera.um_per_px) / self.camera.um_per_px
        half = 0.5 * (n_pixels - 1) * step
        if half > self.half_samples:
            raise ValueError(
                f"a {n_pixels}-sample column {half * self.camera.um_per_px:.0f} µm either side "
                f"of the line is longer than the cross-sections "
                f"(±{self.settings.half_length_um:g} µm): raise reach_um"
            )
        profiles = result.geometry["profiles"]
        centres = result.geometry["centres"]
        grid = np.arange(profiles.shape[1], dtype=float)
        offsets = (np.arange(n_pixels) - 0.5 * (n_pixels - 1)) * step
        return np.stack(
            [np.interp(c + offsets, grid, p) for p, c in zip(profiles, centres, strict=True)]
        )

    # -- one frame ----------------------------------------------------------------------
    def process(self, frame: np.ndarray, index: int = 0, time_s: float = 0.0) -> PartFrame:
        """Measure the traces the program puts in this frame (taken at job time ``time_s``),
        and find the lines it shows where the program prints nothing (``foreign``)."""
        cam = self.camera
        gray = to_gray(frame, f"frame {index}")
        if gray.shape != (cam.height_px, cam.width_px):
            raise VisionInputError(
                f"frame {index} is {gray.shape[1]}x{gray.shape[0]} px but the camera file says "
                f"{cam.width_px}x{cam.height_px}: wrong camera file for this video"
            )
        state = self.job.state_at(time_s)
        result = self._read_windows(gray, index, float(time_s), state)
        if float(gray[::8, ::8].mean()) >= DARK_MEAN_GRAY:
            clock = _StageClock(self.stage_seconds)
            result.lit = True
            result.foreign = lines_off_program(
                gray,
                self.job,
                cam,
                float(time_s),
                self.settings.reach_um,
                self.match,
                self.fiducials,
            )
            clock.lap("7 lines off the program")
        return result

    def _read_windows(self, gray: np.ndarray, index: int, time_s: float, state) -> PartFrame:
        """The windows in view: skipped (why), measured, read."""
        cam, cfg, w = self.camera, self.settings, self.windows
        clock = _StageClock(self.stage_seconds)
        nozzle = (float(state.x_mm), float(state.y_mm))
        view = cam.view_centre(nozzle)
        result = PartFrame(index, float(time_s), (float(view[0]), float(view[1])))
        half_n = cfg.half_length_um * 1e-3
        radius = cam.half_diagonal_mm + half_n + w.length_mm
        ids = w.near(view[0], view[1], radius)
        ids = ids[w.t_from[ids] < time_s]
        if ids.size == 0:
            return result
        # the four corners of each window's cross-section band, in pixels
        corner_x = np.stack(
            [
                w.x_from[ids] - w.uy[ids] * half_n,
                w.x_from[ids] + w.uy[ids] * half_n,
                w.x_to[ids] - w.uy[ids] * half_n,
                w.x_to[ids] + w.uy[ids] * half_n,
            ]
        )
        corner_y = np.stack(
            [
                w.y_from[ids] + w.ux[ids] * half_n,
                w.y_from[ids] - w.ux[ids] * half_n,
                w.y_to[ids] + w.ux[ids] * half_n,
                w.y_to[ids] - w.ux[ids] * half_n,
            ]
        )
        cc, rr = cam.part_to_pixel(corner_x, corner_y, nozzle)
        m = cfg.margin_px
        inside = (
            (cc >= m) & (cc <= cam.width_px - 1 - m) & (rr >= m) & (rr <= cam.height_px - 1 - m)
        )
        touches = (
            (cc.max(0) >= 0)
            & (cc.min(0) <= cam.width_px - 1)
            & (rr.max(0) >= 0)
            & (rr.min(0) <= cam.height_px - 1)
        )
        in_view = touches & (inside.any(0) | _centre_inside(w, ids, cam, nozzle))
        ids, inside = ids[in_view], inside[:, in_view].all(0)
        if ids.size == 0:
            return result
        result.windows_in_view = int(ids.size)
        reason = np.full(ids.size, "", dtype=object)
        reason[~inside] = "border"
        # the stroke being printed: its end is at the nozzle
        live = w.t_to[ids] >= time_s
        if int(state.stroke) >= 0:
            s_now = _arclength_now(self.job, state, time_s)
            live |= (w.stroke[ids] == int(state.stroke)) & (
                w.s_to[ids] > s_now - cfg.reach_um * 1e-3
            )
        reason[(reason == "") & live] = "stroke_end"
        active = w.conflict_t[ids] < time_s
        for bit, name in enumerate(_STATIC):
            reason[(reason == "") & active[:, bit]] = name
        for name in SKIP_REASONS:
            count = int(np.sum(reason == name))
            if count:
                result.skipped[name] = count
        go = np.flatnonzero(reason == "")
        result.drawn = list(zip(ids.tolist(), reason.tolist()))
        if go.size == 0:
            result.status = NOTHING_MEASURABLE
            return result
        if float(gray[::8, ::8].mean()) < DARK_MEAN_GRAY:
            result.failed["no_line"] = int(go.size)
            result.status = TRACES_NOT_FOUND
            self._mark(result, ids[go], "no_line")
            return result
        clock.lap("1 windows in view, skips")
        self._measure(gray, ids[go], nozzle, result)
        return result

    def _mark(self, result: PartFrame, ids, outcome) -> None:
        lookup = dict(result.drawn)
        outcomes = [outcome] * len(ids) if isinstance(outcome, str) else list(outcome)
        for i, o in zip(np.asarray(ids).tolist(), outcomes):
            lookup[i] = o
        result.drawn = list(lookup.items())

    def _measure(self, gray, ids: np.ndarray, nozzle, result: PartFrame) -> None:
        cam, cfg, w = self.camera, self.settings, self.windows
        clock = _StageClock(self.stage_seconds)
        n_win, n = ids.size, cfg.batch
        centre, normal = self._lines(ids)
        matrix = cam.part_to_pixel_matrix(nozzle)
        linear = matrix[:, :2] * cam.mm_per_px  # unit part direction -> pixels per pixel
        col = centre @ matrix[0, :2] + matrix[0, 2]
        row = centre @ matrix[1, :2] + matrix[1, 2]
        ncol = normal @ linear[0]
        nrow = normal @ linear[1]
        f32 = np.float32
        off = self._offsets
        map_x = col.astype(f32).reshape(-1, 1) + ncol.astype(f32).reshape(-1, 1) * off
        map_y = row.astype(f32).reshape(-1, 1) + nrow.astype(f32).reshape(-1, 1) * off
        clock.lap("2 cross-section coordinates")
        samples = cv2.remap(gray, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        clock.lap("3 resample (remap)")
        values = samples.reshape(n_win, n, self.n_across)
        half = n // 2
        first = values[:, :half].sum(axis=1, dtype=np.float32)
        second = values[:, half:].sum(axis=1, dtype=np.float32)
        mean = ((first + second) / n).astype(np.float64)
        halves = (first / half, second / (n - half))
        clock.lap("4 batch means")
        z = self.zone
        d = self._offsets.astype(np.float64)
        left, right = mean[:, :z].mean(axis=1), mean[:, -z:].mean(axis=1)
        d_left, d_right = d[:z].mean(), d[-z:].mean()
        slope = (right - left) / (d_right - d_left)
        background = left[:, None] + slope[:, None] * (d[None, :] - d_left)
        resid = np.concatenate([(mean - background)[:, :z], (mean - background)[:, -z:]], axis=1)
        noise = resid.std(axis=1)
        centre_index = _line_centre(mean, background, z)
        found = F.find_edges_batches(
            mean.T, background.T, threshold=cfg.threshold, noise=noise, center=centre_index
        )
        shoulders, edges = found.shoulders.copy(), found.overspray_edges.copy()
        status = np.array(found.status, dtype=object)
        # the paper's fallback where a side has no brightness peak: the first peak of the
        # per-sample standard deviation over the window (computed only for those windows)
        for k in np.flatnonzero(status == F.NO_SHOULDER).tolist():
            block = values[k].astype(np.float32)
            std = np.sqrt(np.maximum((block * block).mean(axis=0) - mean[k] ** 2, 0.0))
            pts = F.find_edges(
                mean[k],
                background[k],
                std=std,
                threshold=cfg.threshold,
                noise=float(noise[k]),
                center=float(centre_index[k]),
            )
            shoulders[k], edges[k], status[k] = pts.shoulders, pts.overspray_edges, pts.status
        clock.lap("5 feature points (ii)/(iii)/overspray")
        px = cam.um_per_px
        widths = (shoulders[:, 1] - shoulders[:, 0]) * px
        sprays = 0.5 * ((shoulders[:, 0] - edges[:, 0]) + (edges[:, 1] - shoulders[:, 1])) * px
        c = self.half_samples
        offset = (0.5 * (shoulders[:, 0] + shoulders[:, 1]) - c) * px
        inner = slice(z, self.n_across - z)
        depth = (background[:, inner] - mean[:, inner]).max(axis=1)
        bg_level = 0.5 * (left + right)
        with np.errstate(invalid="ignore", divide="ignore"):
            snr = depth / noise
        outcome = np.full(n_win, "ok", dtype=object)
        weak = (depth < MIN_LINE_CONTRAST * bg_level) | (snr < 6.0)
        reach_px = cfg.reach_um / px
        beyond = np.any(np.abs(edges - c) > reach_px + 0.5, axis=1)
        outcome[status == F.NO_SHOULDER] = "no_shoulder"
        outcome[status == F.OVERSPRAY_OUTSIDE] = "overspray_outside"
        outcome[(outcome == "ok") & beyond] = "beyond_reach"
        outcome[np.isfinite(offset) & (np.abs(offset) > cfg.position_tolerance_um)] = "off_program"
        outcome[weak | (status == F.NO_LINE)] = "no_line"
        good = outcome == "ok"
        for name in FAIL_REASONS:
            count = int(np.sum(outcome == name))
            if count:
                result.failed[name] = count
        self._mark(result, ids, outcome.tolist())
        result.status = FRAME_OK if good.any() else TRACES_NOT_FOUND
        g = ids[good]
        spread = _halves_spread(halves, shoulders[good], np.flatnonzero(good)) * px
        result.readings = {
            "frame": np.full(g.size, result.frame),
            "time_s": np.full(g.size, result.time_s),
            "stroke": w.stroke[g],
            "base_stroke": w.base_stroke[g],
            "repetition": w.repetition[g],
            "s_mm": w.s_mid[g],
            "print_time_s": w.t_mid[g],
            "x_mm": w.x[g],
            "y_mm": w.y[g],
            "linewidth_um": widths[good],
            "overspray_um": sprays[good],
            "linewidth_se_um": spread,
            "offset_um": offset[good],
            "snr": snr[good],
            "status": status[good],
        }
        result.geometry = {
            "ids": ids,
            "col": col.ravel(),
            "row": row.ravel(),
            "ncol": ncol.ravel(),
            "nrow": nrow.ravel(),
            "shoulders": shoulders - c,
            "edges": edges - c,
            # the readings' window-mean profiles and line centres (sample index), for
            # columns across the stroke (the height-profile CNN)
            "profiles": mean[good],
            "centres": centre_index[good],
        }
        clock.lap("6 bookkeeping")


SHOULDER_SEARCH = 3  # samples either side of a window's (iii) point searched in its halves


def _halves_spread(halves, shoulders: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Half the difference of the linewidth read on each half of the window (samples).

    Each half's (iii) peaks are taken as the brightest sample within ``SHOULDER_SEARCH`` of
    the whole window's, refined with a parabola: the paper's point where it is well
    defined, at a fraction of the cost of applying the definitions to each half afresh.
    An estimate of the reading's own error (the two halves see independent edges).
    """
    if rows.size == 0:
        return np.zeros(0)
    widths = []
    k = np.arange(-SHOULDER_SEARCH, SHOULDER_SEARCH + 1)
    for profile in halves:
        sides = []
        for side in (0, 1):
            centre = np.rint(shoulders[:, side]).astype(np.int64)
            idx = np.clip(centre[:, None] + k[None, :], 1, profile.shape[1] - 2)
            local = np.take_along_axis(profile[rows], idx, axis=1)
            j = np.argmax(local, axis=1)
            at = idx[np.arange(rows.size), j]
            a = profile[rows, at - 1]
            b = profile[rows, at]
            c = profile[rows, at + 1]
            denom = a - 2.0 * b + c
            with np.errstate(invalid="ignore", divide="ignore"):
                shift = np.where(denom < 0, np.clip(0.5 * (a - c) / denom, -0.5, 0.5), 0.0)
            sides.append(at + shift)
        widths.append(sides[1] - sides[0])
    return 0.5 * np.abs(widths[0] - widths[1])


CENTRE_CONTRAST = 0.7  # the line's centre: centroid of what is darker than 70 % of its depth


def _line_centre(profiles: np.ndarray, background: np.ndarray, zone: int) -> np.ndarray:
    """Centre (sample index) of the dark band of each profile, between the substrate zones.

    The centroid of the samples darker than 70 % of the profile's depth: the two flanks of
    the line, not its overspray band (about half as dark), which would pull a centroid of
    everything darker than half the depth towards one side.
    """
    contrast = (background - profiles)[:, zone:-zone]
    peak = contrast.max(axis=1, keepdims=True)
    weight = np.where(contrast > CENTRE_CONTRAST * peak, contrast, 0.0)
    index = np.arange(zone, profiles.shape[1] - zone, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (weight * index).sum(axis=1) / weight.sum(axis=1)


def _centre_inside(w: Windows, ids, cam: Camera, nozzle) -> np.ndarray:
    col, row = cam.part_to_pixel(w.x[ids], w.y[ids], nozzle)
    return (col >= 0) & (col <= cam.width_px - 1) & (row >= 0) & (row <= cam.height_px - 1)


def _arclength_now(job, state, time_s: float) -> float:
    """How far along its stroke the nozzle is at ``time_s`` (mm), while printing."""
    s = job.segments
    seg = int(state.segment)
    t0, t1 = s["t0_s"][seg], s["t1_s"][seg]
    f = min(max((time_s - t0) / (t1 - t0), 0.0), 1.0) if t1 > t0 else 1.0
    return float(np.nan_to_num(s["s0_mm"][seg]) + f * s["length_mm"][seg])


# -- annotation ---------------------------------------------------------------------------
#: Colour (BGR) of each window outcome in annotated frames.
OUTCOME_COLOURS = {
    "ok": (0, 200, 0),
    "border": (255, 200, 120),
    "fiducial": (255, 255, 255),
    "stroke_end": (0, 220, 255),
    "corner": (0, 140, 255),
    "crossing": (255, 0, 255),
    "overprint": (200, 0, 130),
    "fill": (255, 255, 0),
    "neighbour": (180, 120, 255),
}
FAIL_COLOUR = (0, 0, 255)
#: a line the frame shows where the program prints nothing
FOREIGN_COLOUR = (255, 0, 160)
SHOULDER_COLOUR, OVERSPRAY_COLOUR = (0, 0, 255), (255, 80, 0)


def annotate_part(frame: np.ndarray, result: PartFrame, extractor: PartExtractor) -> np.ndarray:
    """The frame with the program's strokes, the cross-sections and the skips drawn.

    Each window in view is drawn along the stroke in the colour of its outcome
    (:data:`OUTCOME_COLOURS`: green measured, red measured without a reading, other colours
    one per skip reason). For every reading, the middle cross-section is drawn across the
    stroke with the linewidth edges (iii) in red and the overspray edges in blue. A line the
    frame shows where the program prints nothing is drawn along its axis in violet.
    """
    gray = to_gray(frame)
    canvas = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    cam, w = extractor.camera, extractor.windows
    state = extractor.job.state_at(result.time_s)
    nozzle = (float(state.x_mm), float(state.y_mm))
    for window, outcome in result.drawn:
        colour = OUTCOME_COLOURS.get(outcome, FAIL_COLOUR)
        (c0, c1), (r0, r1) = cam.part_to_pixel(
            np.array([w.x_from[window], w.x_to[window]]),
            np.array([w.y_from[window], w.y_to[window]]),
            nozzle,
        )
        cv2.line(canvas, _pt(c0, r0), _pt(c1, r1), colour, 2, cv2.LINE_AA)
    geometry = result.geometry
    if geometry is not None:
        n = extractor.settings.batch
        middle = n // 2
        for k in range(len(geometry["ids"])):
            j = k * n + middle
            col, row = geometry["col"][j], geometry["row"][j]
            ncol, nrow = geometry["ncol"][j], geometry["nrow"][j]
            for points, colour in (
                (geometry["edges"][k], OVERSPRAY_COLOUR),
                (geometry["shoulders"][k], SHOULDER_COLOUR),
            ):
                if np.all(np.isfinite(points)):
                    a = _pt(col + ncol * points[0], row + nrow * points[0])
                    b = _pt(col + ncol * points[1], row + nrow * points[1])
                    cv2.line(canvas, a, b, colour, 1, cv2.LINE_AA)
    for line in result.foreign:
        half = 0.5e-3 * line.length_um
        du, dv = math.cos(math.radians(line.angle_deg)), math.sin(math.radians(line.angle_deg))
        cols, rows = cam.part_to_pixel(
            np.array([line.x_mm - half * du, line.x_mm + half * du]),
            np.array([line.y_mm - half * dv, line.y_mm + half * dv]),
            nozzle,
        )
        cv2.line(canvas, _pt(cols[0], rows[0]), _pt(cols[1], rows[1]), FOREIGN_COLOUR, 3)
    text = f"t={result.time_s:.2f}s  readings {result.n_readings}"
    skipped = ", ".join(f"{k} {v}" for k, v in result.skipped.most_common(3))
    if skipped:
        text += f"  skipped: {skipped}"
    if result.n_readings == 0:
        text += f"  [{result.status}]"
    if result.foreign:
        text += "  line off the program"
    cv2.putText(canvas, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 255, 255), 1)
    return canvas


def _pt(col, row) -> tuple[int, int]:
    return int(round(float(col))), int(round(float(row)))
