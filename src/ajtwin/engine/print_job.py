"""The job a print ran: keep it with the print, map a stored print's part.

A print's record names its program (format 2: ``job`` metadata with the file name, its
SHA-256, the speeds and how it was looped). :func:`job_entry` is what the registry keeps
with a print (``ajtwin ingest --job``: the program's bytes, the speeds used, the looping —
``repeat_to_s`` and ``repeat_pitch_mm`` — and the part's tolerance); the job is read back
as the print ran it by :func:`ajtwin.estimation.print_time.job_as_printed`, the one reader
for a record's metadata and a stored entry alike. :func:`stored_part_map` maps the part of
a stored print: the twin re-run over the measurements it filtered — on a job print the
camera's filed at their print times, with the speed law's factors kept beside them — from
the print's stored start, θ and calibration (the run the ingest or the live twin made, now
smoothed), the stored alarms placed on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ajtwin.apps.quality.part_map import (
    MAP_DEFAULTS,
    MapSettings,
    PartMap,
    Tolerance,
    build_part_map,
)
from ajtwin.engine.chain import chain_start
from ajtwin.engine.commissioning import calibration_twin_kwargs
from ajtwin.engine.start import machine_start
from ajtwin.estimation.line_speed_fit import SpeedExponents
from ajtwin.estimation.print_time import job_as_printed
from ajtwin.estimation.twin import Twin
from ajtwin.job import LoopedJob, ProgramError, read_program_bytes
from ajtwin.store.calibration import calibration_by_id
from ajtwin.store.registry import RegistryError

#: relative difference of a re-run's end state from the stored one that is reported
RERUN_TOLERANCE = 1e-6


def job_entry(
    program,
    record=None,
    *,
    process_speed_mm_s: float | None = None,
    rapid_speed_mm_s: float | None = None,
    repeat_to_s: float | None = None,
    repeat_pitch_mm=None,
    tolerance: Tolerance | None = None,
    speed_schedule=None,
) -> dict:
    """What the registry keeps of the job a print ran (``ajtwin ingest --job``).

    The program is read first (a bad program or one that is not the record's is refused
    before anything is stored); the speeds kept are those the print ran at (the given
    ones, else the record's, else the GUI's defaults the reader used), the looping the
    given one, else the record's.

    Returns
    -------
    dict
        ``program`` (file name), ``program_bytes``, ``settings``: ``process_speed_mm_s``,
        ``rapid_speed_mm_s``, ``speed_source``, ``repeat_to_s``, ``repeat_pitch_mm``
        ([dx, dy] or None), ``tolerance_um`` ([low, high] or None),
        ``process_speed_schedule`` (speeds per layer, stroke or feature,
        :meth:`ajtwin.job.SpeedSchedule.to_meta`, or None) — the settings
        :func:`~ajtwin.estimation.print_time.job_as_printed` reads back.
    """
    path = Path(program)
    raw = read_program_bytes(path)  # a FIFO or device refused before a byte is read
    from_record = dict(((None if record is None else record.meta) or {}).get("job") or {})
    given = {"process_speed_mm_s": process_speed_mm_s, "rapid_speed_mm_s": rapid_speed_mm_s,
             "repeat_to_s": repeat_to_s, "repeat_pitch_mm": repeat_pitch_mm,
             "process_speed_schedule": speed_schedule}  # fmt: skip
    # read and looped as printed (a loop that does not fit the stage is refused); the speeds
    # kept are the program's, whatever the loop's length
    job = job_as_printed(raw, from_record, name=path.name, held=False, **given)
    summary = (job.program if isinstance(job, LoopedJob) else job).summary()
    loop = repeat_to_s if repeat_to_s is not None else from_record.get("repeat_to_s")
    pitch = repeat_pitch_mm if repeat_pitch_mm is not None else from_record.get("repeat_pitch_mm")
    return {
        "program": path.name,
        "program_bytes": raw,
        "settings": {
            "process_speed_mm_s": summary["process_speed_mm_s"],
            "rapid_speed_mm_s": summary["rapid_speed_mm_s"],
            "speed_source": summary["process_speed_source"],
            "repeat_to_s": None if loop is None else float(loop),
            "repeat_pitch_mm": None if pitch is None else [float(v) for v in pitch],
            "tolerance_um": None if tolerance is None else [float(v) for v in tolerance],
            "process_speed_schedule": summary["speed_schedule"],
        },
    }


def entry_job(entry: dict, print_duration_s: float | None = None, **overrides):
    """The job of a stored entry (:meth:`ajtwin.store.registry.Registry.print_job` or
    :func:`job_entry`) as the print ran it: :func:`~ajtwin.estimation.print_time.
    job_as_printed` on its bytes and settings."""
    return job_as_printed(
        entry["program_bytes"],
        entry.get("settings") or {},
        name=entry["program"],
        print_duration_s=print_duration_s,
        **overrides,
    )


def stored_print_twin(registry, print_row: dict) -> tuple[Twin, tuple]:
    """The twin a stored print ran with (its calibration, starting θ and the speed law's
    exponents it learnt) and its start."""
    kwargs = {}
    calibration_id = (print_row.get("summary") or {}).get("calibration_id")
    if calibration_id is not None:
        calibration = calibration_by_id(registry, calibration_id)
        if calibration is not None:
            kwargs = calibration_twin_kwargs(calibration)
    twin = Twin.default(**kwargs)
    twin.theta = np.asarray(print_row["theta_before"], dtype=float)
    learnt = (print_row.get("summary") or {}).get("speed_exponents")
    if learnt:  # the speed law it filed its frames with
        twin.learn_speed_law(SpeedExponents.from_dict(learnt))
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
    (:func:`load_stored_print`); the mapping itself reads nothing more.

    ``arrays``: the print's per-second arrays (:meth:`~ajtwin.store.registry.Registry.
    print_arrays`): the inputs, the measurements the twin filtered and, for a job print,
    their ``line_factors``."""

    machine: str
    row: dict
    arrays: dict
    job: object
    entry: dict | None
    events: list
    twin: Twin
    start: tuple


