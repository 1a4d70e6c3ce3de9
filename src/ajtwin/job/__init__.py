"""ajtwin.job — the machine's program (ACSPL+ ``.prg``) as the job's one representation.

:func:`read_program` runs an Optomec Aerosol Jet program once and returns a :class:`Job`:
the stage's motion as exact segments in time (lines, arcs, dwells) with the shutter, the
strokes (spans with the shutter open), the speeds and where they came from. The job
answers what the rest of the twin asks: the timeline table, the stage at any time, the
per-second figures of a 1 Hz record, the trace under a point of the part, stroke portions,
and the job looped to a long run. Pure Python and NumPy; see docs/reference/job.md.

Examples
--------
>>> from ajtwin.job import read_program_text
>>> job = read_program_text('''
... ptp/ev (X,Y),0,0,gDblRapidSpeed
... OUT0.0=1
... MSEG (X,Y),0,0
... line (X,Y),2,0
... arc2 (X,Y),2,1,3.14159265358979
... ENDS (X,Y)
... till ^X_AST.#MOVE
... OUT0.0=0
... ''', process_speed_mm_s=2.0)
>>> s = job.summary()
>>> s["strokes"], round(s["printed_length_mm"], 4), round(s["print_time_s"], 4)
(1, 5.1416, 2.5708)
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ajtwin.config import InputFileError, read_bounded_bytes
from ajtwin.job.errors import ProgramError, ProgramWarning
from ajtwin.job.geometry import GEOMETRY_FIELDS, segment_bbox
from ajtwin.job.job import (
    SEGMENT_FIELDS,
    TIMELINE_COLUMNS,
    Job,
    JobState,
    StrokePoints,
    read_timeline,
)
from ajtwin.job.locate import TraceHits, TraceIndex
from ajtwin.job.loop import LoopedJob, loop_job
from ajtwin.job.program import (
    KIND_ARC,
    KIND_DWELL,
    KIND_LINE,
    KIND_NAMES,
    SpeedSource,
    parse_program,
)
from ajtwin.job.settings import ReaderSettings, Stage, load_reader_settings, load_stage
from ajtwin.job.speeds import SpeedSchedule, apply_speed_schedule, stroke_layers

__all__ = [
    "read_program",
    "read_program_bytes",
    "decode_program",
    "read_printing",
    "require_printing",
    "read_program_text",
    "Job",
    "JobState",
    "LoopedJob",
    "loop_job",
    "StrokePoints",
    "TraceIndex",
    "TraceHits",
    "SpeedSource",
    "SpeedSchedule",
    "apply_speed_schedule",
    "stroke_layers",
    "Stage",
    "ReaderSettings",
    "ProgramError",
    "ProgramWarning",
    "load_stage",
    "load_reader_settings",
    "read_timeline",
    "SEGMENT_FIELDS",
    "TIMELINE_COLUMNS",
    "KIND_LINE",
    "KIND_ARC",
    "KIND_DWELL",
    "KIND_NAMES",
]


def read_program(
    path: str | Path,
    process_speed_mm_s: float | None = None,
    rapid_speed_mm_s: float | None = None,
    *,
    skip_unknown: bool = False,
    machine: str | None = None,
    stage_origin_mm: tuple[float, float] | None = None,
    axes: tuple = ("X", "Y"),
    shutter_output: tuple[int, int] = (0, 0),
    start_mm: tuple[float, float] | None = None,
    speed_schedule: SpeedSchedule | None = None,
) -> Job:
    """Read an Optomec AJ ACSPL+ program into a :class:`Job`.

    Parameters
    ----------
    path : str or Path
        The ``.prg`` file (UTF-8 or Latin-1 text).
    process_speed_mm_s : float, optional
        The machine GUI's process speed [mm/s]: what ``VEL(X)``/``gDblProcessSpeed`` hold
        unless the program sets them. Default: ``stage.toml`` (the source paper's 2 mm/s).
    rapid_speed_mm_s : float, optional
        The GUI's rapid speed (``gDblRapidSpeed``) unless the program sets it. Default:
        ``stage.toml`` (10 mm/s, an assumption).
    skip_unknown : bool
        Skip unknown commands that do not move the stage (one warning per kind) instead of
        refusing the program.
    machine : str, optional
        Machine table of ``stage.toml`` (default ``aj300``): stage travel and GUI speeds.
    stage_origin_mm : (float, float), optional
        Where the program's (0, 0) sits on the stage, to check the motion against the
        stage's absolute limits; without it only the extent of the motion is checked.
    axes : (str or int, str or int)
        The controller axes that move the part in X and Y (``("X", "Y")`` = 0 and 1).
    shutter_output : (int, int)
        Digital output (port, bit) wired to the shutter: ``OUT0.0`` by default.
    start_mm : (float, float), optional
        Where the stage stands when the program starts; default: at its first commanded
        position (the first move has length 0).
    speed_schedule : SpeedSchedule, optional
        Process speeds per layer, stroke or feature (:mod:`ajtwin.job.speeds`): the printed
        moves of each scheduled part at its speed, the job re-timed.

    Returns
    -------
    Job

    Warns
    -----
    ProgramWarning
        Once per kind of statement skipped (``skip_unknown``), for an If block holding
        motion, and for a program that ends with the shutter open (also in ``Job.warnings``).

    Raises
    ------
    ProgramError
        Naming the file, line and text: unknown command, unreadable or non-finite number,
        an arc1 end off its circle, a zero-radius arc, an arc2 of more than a turn, a path
        that does not start where the previous motion ended, an arc retracing the segment it
        joins, motion beyond the stage travel, unclosed blocks.
    """
    path = Path(path)
    return read_program_text(
        decode_program(read_program_bytes(path), str(path)),
        process_speed_mm_s,
        rapid_speed_mm_s,
        path=str(path),
        skip_unknown=skip_unknown,
        machine=machine,
        stage_origin_mm=stage_origin_mm,
        axes=axes,
        shutter_output=shutter_output,
        start_mm=start_mm,
        speed_schedule=speed_schedule,
    )


def read_program_bytes(path: str | Path) -> bytes:
    """The bytes of a program file, refused (ProgramError naming it) when it is missing, not
    a regular file (a FIFO would block, ``/dev/zero`` never ends) or larger than
    ``max_program_bytes`` of ``job.toml``; nothing is read from a file refused."""
    limit = load_reader_settings().max_program_bytes
    try:
        return read_bounded_bytes(path, "program", limit)
    except (InputFileError, FileNotFoundError) as exc:
        raise ProgramError(str(path), None, "", str(exc).removeprefix(f"{path}: ")) from None


_UTF16_MARKS = {b"\xff\xfe": "utf-16-le", b"\xfe\xff": "utf-16-be"}


def decode_program(raw: bytes, path: str = "<program>") -> str:
    """A program file's bytes as text: UTF-8 (with or without a byte-order mark), UTF-16
    with its byte-order mark (a Windows editor's "Unicode"), else Latin-1 (controllers'
    editors write either).

    Raises
    ------
    ProgramError
        Bytes that are no text: a NUL byte outside UTF-16 (a binary file, or UTF-16 saved
        without its byte-order mark).
    """
    encoding = _UTF16_MARKS.get(raw[:2])
    if encoding is not None:
        try:
            return raw[2:].decode(encoding)
        except UnicodeDecodeError as exc:
            raise ProgramError(
                path,
                None,
                "",
                f"starts with a UTF-16 byte-order mark but byte {exc.start + 2} is not UTF-16 text",
            ) from None
    nul = raw.find(b"\0")
    if nul >= 0:
        line = raw[:nul].count(b"\n") + 1
        raise ProgramError(
            path,
            None,
            "",
            f"byte {nul} (line {line}) is a NUL: this is not a text program (a binary file, "
            "or UTF-16 saved without its byte-order mark: save it as UTF-8)",
        )
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def read_printing(read):
    """``read()`` — a call of a program reader — refused when the job prints nothing
    (:func:`require_printing`); its warnings are passed on only for a job that prints (the
    refusal says what the "prints nothing" warning would)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        job = read()
    require_printing(job)
    for warning in caught:
        warnings.warn(warning.message, warning.category, stacklevel=3)
    return job


def require_printing(job) -> None:
    """Refuse a job that prints nothing (no stroke: its shutter never opens), with the
    reader's reason (the shutter output, the outputs it switches instead).

    Raises
    ------
    ProgramError
    """
    program = getattr(job, "program", job)  # a LoopedJob: its program
    if program.n_strokes == 0:
        reason = next(
            (w for w in program.warnings if w.startswith("prints nothing")),
            "prints nothing: the program never opens the shutter",
        )
        raise ProgramError(
            program.path, None, "", f"{reason}; there is no part to print, map or follow"
        )


def read_program_text(
    text: str,
    process_speed_mm_s: float | None = None,
    rapid_speed_mm_s: float | None = None,
    *,
    path: str = "<text>",
    skip_unknown: bool = False,
    machine: str | None = None,
    stage_origin_mm: tuple[float, float] | None = None,
    axes: tuple = ("X", "Y"),
    shutter_output: tuple[int, int] = (0, 0),
    start_mm: tuple[float, float] | None = None,
    speed_schedule: SpeedSchedule | None = None,
) -> Job:
    """:func:`read_program` on a program given as text (``path`` names it in errors)."""
    stage = load_stage(machine)
    settings = load_reader_settings()
    parsed = parse_program(
        text,
        path,
        settings=settings,
        stage=stage,
        process_speed_mm_s=process_speed_mm_s,
        rapid_speed_mm_s=rapid_speed_mm_s,
        skip_unknown=skip_unknown,
        axes=axes,
        shutter_output=shutter_output,
        start_xy=start_mm,
    )
    job = Job.from_program(parsed, stage=stage, settings=settings)
    _check_travel(job, stage, stage_origin_mm, text)
    _note_unused_speeds(job, process_speed_mm_s, rapid_speed_mm_s)
    for text_of_warning in job.warnings:
        warnings.warn(f"{path}: {text_of_warning}", ProgramWarning, stacklevel=2)
    if speed_schedule is not None:
        job = apply_speed_schedule(job, speed_schedule)
    return job


def _line_text(text: str, line: int) -> str:
    lines = text.splitlines()
    return lines[line - 1].strip() if 0 < line <= len(lines) else ""


def _check_travel(job: Job, stage: Stage, origin, text: str) -> None:
    """Refuse motion that does not fit in the stage's travel (naming its line)."""

    s = job.segments
    moving = np.flatnonzero(s["kind"] != KIND_DWELL)
    xmin, ymin, xmax, ymax = segment_bbox(*(s[k][moving] for k in GEOMETRY_FIELDS))
    for axis, lo, hi, travel, offset in (
        ("X", xmin, xmax, stage.travel_x_mm, None if origin is None else origin[0]),
        ("Y", ymin, ymax, stage.travel_y_mm, None if origin is None else origin[1]),
    ):
        if offset is None:
            extent = np.maximum.accumulate(hi) - np.minimum.accumulate(lo)
            beyond = np.flatnonzero(extent > travel * (1 + 1e-12))
            reason = (
                "the motion spans {:.3f} mm in {} by here, more than the {:g} mm travel of the {} "
                "(stage.toml: {})"
            )
            value = extent
        else:
            beyond = np.flatnonzero((lo + offset < -1e-9) | (hi + offset > travel + 1e-9))
            reason = (
                "the motion reaches {:.3f} mm in {} on the stage here, outside the 0-{:g} mm "
                "travel "
                "of the {} (stage.toml: {})"
            )
            value = np.where(lo + offset < 0, lo + offset, hi + offset)
        if beyond.size:
            first = beyond[0]
            line = int(s["line"][moving[first]])
            raise ProgramError(
                job.path,
                line,
                _line_text(text, line),
                reason.format(float(value[first]), axis, travel, stage.name, stage.travel_source),
            )


def _note_unused_speeds(job: Job, process, rapid) -> None:
    summary_kinds = {"print": set(), "rapid": set()}
    s = job.segments
    moving = s["kind"] != KIND_DWELL
    for role, mask in (
        ("print", moving & s["shutter_open"]),
        ("rapid", moving & ~s["shutter_open"]),
    ):
        for index in np.unique(s["speed_source"][mask]):
            if index >= 0:
                summary_kinds[role].add(job.speed_sources[index].origin)
    used = summary_kinds["print"] | summary_kinds["rapid"]
    if process is not None and not any("process speed (given)" in o for o in used):
        job.notes.append(
            f"the given process speed ({process:g} mm/s) is not used: the program sets the speed "
            "of every move"
        )
    if rapid is not None and not any("rapid speed (given)" in o for o in used):
        job.notes.append(
            f"the given rapid speed ({rapid:g} mm/s) is not used: the program sets the speed of "
            "every move"
        )
