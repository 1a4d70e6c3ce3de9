"""Does a job print's record agree with the program it is given?

A format-2 job print carries its own evidence of the program it ran and how: the shutter
at each row (``shutter_open``), the platen speed (``platen_speed_mm_s``), the print time of
the trace each camera frame saw (``printed_at_s``) and, in its metadata, the speed the job
ran at. Before the twin computes a single state, :func:`check_record_agrees` holds that
evidence against the program as it will be used (read at the given speeds, looped as the
print looped it): a wrong ``--process-speed``, another program, a shifted clock or a speed
column in mm/min would otherwise give states that look plausible and are wrong, stored with
status "ok".

Each check weighs the rows that can tell (at most ``max_rows``, spread over the print) and
refuses when more than ``max_disagreeing_fraction`` of them disagree
(``job.toml [record_agreement]``, with reasons):

* **speed metadata** — the record's ``job.process_speed_mm_s`` against the speed the
  program is read at, over most of its printed length;
* **shutter** — a row logged open must find the program's shutter open within
  ``timing_tolerance_s`` of its time, a row logged closed the shutter closed;
* **platen speed** — a row printing (logged open, the program open and at one speed around
  it) must log the program's speed within ``speed_tolerance``;
* **print times** — the trace a camera row saw must have been printed with the shutter open
  and, for a camera that trails the nozzle (or looks at it), lie within ``view_radius_mm``
  of where the camera looked during the row's second;
* without a program, **speeds in range** — the logged printing speeds must lie in the twin's
  speed-law range (a column in mm/min reads 60 times too fast).

The refusal is one sentence naming the column, its value, the row and the program's line,
and what to do.

Examples
--------
>>> import numpy as np
>>> from ajtwin.job import read_program_text
>>> job = read_program_text("ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),20,0\\nOUT0.0=0",
...                         process_speed_mm_s=2.0)
>>> t = np.arange(10.0)
>>> evidence = JobEvidence("print.csv", t, t.astype(int) + 1, np.ones(10), np.full(10, 4.0),
...                        np.full(10, np.nan))
>>> check_record_agrees(evidence, job)
Traceback (most recent call last):
...
ajtwin.job.agreement.RecordMismatch: print.csv does not agree with <text>: column \
'platen_speed_mm_s' is 4 mm/s at t = 1 s (row 2) where the program moves at 2 mm/s (line 3, \
the GUI's process speed (given)); 8 of 8 printing rows disagree (median ratio 2): give \
--process-speed 4 if the column is right. Nothing was estimated or stored.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ajtwin.job.settings import _read

__all__ = [
    "AgreementSettings",
    "JobEvidence",
    "RecordMismatch",
    "check_record_agrees",
    "load_agreement_settings",
    "sample_rows",
]

# the ratio a speed logged in mm/min read as mm/s gives
_MM_PER_MIN = 60.0
# a shutter switching within this of a print time still printed it (a spot at the very end of
# a stroke is printed as the shutter closes: as the twin's filing looks just before)
_AT_CLOSE_S = 1e-6


# the shift of a clock is estimated from this many camera rows, each asked the trace printed
# last under the view's centre within this radius [mm] (a trace the camera sees there, as the
# virtual printer's camera finds it: data/print_time.toml field_radius_mm)
_SHIFT_ROWS = 500
_SHIFT_RADIUS_MM = 0.05
# the fields of JobEvidence that hold one value per row
_ROWS = ("time_s", "row", "shutter_open", "platen_speed_mm_s", "printed_at_s")


class RecordMismatch(ValueError):
    """A job print's record contradicts the program (or the speeds) it is given."""


@dataclass(frozen=True)
class AgreementSettings:
    """How closely a record must agree with its program (``job.toml [record_agreement]``)."""

    timing_tolerance_s: float
    speed_tolerance: float
    max_disagreeing_fraction: float
    min_rows: int
    max_rows: int
    view_radius_mm: float


@functools.cache
def load_agreement_settings() -> AgreementSettings:
    """The settings of ``job.toml [record_agreement]``.

    >>> load_agreement_settings().timing_tolerance_s
    1.0
    """
    table = _read("job.toml", None)["record_agreement"]
    return AgreementSettings(
        timing_tolerance_s=float(table["timing_tolerance_s"]),
        speed_tolerance=float(table["speed_tolerance"]),
        max_disagreeing_fraction=float(table["max_disagreeing_fraction"]),
        min_rows=int(table["min_rows"]),
        max_rows=int(table["max_rows"]),
        view_radius_mm=float(table["view_radius_mm"]),
    )