def load_stored_print(registry, machine: str, seq: int | None = None, program=None):
    """Read a stored print, its job (``program``: a program file instead of, or for a
    print stored without, its stored job), alarms, twin and start. RegistryError when the
    print has no job and none is given, or keeps no samples."""
    row = stored_print(registry, machine, seq)
    arrays = registry.print_arrays(row["id"])
    if "inputs" not in arrays or "measurements" not in arrays:
        raise RegistryError(
            f"print {row['seq']} keeps no samples (stored by an older ajtwin): its part "
            "cannot be mapped"
        )
    entry = registry.print_job(row["id"])
    time_s = np.asarray(arrays["time_s"], dtype=float)
    duration = float(time_s[-1] - time_s[0] + 1.0)
    try:
        if program is not None:
            info = (row.get("meta") or {}).get("job")
            job = job_as_printed(
                program, info if isinstance(info, dict) else None, print_duration_s=duration
            )
        elif entry is not None:
            job = entry_job(entry, print_duration_s=duration)
    except ProgramError as exc:  # e.g. a program that prints nothing, stored before it was refused
        raise RegistryError(
            f"print {row['seq']} of {machine!r}: its part cannot be mapped: {exc}"
        ) from None
    if program is None and entry is None:
        raise RegistryError(
            f"print {row['seq']} of {machine!r} was stored without its job: give the program "
            f"(--job PROGRAM.prg), or ingest prints with `ajtwin ingest --job`"
        )
    alarms = registry.anomalies(machine)
    events = alarms[alarms["seq"] == row["seq"]].to_dict("records")
    twin, start = stored_print_twin(registry, row)
    return StoredPrint(machine, row, arrays, job, entry, events, twin, start)


def stored_run(stored: StoredPrint, progress=None):
    """The twin re-run (smoothed) over a stored print as it ran: from its stored start, θ
    and calibration over the measurements it filtered (on a job print, filed at their print
    times, with their speed-law factors). Returns the :class:`~ajtwin.estimation.twin.TwinRun`."""
    arrays = stored.arrays
    line = arrays.get("line_factors")
    return stored.twin.run(
        inputs=arrays["inputs"],
        measurements=arrays["measurements"],
        time_s=arrays["time_s"],
        line_factors=None if line is None else np.asarray(line, dtype=float).reshape(-1, 4),
        start=stored.start,
        smooth=True,
        progress=progress,
    )


def map_stored_print(
    stored: StoredPrint,
    tolerance: Tolerance | None = None,
    *,
    map_settings: MapSettings = MAP_DEFAULTS,
    twin_progress=None,
    line_progress=None,
) -> PartMap:
    """The part map of a stored print (:func:`stored_run`); ``tolerance`` instead of the
    one stored with the job."""
    entry = stored.entry
    if tolerance is None and entry is not None and entry["settings"].get("tolerance_um"):
        tolerance = Tolerance(*entry["settings"]["tolerance_um"])
    run = stored_run(stored, twin_progress)
    part = build_part_map(
        stored.job,
        run,
        tolerance,
        events=stored.events,
        source=f"{stored.machine} print {stored.row['seq']}",
        map_settings=map_settings,
        progress=line_progress,
    )
    part.run = run
    part.speed_exponents = stored.twin.speed_exponents
    part.machine = stored.machine
    end = np.asarray(run.end_mean, dtype=float)
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
    if begin["speed_exponents"] is not None:
        twin.learn_speed_law(begin["speed_exponents"])
    return twin, begin["start"]
