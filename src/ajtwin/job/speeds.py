"""Process speeds per layer, stroke or feature: a program run with its speed changed between
its parts (docs/reference/job.md, "Speeds per layer").

An operator changes the GUI's process speed between the layers of a part, or a program is
edited to print each feature at its own speed. A :class:`SpeedSchedule` says which speed
applies where; :func:`apply_speed_schedule` re-times the job: every printed move of a
scheduled stroke runs at the scheduled speed (its duration = length / speed), rapids and
dwells keep theirs, and everything after shifts in time.

Units of a schedule (``per``):

``layer``
    Layers found in the program's geometry (:func:`stroke_layers`): a new layer starts at a
    stroke that prints mostly over the traces of the layer so far (the part drawn again).
``stroke``
    The program's strokes (spans with the shutter open), numbered from 0.
``feature``
    The program's feature numbers (``! feature N`` comments); strokes without one keep their
    speed.

A schedule is either a list of speeds for successive units, repeating when the units
outnumber it (``2,4,3``: layers 0, 3, 6 … at 2 mm/s, 1, 4, 7 … at 4, 2, 5, 8 … at 3), or
ranges of units with a speed each (units outside every range keep the program's speed).

Examples
--------
>>> from ajtwin.job import read_program_text
>>> prg = '''
... ptp/e (X,Y),0,0
... OUT0.0=1
... ptp/e (X,Y),4,0
... OUT0.0=0
... ptp/e (X,Y),0,1
... OUT0.0=1
... ptp/e (X,Y),4,1
... OUT0.0=0'''
>>> job = read_program_text(prg, process_speed_mm_s=2.0)
>>> fast = apply_speed_schedule(job, SpeedSchedule.parse("stroke:2,4"))
>>> fast.strokes["duration_s"].round(6).tolist()       # 4 mm at 2 mm/s, then at 4 mm/s
[2.0, 1.0]
>>> round(fast.duration_s - job.duration_s, 6)         # the second stroke took 1 s less
-1.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ajtwin.config import load_toml
from ajtwin.job.job import SEGMENT_FIELDS, Job
from ajtwin.job.program import KIND_DWELL, SpeedSource

__all__ = [
    "SCHEDULE_UNITS",
    "SpeedSchedule",
    "apply_speed_schedule",
    "load_layer_settings",
    "stroke_layers",
]

#: What a schedule's entries count.
SCHEDULE_UNITS = ("layer", "stroke", "feature")


def load_layer_settings(path: str | Path | None = None) -> dict:
    """``[layers]`` of ``data/job.toml`` (or a user's file): how layers are found."""
    table = load_toml(path, "data/job.toml", what="job reader settings").get("layers", {})
    out = {}
    for key in ("overlap_radius_mm", "overlap_fraction", "probe_step_mm"):
        value = table.get(key)
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            raise ValueError(f"job.toml [layers]: {key} must be a positive number, got {value!r}")
        out[key] = float(value)
    if out["overlap_fraction"] > 1:
        raise ValueError(f"job.toml [layers]: overlap_fraction {out['overlap_fraction']} > 1")
    return out


def _positive_speed(value, where: str) -> float:
    try:
        speed = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {value!r} is not a speed in mm/s") from None
    if isinstance(value, bool) or not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"{where}: a speed must be a positive number of mm/s, got {value!r}")
    return speed


