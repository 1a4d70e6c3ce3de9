"""The job a print ran: read it as the print ran it, keep it with the print, map a stored
print's part.

A print's record names its program (format 2: ``job`` metadata with the file name, its
SHA-256, the speeds and ``repeat_to_s``). :func:`job_of_print` reads the program as the
print ran it (a different program is refused); :func:`job_entry` is what the registry keeps
with a print (``ajtwin ingest --job``: the program's bytes, the speeds used, the looping,
the part's tolerance); :func:`stored_part_map` maps the part of a stored print: the
record rebuilt from the registry, the twin re-run from the print's stored start, θ and
calibration (the same run the ingest made, now smoothed), the stored alarms placed on it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.engine.chain import chain_start
from ajtwin.engine.commissioning import calibration_twin_kwargs
from ajtwin.engine.part_map import (
    FLAG_PROBABILITY,
    PORTION_MM,
    STEP_MM,
    PartMap,
    Tolerance,
    part_map_of_record,
)
from ajtwin.engine.start import machine_start
from ajtwin.estimation.twin import Twin
from ajtwin.io.records import INPUT_COLUMNS, JOB_COLUMNS, OUTPUT_COLUMNS, PrintRecord
from ajtwin.job import decode_program, read_program_text
from ajtwin.store.calibration import calibration_by_id
from ajtwin.store.registry import RegistryError

#: relative difference of a re-run's end state from the stored one that is reported
RERUN_TOLERANCE = 1e-6


def program_digest(raw: bytes) -> str:
    """SHA-256 of a program's bytes (what a record's ``job`` metadata names)."""
    return hashlib.sha256(raw).hexdigest()


def job_of_print(
    program_bytes: bytes,
    program_name: str,
    record_meta: dict | None = None,
    *,
    process_speed_mm_s: float | None = None,
    rapid_speed_mm_s: float | None = None,
    repeat_to_s: float | None = None,
    print_duration_s: float | None = None,
):
    """The job as a print ran it: the program read with the print's speeds and looped as
    the print looped it.

    The record's ``job`` metadata (format 2) names the program's SHA-256 (a different
    program is refused with a ValueError), the speeds used and ``repeat_to_s``;
    ``process_speed_mm_s``, ``rapid_speed_mm_s``, ``repeat_to_s`` override them. Without
    either the program runs at the GUI's default speeds (``stage.toml``), once, or looped
    to ``print_duration_s`` when the print outlasts it (the machine ran it again, as the
    live twin assumes). A program that cannot be read raises
    :class:`ajtwin.job.ProgramError` naming its line.
    """
    from_record = dict((record_meta or {}).get("job") or {})
    expected = from_record.get("sha256")
    digest = program_digest(program_bytes)
    if expected and expected != digest:
        raise ValueError(
            f"{program_name} (sha256 {digest[:12]}…) is not the program this print ran: its "
            f"record names {from_record.get('program', '?')} (sha256 {str(expected)[:12]}…)"
        )
    process = process_speed_mm_s
    if process is None:
        process = from_record.get("process_speed_mm_s")
    rapid = rapid_speed_mm_s
    if rapid is None:
        rapid = from_record.get("rapid_speed_mm_s")
    job = read_program_text(
        decode_program(program_bytes),
        None if process is None else float(process),
        None if rapid is None else float(rapid),
        path=program_name,
    )
    loop = repeat_to_s if repeat_to_s is not None else from_record.get("repeat_to_s")
    if loop is None and print_duration_s is not None and print_duration_s > job.duration_s:
        loop = print_duration_s
    if loop is not None and float(loop) > 0:
        job = job.repeat(float(loop))
    return job


def record_duration_s(record) -> float:
    """How long a record's print ran [s]: one second per row (the last row's second
    included)."""
    return float(record.duration_s + 1.0)


def job_entry(
    program,
    record=None,
    *,
    process_speed_mm_s: float | None = None,
    rapid_speed_mm_s: float | None = None,
    repeat_to_s: float | None = None,
    tolerance: Tolerance | None = None,
) -> dict:
    """What the registry keeps of the job a print ran (``ajtwin ingest --job``).

    The program is read first (a bad program or one that is not the record's is refused
    before anything is stored); the speeds kept are those the print ran at (the given
    ones, else the record's, else the GUI's defaults the reader used).

    Returns
    -------
    dict
        ``program`` (file name), ``program_bytes``, ``settings``: ``process_speed_mm_s``,
        ``rapid_speed_mm_s``, ``speed_source``, ``repeat_to_s``, ``tolerance_um``
        ([low, high] or None).
    """
    path = Path(program)
    raw = path.read_bytes()
    meta = None if record is None else record.meta
    job = job_of_print(
        raw,
        path.name,
        meta,
        process_speed_mm_s=process_speed_mm_s,
        rapid_speed_mm_s=rapid_speed_mm_s,
        repeat_to_s=repeat_to_s,
    )
    summary = job.summary()
    from_record = dict((meta or {}).get("job") or {})
    loop = repeat_to_s if repeat_to_s is not None else from_record.get("repeat_to_s")
    return {
        "program": path.name,
        "program_bytes": raw,
        "settings": {
            "process_speed_mm_s": summary["process_speed_mm_s"],
            "rapid_speed_mm_s": summary["rapid_speed_mm_s"],
            "speed_source": summary["process_speed_source"],
            "repeat_to_s": None if loop is None else float(loop),
            "tolerance_um": None if tolerance is None else [float(v) for v in tolerance],
        },
    }


def job_from_entry(entry: dict, repeat_to_s: float | None = None, print_duration_s=None):
    """The job of a stored entry (:meth:`ajtwin.store.registry.Registry.print_job`), read
    with the speeds it was stored with and looped as stored (or to ``repeat_to_s``; or, with
    no looping stored, to ``print_duration_s`` when the print outlasted the program)."""
    settings = entry.get("settings") or {}
    return job_of_print(
        entry["program_bytes"],
        entry["program"],
        None,
        process_speed_mm_s=settings.get("process_speed_mm_s"),
        rapid_speed_mm_s=settings.get("rapid_speed_mm_s"),
        repeat_to_s=repeat_to_s if repeat_to_s is not None else settings.get("repeat_to_s"),
        print_duration_s=print_duration_s,
    )


def stored_record(registry, print_row: dict) -> PrintRecord:
    """A stored print as a record: its samples (kept exactly), the job's columns when the
    print had them, its metadata."""
    arrays = registry.print_arrays(print_row["id"])
    if "inputs" not in arrays or "measurements" not in arrays:
        raise RegistryError(
            f"print {print_row['seq']} keeps no samples (stored by an older ajtwin): its part "
            "cannot be mapped"
        )
    data = {"time_s": arrays["time_s"]}
    data.update({c: arrays["inputs"][:, i] for i, c in enumerate(INPUT_COLUMNS)})
    data.update({c: arrays["measurements"][:, i] for i, c in enumerate(OUTPUT_COLUMNS)})
    data.update({c: arrays[c] for c in JOB_COLUMNS if c in arrays})
    meta = dict(print_row.get("meta") or {})
    meta.setdefault("source_file", f"registry print {print_row['seq']}")
    return PrintRecord(pd.DataFrame(data), meta)


def stored_print_twin(registry, print_row: dict) -> tuple[Twin, tuple]:
    """The twin a stored print ran with (its calibration and starting θ) and its start."""
    kwargs = {}
    calibration_id = (print_row.get("summary") or {}).get("calibration_id")
    if calibration_id is not None:
        calibration = calibration_by_id(registry, calibration_id)
        if calibration is not None:
            kwargs = calibration_twin_kwargs(calibration)
    twin = Twin.default(**kwargs)
    twin.theta = np.asarray(print_row["theta_before"], dtype=float)
    return twin, (print_row["start_mean"], print_row["start_cov"])


def stored_print(registry, machine: str, seq: int | None = None) -> dict:
    """The machine's print ``seq`` (default: its newest print, in the chain or not)."""
    if seq is not None:
        return registry.print_by_seq(machine, seq)
    row = registry.last_print(machine, in_chain=False)
    if row is None:
        raise RegistryError(f"machine {machine!r} has no prints yet")
    return row


