"""The job: a program's one representation — an exact, piecewise timeline of the stage.

A :class:`Job` holds the program as *segments* in time order, covering the whole run
without gaps: straight lines, circular arcs and dwells (the stage still), each with its
times, exact geometry, constant speed, shutter state, stroke and feature. A *stroke* is one
span of time with the shutter open (the trace it leaves may hold lines, arcs and dwells).
Everything downstream — the virtual printer, the twin, the part map, the trailing camera —
asks the job: where is the nozzle at time t, what was printed during second k, which
trace lies under a point of the part and when was it printed.

Times are seconds from the program's start, positions millimetres in the program's
coordinates, speeds mm/s. See docs/reference/job.md.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.io.schema import MAX_RECORD_SECONDS
from ajtwin.job.errors import ProgramError
from ajtwin.job.geometry import (
    GEOMETRY_FIELDS,
    arc_steps,
    point_and_tangent,
    point_at,
    segment_bbox,
)
from ajtwin.job.locate import TraceIndex
from ajtwin.job.program import (
    KIND_ARC,
    KIND_DWELL,
    KIND_LINE,
    KIND_NAMES,
    P_A0,
    P_CX,
    P_CY,
    P_FEATURE,
    P_KIND,
    P_LEN,
    P_LINE,
    P_R,
    P_SOURCE,
    P_SPEED,
    P_SWEEP,
    P_T0,
    P_T1,
    P_X0,
    P_X1,
    P_Y0,
    P_Y1,
    ParsedProgram,
    SpeedSource,
)
from ajtwin.job.settings import ReaderSettings, Stage

__all__ = [
    "Job",
    "JobState",
    "LoopPlan",
    "stage_state",
    "StrokePoints",
    "TIMELINE_COLUMNS",
    "SEGMENT_FIELDS",
    "read_timeline",
]

# Arrays of Job.segments (all of length n_segments).
SEGMENT_FIELDS = (
    "kind",
    "t0_s",
    "t1_s",
    "x0_mm",
    "y0_mm",
    "x1_mm",
    "y1_mm",
    "cx_mm",
    "cy_mm",
    "radius_mm",
    "a0_rad",
    "sweep_rad",
    "length_mm",
    "speed_mm_s",
    "shutter_open",
    "stroke",
    "feature",
    "line",
    "s0_mm",
    "speed_source",
    "repetition",
    "base_stroke",
)

TIMELINE_COLUMNS = (
    "time_s",
    "x_mm",
    "y_mm",
    "speed_mm_s",
    "shutter_open",
    "stroke",
    "feature",
    "line",
    "segment",
)

_META_KEY = "ajtwin_job"


@dataclass(frozen=True)
class JobState:
    """The stage at given times (arrays shaped like the times asked for).

    Attributes
    ----------
    x_mm, y_mm : ndarray
        Nozzle position over the part.
    vx_mm_s, vy_mm_s, speed_mm_s : ndarray
        Platen velocity (direction of travel of the nozzle over the part) and its norm.
    shutter_open : ndarray of bool
    stroke, feature, segment : ndarray of int
        Stroke being printed (-1: shutter closed), feature (-1: none), segment index
        (-1 before the start and after the end).
    line, speed_source : ndarray of int
        The program line of that segment (0: a loop's wait or move between runs) and where
        its speed came from (index into the job's ``speed_sources``; -1: a dwell).
    """

    x_mm: np.ndarray
    y_mm: np.ndarray
    vx_mm_s: np.ndarray
    vy_mm_s: np.ndarray
    speed_mm_s: np.ndarray
    shutter_open: np.ndarray
    stroke: np.ndarray
    feature: np.ndarray
    segment: np.ndarray
    line: np.ndarray
    speed_source: np.ndarray


@dataclass(frozen=True)
class StrokePoints:
    """Points along strokes by arclength: position, print time and direction of travel."""

    x_mm: np.ndarray
    y_mm: np.ndarray
    time_s: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    segment: np.ndarray


def _empty_like_fields(n: int) -> dict:
    return {name: np.zeros(n) for name in SEGMENT_FIELDS}


def _sub_segments(seg: dict, parent: np.ndarray, f_s: np.ndarray, f_e: np.ndarray) -> dict:
    """Parts [f_s, f_e] (fractions of length and time) of the segments ``parent``."""
    g = {name: seg[name][parent] for name in SEGMENT_FIELDS}
    args = [g[k] for k in GEOMETRY_FIELDS]
    xs, ys = point_at(*args, f_s)
    xe, ye = point_at(*args, f_e)
    dt = g["t1_s"] - g["t0_s"]
    t0 = g["t0_s"] + f_s * dt
    t1 = np.where(f_e >= 1.0, g["t1_s"], g["t0_s"] + f_e * dt)
    arc = g["kind"] == KIND_ARC
    g["a0_rad"] = np.where(arc, g["a0_rad"] + f_s * g["sweep_rad"], g["a0_rad"])
    g["sweep_rad"] = g["sweep_rad"] * (f_e - f_s)
    g["s0_mm"] = g["s0_mm"] + f_s * g["length_mm"]
    g["length_mm"] = g["length_mm"] * (f_e - f_s)
    g.update(x0_mm=xs, y0_mm=ys, x1_mm=xe, y1_mm=ye, t0_s=t0, t1_s=t1)
    return g


def _concat(parts: list[dict]) -> dict:
    return {name: np.concatenate([p[name] for p in parts]) for name in SEGMENT_FIELDS}


def _take(seg: dict, index) -> dict:
    return {name: seg[name][index] for name in SEGMENT_FIELDS}


def _cut_at_times(seg: dict, times: np.ndarray) -> dict:
    """Split segments at the given times wherever one falls strictly inside a segment."""
    times = np.unique(times)
    if times.size == 0 or seg["t0_s"].size == 0:
        return seg
    t0, t1 = seg["t0_s"], seg["t1_s"]
    lo = np.searchsorted(times, t0, side="right")
    hi = np.searchsorted(times, t1, side="left")
    cuts = np.maximum(hi - lo, 0)
    if not cuts.any():
        return seg
    pieces = cuts + 1
    parent = np.repeat(np.arange(t0.size), pieces)
    within = np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    start_t = np.where(
        within == 0, t0[parent], times[np.minimum(lo[parent] + within - 1, times.size - 1)]
    )
    last = within == cuts[parent]
    end_t = np.where(last, t1[parent], times[np.minimum(lo[parent] + within, times.size - 1)])
    dt = (t1 - t0)[parent]
    f_s = np.where(within == 0, 0.0, (start_t - t0[parent]) / dt)
    f_e = np.where(last, 1.0, (end_t - t0[parent]) / dt)
    out = _sub_segments(seg, parent, f_s, f_e)
    out["t0_s"], out["t1_s"] = start_t, end_t
    keep = out["t1_s"] > out["t0_s"]
    return _take(out, keep)


def _segments_from_program(parsed: ParsedProgram) -> dict:
    """Pieces + the still spans between them, cut where the shutter switches."""
    P = parsed.pieces
    n = len(P)
    sx, sy = parsed.start_xy
    m = 2 * n + 1
    seg = _empty_like_fields(m)
    pieces = slice(1, m, 2)
    gaps = slice(0, m, 2)
    seg["kind"][gaps] = KIND_DWELL
    seg["t0_s"][gaps] = np.r_[0.0, P[:, P_T1]]
    seg["t1_s"][gaps] = np.r_[P[:, P_T0], max(parsed.end_time_s, P[-1, P_T1] if n else 0.0)]
    gx, gy = np.r_[sx, P[:, P_X1]], np.r_[sy, P[:, P_Y1]]
    for name, g_value, column in (
        ("kind", None, P_KIND),
        ("x0_mm", gx, P_X0),
        ("y0_mm", gy, P_Y0),
        ("x1_mm", gx, P_X1),
        ("y1_mm", gy, P_Y1),
        ("cx_mm", np.nan, P_CX),
        ("cy_mm", np.nan, P_CY),
        ("radius_mm", np.nan, P_R),
        ("a0_rad", np.nan, P_A0),
        ("sweep_rad", 0.0, P_SWEEP),
        ("length_mm", 0.0, P_LEN),
        ("t0_s", None, P_T0),
        ("t1_s", None, P_T1),
        ("speed_mm_s", 0.0, P_SPEED),
        ("line", None, P_LINE),
        ("feature", None, P_FEATURE),
        ("speed_source", -1.0, P_SOURCE),
    ):
        if g_value is not None:
            seg[name][gaps] = g_value
        seg[name][pieces] = P[:, column]
    # what the stage was waiting on, and the feature in force, during each still span
    t_gap = seg["t0_s"][gaps]
    if parsed.mark_t.size:
        k = np.searchsorted(parsed.mark_t, t_gap, side="right") - 1
        seg["line"][gaps] = np.where(k >= 0, parsed.mark_line[np.maximum(k, 0)], 0)
    k = np.searchsorted(parsed.feature_t, t_gap, side="right") - 1
    seg["feature"][gaps] = parsed.feature_value[np.maximum(k, 0)]
    seg = _take(seg, seg["t1_s"] > seg["t0_s"])
    seg = _cut_at_times(seg, parsed.shutter_t)
    if parsed.shutter_t.size:
        k = np.searchsorted(parsed.shutter_t, seg["t0_s"], side="right") - 1
        seg["shutter_open"] = np.where(k >= 0, parsed.shutter_open[np.maximum(k, 0)], False)
    else:
        seg["shutter_open"] = np.zeros(seg["t0_s"].size, dtype=bool)
    seg["repetition"] = np.zeros(seg["t0_s"].size)
    return seg


def _typed(seg: dict) -> dict:
    out = dict(seg)
    for name in ("kind",):
        out[name] = np.asarray(seg[name], dtype=np.int8)
    for name in ("stroke", "feature", "line", "speed_source", "repetition", "base_stroke"):
        out[name] = np.asarray(seg[name], dtype=np.int64)
    out["shutter_open"] = np.asarray(seg["shutter_open"], dtype=bool)
    for name in SEGMENT_FIELDS:
        if out[name].dtype.kind == "f" or name not in out:
            out[name] = np.asarray(out[name], dtype=float)
        out[name].setflags(write=False)
    return out


def _number_strokes(seg: dict) -> dict:
    """Stroke ids (one per run of shutter-open segments) and the arclength within each."""
    is_open = np.asarray(seg["shutter_open"], dtype=bool)
    starts = is_open & ~np.r_[False, is_open[:-1]]
    stroke = np.where(is_open, np.cumsum(starts) - 1, -1)
    printed = np.where(is_open, seg["length_mm"], 0.0)
    before = np.cumsum(printed) - printed
    first = np.flatnonzero(starts)
    s0 = np.full(is_open.size, np.nan)
    if first.size:
        s0[is_open] = (before - before[first][np.maximum(stroke, 0)])[is_open]
    seg["stroke"], seg["s0_mm"] = stroke, s0
    return seg


@dataclass(frozen=True)
class LoopPlan:
    """When and where each run of a looped job starts (:meth:`Job.loop_plan`).

    Attributes
    ----------
    duration_s, gap_s : float
        The loop's length and the wait between runs [s].
    offsets_s : ndarray (runs,)
        Run k's program times are shifted by ``offsets_s[k]`` [s].
    places_mm : ndarray (runs, 2)
        Where run k sits on the substrate relative to the program [mm].
    pitch_mm : (float, float) or None
        The runs' pitch side by side (None: every run prints over the first).
    period_s : float or None
        Program, wait and return move [s] when every run prints over the first (None:
        runs side by side).
    program_duration_s : float
        One run of the program [s].
    program_end_xy, program_start_xy : (float, float)
        Where the program ends and starts [mm].
    program_end_shutter_open : bool
        The shutter as the program leaves it (it stays so between runs).
    return_speed_mm_s : float
        Speed of the move to the next run's start.
    return_source : int
        Where that speed came from (index into the job's ``speed_sources``).
    note : str
        What the looping did, in words.
    """

    duration_s: float
    gap_s: float
    offsets_s: np.ndarray
    places_mm: np.ndarray
    pitch_mm: tuple | None
    period_s: float | None
    program_duration_s: float
    program_end_xy: tuple
    program_start_xy: tuple
    program_end_shutter_open: bool
    return_speed_mm_s: float
    return_source: int
    note: str

    @property
    def runs(self) -> int:
        """How many runs the loop starts."""
        return int(self.offsets_s.size)

    def spans_before(self, k: int) -> list[tuple]:
        """The wait and the move before run ``k`` as (kind, t0, t1, from, to, length) [s, mm]:
        the wait when it lasts, the move when the parts' end and start differ."""
        if k == 0:
            return []
        D, previous = self.program_duration_s, float(self.offsets_s[k - 1])
        end = (self.program_end_xy[0] + self.places_mm[k - 1, 0],
               self.program_end_xy[1] + self.places_mm[k - 1, 1])  # fmt: skip
        start = (self.program_start_xy[0] + self.places_mm[k, 0],
                 self.program_start_xy[1] + self.places_mm[k, 1])  # fmt: skip
        if self.period_s is not None:  # the times as the unpitched loop has always made them
            t_end, t_wait, t_move = (D + previous, (D + self.gap_s) + previous,
                                     self.period_s + previous)  # fmt: skip
        else:
            t_end, t_wait, t_move = previous + D, previous + D + self.gap_s, self.offsets_s[k]
        distance = math.hypot(start[0] - end[0], start[1] - end[1])
        spans = []
        if t_wait > t_end:
            spans.append((KIND_DWELL, t_end, t_wait, end, end, 0.0))
        if distance > 0:
            spans.append((KIND_LINE, t_wait, float(t_move), end, start, distance))
        return spans

    def end_shutter_open(self, last_segment_open: bool) -> bool:
        """The looped job's shutter after its end: the last segment's when the loop cuts a
        run short, else as the program leaves it."""
        last = self.offsets_s[-1] + self.program_duration_s
        truncated = self.duration_s < last - 1e-9
        return bool(last_segment_open) if truncated else self.program_end_shutter_open


@dataclass(frozen=True)
class JobOrigin:
    """What a job was read from, passed on to every job made from it (cut, looped, re-timed).

    Attributes
    ----------
    path : str
        The program file.
    n_lines : int
        Its number of lines.
    speed_sources : list of SpeedSource
        Where each speed came from (re-timing adds the schedule's).
    feature_names : dict of int to str
        The program's feature labels.
    stage : Stage
        The stage's travel and rapid speed (``stage.toml``).
    settings : ReaderSettings
        The reader's settings (``job.toml``).
    return_source : int
        The speed source of the move back to a run's start when the job is looped.

    Examples
    --------
    >>> from ajtwin.job import read_program_text
    >>> prg = "ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),4,0\\nOUT0.0=0"
    >>> job = read_program_text(prg, process_speed_mm_s=2)
    >>> looped = job.repeat(60.0)
    >>> looped.origin == job.origin, job.origin.n_lines
    (True, 4)
    """

    path: str
    n_lines: int
    speed_sources: list[SpeedSource]
    feature_names: dict[int, str]
    stage: Stage
    settings: ReaderSettings
    return_source: int


class Job:
    """A program as the stage runs it: segments, strokes, and the questions asked of them.

    Build one with :func:`ajtwin.job.read_program`. Attributes are read-only.

    Attributes
    ----------
    path : str
        The program file.
    segments : dict of ndarray
        One entry per field of :data:`SEGMENT_FIELDS`, all of length ``n_segments``, in time
        order and covering ``[0, duration_s]`` without gaps: ``kind`` (0 line, 1 arc,
        2 dwell), ``t0_s``/``t1_s``, start ``x0_mm``/``y0_mm`` and end ``x1_mm``/``y1_mm``,
        arc centre ``cx_mm``/``cy_mm``, ``radius_mm``, start angle ``a0_rad`` and signed
        ``sweep_rad`` (+ counter-clockwise; NaN/0 for lines), ``length_mm``,
        ``speed_mm_s`` (constant over the segment; 0 for dwells), ``shutter_open``,
        ``stroke`` (-1 when closed), ``feature`` (-1: none), ``line`` (source line),
        ``s0_mm`` (arclength of the stroke at the segment's start, NaN when closed),
        ``speed_source`` (index into ``speed_sources``, -1 for dwells), ``repetition`` and
        ``base_stroke`` (the stroke's number in the program, for repeated jobs).
    speed_sources : list of SpeedSource
        Where each speed came from.
    strokes : pandas.DataFrame
        One row per stroke (see :meth:`stroke_table`).
    notes, warnings : list of str
        What was skipped or assumed (blocks, ignored assignments) and what may be wrong.
    speed_schedule : ajtwin.job.speeds.SpeedSchedule or None
        The process speeds per layer, stroke or feature the job was re-timed to
        (:func:`ajtwin.job.speeds.apply_speed_schedule`); kept when the job is looped.
    """

    def __init__(
        self,
        segments: dict,
        *,
        origin: JobOrigin,
        notes: list[str],
        warnings: list[str],
        end_shutter_open: bool,
        repetition_offsets_s: np.ndarray | None = None,
        program_duration_s: float | None = None,
        repetition_offsets_mm: np.ndarray | None = None,
        speed_schedule=None,
    ):
        segments = _number_strokes(dict(segments))
        if repetition_offsets_s is None:  # a job read from a program: strokes are its own
            segments["base_stroke"] = segments["stroke"].copy()
        self._seg = _typed(segments)
        self.origin = origin
        self.path = str(origin.path)
        self.n_lines = origin.n_lines
        self.speed_sources = list(origin.speed_sources)
        self.feature_names = dict(origin.feature_names)
        self.notes = list(notes)
        self.warnings = list(warnings)
        self.stage = origin.stage
        self.settings = origin.settings
        self.return_source = origin.return_source
        self.end_shutter_open = bool(end_shutter_open)
        self.repetition_offsets_s = np.array(
            [0.0] if repetition_offsets_s is None else repetition_offsets_s
        )
        #: (runs, 2) where each run sits on the substrate [mm] (all 0: printed over each other)
        self.repetition_offsets_mm = (
            np.zeros((self.repetition_offsets_s.size, 2))
            if repetition_offsets_mm is None
            else np.asarray(repetition_offsets_mm, dtype=float).reshape(-1, 2)
        )
        #: the process speeds per layer, stroke or feature applied to the program
        #: (:class:`ajtwin.job.speeds.SpeedSchedule`; None: the program's own speeds)
        self.speed_schedule = speed_schedule
        self._index = {}
        self._build_strokes()
        self.program_duration_s = (
            self.duration_s if program_duration_s is None else float(program_duration_s)
        )

    # -- construction ----------------------------------------------------------------------

    @classmethod
    def from_program(cls, parsed: ParsedProgram, *, stage: Stage, settings: ReaderSettings) -> Job:
        """Assemble a job from one pass of the reader (see :func:`ajtwin.job.read_program`)."""
        if len(parsed.pieces) == 0:
            # what the reader noted (another buffer not read, blocks skipped) says why
            why = "".join(f"; {note}" for note in parsed.notes)
            raise ProgramError(
                parsed.path,
                None,
                "",
                f"the program moves nothing in X-Y: there is no timeline to build{why}",
            )
        bad = ~np.isfinite(parsed.pieces[:, [P_X0, P_Y0, P_X1, P_Y1, P_T1]]).all(axis=1)
        if bad.any():
            line = int(parsed.pieces[np.argmax(bad), P_LINE])
            raise ProgramError(
                parsed.path, line, "", "a coordinate or time of this motion is not a finite number"
            )
        seg = _segments_from_program(parsed)
        end_open = bool(parsed.shutter_open[-1]) if parsed.shutter_open.size else False
        warnings = list(parsed.warnings)
        if end_open:
            line = int(parsed.shutter_line[-1])
            warnings.append(f"the program ends with the shutter open (opened at line {line})")
        origin = JobOrigin(
            path=parsed.path,
            n_lines=parsed.n_lines,
            speed_sources=parsed.speed_sources,
            feature_names=parsed.feature_names,
            stage=stage,
            settings=settings,
            return_source=parsed.return_source,
        )
        return cls(
            seg, origin=origin, notes=parsed.notes, warnings=warnings, end_shutter_open=end_open
        )

    def _build_strokes(self) -> None:
        s = self._seg
        is_open = s["shutter_open"]
        starts = np.flatnonzero(is_open & ~np.r_[False, is_open[:-1]])
        ends = np.flatnonzero(is_open & ~np.r_[is_open[1:], False])
        self._stroke_first, self._stroke_last = starts, ends
        length = s["length_mm"]
        moving = is_open & (length > 0)
        moving_index = np.flatnonzero(moving)
        if starts.size:
            # sums over [start_k, start_k+1): the closed segments in between add 0
            lengths = np.add.reduceat(np.where(is_open, length, 0.0), starts)
            # a stroke's feature: that of its first moving segment (else of its first segment)
            position = np.searchsorted(moving_index, starts)
            candidate = (
                moving_index[np.minimum(position, moving_index.size - 1)]
                if moving_index.size
                else starts
            )
            use = (position < moving_index.size) & (candidate <= ends)
            feature_index = np.where(use, candidate, starts)
        else:
            lengths = np.zeros(0)
            feature_index = starts
        self._stroke_length = lengths
        t_start, t_end = s["t0_s"][starts], s["t1_s"][ends]
        self._stroke_t = (t_start, t_end)
        self._stroke_feature = s["feature"][feature_index]
        # printed length of all strokes before each stroke (global arclength key)
        self._stroke_base = np.cumsum(lengths) - lengths
        self._moving = moving_index
        ms = s["stroke"][self._moving]
        ids = np.arange(starts.size)
        self._moving_first = np.searchsorted(ms, ids, side="left")
        self._moving_stop = np.searchsorted(ms, ids, side="right")
        self._moving_key = (
            self._stroke_base[ms] + s["s0_mm"][self._moving] if ms.size else np.zeros(0)
        )
        duration = np.maximum(t_end - t_start, 0.0)
        self.strokes = pd.DataFrame(
            {
                "stroke": ids.astype(np.int64),
                "feature": self._stroke_feature.astype(np.int64),
                "repetition": s["repetition"][starts].astype(np.int64),
                "base_stroke": s["base_stroke"][starts].astype(np.int64),
                "t_start_s": t_start,
                "t_end_s": t_end,
                "duration_s": duration,
                "length_mm": lengths,
                "mean_speed_mm_s": np.divide(
                    lengths, duration, out=np.zeros_like(lengths), where=duration > 0
                ),
                "x_start_mm": s["x0_mm"][starts],
                "y_start_mm": s["y0_mm"][starts],
                "x_end_mm": s["x1_mm"][ends],
                "y_end_mm": s["y1_mm"][ends],
                "first_line": s["line"][starts].astype(np.int64),
                "last_line": s["line"][ends].astype(np.int64),
                "first_segment": starts.astype(np.int64),
                "last_segment": ends.astype(np.int64),
            }
        )

    # -- plain properties ------------------------------------------------------------------

    @property
    def segments(self) -> dict:
        """The segment arrays by field name (:data:`SEGMENT_FIELDS`), one entry per segment."""
        return self._seg

    @property
    def n_segments(self) -> int:
        """Segments of the timeline (lines, arcs, dwells)."""
        return int(self._seg["t0_s"].size)

    @property
    def n_strokes(self) -> int:
        """Strokes: runs of segments printed with the shutter open."""
        return int(self._stroke_first.size)

    @property
    def duration_s(self) -> float:
        """Time from the program's start to the end of its last segment [s]."""
        return float(self._seg["t1_s"][-1])

    @property
    def repetitions(self) -> int:
        """How many times the program runs (its repetition offsets)."""
        return int(self.repetition_offsets_s.size)

    def segment_table(self) -> pd.DataFrame:
        """The segments as a DataFrame (``kind`` as its name: line, arc, dwell)."""
        table = pd.DataFrame({name: self._seg[name] for name in SEGMENT_FIELDS})
        table["kind"] = pd.Categorical.from_codes(self._seg["kind"], categories=list(KIND_NAMES))
        return table

    def stroke_table(self) -> pd.DataFrame:
        """One row per stroke: ``stroke``, ``feature``, ``repetition``, ``base_stroke``,
        ``t_start_s``/``t_end_s`` (shutter open/close), ``duration_s``, ``length_mm``,
        ``mean_speed_mm_s``, start/end point, first/last source line, first/last segment."""
        return self.strokes.copy()

    # -- summary ---------------------------------------------------------------------------

    def _bbox(self, mask) -> list[float] | None:
        s = self._seg
        if not np.any(mask):
            return None
        xmin, ymin, xmax, ymax = segment_bbox(*(s[k][mask] for k in GEOMETRY_FIELDS))
        return [float(xmin.min()), float(ymin.min()), float(xmax.max()), float(ymax.max())]

    def _speed_uses(self, mask) -> list[dict]:
        s = self._seg
        uses = []
        sources = s["speed_source"][mask]
        for index in np.unique(sources):
            if index < 0:
                continue
            sel = sources == index
            source = self.speed_sources[index]
            uses.append(
                {
                    "speed_mm_s": source.value_mm_s,
                    "kind": source.kind,
                    "source": source.origin,
                    "length_mm": float(s["length_mm"][mask][sel].sum()),
                    "time_s": float((s["t1_s"] - s["t0_s"])[mask][sel].sum()),
                }
            )
        return sorted(uses, key=lambda u: -u["length_mm"])

    def summary(self) -> dict:
        """Figures of the job, as plain Python (JSON-ready).

        Keys: ``program``, ``lines``, ``strokes``, ``printed_length_mm``, ``rapid_length_mm``,
        ``print_time_s`` (program start to end), ``printing_time_s`` (shutter open),
        ``bbox_mm`` (printed traces, [x_min, y_min, x_max, y_max]), ``travel_bbox_mm`` (all
        motion), ``features`` (per feature: strokes, printed length, name), ``print_speeds``
        and ``rapid_speeds`` (each speed used, where it came from, length and time at it),
        ``process_speed_mm_s``/``process_speed_source`` (the print speed over most of the
        printed length), ``rapid_speed_mm_s``/``rapid_speed_source``, ``stage``,
        ``repetitions``, ``notes``, ``warnings``.
        """
        s = self._seg
        is_open = s["shutter_open"]
        moving = s["kind"] != KIND_DWELL
        printed = is_open & moving
        rapid = ~is_open & moving
        duration = s["t1_s"] - s["t0_s"]
        print_speeds = self._speed_uses(printed)
        rapid_speeds = self._speed_uses(rapid)
        features = []
        for feature in np.unique(self._stroke_feature):
            sel = self._stroke_feature == feature
            features.append(
                {
                    "feature": int(feature),
                    "name": self.feature_names.get(int(feature), ""),
                    "strokes": int(sel.sum()),
                    "printed_length_mm": float(self._stroke_length[sel].sum()),
                }
            )
        main_print = print_speeds[0] if print_speeds else None
        main_rapid = rapid_speeds[0] if rapid_speeds else None
        return {
            "program": self.path,
            "lines": int(self.n_lines),
            "strokes": self.n_strokes,
            "printed_length_mm": float(s["length_mm"][printed].sum()),
            "rapid_length_mm": float(s["length_mm"][rapid].sum()),
            "print_time_s": self.duration_s,
            "printing_time_s": float(duration[is_open].sum()),
            "bbox_mm": self._bbox(printed),
            "travel_bbox_mm": self._bbox(moving),
            "features": features if any(f["feature"] >= 0 for f in features) else [],
            "print_speeds": print_speeds,
            "rapid_speeds": rapid_speeds,
            "process_speed_mm_s": main_print["speed_mm_s"] if main_print else None,
            "process_speed_source": f"{main_print['kind']}: {main_print['source']}"
            if main_print
            else None,
            "rapid_speed_mm_s": main_rapid["speed_mm_s"] if main_rapid else None,
            "rapid_speed_source": f"{main_rapid['kind']}: {main_rapid['source']}"
            if main_rapid
            else None,
            "stage": {
                "name": self.stage.name,
                "travel_x_mm": self.stage.travel_x_mm,
                "travel_y_mm": self.stage.travel_y_mm,
            },
            "segments": self.n_segments,
            "repetitions": self.repetitions,
            "speed_schedule": (
                None if self.speed_schedule is None else self.speed_schedule.to_meta()
            ),
            "notes": list(self.notes),
            "warnings": list(self.warnings),
        }

    # -- timeline --------------------------------------------------------------------------

    def timeline(self) -> pd.DataFrame:
        """The timeline table: one row per segment breakpoint, arcs cut into short chords.

        Columns (:data:`TIMELINE_COLUMNS`): ``time_s``, ``x_mm``, ``y_mm`` (the nozzle over
        the part at that time), and, holding from that row until the next one,
        ``speed_mm_s``, ``shutter_open`` (0/1), ``stroke`` (-1 closed), ``feature``,
        ``line`` (source line), ``segment``. A dwell is a row with speed 0 followed by the
        row where the stage moves again; the last row is the end of the program. Between
        rows positions are linear (chords of at most ``max_arc_step_deg`` and
        ``chord_tolerance_mm`` on arcs); :meth:`state_at` gives the exact arc.
        """
        s = self._seg
        steps = arc_steps(
            s["kind"],
            s["radius_mm"],
            s["sweep_rad"],
            math.radians(self.settings.max_arc_step_deg),
            self.settings.chord_tolerance_mm,
        )
        parent = np.repeat(np.arange(self.n_segments), steps)
        within = np.arange(parent.size) - np.repeat(np.cumsum(steps) - steps, steps)
        f = within / steps[parent]
        g = {k: s[k][parent] for k in GEOMETRY_FIELDS}
        x, y = point_at(*g.values(), f)
        t = s["t0_s"][parent] + f * (s["t1_s"] - s["t0_s"])[parent]
        last = self.n_segments - 1
        end_open = self.end_shutter_open
        table = pd.DataFrame(
            {
                "time_s": np.r_[t, self.duration_s],
                "x_mm": np.r_[x, s["x1_mm"][last]],
                "y_mm": np.r_[y, s["y1_mm"][last]],
                "speed_mm_s": np.r_[s["speed_mm_s"][parent], 0.0],
                "shutter_open": np.r_[s["shutter_open"][parent], end_open].astype(np.int8),
                "stroke": np.r_[s["stroke"][parent], s["stroke"][last] if end_open else -1].astype(
                    np.int32
                ),
                "feature": np.r_[s["feature"][parent], s["feature"][last]].astype(np.int32),
                "line": np.r_[s["line"][parent], s["line"][last]].astype(np.int32),
                "segment": np.r_[parent, last].astype(np.int32),
            }
        )
        return table

    def write_timeline(self, path: str | Path) -> Path:
        """Write :meth:`timeline` to ``.parquet``/``.pq`` (summary in the schema metadata
        under ``ajtwin_job``) or ``.csv`` (summary on a first ``# ajtwin_job: {json}`` line)."""
        path = Path(path)
        table = self.timeline()
        meta = json.dumps(self.summary())
        suffix = path.suffix.lower()
        if suffix in (".parquet", ".pq"):
            import pyarrow as pa
            import pyarrow.parquet as pq

            arrow = pa.Table.from_pandas(table, preserve_index=False)
            arrow = arrow.replace_schema_metadata(
                {**(arrow.schema.metadata or {}), _META_KEY.encode(): meta.encode()}
            )
            pq.write_table(arrow, path)
        elif suffix == ".csv":
            with path.open("w", encoding="utf-8", newline="") as handle:
                handle.write(f"# {_META_KEY}: {meta}\n")
                table.to_csv(handle, index=False)
        else:
            raise ValueError(
                f"{path}: the timeline is written as .parquet, .pq or .csv, not {path.suffix!r}"
            )
        return path

    # -- the stage at given times ----------------------------------------------------------

    def state_at(self, t) -> JobState:
        """Position, velocity and shutter state at times ``t`` [s] (any shape, exact arcs).

        Before 0 the stage is at its start and still with the shutter closed; after the end
        it is at its end, still, with the shutter as the program left it.

        Examples
        --------
        >>> from ajtwin.job import read_program_text
        >>> prg = "ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),4,0\\nOUT0.0=0"
        >>> job = read_program_text(prg, process_speed_mm_s=2)
        >>> state = job.state_at([1.0, 3.0])
        >>> state.x_mm.tolist(), state.shutter_open.tolist()
        ([2.0, 4.0], [True, False])
        """
        return stage_state(self._seg, t, self.duration_s, self.end_shutter_open)

    # -- the 1 Hz record -------------------------------------------------------------------

    def _cumulative(self, rate: np.ndarray, times: np.ndarray) -> np.ndarray:
        """∫_0^t rate dt at ``times`` (rate piecewise constant over the segments)."""
        s = self._seg
        dt = s["t1_s"] - s["t0_s"]
        area = np.cumsum(rate * dt) - rate * dt
        index = np.clip(np.searchsorted(s["t0_s"], times, side="right") - 1, 0, self.n_segments - 1)
        inside = np.clip(times - s["t0_s"][index], 0.0, dt[index])
        return np.where(times <= 0.0, 0.0, area[index] + rate[index] * inside)

    def per_second(self, duration_s: float | None = None, start_s: float = 0.0) -> pd.DataFrame:
        """Aggregate the job over 1-s bins ``[start_s + k, start_s + k + 1)``.

        Parameters
        ----------
        duration_s : float, optional
            Number of seconds to cover (default: the job's duration, rounded up). Seconds
            after the end have the shutter closed and nothing printed.
        start_s : float
            Time of bin 0 on the job's clock.

        Returns
        -------
        pandas.DataFrame
            ``time_s`` (bin start), ``shutter_open_fraction`` (of the second),
            ``printing_speed_mm_s`` (mean platen speed while the shutter was open: printed
            length / open time, NaN when the shutter stayed closed; dwells with the shutter
            open count at 0), ``printed_length_mm``, ``platen_speed_mm_s`` (mean over the
            whole second), ``stroke_first``/``stroke_last`` (-1: none) and ``strokes`` (a
            tuple of every stroke printed during the second).
        """
        if duration_s is None:
            duration_s = math.ceil(self.duration_s - start_s - 1e-9)
        n = max(int(math.ceil(duration_s - 1e-9)), 0)
        s = self._seg
        edges = start_s + np.arange(n + 1, dtype=float)
        is_open = s["shutter_open"].astype(float)
        open_time = np.diff(self._cumulative(is_open, edges))
        printed = np.diff(self._cumulative(is_open * s["speed_mm_s"], edges))
        moved = np.diff(self._cumulative(s["speed_mm_s"], edges))
        with np.errstate(invalid="ignore", divide="ignore"):
            printing_speed = np.where(open_time > 1e-12, printed / open_time, np.nan)
        # strokes overlapping each bin
        t_start, t_end = self._stroke_t
        k0 = np.floor(t_start - start_s).astype(np.int64)
        k1 = np.ceil(t_end - start_s).astype(np.int64) - 1
        k1 = np.maximum(k1, k0)
        count = np.clip(np.minimum(k1, n - 1) - np.maximum(k0, 0) + 1, 0, None)
        stroke_of = np.repeat(np.arange(t_start.size), count)
        bins = np.repeat(np.maximum(k0, 0), count) + (
            np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        )
        order = np.lexsort((stroke_of, bins))
        stroke_of, bins = stroke_of[order], bins[order]
        first = np.full(n, -1, dtype=np.int64)
        last = np.full(n, -1, dtype=np.int64)
        strokes = [()] * n
        if bins.size:
            boundaries = np.flatnonzero(np.r_[True, bins[1:] != bins[:-1]])
            ends = np.r_[boundaries[1:], bins.size]
            first[bins[boundaries]] = stroke_of[boundaries]
            last[bins[boundaries]] = stroke_of[ends - 1]
            for b, e in zip(boundaries.tolist(), ends.tolist()):
                strokes[int(bins[b])] = tuple(stroke_of[b:e].tolist())
        return pd.DataFrame(
            {
                "time_s": edges[:-1],
                "shutter_open_fraction": open_time,
                "printing_speed_mm_s": printing_speed,
                "printed_length_mm": printed,
                "platen_speed_mm_s": moved,
                "stroke_first": first,
                "stroke_last": last,
                "strokes": strokes,
            }
        )

    # -- points along strokes --------------------------------------------------------------

    def point_at(self, stroke, s_mm) -> StrokePoints:
        """Points at arclength ``s_mm`` along strokes ``stroke`` (arrays, broadcast).

        ``s_mm`` is clipped to [0, stroke length]. ``time_s`` is when the nozzle passed
        there (at a point where it dwelt, the time it arrived).
        """
        s = self._seg
        stroke, s_mm = np.broadcast_arrays(
            np.asarray(stroke, dtype=np.int64), np.asarray(s_mm, dtype=float)
        )
        if stroke.size and (stroke.min() < 0 or stroke.max() >= self.n_strokes):
            raise IndexError(f"stroke numbers run from 0 to {self.n_strokes - 1}")
        length = self._stroke_length[stroke]
        along = np.clip(s_mm, 0.0, length)
        first, stop = self._moving_first[stroke], self._moving_stop[stroke]
        has_motion = stop > first
        key = self._stroke_base[stroke] + along
        j = np.searchsorted(self._moving_key, key, side="right") - 1
        j = np.clip(j, first, np.maximum(stop - 1, first))
        seg = np.where(
            has_motion,
            self._moving[np.minimum(j, max(self._moving.size - 1, 0))] if self._moving.size else 0,
            self._stroke_first[stroke],
        )
        seg_len = s["length_mm"][seg]
        f = np.where(
            seg_len > 0,
            np.clip(
                (along - np.nan_to_num(s["s0_mm"][seg])) / np.where(seg_len > 0, seg_len, 1.0),
                0.0,
                1.0,
            ),
            0.0,
        )
        x, y, ux, uy = point_and_tangent(s, seg, f)
        t = s["t0_s"][seg] + f * (s["t1_s"][seg] - s["t0_s"][seg])
        t = np.where(has_motion, t, self._stroke_t[0][stroke])
        return StrokePoints(x_mm=x, y_mm=y, time_s=t, ux=ux, uy=uy, segment=seg.astype(np.int64))

    def _portion_counts(self, max_length_mm: float) -> np.ndarray:
        """Portions per stroke (:meth:`portions`), refused beyond ``max_portions``."""
        if not (max_length_mm > 0 and math.isfinite(max_length_mm)):
            raise ValueError(f"max_length_mm must be a positive length, got {max_length_mm}")
        length = self._stroke_length
        count = np.maximum(1, np.ceil(length / max_length_mm - 1e-9))
        limit = self.settings.max_portions
        if count.sum() > limit:
            raise ValueError(
                f"{self.path}: {length.sum():.1f} mm of strokes cut into portions of at most "
                f"{max_length_mm:g} mm make {count.sum():,.0f} portions, more than the "
                f"{limit:,} a part map holds (job.toml max_portions): longer portions"
            )
        return count

    def check_portions(self, max_length_mm: float) -> int:
        """How many portions :meth:`portions` would cut (ValueError beyond ``max_portions``
        of ``job.toml``): asked before a part map's work."""
        return int(self._portion_counts(max_length_mm).sum())

    def portions(self, max_length_mm: float = 1.0) -> pd.DataFrame:
        """Each stroke cut into equal portions of at most ``max_length_mm``.

        Returns
        -------
        pandas.DataFrame
            One row per portion: ``stroke``, ``portion`` (0, 1, … along the stroke),
            ``feature``, ``repetition``, ``base_stroke``, ``x_from_mm``/``y_from_mm``,
            ``x_to_mm``/``y_to_mm``, ``s_from_mm``/``s_to_mm`` (arclength along the stroke),
            ``length_mm``, ``t_from_s``/``t_to_s`` (when the nozzle printed its ends; the
            first portion starts when the shutter opens, the last ends when it closes).
            A stroke of zero length (the shutter opened over a still stage) is one portion.
        """
        count = self._portion_counts(max_length_mm).astype(np.int64)
        length = self._stroke_length
        stroke = np.repeat(np.arange(self.n_strokes), count)
        portion = np.arange(stroke.size) - np.repeat(np.cumsum(count) - count, count)
        step = length[stroke] / count[stroke]
        s_from, s_to = portion * step, (portion + 1) * step
        a, b = self.point_at(stroke, s_from), self.point_at(stroke, s_to)
        t_from = np.where(portion == 0, self._stroke_t[0][stroke], a.time_s)
        t_to = np.where(portion == count[stroke] - 1, self._stroke_t[1][stroke], b.time_s)
        table = self.strokes
        return pd.DataFrame(
            {
                "stroke": stroke,
                "portion": portion,
                "feature": table["feature"].to_numpy()[stroke],
                "repetition": table["repetition"].to_numpy()[stroke],
                "base_stroke": table["base_stroke"].to_numpy()[stroke],
                "x_from_mm": a.x_mm,
                "y_from_mm": a.y_mm,
                "x_to_mm": b.x_mm,
                "y_to_mm": b.y_mm,
                "s_from_mm": s_from,
                "s_to_mm": s_to,
                "length_mm": s_to - s_from,
                "t_from_s": t_from,
                "t_to_s": t_to,
            }
        )

    # -- the inverse query -----------------------------------------------------------------

    def trace_index(self, cell_mm: float | None = None):
        """The spatial index of the printed traces (built once per cell size, then cached)."""

        key = cell_mm
        if key not in self._index:
            self._index[key] = TraceIndex(self, cell_mm=cell_mm)
        return self._index[key]

    def locate(self, x_mm, y_mm, radius_mm: float, before_s=None):
        """Which printed trace passes within ``radius_mm`` of each point; see
        :meth:`ajtwin.job.locate.TraceIndex.query`."""
        return self.trace_index().query(x_mm, y_mm, radius_mm, before_s=before_s)

    def until(self, time_s: float) -> Job:
        """The job up to ``time_s``, the stroke printing then kept whole: what a camera can
        have seen by then. Strokes keep their numbers, lengths and times (a window cut along
        a stroke depends on its whole length); nothing printed later is held.

        Examples
        --------
        >>> from ajtwin.job import read_program_text
        >>> prg = "ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),4,0\\nOUT0.0=0\\nptp/e (X,Y),4,3"
        >>> job = read_program_text(prg, process_speed_mm_s=2)
        >>> cut = job.until(1.0)
        >>> cut.n_strokes, cut.duration_s
        (1, 2.0)
        """
        t = float(time_s)
        if t >= self.duration_s:
            return self
        stroke = int(self.state_at(t).stroke)
        if stroke >= 0:
            t = max(t, float(self._stroke_t[1][stroke]))
        seg = _cut_at_times(self._seg, np.array([t]))
        seg = _take(seg, seg["t0_s"] < t)
        runs = int(np.searchsorted(self.repetition_offsets_s, t, side="left")) or 1
        return Job(
            dict(seg),
            origin=self.origin,
            notes=self.notes,
            warnings=self.warnings,
            end_shutter_open=bool(seg["shutter_open"][-1]),
            repetition_offsets_s=self.repetition_offsets_s[:runs],
            program_duration_s=self.program_duration_s,
            repetition_offsets_mm=self.repetition_offsets_mm[:runs],
            speed_schedule=self.speed_schedule,
        )

    # -- looping ---------------------------------------------------------------------------

    def repeat(self, duration_s: float, gap_s: float = 0.0, pitch_mm=None) -> Job:
        """The job run again and again until ``duration_s`` (the last run cut there).

        Between runs the stage waits ``gap_s`` at the program's end position (shutter as the
        program left it), then moves to the next run's start at the speed of the program's
        first move (in the public programs, the rapid speed), as the controller does when the
        program is started again from where it ended. Run k's program times are shifted by
        ``repetition_offsets_s[k]``. Every run's segments are held: for a long loop that is
        asked only where the stage is and what lies under a point (a print's camera filing),
        :func:`ajtwin.job.loop_job` answers the same from the program alone.

        Parameters
        ----------
        duration_s : float
            Length of the looped job [s].
        gap_s : float
            Wait between runs [s].
        pitch_mm : (float, float), optional
            Place the runs side by side, an array of parts as a lab loops a job on one
            substrate: run k is the program moved by (column · dx, row · dy) [mm], the
            columns filling the stage's X travel first, then the next row. Default: every
            run prints over the first (the same part again). Refused when the array does not
            fit in the stage's travel (``stage.toml``).

        Returns
        -------
        Job
            With ``repetition`` and ``base_stroke`` (the stroke's number in the program) on
            every segment and stroke, ``repetition_offsets_mm`` (runs, 2) where each run sits;
            strokes are numbered anew across runs.
        """
        plan = self.loop_plan(duration_s, gap_s, pitch_mm)
        held = plan.runs * (self.n_segments + 2)
        limit = self.settings.max_held_segments
        if held > limit:
            raise ValueError(
                f"{self.path}: looped to {duration_s:g} s the job holds {held:,} segments "
                f"({plan.runs:,} runs of {self.n_segments:,}), more than the {limit:,} a job "
                "held whole may hold (job.toml max_held_segments): loop it to a shorter time"
            )
        seg = _concat([part for k in range(plan.runs) for part in self.loop_block(plan, k)])
        seg = _cut_at_times(seg, np.array([plan.duration_s]))
        seg = _take(seg, seg["t0_s"] < plan.duration_s)
        return Job(
            seg,
            origin=self.origin,
            notes=list(self.notes) + [plan.note],
            warnings=self.warnings,
            end_shutter_open=plan.end_shutter_open(seg["shutter_open"][-1]),
            repetition_offsets_s=plan.offsets_s,
            program_duration_s=plan.program_duration_s,
            repetition_offsets_mm=plan.places_mm,
            speed_schedule=self.speed_schedule,
        )

    def loop_plan(self, duration_s: float, gap_s: float = 0.0, pitch_mm=None) -> LoopPlan:
        """When and where each run of :meth:`repeat` starts (its arguments), without its
        segments."""
        if self.repetitions > 1:
            raise ValueError("this job is already repeated: repeat the job read from the program")
        if not (duration_s > 0 and math.isfinite(duration_s)) or not (
            gap_s >= 0 and math.isfinite(gap_s)
        ):
            raise ValueError(
                f"duration_s must be positive and gap_s non-negative, got {duration_s}, {gap_s}"
            )
        if duration_s > MAX_RECORD_SECONDS:
            raise ValueError(
                f"{self.path}: a loop of {duration_s:g} s is longer than the "
                f"{MAX_RECORD_SECONDS / 86400:g} days a print record may last"
            )
        s = self._seg
        D = self.duration_s
        end = (float(s["x1_mm"][-1]), float(s["y1_mm"][-1]))
        start = (float(s["x0_mm"][0]), float(s["y0_mm"][0]))
        source = self.speed_sources[self.return_source]
        if pitch_mm is None:
            distance = math.hypot(start[0] - end[0], start[1] - end[1])
            back = distance / source.value_mm_s
            period = D + gap_s + back
            runs = 1 if duration_s <= D else 1 + math.ceil((duration_s - D) / period - 1e-12)
            self._check_runs(runs, duration_s)
            offsets, places = np.arange(runs) * period, np.zeros((runs, 2))
            note = (
                f"{gap_s:g} s wait and {back:.3f} s return ({distance:.3f} mm at "
                f"{source.value_mm_s:g} mm/s) between runs"
            )
        else:
            offsets, places = self._array_schedule(duration_s, gap_s, pitch_mm)
            runs, period = offsets.size, None
            note = (
                f"side by side at a pitch of ({float(pitch_mm[0]):g}, {float(pitch_mm[1]):g}) "
                f"mm, {gap_s:g} s wait and a move at {source.value_mm_s:g} mm/s to the next "
                "part between runs"
            )
        return LoopPlan(
            duration_s=float(duration_s),
            gap_s=float(gap_s),
            offsets_s=offsets,
            places_mm=places,
            pitch_mm=None if pitch_mm is None else tuple(float(v) for v in pitch_mm),
            period_s=period,
            program_duration_s=D,
            program_end_xy=end,
            program_start_xy=start,
            program_end_shutter_open=self.end_shutter_open,
            return_speed_mm_s=float(source.value_mm_s),
            return_source=int(self.return_source),
            note=f"repeated {runs} time(s) to {duration_s:g} s: {note}",
        )

    def _check_runs(self, runs: int, duration_s: float) -> None:
        """Refuse a loop of more runs than ``max_loop_runs`` (``job.toml``)."""
        limit = self.settings.max_loop_runs
        if runs > limit:
            raise ValueError(
                f"{self.path}: one run lasts {self.duration_s:.4g} s, so a loop to "
                f"{duration_s:g} s starts {runs:,} runs, more than the {limit:,} a loop may "
                "start (job.toml max_loop_runs): is this the program the print looped?"
            )

    def loop_block(self, plan: LoopPlan, k: int) -> list[dict]:
        """Run ``k`` of the loop ``plan`` as segment arrays: the wait and the move that lead
        to it (none before run 0), then the program moved to its place and time."""
        parts = [_between_piece(plan, span, k) for span in plan.spans_before(k)]
        run = {name: np.asarray(self._seg[name], dtype=float) for name in SEGMENT_FIELDS}
        run["shutter_open"] = self._seg["shutter_open"].copy()
        run = _translated(run, *plan.places_mm[k])
        run["t0_s"] = run["t0_s"] + plan.offsets_s[k]
        run["t1_s"] = run["t1_s"] + plan.offsets_s[k]
        run["repetition"] = np.full(run["t0_s"].size, float(k))
        return parts + [run]

    def _array_schedule(self, duration_s: float, gap_s: float, pitch_mm):
        """Start times (runs,) and places (runs, 2) [mm] of runs side by side (:meth:`repeat`).

        A run k > 0 is made when run k − 1 ends before ``duration_s`` (as without a pitch);
        the move to it takes the distance between the parts at the return speed.
        """
        try:
            dx, dy = (float(v) for v in pitch_mm)
        except (TypeError, ValueError):
            raise ValueError(f"pitch_mm = {pitch_mm!r}: give (dx, dy) in mm") from None
        if not (math.isfinite(dx) and math.isfinite(dy)) or (dx == 0 and dy == 0):
            raise ValueError(f"pitch_mm = {pitch_mm!r}: a finite, non-zero (dx, dy) in mm")
        x0, y0, x1, y1 = self._bbox(np.ones(self.n_segments, dtype=bool))
        width, height = x1 - x0, y1 - y0
        if duration_s > self.duration_s:  # parts side by side must not print over each other
            printed = self._bbox(self._seg["shutter_open"] & (self._seg["kind"] != KIND_DWELL))
            part_w, part_h = (0.0, 0.0) if printed is None else (
                printed[2] - printed[0], printed[3] - printed[1])  # fmt: skip
            if (dx != 0 and abs(dx) < part_w) or (dy != 0 and abs(dy) < part_h):
                raise ValueError(
                    f"{self.path}: parts {part_w:.4g} x {part_h:.4g} mm (printed) at a pitch "
                    f"of ({dx:g}, {dy:g}) mm would print over each other: give a pitch of at "
                    "least the part's size in each direction it steps"
                )
        travel_x, travel_y = self.stage.travel_x_mm, self.stage.travel_y_mm
        columns = 1 if dx == 0 else 1 + int(math.floor((travel_x - width) / abs(dx) + 1e-9))
        rows = 1 if dy == 0 else 1 + int(math.floor((travel_y - height) / abs(dy) + 1e-9))
        D = self.duration_s
        speed = self.speed_sources[self.return_source].value_mm_s
        s = self._seg
        end = np.array([s["x1_mm"][-1], s["y1_mm"][-1]])
        start = np.array([s["x0_mm"][0], s["y0_mm"][0]])
        offsets, places = [0.0], [(0.0, 0.0)]
        while offsets[-1] + D < duration_s - 1e-12 * max(D, 1.0):
            k = len(offsets)
            self._check_runs(k + 1, duration_s)
            if k >= columns * rows or columns < 1 or rows < 1:
                raise ValueError(
                    f"{self.path}: {k + 1} parts of {width:.2f} x {height:.2f} mm at a pitch of "
                    f"({dx:g}, {dy:g}) mm do not fit in the {travel_x:g} x {travel_y:g} mm "
                    f"travel of the {self.stage.name} ({columns} x {rows} do): a smaller "
                    "pitch, a shorter run or a pitch in both X and Y"
                )
            place = (dx * (k % columns), dy * (k // columns))
            distance = float(np.hypot(*(start + place - end - places[-1])))
            offsets.append(offsets[-1] + D + gap_s + distance / speed)
            places.append(place)
        return np.array(offsets), np.array(places, dtype=float).reshape(-1, 2)


def stage_state(seg: dict, t, duration_s: float, end_shutter_open: bool) -> JobState:
    """The stage at times ``t`` over the segments ``seg`` (:meth:`Job.state_at`).

    ``seg`` covers ``[seg["t0_s"][0], duration_s]`` in time order; ``segment`` counts from
    its first entry. Before 0 the stage is at its start, still, shutter closed; from
    ``duration_s`` on at the end of the last segment, still, shutter ``end_shutter_open``.
    """
    s = seg
    t = np.asarray(t, dtype=float)
    n = s["t0_s"].size
    index = np.clip(np.searchsorted(s["t0_s"], t, side="right") - 1, 0, n - 1)
    dt = s["t1_s"][index] - s["t0_s"][index]
    f = np.clip((t - s["t0_s"][index]) / dt, 0.0, 1.0)
    x, y, ux, uy = point_and_tangent(s, index, f)
    before, after = t < 0.0, t >= duration_s
    outside = before | after
    speed = np.where(outside, 0.0, s["speed_mm_s"][index])
    shutter = np.where(outside, np.where(after, end_shutter_open, False), s["shutter_open"][index])
    stroke = np.where(outside & ~(after & end_shutter_open), -1, s["stroke"][index])
    return JobState(
        x_mm=x,
        y_mm=y,
        vx_mm_s=speed * ux,
        vy_mm_s=speed * uy,
        speed_mm_s=speed,
        shutter_open=shutter.astype(bool),
        stroke=stroke.astype(np.int64),
        feature=s["feature"][index].astype(np.int64),
        segment=np.where(outside, -1, index).astype(np.int64),
        line=s["line"][index].astype(np.int64),
        speed_source=np.where(outside, -1, s["speed_source"][index]).astype(np.int64),
    )


def _translated(seg: dict, dx: float, dy: float) -> dict:
    """Segments moved by (dx, dy) mm (positions and arc centres; angles unchanged)."""
    if dx == 0 and dy == 0:
        return seg
    for name in ("x0_mm", "x1_mm", "cx_mm"):
        seg[name] = seg[name] + dx
    for name in ("y0_mm", "y1_mm", "cy_mm"):
        seg[name] = seg[name] + dy
    return seg


def _between_piece(plan: LoopPlan, span: tuple, k: int) -> dict:
    """One segment before run ``k`` (a :meth:`LoopPlan.spans_before` span): shutter as the
    program left it, no stroke or feature."""
    kind, t0, t1, a, b, length = span
    moving = kind == KIND_LINE
    p = _empty_like_fields(1)
    p.update(
        kind=np.array([kind]),
        t0_s=np.array([t0]),
        t1_s=np.array([t1]),
        x0_mm=np.array([a[0]]),
        y0_mm=np.array([a[1]]),
        x1_mm=np.array([b[0]]),
        y1_mm=np.array([b[1]]),
        cx_mm=np.array([np.nan]),
        cy_mm=np.array([np.nan]),
        radius_mm=np.array([np.nan]),
        a0_rad=np.array([np.nan]),
        length_mm=np.array([length]),
        speed_mm_s=np.array([plan.return_speed_mm_s if moving else 0.0]),
        speed_source=np.array([float(plan.return_source) if moving else -1.0]),
        feature=np.array([-1.0]),
        base_stroke=np.array([-1.0]),
        repetition=np.array([float(k)]),
    )
    p["shutter_open"] = np.array([plan.program_end_shutter_open])
    return p


def read_timeline(path: str | Path) -> tuple[pd.DataFrame, dict]:
    """Read a timeline written by :meth:`Job.write_timeline`: the table and the job summary."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".parquet", ".pq"):
        import pyarrow.parquet as pq

        arrow = pq.read_table(path)
        meta = (arrow.schema.metadata or {}).get(_META_KEY.encode())
        return arrow.to_pandas(), json.loads(meta) if meta else {}
    if suffix == ".csv":
        with path.open(encoding="utf-8") as handle:
            first = handle.readline()
            meta = {}
            prefix = f"# {_META_KEY}: "
            if first.startswith(prefix):
                meta = json.loads(first[len(prefix) :])
            else:
                handle.seek(0)
            return pd.read_csv(handle), meta
    raise ValueError(f"{path}: a timeline is .parquet, .pq or .csv, not {path.suffix!r}")