class JobEvidence(NamedTuple):
    """What a job print's record says of its program (rows as :func:`sample_rows` picks them).

    Attributes
    ----------
    where : str
        The record, for the messages.
    time_s, row : ndarray (n,)
        The rows' times [s] (the program's clock) and their numbers in the record (1-based).
    shutter_open, platen_speed_mm_s, printed_at_s : ndarray (n,)
        The job columns (NaN: not logged; ``printed_at_s`` NaN: no camera measurement).
    camera_mode : str or None
        ``trailing``, ``inspection`` or ``at_nozzle`` (None: the record does not say).
    camera_offset_mm : (float, float)
        Where a trailing camera looks, relative to the nozzle [mm].
    process_speed_mm_s : float or None
        The speed the record's metadata says the job ran at.
    """

    where: str
    time_s: np.ndarray
    row: np.ndarray
    shutter_open: np.ndarray
    platen_speed_mm_s: np.ndarray
    printed_at_s: np.ndarray
    camera_mode: str | None = None
    camera_offset_mm: tuple = (0.0, 0.0)
    process_speed_mm_s: float | None = None


def sample_rows(n: int, max_rows: int | None = None) -> np.ndarray:
    """Indices of at most ``max_rows`` rows of ``n``, spread evenly (all when fewer)."""
    limit = load_agreement_settings().max_rows if max_rows is None else int(max_rows)
    if n <= limit:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))


def check_record_agrees(
    evidence: JobEvidence,
    job=None,
    *,
    speed_range_mm_s: tuple[float, float] | None = None,
    settings: AgreementSettings | None = None,
) -> None:
    """Refuse a record that contradicts ``job`` (the module docstring lists the checks).

    Parameters
    ----------
    evidence : JobEvidence
    job : ajtwin.job.Job or ajtwin.job.LoopedJob, optional
        The program as it will be used (speeds, looping). Without it only the speeds'
        range is checked.
    speed_range_mm_s : (float, float), optional
        Without a program: the printing speeds the twin's speed law covers [mm/s].
    settings : AgreementSettings, optional
        Default ``job.toml``.

    Raises
    ------
    RecordMismatch
        One sentence: the column, its value, the row and the program's line, and what to do.
    """
    settings = settings or load_agreement_settings()
    if job is None:
        problems = [_speeds_in_range(evidence, speed_range_mm_s, settings)]
        against = None
    else:
        program = getattr(job, "program", job)  # a LoopedJob: the program it loops
        # rows after the job's end (an inspection pass, the machine idling) are not its evidence
        mask = evidence.time_s <= job.duration_s
        during = evidence._replace(**{name: getattr(evidence, name)[mask] for name in _ROWS})
        states = _states_around(job, during.time_s, settings.timing_tolerance_s)
        speed_rows, speed_problem = _platen_speed(during, job, states, settings)
        problems = [
            speed_problem,
            # the logged speeds are the direct evidence: the metadata's speed decides only
            # where they cannot (no row printing at one programmed speed)
            None
            if speed_rows >= settings.min_rows
            else _metadata_speed(evidence, program, settings),
            _shutter(during, job, states, settings),
            _print_times(evidence, job, settings),
        ]
        against = program.path
    problem = next((p for p in problems if p), None)
    if problem is not None:
        head = (
            f"{evidence.where} does not agree with {against}"
            if against
            else f"{evidence.where} cannot be estimated as it is"
        )
        raise RecordMismatch(f"{head}: {problem}. Nothing was estimated or stored.")


# --------------------------------------------------------------------------- #


def _too_many(bad: np.ndarray, settings: AgreementSettings) -> bool:
    return bad.size >= settings.min_rows and bad.mean() > settings.max_disagreeing_fraction


def _states_around(job, t: np.ndarray, tolerance_s: float):
    """The job's states at 21 times across [t − tolerance, t + tolerance] (row 10: at t)."""
    offsets = np.linspace(-tolerance_s, tolerance_s, 21)
    return job.state_at(t[None, :] + offsets[:, None])


