"""The part map for the dashboard: a map as JSON, and the map of a live print filling in.

:func:`part_payload` turns a :class:`~ajtwin.apps.quality.part_map.PartMap` (a finished or
stored print) into what a page draws: the job's strokes (the part's outline), the printed
portions with their line and probability, the sample points along them, the alarms.

:class:`LivePartMap` builds the same thing while the machine prints, from the live twin's
*filtered* states (the live twin has no smoother: a portion's line is what the twin knew
when the portion was final, and the stored print's map, smoothed, replaces it
afterwards). It follows the engine's *committed* steps only: on a job print a step is
committed once it is final — H seconds after it was printed, when no camera frame of it
can still arrive (:mod:`ajtwin.estimation.print_time`) — and the engine's provisional
"now" is not used, since a late frame can still move it. Each committed step k gives the
state and covariance at t_k (P_k with the floor of never-seen states, as the engine
reports σ); the portions finished by t_k are evaluated by the twin's own
:func:`ajtwin.estimation.part_line.line_at` over the last steps (the same line, band and
probability as the batch map) and handed out as a chunk. :func:`follow_engine` feeds it
from a :class:`~ajtwin.engine.fleet.LiveEngine`.

Coordinates in a payload are the drawing's: a looped job's runs side by side
(:func:`ajtwin.job.plot.repetition_layout`), as in ``part.png``.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np
import pandas as pd

from ajtwin.apps.quality.part_map import (
    MAP_DEFAULTS,
    MapSettings,
    PartMap,
    Tolerance,
    place_alarms,
    portion_table,
    sample_points,
)
from ajtwin.apps.quality.report import summary_facts
from ajtwin.estimation.part_line import line_at
from ajtwin.job.plot import repetition_layout

log = logging.getLogger("ajtwin.live")

#: sample points per portion sent to a page (the map's own points are denser)
PAGE_POINTS = 6
#: points of the part's outline sent to a page at most
OUTLINE_POINTS = 40_000
#: steps of filtered states kept to evaluate the portions that finish (a portion longer
#: than this many seconds is evaluated over the last ones only)
LIVE_HISTORY_STEPS = 120


def _round(values, digits: int = 4) -> list:
    """Finite values rounded, NaN → None (JSON)."""
    array = np.round(np.asarray(values, dtype=float), digits)
    return [None if not np.isfinite(v) else float(v) for v in array]


def outline_payload(job, layout: np.ndarray) -> dict:
    """The job's strokes as polylines (x, y with None between strokes), drawing coordinates."""
    table = job.timeline()
    is_open = table["shutter_open"].to_numpy()[:-1].astype(bool)
    stroke = table["stroke"].to_numpy()[:-1]
    rep = job.strokes["repetition"].to_numpy(dtype=np.int64)
    x, y = table["x_mm"].to_numpy(), table["y_mm"].to_numpy()
    xs, ys = [], []
    starts = np.flatnonzero(is_open & ~np.r_[False, is_open[:-1]])
    ends = np.flatnonzero(is_open & ~np.r_[is_open[1:], False])
    total = int(np.sum(ends - starts + 2))
    keep = max(1, int(np.ceil(total / OUTLINE_POINTS)))
    for a, b in zip(starts, ends):
        r = min(int(rep[stroke[a]]), len(layout) - 1) if stroke[a] >= 0 else 0
        idx = np.unique(np.r_[np.arange(a, b + 2, keep), b + 1])
        xs += _round(x[idx] + layout[r, 0]) + [None]
        ys += _round(y[idx] + layout[r, 1]) + [None]
    return {"x": xs, "y": ys}


