"""The stage and the reader's tolerances, read from ``data/stage.toml`` and ``data/job.toml``."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from ajtwin.config import load_toml

__all__ = ["Stage", "ReaderSettings", "load_stage", "load_reader_settings"]


@dataclass(frozen=True)
class Stage:
    """A printer's X-Y stage and the speeds its GUI supplies.

    Attributes
    ----------
    key, name : str
        Table key in ``stage.toml`` and the machine's name.
    travel_x_mm, travel_y_mm : float
        X-Y travel of the platen stage [mm].
    process_speed_mm_s, rapid_speed_mm_s : float
        The GUI's process speed (``VEL(X)``, ``gDblProcessSpeed``) and rapid speed
        (``gDblRapidSpeed``) when neither the program nor the user sets them [mm/s].
    travel_source, process_speed_source, rapid_speed_source : str
        Where each value comes from.
    """

    key: str
    name: str
    travel_x_mm: float
    travel_y_mm: float
    travel_source: str
    process_speed_mm_s: float
    process_speed_source: str
    rapid_speed_mm_s: float
    rapid_speed_source: str


@dataclass(frozen=True)
class ReaderSettings:
    """Tolerances of the program checks, the timeline's arc sampling and the bounds on the
    work a program may ask (``job.toml``)."""

    join_tolerance_mm: float
    min_arc_radius_mm: float
    max_arc_turn_deg: float
    max_arc_step_deg: float
    chord_tolerance_mm: float
    max_program_time_s: float
    max_program_bytes: int
    max_held_segments: int
    max_loop_runs: int
    max_portions: int


def _read(name: str, path: str | Path | None) -> dict:
    # a user's file must be a regular file of bounded size; errors name it (InputFileError)
    return load_toml(path, f"data/{name}", what=name.removesuffix(".toml"))


def _positive(table: dict, key: str, where: str) -> float:
    value = table.get(key)
    if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{where}: {key} must be a positive number, got {value!r}")
    return float(value)


@cache
def _stage_cached(machine: str | None, path: str | None) -> Stage:
    data = _read("stage.toml", path)
    where = path or "stage.toml"
    key = machine or data.get("default_machine")
    machines = data.get("machines", {})
    if key not in machines:
        known = ", ".join(sorted(machines)) or "none"
        raise ValueError(f"{where}: no machine {key!r} (known: {known})")
    table = machines[key]
    return Stage(
        key=key,
        name=str(table.get("name", key)),
        travel_x_mm=_positive(table, "travel_x_mm", where),
        travel_y_mm=_positive(table, "travel_y_mm", where),
        travel_source=str(table.get("travel_source", "")),
        process_speed_mm_s=_positive(table, "process_speed_mm_s", where),
        process_speed_source=str(table.get("process_speed_source", "")),
        rapid_speed_mm_s=_positive(table, "rapid_speed_mm_s", where),
        rapid_speed_source=str(table.get("rapid_speed_source", "")),
    )


def load_stage(machine: str | None = None, path: str | Path | None = None) -> Stage:
    """The stage of ``machine`` (default: ``default_machine`` of ``stage.toml``).

    Examples
    --------
    >>> load_stage().travel_x_mm
    300.0
    """
    return _stage_cached(machine, None if path is None else str(path))


@cache
def load_reader_settings(path: str | None = None) -> ReaderSettings:
    """The reader's tolerances (``job.toml``).

    Examples
    --------
    >>> load_reader_settings().join_tolerance_mm
    0.001
    """
    data = _read("job.toml", path)
    where = path or "job.toml"
    checks, timeline = data.get("checks", {}), data.get("timeline", {})
    bounds = data.get("bounds", {})
    return ReaderSettings(
        join_tolerance_mm=_positive(checks, "join_tolerance_mm", where),
        min_arc_radius_mm=_positive(checks, "min_arc_radius_mm", where),
        max_arc_turn_deg=_positive(checks, "max_arc_turn_deg", where),
        max_arc_step_deg=_positive(timeline, "max_arc_step_deg", where),
        chord_tolerance_mm=_positive(timeline, "chord_tolerance_mm", where),
        max_program_time_s=_positive(checks, "max_program_time_s", where),
        max_program_bytes=int(_positive(bounds, "max_program_bytes", where)),
        max_held_segments=int(_positive(bounds, "max_held_segments", where)),
        max_loop_runs=int(_positive(bounds, "max_loop_runs", where)),
        max_portions=int(_positive(bounds, "max_portions", where)),
    )