@dataclass
class StoredPrint:
    """What mapping a stored print's part needs, read from the registry in one go
    (:func:`load_stored_print`); the mapping itself reads nothing more."""

    machine: str
    row: dict
    record: PrintRecord
    job: object
    entry: dict | None
    events: list
    twin: Twin
    start: tuple


def load_stored_print(registry, machine: str, seq: int | None = None, program=None):
    """Read a stored print, its job (``program``: a program file instead of, or for a
    print stored without, its stored job), alarms, twin and start. RegistryError when the
    print has no job and none is given."""
    row = stored_print(registry, machine, seq)
    record = stored_record(registry, row)
    entry = registry.print_job(row["id"])
    duration = record_duration_s(record)
    if program is not None:
        job = job_of_print(
            Path(program).read_bytes(), Path(program).name, record.meta, print_duration_s=duration
        )
    elif entry is not None:
        job = job_from_entry(entry, print_duration_s=duration)
    else:
        raise RegistryError(
            f"print {row['seq']} of {machine!r} was stored without its job: give the program "
            f"(--job PROGRAM.prg), or ingest prints with `ajtwin ingest --job`"
        )
    alarms = registry.anomalies(machine)
    events = alarms[alarms["seq"] == row["seq"]].to_dict("records")
    twin, start = stored_print_twin(registry, row)
    return StoredPrint(machine, row, record, job, entry, events, twin, start)