def _portion_columns(table: pd.DataFrame, offset: int = 0) -> dict:
    """The per-portion columns a page uses (``index`` numbers the portions globally)."""
    return {
        "index": list(range(offset, offset + len(table))),
        "stroke": table["stroke"].astype(int).tolist(),
        "portion": table["portion"].astype(int).tolist(),
        "feature": table["feature"].astype(int).tolist(),
        "repetition": table["repetition"].astype(int).tolist(),
        "printed_from_s": _round(table["printed_from_s"], 3),
        "printed_to_s": _round(table["printed_to_s"], 3),
        "length_mm": _round(table["length_mm"]),
        "lw_mean_um": _round(table["lw_mean_um"], 3),
        "lw_lo_um": _round(table["lw_lo_um"], 3),
        "lw_hi_um": _round(table["lw_hi_um"], 3),
        "lo_mean_um": _round(table["lo_mean_um"], 3),
        "p_out": _round(table["p_out"], 4),
        "flagged": table["flagged"].astype(bool).tolist(),
    }


def _page_points(points: pd.DataFrame, table: pd.DataFrame, layout, offset: int = 0) -> dict:
    """Up to :data:`PAGE_POINTS` points per portion, in drawing coordinates."""
    index = points["portion"].to_numpy(dtype=np.int64)
    first = np.r_[True, index[1:] != index[:-1]]
    rank = np.arange(index.size) - np.maximum.accumulate(np.where(first, np.arange(index.size), 0))
    count = np.bincount(index, minlength=len(table))[index]
    step = np.maximum(1, np.ceil(count / PAGE_POINTS)).astype(np.int64)
    keep = (rank % step == 0) | (rank == count - 1)
    rep = table["repetition"].to_numpy(dtype=np.int64)[index[keep]]
    rep = np.clip(rep, 0, len(layout) - 1)
    return {
        "portion": (index[keep] + offset).tolist(),
        "x": _round(points["x_mm"].to_numpy()[keep] + layout[rep, 0]),
        "y": _round(points["y_mm"].to_numpy()[keep] + layout[rep, 1]),
    }


def alarm_payload(alarms: pd.DataFrame, layout: np.ndarray) -> list[dict]:
    """The alarms on the part in drawing coordinates (raised and onset positions)."""
    out = []
    for row in alarms.itertuples(index=False):
        r = min(int(row.detected_repetition), len(layout) - 1)
        o = min(int(row.onset_repetition), len(layout) - 1)
        out.append(
            {
                "alarm": int(row.alarm),
                "cause": row.cause,
                "description": row.description,
                "detected_s": float(row.detected_s),
                "onset_s": float(row.onset_s),
                "x": float(row.detected_x_mm + layout[r, 0]),
                "y": float(row.detected_y_mm + layout[r, 1]),
                "onset_x": float(row.onset_x_mm + layout[o, 0]),
                "onset_y": float(row.onset_y_mm + layout[o, 1]),
            }
        )
    return out


def _header(job, tolerance: Tolerance | None, flag_probability: float, layout) -> dict:
    return {
        "program": str(job.path).replace("\\", "/").rsplit("/", 1)[-1],
        "tolerance_um": None if tolerance is None else [float(v) for v in tolerance],
        "target_um": None if tolerance is None else tolerance.target_um,
        "flag_probability": float(flag_probability),
        "outline": outline_payload(job, layout),
        "repetitions": int(len(layout)),
    }


def part_payload(part: PartMap) -> dict:
    """A part map as the dashboard draws it (module docstring)."""
    layout = repetition_layout(part.job)
    return {
        **_header(part.job, part.tolerance, part.flag_probability, layout),
        "source": part.source,
        "live": False,
        "portions": _portion_columns(part.portions),
        "points": _page_points(part.points, part.portions, layout),
        "alarms": alarm_payload(part.alarms, layout),
        "summary": summary_facts(part),
        "notes": list(part.notes),
    }