def _source_text(job, index: int) -> str:
    sources = job.speed_sources
    return sources[index].origin if 0 <= index < len(sources) else "the loop's move"


def _metadata_speed(ev: JobEvidence, program, settings) -> str | None:
    recorded = ev.process_speed_mm_s
    if recorded is None or not recorded > 0:
        return None
    speeds = program.summary()["print_speeds"]
    if not speeds:
        return None
    main = speeds[0]
    if abs(main["speed_mm_s"] - recorded) <= settings.speed_tolerance * recorded:
        return None
    text = (
        f"the record's metadata says the job ran at {recorded:g} mm/s (job.process_speed_mm_s) "
        f"but the program is read at {main['speed_mm_s']:g} mm/s over "
        f"{main['length_mm']:.1f} mm of its strokes ({main['source']})"
    )
    if main["kind"] == "given":
        return text + f": leave out --process-speed, or give the record's {recorded:g} mm/s"
    return text + ": the record was not printed with this program as it reads"


def _platen_speed(ev: JobEvidence, job, states, settings) -> tuple[int, str | None]:
    """(rows compared, the disagreement or None)."""
    logged = ev.platen_speed_mm_s
    speed = states.speed_mm_s
    at = speed[10]
    steady = (np.ptp(speed, axis=0) <= 1e-9 * at) & (at > 0)
    rows = (ev.shutter_open >= 0.5) & np.isfinite(logged) & states.shutter_open.all(0) & steady
    index = np.flatnonzero(rows)
    if index.size == 0:
        return 0, None
    ratio = logged[index] / at[index]
    bad = np.abs(ratio - 1.0) > settings.speed_tolerance
    if not _too_many(bad, settings):
        return index.size, None
    return index.size, _speed_sentence(ev, job, states, index, bad, settings)


def _speed_sentence(ev, job, states, index, bad, settings) -> str:
    logged, at = ev.platen_speed_mm_s, states.speed_mm_s[10]
    ratio = logged[index] / at[index]
    first = index[np.argmax(bad)]
    median_ratio = float(np.median(ratio))
    text = (
        f"column 'platen_speed_mm_s' is {logged[first]:g} mm/s at t = {ev.time_s[first]:g} s "
        f"(row {ev.row[first]}) where the program moves at {at[first]:g} mm/s (line "
        f"{states.line[10][first]}, {_source_text(job, int(states.speed_source[10][first]))}); "
        f"{int(bad.sum())} of {bad.size} printing rows disagree (median ratio {median_ratio:.3g})"
    )
    if abs(median_ratio / _MM_PER_MIN - 1.0) <= settings.speed_tolerance:
        return text + (
            ": the column looks like mm/min; name it 'platen_speed [mm/min]' to have it converted"
        )
    logged_speed = float(np.median(logged[index]))
    recorded = ev.process_speed_mm_s
    if recorded and abs(recorded - logged_speed) <= settings.speed_tolerance * recorded:
        return text + (
            f"; the record's metadata says {recorded:g} mm/s too: leave out --process-speed, "
            "or give the record's speed"
        )
    if recorded:
        return text + (
            f"; the record's metadata says {recorded:g} mm/s, its column {logged_speed:g}: "
            f"give --process-speed {logged_speed:g} to read the program at the column's speed"
        )
    return text + f": give --process-speed {logged_speed:g} if the column is right"


def _shutter(ev: JobEvidence, job, states, settings) -> str | None:
    known = np.isfinite(ev.shutter_open)
    logged_open = ev.shutter_open >= 0.5
    program_open = states.shutter_open
    agrees = np.where(logged_open, program_open.any(0), (~program_open).any(0))
    w = settings.timing_tolerance_s
    for is_open in (False, True):
        index = np.flatnonzero(known & (logged_open == is_open))
        bad = ~agrees[index]
        if not _too_many(bad, settings):
            continue
        first = index[np.argmax(bad)]
        logged, program = ("1 (open)", "has it closed") if is_open else ("0 (closed)", "prints")
        stroke = int(states.stroke[10][first])
        where = f"line {states.line[10][first]}" + (f", stroke {stroke}" if stroke >= 0 else "")
        return (
            f"column 'shutter_open' is {logged} at t = {ev.time_s[first]:g} s (row "
            f"{ev.row[first]}) where the program {program} throughout ±{w:g} s ({where}); "
            f"{int(bad.sum())} of {bad.size} rows logged {logged.split()[1][1:-1]} disagree: "
            "the record was printed with another program, at other speeds or on another clock"
        )
    return None