def map_stored_print(
    stored: StoredPrint,
    tolerance: Tolerance | None = None,
    *,
    portion_mm: float = PORTION_MM,
    step_mm: float = STEP_MM,
    flag_probability: float = FLAG_PROBABILITY,
    twin_progress=None,
    line_progress=None,
) -> PartMap:
    """The part map of a stored print: the twin re-run (smoothed) from its stored start,
    θ and calibration; ``tolerance`` instead of the one stored with the job."""
    entry = stored.entry
    if tolerance is None and entry is not None and entry["settings"].get("tolerance_um"):
        tolerance = Tolerance(*entry["settings"]["tolerance_um"])
    part = part_map_of_record(
        stored.record,
        stored.job,
        tolerance,
        twin=stored.twin,
        start=stored.start,
        source=f"{stored.machine} print {stored.row['seq']}",
        portion_mm=portion_mm,
        step_mm=step_mm,
        flag_probability=flag_probability,
        events=stored.events,
        twin_progress=twin_progress,
        line_progress=line_progress,
    )
    end = np.asarray(part.run.run.end_mean, dtype=float)
    stored_end = np.asarray(stored.row["end_mean"], dtype=float)
    scale = np.maximum(np.abs(stored_end), 1e-30)
    if np.any(np.abs(end - stored_end) / scale > RERUN_TOLERANCE):
        part.notes.append(
            "the twin re-run over the stored samples ends away from the stored end state "
            "(the twin changed since this print was stored): the map is the current twin's"
        )
    return part


def stored_part_map(
    registry, machine: str, seq: int | None = None, *, program=None, tolerance=None, **options
) -> PartMap:
    """The part map of a stored print (module docstring): :func:`load_stored_print` then
    :func:`map_stored_print` (``options``: its keywords)."""
    stored = load_stored_print(registry, machine, seq, program)
    return map_stored_print(stored, tolerance, **options)


def next_print_twin(registry, machine: str) -> tuple[Twin, tuple | None]:
    """The machine's twin and start for a print not yet stored: where its next print would
    start (:func:`ajtwin.engine.start.machine_start`: chain, calibration, maintenance)."""
    begin = machine_start(registry, machine, chain_start(registry, machine))
    twin = Twin.default(**begin["twin_kwargs"])
    twin.theta = np.asarray(begin["theta"], dtype=float)
    return twin, begin["start"]