@dataclass(frozen=True)
class SpeedSchedule:
    """Which process speed applies to which part of a program (module docstring).

    Attributes
    ----------
    per : {"layer", "stroke", "feature"}
        What the entries count.
    speeds_mm_s : tuple of float
        Speeds of successive units, repeating (empty when ``ranges`` are given).
    ranges : tuple of (first, last, speed_mm_s)
        Units first … last (inclusive) at a speed; the others keep the program's.
    """

    per: str = "layer"
    speeds_mm_s: tuple = ()
    ranges: tuple = ()

    def __post_init__(self):
        if self.per not in SCHEDULE_UNITS:
            raise ValueError(
                f"speed schedule per {self.per!r}: choose one of {', '.join(SCHEDULE_UNITS)}"
            )
        speeds = tuple(_positive_speed(v, "speed schedule") for v in self.speeds_mm_s)
        ranges = []
        for entry in self.ranges:
            try:
                first, last, speed = entry
            except (TypeError, ValueError):
                raise ValueError(
                    f"speed schedule range {entry!r}: give (first, last, speed_mm_s)"
                ) from None
            if isinstance(first, bool) or isinstance(last, bool):
                raise ValueError(f"speed schedule range {entry!r}: first and last are numbers")
            if int(first) != first or int(last) != last or not 0 <= int(first) <= int(last):
                raise ValueError(
                    f"speed schedule range {entry!r}: first and last are whole {self.per} "
                    "numbers, 0 <= first <= last"
                )
            ranges.append((int(first), int(last), _positive_speed(speed, "speed schedule range")))
        if bool(speeds) == bool(ranges):
            raise ValueError("a speed schedule has either a list of speeds or ranges, not both")
        object.__setattr__(self, "speeds_mm_s", speeds)
        object.__setattr__(self, "ranges", tuple(ranges))

    # -- reading -------------------------------------------------------------------------

    @classmethod
    def parse(cls, text: str) -> SpeedSchedule:
        """``[UNIT:]V1,V2,…`` (UNIT layer, stroke or feature; default layer) or a TOML file.

        Examples
        --------
        >>> SpeedSchedule.parse("2,4,3").describe()
        'per layer: 2, 4, 3 mm/s, repeating'
        >>> SpeedSchedule.parse("stroke:2,4").per
        'stroke'
        """
        raw = str(text).strip()
        if raw.lower().endswith(".toml"):
            return cls.from_file(raw)
        per, _, values = raw.rpartition(":")
        per = per.strip().lower() or "layer"
        parts = [p.strip() for p in values.split(",")]
        if not parts or any(not p for p in parts):
            raise ValueError(f"{text!r}: give speeds in mm/s as V1,V2,… (e.g. 2,4,3)")
        return cls(per, tuple(_positive_speed(p, repr(text)) for p in parts))

    @classmethod
    def from_file(cls, path: str | Path) -> SpeedSchedule:
        """A schedule file::

        per = "layer"             # layer | stroke | feature
        speeds_mm_s = [2, 4, 3]   # successive units, repeating
        # or, instead of speeds_mm_s, ranges of units:
        [[range]]
        first = 0
        last = 27
        speed_mm_s = 2.0
        """
        data = load_toml(path, "", what="speed schedule")
        try:
            ranges = tuple((r["first"], r["last"], r["speed_mm_s"]) for r in data.get("range", []))
            return cls(str(data.get("per", "layer")), tuple(data.get("speeds_mm_s", ())), ranges)
        except (KeyError, TypeError) as exc:
            raise ValueError(
                f"{path}: a [[range]] needs first, last and speed_mm_s ({exc})"
            ) from None
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None

    @classmethod
    def from_meta(cls, meta: dict | None) -> SpeedSchedule | None:
        """The schedule kept in a record's ``job`` metadata (:meth:`to_meta`); None: none."""
        if not meta:
            return None
        return cls(
            str(meta.get("per", "layer")),
            tuple(meta.get("speeds_mm_s", ())),
            tuple(tuple(r) for r in meta.get("ranges", ())),
        )

    def to_meta(self) -> dict:
        """JSON-ready form (a record's ``job.process_speed_schedule``)."""
        return {
            "per": self.per,
            "speeds_mm_s": list(self.speeds_mm_s),
            "ranges": [list(r) for r in self.ranges],
        }

    def describe(self) -> str:
        """In words, e.g. ``per layer: 2, 4, 3 mm/s, repeating``."""
        if self.speeds_mm_s:
            values = ", ".join(f"{v:g}" for v in self.speeds_mm_s)
            return f"per {self.per}: {values} mm/s, repeating"
        spans = "; ".join(f"{a}-{b} at {v:g} mm/s" for a, b, v in self.ranges)
        return f"per {self.per}: {spans}"

    # -- applying ------------------------------------------------------------------------

    def unit_speeds(self, units: np.ndarray) -> np.ndarray:
        """The speed of each unit number in ``units`` (NaN: not scheduled; -1 never is)."""
        units = np.asarray(units, dtype=np.int64)
        out = np.full(units.shape, np.nan)
        valid = units >= 0
        if self.speeds_mm_s:
            speeds = np.asarray(self.speeds_mm_s)
            out[valid] = speeds[units[valid] % speeds.size]
            return out
        for first, last, speed in self.ranges:
            out[valid & (units >= first) & (units <= last)] = speed
        return out