class LivePartMap:
    """A live print's part map, filled in step by step from the filtered states.

    Parameters
    ----------
    job : ajtwin.job.Job
        The job the machine runs (looped already, or the program once: then it is looped
        further whenever the print outlasts it).
    line_model : LineModel, optional
        The live twin's line (:attr:`ajtwin.estimation.twin.Twin.line_model`, with the
        machine's calibration); :func:`follow_engine` takes it from the machine's stream.
    tolerance : Tolerance, optional
    map_settings : MapSettings, optional
        How the part is cut, sampled and judged, as for
        :func:`ajtwin.apps.quality.part_map.build_part_map`.
    """

    def __init__(
        self,
        job,
        line_model=None,
        tolerance: Tolerance | None = None,
        *,
        map_settings: MapSettings = MAP_DEFAULTS,
    ):
        self.base_job = job
        self.line_model = line_model
        self.tolerance = tolerance
        self.portion_mm, self.step_mm = float(map_settings.portion_mm), float(map_settings.step_mm)
        self.flag_probability = float(map_settings.flag_probability)
        self._steps = deque(maxlen=LIVE_HISTORY_STEPS)
        self.done_until_s = -np.inf  # portions finishing up to here were handed out
        self.n_sent = 0
        self._set_job(job)

    def _set_job(self, job) -> None:
        self.job = job
        self.layout = repetition_layout(job)
        self.portions = job.portions(self.portion_mm)
        self._t_to = self.portions["t_to_s"].to_numpy(dtype=float)

    def header(self) -> dict:
        """The part before anything is printed: outline, tolerance (a page draws it grey)."""
        return {**_header(self.job, self.tolerance, self.flag_probability, self.layout),
                "live": True}  # fmt: skip

    def _extend(self, time_s: float) -> bool:
        """Loop the program further when the print outlasts the job; whether it did."""
        if time_s <= self.job.duration_s or self.base_job.repetitions > 1:
            return False
        period = max(self.base_job.duration_s, 1.0)
        self._set_job(self.base_job.repeat(max(2.0 * self.job.duration_s, time_s + period)))
        return True

    def step(self, time_s: float, mean, covariance, inputs) -> dict | None:
        """One committed (final) step of the live twin: its state, covariance (as the twin
        reports it) and inputs; the chunk of portions finished by ``time_s`` (None: none),
        numbered on from the previous chunks.

        Returns
        -------
        dict or None
            ``portions`` (columns as :func:`part_payload`'s), ``points``, and ``outline``
            when the job was looped further (a page redraws the part).
        """
        self._steps.append(
            (float(time_s), np.asarray(mean, float), np.asarray(covariance, float),
             np.asarray(inputs, float))
        )  # fmt: skip
        grown = self._extend(float(time_s))
        ready = (self._t_to <= time_s + 1e-9) & (self._t_to > self.done_until_s)
        if not ready.any():
            return {"outline": self.header()} if grown else None
        table = self.portions[ready].reset_index(drop=True)
        self.done_until_s = float(self._t_to[ready].max())
        chunk = self._evaluate(table)
        if grown:
            chunk["outline"] = self.header()
        return chunk

    def _evaluate(self, portions: pd.DataFrame) -> dict:
        points = sample_points(self.job, portions, self.step_mm)
        t, means, covs, u = (np.array(v) for v in zip(*self._steps))
        line = line_at(
            self.line_model,
            t,
            means,
            covs,
            u,
            points["time_s"].to_numpy(),
            points["speed_mm_s"].to_numpy(),
        )
        points["lw_mean_um"], points["lo_mean_um"] = line.linewidth_um, line.overspray_um
        points["lw_sd_um"], points["lo_sd_um"] = line.linewidth_std_um, line.overspray_std_um
        table = portion_table(portions, points, self.tolerance, self.flag_probability)
        chunk = {
            "portions": _portion_columns(table, self.n_sent),
            "points": _page_points(points, table, self.layout, self.n_sent),
        }
        self.n_sent += len(table)
        return chunk

    def alarms(self, events) -> list[dict]:
        """Alarms (dicts with ``detected_s``, ``onset_s``, ``cause``, …) on the live part."""
        return alarm_payload(place_alarms(self.job, events), self.layout)
