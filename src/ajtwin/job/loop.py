"""A job looped to a long print without holding every run: the program and where each run goes.

:meth:`Job.repeat <ajtwin.job.Job.repeat>` holds the segments of every run, so a looped job
grows with the print (the public seven-layer program looped to 24 h holds 137,411
segments). A print's camera filing asks a looped job two things only: where the stage is at
a time (position, speed, shutter) and which trace lies under a point of the part (its print
time). :class:`LoopedJob` answers both from the program and the loop's plan
(:class:`~ajtwin.job.job.LoopPlan`), with the same numbers :meth:`Job.repeat` gives,
segments and strokes counted across runs:

* the stage at t: the run (with the wait and move before it) that holds t, built from the
  program when asked (the last few are kept);
* the trace under a point before t: run k is the program moved by its place and time, so
  each run that can hold the trace is asked through the *program's* trace index, the point
  and the time moved back by that run's place and start. Where every run prints over the
  first, the run at t and the one before it are enough: an older run's traces lie where the
  one before printed them again later, and the latest print wins.

Examples
--------
>>> from ajtwin.job import read_program_text
>>> prg = "ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),4,0\\nOUT0.0=0"
>>> looped = loop_job(read_program_text(prg, process_speed_mm_s=2), 3600.0)
>>> looped.repetitions, looped.state_at([1.0]).x_mm.tolist()
(901, [2.0])
>>> hits = looped.locate([1.0, 1.0], [0.0, 0.0], radius_mm=0.05, before_s=[1800.3, 1801.0])
>>> hits.repetition.tolist(), hits.print_time_s.round(6).tolist()   # run 450 starts at 1800 s
([449, 450], [1796.5, 1800.5])
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
import pandas as pd

from ajtwin.job.job import (
    Job,
    JobState,
    LoopPlan,
    _concat,
    _cut_at_times,
    _take,
    _typed,
    stage_state,
)
from ajtwin.job.locate import TraceHits, nearest_then_latest

__all__ = ["LoopedJob", "loop_job"]

# runs built for the stage at a time and kept (a camera filing asks times in order)
_KEPT_RUNS = 4
# points asked of the program's index at once (each asks one to a few runs)
_POINTS_PER_PASS = 65_536
# (point, run) cells weighed at once when runs lie side by side
_PLACE_CELLS = 2_000_000
# a trace printed this close to a point's time counts as printed at it, not before: a
# run's time moved back by its start rounds, and the trace under the nozzle is not yet seen
_SAME_TIME_S = 1e-9


def loop_job(job: Job, duration_s: float, gap_s: float = 0.0, pitch_mm=None) -> LoopedJob:
    """``job`` looped as :meth:`Job.repeat` loops it, without holding every run.

    Parameters are those of :meth:`Job.repeat` (the same refusals). The answers of the
    returned job's :meth:`~LoopedJob.state_at` and :meth:`~LoopedJob.locate` are those of
    the repeated job; a program whose strokes run on from one run into the next (it ends
    with the shutter open, or opens it at its start while it is still open at its end) is
    repeated whole instead (``held_whole``).
    """
    return LoopedJob(job, job.loop_plan(duration_s, gap_s, pitch_mm))


class LoopedJob:
    """A program looped to a long print, answered run by run (see the module).

    Parameters
    ----------
    program : ajtwin.job.Job
        The job read from the program (one run).
    plan : ajtwin.job.job.LoopPlan
        Its loop (:meth:`ajtwin.job.Job.loop_plan`).

    Attributes
    ----------
    program : ajtwin.job.Job
    plan : ajtwin.job.job.LoopPlan
    duration_s : float
        The looped job's length [s].
    repetition_offsets_s, repetition_offsets_mm : ndarray (runs,), (runs, 2)
        When and where each run starts.
    program_duration_s : float
    end_shutter_open : bool
        The shutter after the end.
    held_whole : bool
        The loop is held as :meth:`Job.repeat` makes it (a stroke runs across runs).
    path, stage, settings, speed_sources, notes, warnings
        As the program's (the notes say how it was looped).
    """

    def __init__(self, program: Job, plan: LoopPlan):
        self.program, self.plan = program, plan
        self.path, self.stage, self.settings = program.path, program.stage, program.settings
        self.speed_sources = program.speed_sources
        self.notes = list(program.notes) + [plan.note]
        self.warnings = list(program.warnings)
        self.repetition_offsets_s = plan.offsets_s
        self.repetition_offsets_mm = plan.places_mm
        self.program_duration_s = plan.program_duration_s
        is_open = program.segments["shutter_open"]
        self.held_whole = bool(program.end_shutter_open or (is_open[0] and is_open[-1]))
        self._whole = None
        self._runs = OrderedDict()
        if self.held_whole:
            self._whole = program.repeat(plan.duration_s, plan.gap_s, plan.pitch_mm)
            self.duration_s = self._whole.duration_s
            self.end_shutter_open = self._whole.end_shutter_open
            return
        n_program = program.n_segments
        spans = [plan.spans_before(k) for k in range(plan.runs)]
        n_before = np.array([len(s) for s in spans], dtype=np.int64)
        #: segments of the loop before each run's first (its wait and move included)
        self._first_segment = np.cumsum(n_before) + n_program * np.arange(plan.runs)
        self._block_offset = self._first_segment - n_before
        starts = [s[0][1] if s else program.segments["t0_s"][0] + plan.offsets_s[k]
                  for k, s in enumerate(spans)]  # fmt: skip
        self._block_start = np.array(starts, dtype=float)
        self._block_start[0] = -np.inf
        last = self.run_segments(plan.runs - 1)
        self.duration_s = float(last["t1_s"][-1])
        self.end_shutter_open = plan.end_shutter_open(last["shutter_open"][-1])
        # the program's printed extent, for which runs' traces can lie near a point
        self._printed_bbox = program.summary()["bbox_mm"]

    @property
    def repetitions(self) -> int:
        """How many runs the loop starts."""
        return self.plan.runs

    def whole(self) -> Job:
        """The loop as :meth:`Job.repeat` holds it (every run's segments)."""
        if self._whole is not None:
            return self._whole
        return self.program.repeat(self.plan.duration_s, self.plan.gap_s, self.plan.pitch_mm)

    def run_segments(self, k: int) -> dict:
        """Run ``k`` with the wait and move before it, as :meth:`Job.repeat`'s segments
        (strokes numbered across runs, the last run cut at the loop's end)."""
        if k in self._runs:
            self._runs.move_to_end(k)
            return self._runs[k]
        parts = self.program.loop_block(self.plan, int(k))
        for piece in parts[:-1]:
            piece["stroke"], piece["s0_mm"] = np.array([-1.0]), np.array([np.nan])
        run = parts[-1]
        shift = k * self.program.n_strokes
        run["stroke"] = np.where(run["stroke"] >= 0, run["stroke"] + shift, -1.0)
        seg = _concat(parts)
        if seg["t1_s"][-1] > self.plan.duration_s:
            seg = _cut_at_times(seg, np.array([self.plan.duration_s]))
            seg = _take(seg, seg["t0_s"] < self.plan.duration_s)
        seg = _typed(seg)
        self._runs[k] = seg
        if len(self._runs) > _KEPT_RUNS:
            self._runs.popitem(last=False)
        return seg

    def state_at(self, t) -> JobState:
        """The stage at times ``t`` [s], as :meth:`ajtwin.job.Job.state_at` of the repeated
        job (any shape)."""
        if self._whole is not None:
            return self._whole.state_at(t)
        t = np.asarray(t, dtype=float)
        flat = t.reshape(-1)
        block = np.searchsorted(self._block_start, flat, side="right") - 1
        out = {}
        for k in np.unique(block):
            sel = block == k
            state = stage_state(
                self.run_segments(int(k)), flat[sel], self.duration_s, self.end_shutter_open
            )
            for name in JobState.__dataclass_fields__:
                value = getattr(state, name)
                if name == "segment":
                    value = np.where(value >= 0, value + self._block_offset[k], -1)
                out.setdefault(name, np.empty(flat.size, dtype=value.dtype))[sel] = value
        return JobState(**{name: value.reshape(t.shape) for name, value in out.items()})

    def per_second(self, duration_s: float | None = None, start_s: float = 0.0) -> pd.DataFrame:
        """The loop over 1-s bins ``[start_s + k, start_s + k + 1)``:
        :meth:`ajtwin.job.Job.per_second` of the repeated job, from the runs those seconds
        reach (strokes numbered as the repeated job numbers them)."""
        if self._whole is not None:
            return self._whole.per_second(duration_s, start_s)
        if duration_s is None:
            duration_s = math.ceil(self.duration_s - start_s - 1e-9)
        end = start_s + max(float(duration_s), 0.0)
        first, last = np.searchsorted(self._block_start, [start_s, end], side="right") - 1
        first = max(int(first), 0)
        runs = [self.run_segments(k) for k in range(first, max(int(last), first) + 1)]
        program = self.program
        window = Job(
            _concat(runs),
            origin=program.origin,
            notes=[],
            warnings=[],
            end_shutter_open=self.end_shutter_open,
            repetition_offsets_s=self.plan.offsets_s[first : max(int(last), first) + 1],
        )
        table = window.per_second(duration_s, start_s)
        # the window numbers its strokes from its first run's
        shift = first * program.n_strokes
        for name in ("stroke_first", "stroke_last"):
            table[name] = np.where(table[name] >= 0, table[name] + shift, -1)
        table["strokes"] = [tuple(k + shift for k in ks) for ks in table["strokes"]]
        return table

    def locate(self, x_mm, y_mm, radius_mm: float, before_s=None) -> TraceHits:
        """Which printed trace passes within ``radius_mm`` of each point (before
        ``before_s``): :meth:`ajtwin.job.Job.locate` of the repeated job."""
        if self._whole is not None:
            return self._whole.locate(x_mm, y_mm, radius_mm, before_s=before_s)
        if before_s is None:
            x, y = np.broadcast_arrays(np.asarray(x_mm, dtype=float), np.asarray(y_mm, dtype=float))
            before = np.full(x.shape, self.duration_s)
        else:
            x, y, before = np.broadcast_arrays(
                np.asarray(x_mm, dtype=float),
                np.asarray(y_mm, dtype=float),
                np.asarray(before_s, dtype=float),
            )
        shape = x.shape
        x, y, before = x.ravel(), y.ravel(), np.minimum(before.ravel(), self.duration_s)
        parts = [
            self._locate_pass(x[lo:hi], y[lo:hi], float(radius_mm), before[lo:hi])
            for lo, hi in _passes(x.size)
        ]
        return TraceHits(
            **{
                name: np.concatenate([getattr(p, name) for p in parts]).reshape(shape)
                for name in TraceHits.__dataclass_fields__
            }
        )

    def _locate_pass(self, x, y, radius, before) -> TraceHits:
        point, run = self._candidate_runs(x, y, radius, before)
        offsets, places = self.plan.offsets_s, self.plan.places_mm
        hits = self.program.trace_index().query(
            x[point] - places[run, 0],
            y[point] - places[run, 1],
            radius,
            before_s=before[point] - offsets[run] - _SAME_TIME_S,
        )
        pair = np.flatnonzero(hits.found)
        point, run = point[pair], run[pair]
        t = hits.print_time_s[pair] + offsets[run]
        px, py = hits.x_mm[pair] + places[run, 0], hits.y_mm[pair] + places[run, 1]
        pick = nearest_then_latest(point, hits.distance_mm[pair], t,
                                   lambda near: (px[near], py[near]))  # fmt: skip
        return self._hits_of(hits, pair[pick], point[pick], run[pick], x.size)

    def _hits_of(self, hits: TraceHits, chosen, where, run, n: int) -> TraceHits:
        """The program's hits ``chosen`` (of runs ``run``) as the loop's, for the points
        ``where`` of ``n``; the other points found nothing."""
        moved = {
            "print_time_s": self.plan.offsets_s[run],
            "x_mm": self.plan.places_mm[run, 0],
            "y_mm": self.plan.places_mm[run, 1],
            "stroke": run * self.program.n_strokes,
            "segment": self._first_segment[run],
        }
        values = {}
        for name in TraceHits.__dataclass_fields__:
            source = getattr(hits, name)
            fill = False if name == "found" else -1 if source.dtype.kind in "iu" else np.nan
            value = np.full(n, fill, dtype=source.dtype)
            picked = run if name == "repetition" else source[chosen]
            value[where] = picked + moved[name] if name in moved else picked
            values[name] = value
        return TraceHits(**values)

    def _candidate_runs(self, x, y, radius, before):
        """(point, run) pairs to ask: the runs before each point's time that can hold a
        trace within ``radius`` of it (the latest two over the same part)."""
        k = np.searchsorted(self.plan.offsets_s, before, side="right") - 1
        if self._printed_bbox is None:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        if self.plan.pitch_mm is None:
            point = np.repeat(np.arange(x.size), 2)
            run = np.stack([k - 1, k], axis=1).ravel()
            keep = run >= 0
            return point[keep], run[keep]
        x0, y0, x1, y1 = self._printed_bbox
        places = self.plan.places_mm
        points, runs = [], []
        step = max(1, _PLACE_CELLS // places.shape[0])
        for lo in range(0, x.size, step):
            sl = slice(lo, lo + step)
            dx = x[sl, None] - places[None, :, 0]
            dy = y[sl, None] - places[None, :, 1]
            near = (dx >= x0 - radius) & (dx <= x1 + radius) & (dy >= y0 - radius)
            near &= (dy <= y1 + radius) & (np.arange(places.shape[0])[None, :] <= k[sl, None])
            p, j = np.nonzero(near)
            points.append(p + lo)
            runs.append(j)
        return np.concatenate(points), np.concatenate(runs)


def _passes(n: int):
    """Slices [lo, hi) of at most ``_POINTS_PER_PASS`` points (one empty pass for none)."""
    if n == 0:
        yield 0, 0
    for lo in range(0, n, _POINTS_PER_PASS):
        yield lo, min(n, lo + _POINTS_PER_PASS)