def stroke_layers(job: Job, settings: dict | None = None) -> np.ndarray:
    """The layer of each stroke (n_strokes,): 0, 0, …, 1, … (module docstring).

    Each stroke is probed every ``probe_step_mm`` along its length (the middle of each
    portion); a probe *overlaps* where a trace printed before the stroke started, by a stroke
    of the current layer, lies within ``overlap_radius_mm``. A stroke whose overlapping
    fraction reaches ``overlap_fraction`` starts a new layer.
    """
    settings = settings or load_layer_settings()
    n = job.n_strokes
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    portions = job.portions(max_length_mm=settings["probe_step_mm"])
    stroke = portions["stroke"].to_numpy()
    x = 0.5 * (portions["x_from_mm"].to_numpy() + portions["x_to_mm"].to_numpy())
    y = 0.5 * (portions["y_from_mm"].to_numpy() + portions["y_to_mm"].to_numpy())
    start = job.strokes["t_start_s"].to_numpy()
    hits = job.locate(x, y, settings["overlap_radius_mm"], before_s=start[stroke])
    under = np.where(hits.found, hits.stroke, -1)
    layers = np.zeros(n, dtype=np.int64)
    first_of_layer, layer = 0, 0
    bounds = np.searchsorted(stroke, np.arange(n + 1))
    for s in range(1, n):
        probes = under[bounds[s] : bounds[s + 1]]
        if probes.size and np.mean(probes >= first_of_layer) >= settings["overlap_fraction"]:
            layer += 1
            first_of_layer = s
        layers[s] = layer
    return layers


def _stroke_units(job: Job, per: str) -> np.ndarray:
    if per == "layer":
        return stroke_layers(job)
    if per == "stroke":
        return np.arange(job.n_strokes, dtype=np.int64)
    features = job.strokes["feature"].to_numpy(dtype=np.int64)
    if not (features >= 0).any():
        raise ValueError(
            f"{job.path}: the program names no features; give the speeds per layer or stroke"
        )
    return features


def apply_speed_schedule(job: Job, schedule: SpeedSchedule) -> Job:
    """The job with its printed moves at the schedule's speeds, re-timed (module docstring).

    Parameters
    ----------
    job : Job
        As read from the program (not looped: loop the result, each run then follows the
        schedule from its start).
    schedule : SpeedSchedule

    Returns
    -------
    Job
        The same geometry; every moving segment with the shutter open in a scheduled unit
        at its unit's speed (speed source kind ``"schedule"``); times shifted to follow;
        ``speed_schedule`` set and a note saying what was applied.
    """
    if job.repetitions > 1:
        raise ValueError("apply the speed schedule to the job read from the program, then loop it")
    units = _stroke_units(job, schedule.per)
    stroke_speed = schedule.unit_speeds(units)
    s = {name: np.array(job.segments[name], dtype=float) for name in SEGMENT_FIELDS}
    s["shutter_open"] = np.array(job.segments["shutter_open"], dtype=bool)
    stroke = job.segments["stroke"]
    printing = s["shutter_open"] & (job.segments["kind"] != KIND_DWELL) & (stroke >= 0)
    new_speed = np.where(printing, stroke_speed[np.maximum(stroke, 0)], np.nan)
    changed = np.isfinite(new_speed)
    sources = list(job.speed_sources)
    for value in np.unique(new_speed[changed]):
        sources.append(
            SpeedSource(float(value), "schedule", f"process speed schedule, {schedule.describe()}")
        )
        s["speed_source"][changed & (new_speed == value)] = len(sources) - 1
    duration = np.where(
        changed, s["length_mm"] / np.where(changed, new_speed, 1.0), s["t1_s"] - s["t0_s"]
    )
    s["speed_mm_s"] = np.where(changed, new_speed, s["speed_mm_s"])
    s["t0_s"] = s["t0_s"][0] + np.cumsum(duration) - duration
    s["t1_s"] = s["t0_s"] + duration
    n_units = int(units.max()) + 1 if units.size else 0
    note = (
        f"process speed {schedule.describe()} ({n_units} {schedule.per}s; "
        f"{int(changed.sum())} printed moves re-timed)"
    )
    return Job(
        s,
        origin=replace(job.origin, speed_sources=sources),
        notes=[*job.notes, note],
        warnings=job.warnings,
        end_shutter_open=job.end_shutter_open,
        speed_schedule=schedule,
    )