def _print_times(ev: JobEvidence, job, settings) -> str | None:
    index = np.flatnonzero(np.isfinite(ev.printed_at_s))
    if index.size < settings.min_rows:
        return None
    index = index[sample_rows(index.size, settings.max_rows)]
    t, tau = ev.time_s[index], ev.printed_at_s[index]
    at = job.state_at(np.stack([tau, tau - _AT_CLOSE_S]))
    closed = ~at.shutter_open.any(0)
    far = np.zeros(index.size, dtype=bool)
    distance = np.zeros(index.size)
    if ev.camera_mode in ("trailing", "at_nozzle"):
        dx, dy = (0.0, 0.0) if ev.camera_mode == "at_nozzle" else ev.camera_offset_mm
        x, y = at.x_mm[0], at.y_mm[0]
        distance = np.full(index.size, np.inf)
        for back in np.linspace(0.0, 1.0, 5):  # the row holds the frames of its second
            view = job.state_at(t - back)
            distance = np.minimum(distance, np.hypot(x - view.x_mm - dx, y - view.y_mm - dy))
        far = distance > settings.view_radius_mm
    bad = closed | far
    if not _too_many(bad, settings):
        return None
    k = int(np.argmax(bad))
    first = index[k]
    why = (
        "with the shutter closed there"
        if closed[k]
        else f"{distance[k]:.2f} mm from where the camera looked"
    )
    text = (
        f"column 'printed_at_s' is {tau[k]:g} s at t = {t[k]:g} s (row {ev.row[first]}): the "
        f"program printed at that time {why} (line {at.line[0][k]}); {int(bad.sum())} of "
        f"{bad.size} camera rows do not fit the program ({int(far.sum())} out of the camera's "
        f"view, {int(closed.sum())} printed with the shutter closed)"
    )
    shift = _clock_shift(ev, job, t, tau, settings)
    if shift is not None:
        text += f"; the print times look shifted by {shift:+.1f} s"
    return text + ": the print times belong to another clock, program or camera"


def _clock_shift(ev: JobEvidence, job, t, tau, settings) -> float | None:
    """The shift of the record's print times from those the program gives, when one shift
    explains most rows (None otherwise, or for a camera that does not trail the nozzle)."""
    if ev.camera_mode != "trailing":
        return None
    pick = sample_rows(t.size, _SHIFT_ROWS)  # a hint: a few hundred rows tell a shift
    t, tau = t[pick], tau[pick]
    dx, dy = ev.camera_offset_mm
    view = job.state_at(t)
    hits = job.locate(view.x_mm + dx, view.y_mm + dy, _SHIFT_RADIUS_MM, before_s=t)
    if hits.found.sum() < settings.min_rows:
        return None
    delta = tau[hits.found] - hits.print_time_s[hits.found]
    middle = float(np.median(delta))
    near = np.abs(delta - middle) <= settings.timing_tolerance_s
    return middle if near.mean() > 0.5 and abs(middle) > settings.timing_tolerance_s else None


def _speeds_in_range(ev: JobEvidence, speed_range, settings) -> str | None:
    if speed_range is None:
        return None
    lo, hi = speed_range
    printing = (ev.shutter_open >= 0.5) & np.isfinite(ev.platen_speed_mm_s)
    printing &= ev.platen_speed_mm_s > 0
    if printing.sum() < settings.min_rows:
        return None
    median = float(np.median(ev.platen_speed_mm_s[printing]))
    if lo <= median <= hi:
        return None
    text = (
        f"column 'platen_speed_mm_s' holds {median:g} mm/s while printing (median of "
        f"{int(printing.sum())} rows), outside the {lo:g}-{hi:g} mm/s the twin's speed law "
        "covers (data/line_speed.toml): the line model would be held at its edge"
    )
    if lo <= median / _MM_PER_MIN <= hi:
        return text + (
            f"; read as mm/min it would be {median / _MM_PER_MIN:g} mm/s: name the column "
            "'platen_speed [mm/min]' to have it converted"
        )
    return text + "; if the speeds are right, this print lies outside what the twin models"
