"""The virtual printer prints a job: a machine program under a camera (model reference §12).

A job print is an ordinary virtual print whose line depends on what the program does:

* **the machine** evolves exactly as on a straight line (the aerosol keeps flowing with the
  shutter closed and is caught below the nozzle), so the true states are those of the
  straight-line print of the same scenario and seed;
* **the substrate** receives material only while the shutter is open: the line printed at
  t_k (``true_linewidth_um``, ``true_overspray_um``) and the CNN's Q_m are NaN while it is
  closed;
* **the line** depends on the platen speed ν by the speed law (:mod:`ajtwin.model.line_speed`),
  with the truth's own draw of the law's constants (:func:`truth_line_speed`): the twin is
  not handed them. The second truth generator uses another form
  (:func:`ajtwin.simulation.truth_alt.alt_line_speed_factors`);
* **the camera** (:class:`CameraSettings`): *trailing* at an offset — the frame at t_k sees
  the part at p(t_k) + offset and measures the trace printed there last, at τ < t_k, or
  nothing; *inspection* — nothing during the print, then a pass along the printed strokes
  (shutter closed, inputs held), one frame a second; *at_nozzle* — the line as it is printed.
  The measured value is the true line *at τ* through the printer's usual camera noise.

:class:`JobPlan` holds everything that depends only on the job and the camera (per row: the
shutter, the speed, τ and the speed at τ); :func:`line_at_print_times` and
:func:`measure_job_outputs` turn the truth into the measured columns. The batch print
(:func:`run_job_print`) and :class:`ajtwin.simulation.stepper.SteppedPrinter` call the same
functions, so a stepped job print equals the batch one.

Examples
--------
>>> from ajtwin.job import read_program_text
>>> job = read_program_text("ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),200,0\\nOUT0.0=0",
...                         process_speed_mm_s=2.0)
>>> jp = run_job_print(job, "exp1", seed=1, duration_min=1.0,
...                    camera=CameraSettings(mode="trailing", offset_mm=(-5.0, 0.0)))
>>> rec = jp.record
>>> rec.has_job, rec.meta["camera"]
(True, {'mode': 'trailing', 'offset_mm': [-5.0, 0.0]})
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin._jax import jax
from ajtwin.config import packaged_toml
from ajtwin.io.records import (
    CAMERA_MODES,
    INPUT_COLUMNS,
    JOB_COLUMNS,
    LINE_TRUTH_COLUMNS,
    OUTPUT_COLUMNS,
    RECORD_COLUMNS,
    TIME_COLUMN,
    TRUTH_COLUMNS,
    PrintRecord,
)
from ajtwin.job import Job, read_printing, read_program
from ajtwin.model import load_parameters
from ajtwin.model.line_speed import (
    LineSpeedLaw,
    line_speed_factors,
    load_line_speed_law,
    read_line_speed_file,
)
from ajtwin.model.system import output_function
from ajtwin.simulation.printer import make_streams, measure, run_virtual_print
from ajtwin.simulation.scenarios import load_scenario
from ajtwin.simulation.truth_alt import alt_line_speed_factors, alt_measure, draw_alt_line_speed

#: Print times closer than this to a whole second count as that second (τ = t_k).
_ON_GRID_S = 1e-9
#: The output model at the print times, compiled once per padded batch size.
_outputs_at = jax.jit(output_function)


def _padded_outputs(x, u, params, coefficients) -> np.ndarray:
    """output_function on n rows, padded to a power of two (≥ 64) so that few sizes compile."""
    n = len(x)
    size = max(64, 1 << (n - 1).bit_length())
    pad = size - n
    xp = np.concatenate([x, np.repeat(x[-1:], pad, axis=0)]) if pad else x
    up = np.concatenate([u, np.repeat(u[-1:], pad, axis=0)]) if pad else u
    return np.asarray(_outputs_at(xp, up, params, coefficients))[:n]


# --------------------------------------------------------------------------- #
# The camera
# --------------------------------------------------------------------------- #


def load_camera_defaults() -> dict:
    """``data/virtual_camera.toml`` ``[camera]`` as a dict."""
    return packaged_toml("data/virtual_camera.toml")["camera"]


@dataclass(frozen=True)
class CameraSettings:
    """The virtual alignment camera of a job print (defaults: ``data/virtual_camera.toml``).

    Attributes
    ----------
    mode : {"trailing", "inspection", "at_nozzle"}
    offset_mm : (float, float)
        View centre relative to the nozzle, program coordinates [mm] (0 for ``at_nozzle``).
    field_radius_mm : float
        A trace is seen when its centre line passes this close to the view centre [mm].
    inspection_speed_mm_s : float
        Speed of the inspection pass along the printed strokes, one frame a second [mm/s].
    """

    mode: str | None = None
    offset_mm: tuple | None = None
    field_radius_mm: float | None = None
    inspection_speed_mm_s: float | None = None

    def __post_init__(self):
        defaults = load_camera_defaults()
        mode = defaults["mode"] if self.mode is None else self.mode
        if mode not in CAMERA_MODES:
            raise ValueError(f"camera mode {mode!r}: choose one of {', '.join(CAMERA_MODES)}")
        if mode == "at_nozzle":
            if self.offset_mm is not None and any(float(v) != 0.0 for v in self.offset_mm):
                raise ValueError("an at_nozzle camera has no offset (it sees the nozzle's spot)")
            offset = (0.0, 0.0)
        else:
            offset = defaults["offset_mm"] if self.offset_mm is None else self.offset_mm
            offset = tuple(float(v) for v in offset)
            if len(offset) != 2 or not all(math.isfinite(v) for v in offset):
                raise ValueError(f"camera offset {self.offset_mm!r}: give [dx, dy] in mm")
        radius = float(
            defaults["field_radius_mm"] if self.field_radius_mm is None else self.field_radius_mm
        )
        speed = float(
            defaults["inspection_speed_mm_s"]
            if self.inspection_speed_mm_s is None
            else self.inspection_speed_mm_s
        )
        if not (radius > 0 and math.isfinite(radius)):
            raise ValueError(f"field_radius_mm = {radius!r} must be a positive length")
        if not (speed > 0 and math.isfinite(speed)):
            raise ValueError(f"inspection_speed_mm_s = {speed!r} must be a positive speed")
        object.__setattr__(self, "mode", mode)
        object.__setattr__(self, "offset_mm", offset)
        object.__setattr__(self, "field_radius_mm", radius)
        object.__setattr__(self, "inspection_speed_mm_s", speed)

    def meta(self) -> dict:
        """The record's ``camera`` metadata (format 2)."""
        return {"mode": self.mode, "offset_mm": [float(v) for v in self.offset_mm]}


@dataclass(frozen=True)
class JobSettings:
    """How the printer's GUI runs a job: its speeds and where the loop's runs sit.

    Attributes
    ----------
    process_speed_mm_s : float, optional
        The GUI's process speed for a program that does not set its own [mm/s].
    rapid_speed_mm_s : float, optional
        The GUI's speed of moves with the shutter closed, for a program that does not set
        its own [mm/s].
    speed_schedule : ajtwin.job.SpeedSchedule, optional
        Process speeds per layer, stroke or feature (each run of the loop follows it from
        its start), recorded as ``job.process_speed_schedule``; instead of
        ``process_speed_mm_s``.
    repeat_pitch_mm : (float, float), optional
        Loop the job as an array of parts side by side at this pitch (dx, dy) [mm] (a lab's
        practice; an inspection pass then sees every run), recorded as
        ``job.repeat_pitch_mm``; default: each run prints over the last.

    Examples
    --------
    >>> JobSettings(process_speed_mm_s=4.0, repeat_pitch_mm=(35.0, 10.0)).repeat_pitch_mm
    (35.0, 10.0)
    """

    process_speed_mm_s: float | None = None
    rapid_speed_mm_s: float | None = None
    speed_schedule: object = None
    repeat_pitch_mm: tuple[float, float] | None = None


# --------------------------------------------------------------------------- #
# The plan: what the job and the camera decide, row by row
# --------------------------------------------------------------------------- #


@dataclass
class JobPlan:
    """Per-row facts of a job print that do not depend on the machine's states.

    Rows are t_k = k s, k < ``n_rows``; the print is rows < ``n_print`` (the job looped to
    that length), an inspection pass the rows after.

    Attributes
    ----------
    job : ajtwin.job.Job
        The job as printed (looped to ``n_print`` s).
    shutter_open : ndarray (n_rows,) of float
        Shutter at t_k (0/1).
    platen_speed_mm_s : ndarray (n_rows,)
        Stage speed at t_k (the pass: the inspection speed).
    camera_printed_at_s : ndarray (n_rows,)
        τ of the trace the frame at t_k sees; NaN: no trace in the field.
    camera_speed_mm_s : ndarray (n_rows,)
        The platen speed when that trace was printed (NaN: none).
    pitch_mm : (float, float) or None
        Runs of the looped job side by side at this pitch (:meth:`ajtwin.job.Job.repeat`);
        None: printed over each other.
    """

    job: object
    camera: CameraSettings
    n_print: int
    shutter_open: np.ndarray
    platen_speed_mm_s: np.ndarray
    camera_printed_at_s: np.ndarray
    camera_speed_mm_s: np.ndarray
    program_meta: dict = field(default_factory=dict)
    pitch_mm: tuple | None = None

    @property
    def n_rows(self) -> int:
        """Rows of the record: the print's seconds and the inspection pass's."""
        return int(self.shutter_open.size)

    @property
    def n_pass(self) -> int:
        """Rows of the inspection pass after the print (0 for a trailing camera)."""
        return self.n_rows - self.n_print


def _segment_speed(job, segment: np.ndarray) -> np.ndarray:
    speeds = np.asarray(job.segments["speed_mm_s"], dtype=float)
    return np.where(segment >= 0, speeds[np.maximum(segment, 0)], np.nan)


def inspection_pass(job, camera: CameraSettings, end_s: float):
    """Frames of the pass after the print: (print times τ, speeds at τ), one a second.

    The camera walks the printed strokes in print order, one frame every
    ``inspection_speed_mm_s`` × 1 s of printed length (a stroke shorter than that gets one
    frame at its middle). A frame measures the trace seen there at the end of the print (the
    latest printed over that spot); frames on a spot printed over later are dropped, the
    later stroke's own frames measure it.
    """
    strokes = job.strokes
    if len(strokes) == 0:
        return np.zeros(0), np.zeros(0)
    spacing = camera.inspection_speed_mm_s * 1.0
    length = strokes["length_mm"].to_numpy(dtype=float)
    count = np.where(length > 0, np.maximum(1, np.round(length / spacing)), 0).astype(np.int64)
    stroke = np.repeat(strokes["stroke"].to_numpy(dtype=np.int64), count)
    within = np.arange(stroke.size) - np.repeat(np.cumsum(count) - count, count)
    along = (within + 0.5) * np.repeat(length / np.maximum(count, 1), count)
    points = job.point_at(stroke, along)
    hits = job.locate(points.x_mm, points.y_mm, camera.field_radius_mm, before_s=end_s)
    own = hits.found & (hits.stroke == stroke) & (np.abs(hits.print_time_s - points.time_s) < 1e-6)
    order = np.argsort(hits.print_time_s[own], kind="stable")
    printed_at = hits.print_time_s[own][order]
    return printed_at, _segment_speed(job, hits.segment[own][order])


def plan_job_print(
    job, print_duration_s: int, camera: CameraSettings | None = None, pitch_mm=None
) -> JobPlan:
    """The rows of a job print of ``print_duration_s`` seconds under ``camera``.

    The job is looped to the print's length (:meth:`ajtwin.job.Job.repeat`; a longer program
    is cut there), its runs side by side at ``pitch_mm`` (dx, dy) when given, else over each
    other. Inspection mode appends the pass (:func:`inspection_pass`).
    """
    camera = camera or CameraSettings()
    n_print = int(print_duration_s)
    if n_print < 2:
        raise ValueError(f"a job print needs at least 2 s, got {print_duration_s}")
    if job.repetitions > 1:
        if job.duration_s < n_print - 1e-9:
            raise ValueError(
                f"the job is already looped to {job.duration_s:g} s, shorter than the "
                f"{n_print} s print: loop the job read from the program"
            )
        run = job
    else:
        run = job.repeat(float(n_print), pitch_mm=pitch_mm)
    t = np.arange(n_print, dtype=float)
    state = run.state_at(t)
    shutter = state.shutter_open.astype(float)
    speed = np.asarray(state.speed_mm_s, dtype=float)
    if camera.mode == "at_nozzle":
        printed_at = np.where(state.shutter_open, t, np.nan)
        at_speed = np.where(state.shutter_open, speed, np.nan)
    elif camera.mode == "trailing":
        dx, dy = camera.offset_mm
        hits = run.locate(state.x_mm + dx, state.y_mm + dy, camera.field_radius_mm, before_s=t)
        printed_at = np.where(hits.found, hits.print_time_s, np.nan)
        at_speed = _segment_speed(run, np.where(hits.found, hits.segment, -1))
    else:
        printed_at = np.full(n_print, np.nan)
        at_speed = np.full(n_print, np.nan)
        pass_at, pass_speed = inspection_pass(run, camera, float(n_print))
        n_pass = pass_at.size
        shutter = np.concatenate([shutter, np.zeros(n_pass)])
        speed = np.concatenate([speed, np.full(n_pass, camera.inspection_speed_mm_s)])
        printed_at = np.concatenate([printed_at, pass_at])
        at_speed = np.concatenate([at_speed, pass_speed])
    return JobPlan(
        run, camera, n_print, shutter, speed, printed_at, at_speed, pitch_mm=_pitch(pitch_mm)
    )


def _pitch(pitch_mm) -> tuple | None:
    return None if pitch_mm is None else tuple(float(v) for v in pitch_mm)


# --------------------------------------------------------------------------- #
# The truth's speed law
# --------------------------------------------------------------------------- #


def draw_power_law(rng: np.random.Generator, exponent_sd: float) -> dict:
    """The first generator's speed law: the model's form, exponents drawn around its own.

    b, c ~ N(nominal, ``exponent_sd``) clipped to the ranges of ``data/line_speed.toml``.
    """

    nominal = load_line_speed_law()
    ranges = read_line_speed_file()["uncertainty"]
    b = nominal.linewidth_exponent + exponent_sd * rng.standard_normal()
    c = nominal.overspray_exponent + exponent_sd * rng.standard_normal()
    law = nominal._replace(
        linewidth_exponent=float(np.clip(b, *ranges["linewidth_exponent_range"])),
        overspray_exponent=float(np.clip(c, *ranges["overspray_exponent_range"])),
    )
    return {"form": "power", **{k: float(v) for k, v in law._asdict().items()}}


def truth_line_speed(
    scenario,
    seed: int,
    truth_generator: str = "model",
    machine_seed: int | None = None,
    inherited: dict | None = None,
) -> dict:
    """The speed law of a virtual print's truth (a JSON-ready dict).

    A property of the machine: drawn from ``machine_seed`` when the machine is drawn from a
    seed (the same law on every print of it), else from the print's ``seed``; ``inherited``
    (the law of the print this one continues) is kept as it is. The first generator draws
    the model's power law (:func:`draw_power_law`, spread ``truth.line_speed_exponent_sd``),
    the second its own form (:func:`ajtwin.simulation.truth_alt.draw_alt_line_speed`).
    """
    if inherited is not None:
        return dict(inherited)
    key = [int(machine_seed), 2801] if machine_seed is not None else [int(seed), 2802]
    if truth_generator == "alt":
        return draw_alt_line_speed(np.random.default_rng(np.random.SeedSequence([*key, 7003])))
    sd = float(scenario.config["truth"]["line_speed_exponent_sd"])
    return draw_power_law(np.random.default_rng(np.random.SeedSequence(key)), sd)


def truth_speed_factors(platen_speed_mm_s, law: dict) -> tuple[np.ndarray, np.ndarray]:
    """(f_w, f_o) of a truth's speed law (:func:`truth_line_speed`) at speeds ν [mm/s]."""
    if law["form"] == "power":
        constants = LineSpeedLaw(**{k: law[k] for k in LineSpeedLaw._fields})
        f_w, f_o = line_speed_factors(np.asarray(platen_speed_mm_s, dtype=float), constants)
        return np.asarray(f_w), np.asarray(f_o)
    if law["form"] == "beam_plus_spreading":
        return alt_line_speed_factors(platen_speed_mm_s, law)
    raise ValueError(f"unknown speed-law form {law['form']!r}")


# --------------------------------------------------------------------------- #
# The truth of the line, at the nozzle and at the print time of what the camera saw
# --------------------------------------------------------------------------- #


def nozzle_line(plan: JobPlan, outputs_true: np.ndarray, law: dict, rows=slice(None)) -> np.ndarray:
    """True (L_w, L_o) printed at t_k (rows), NaN while the shutter is closed: (n, 2)."""
    shutter = plan.shutter_open[rows]
    f_w, f_o = truth_speed_factors(plan.platen_speed_mm_s[rows], law)
    line = np.asarray(outputs_true[rows, :2], dtype=float) * np.stack([f_w, f_o], axis=-1)
    return np.where(shutter[:, None] > 0, line, np.nan)


def line_at_print_times(
    printed_at_s: np.ndarray,
    speed_mm_s: np.ndarray,
    states: np.ndarray,
    head_inputs: np.ndarray,
    outputs_true: np.ndarray,
    params,
    line_coefficients: np.ndarray,
    deviation,
    law: dict,
) -> np.ndarray:
    """The true (L_w, L_o) of the trace printed at each τ, NaN where τ is NaN: (n, 2).

    The machine's outputs at τ are the output model at the state interpolated linearly
    between the 1 Hz truth samples around τ and the input held over that second (as the
    truth integrates it), through this machine's deviation; at a whole second they are the
    truth's own outputs (bit for bit). Then the truth's speed law at the speed of the stroke
    when it printed that spot.

    Parameters
    ----------
    printed_at_s, speed_mm_s : ndarray (n,)
        τ [s] and ν(τ) [mm/s].
    states, head_inputs, outputs_true : ndarray (T, 5), (T, 3), (T, 5)
        The truth at t_k (rows up to ⌈max τ⌉ must be filled).
    """
    tau = np.asarray(printed_at_s, dtype=float)
    out = np.full((tau.size, 2), np.nan)
    seen = np.isfinite(tau)
    if not seen.any():
        return out
    k = np.floor(tau[seen] + _ON_GRID_S).astype(np.int64)
    w = np.clip(tau[seen] - k, 0.0, None)
    on_grid = w <= _ON_GRID_S
    line = np.asarray(outputs_true[k, :2], dtype=float).copy()
    off = np.flatnonzero(~on_grid)
    if off.size:
        ko, wo = k[off], w[off][:, None]
        x = states[ko] + wo * (states[np.minimum(ko + 1, len(states) - 1)] - states[ko])
        u = head_inputs[ko]
        y = _padded_outputs(x, u, params, np.asarray(line_coefficients, dtype=float))
        line[off] = deviation.apply(y, x, u, params)[:, :2]
    f_w, f_o = truth_speed_factors(np.asarray(speed_mm_s, dtype=float)[seen], law)
    out[seen] = line * np.stack([f_w, f_o], axis=-1)
    return out


def measure_job_outputs(measure, outputs_true: np.ndarray, camera_line: np.ndarray, plan: JobPlan):
    """Measured inputs and outputs of a job print, and each row's print time.

    ``measure(outputs)`` is the printer's measurement layer (noise, missing samples) on a
    (T, 5) truth; the camera's columns get the line at τ (``camera_line``, (T, 2)). Rows
    with no trace in view have no L_w, L_o; rows with the shutter closed no Q_m.

    Returns
    -------
    (inputs (T, 3), outputs (T, 5), printed_at_s (T,))
    """
    n = len(outputs_true)
    truth = np.nan_to_num(np.asarray(outputs_true, dtype=float), nan=1.0)
    seen = np.isfinite(camera_line[:, 0]) & np.isfinite(camera_line[:, 1])
    truth[seen, :2] = camera_line[seen]
    inputs, outputs = measure(truth)
    outputs = np.array(outputs, dtype=float)
    outputs[~seen, :2] = np.nan
    outputs[plan.shutter_open[:n] <= 0, 4] = np.nan
    measured = np.isfinite(outputs[:, 0]) | np.isfinite(outputs[:, 1])
    printed_at = np.where(measured, plan.camera_printed_at_s[:n], np.nan)
    return inputs, outputs, printed_at


# --------------------------------------------------------------------------- #
# The record
# --------------------------------------------------------------------------- #


def program_meta(job, path=None) -> dict:
    """The record's ``job`` metadata (format 2): program, sha256, speeds, repeat_to_s."""
    summary = job.summary()
    source = Path(path if path is not None else job.path)
    sha = hashlib.sha256(source.read_bytes()).hexdigest() if source.is_file() else None
    meta = {
        "program": source.name,
        "sha256": sha,
        "process_speed_mm_s": summary["process_speed_mm_s"],
        "rapid_speed_mm_s": summary["rapid_speed_mm_s"],
        "speed_source": summary["process_speed_source"],
        "repeat_to_s": None,
    }
    if summary.get("speed_schedule"):  # speeds per layer/stroke/feature (ajtwin.job.speeds)
        meta["process_speed_schedule"] = summary["speed_schedule"]
    return meta


def job_table(
    plan: JobPlan,
    inputs: np.ndarray,
    outputs: np.ndarray,
    printed_at: np.ndarray,
    states: np.ndarray,
    line_truth: np.ndarray,
) -> pd.DataFrame:
    """A job print's 1 Hz table in record column order (format 2)."""
    n = len(inputs)
    columns = {TIME_COLUMN: np.arange(n, dtype=float)}
    columns.update({c: inputs[:, i] for i, c in enumerate(INPUT_COLUMNS)})
    columns.update({c: outputs[:, i] for i, c in enumerate(OUTPUT_COLUMNS)})
    columns.update(
        {
            "shutter_open": plan.shutter_open[:n],
            "platen_speed_mm_s": plan.platen_speed_mm_s[:n],
            "printed_at_s": printed_at,
        }
    )
    columns.update({c: states[:n, i] for i, c in enumerate(TRUTH_COLUMNS)})
    columns.update({c: line_truth[:n, i] for i, c in enumerate(LINE_TRUTH_COLUMNS)})
    order = (*RECORD_COLUMNS, *JOB_COLUMNS, *TRUTH_COLUMNS, *LINE_TRUTH_COLUMNS)
    return pd.DataFrame({c: columns[c] for c in order})


def job_meta(plan: JobPlan, law: dict, n_rows: int) -> dict:
    """The metadata a job print adds to (or replaces in) a virtual print's."""
    job_info = dict(plan.program_meta)
    job_info["repeat_to_s"] = float(plan.n_print)
    if plan.pitch_mm is not None:  # runs side by side: where each sits follows from the pitch
        job_info["repeat_pitch_mm"] = list(plan.pitch_mm)
    process = job_info.get("process_speed_mm_s")
    return {
        "job": job_info,
        "camera": plan.camera.meta(),
        "virtual_camera": {
            "field_radius_mm": plan.camera.field_radius_mm,
            "inspection_speed_mm_s": plan.camera.inspection_speed_mm_s,
            "print_end_s": plan.n_print,
            "inspection_rows": plan.n_pass,
        },
        "platen_speed_mm_s": float(process) if process else 2.0,
        "duration_s": int(n_rows),
        "line_speed_law": law,
    }


@dataclass
class JobPrint:
    """A virtual job print: the record, the plan, the truth's speed law and the print behind.

    ``virtual`` is the :class:`~ajtwin.simulation.printer.VirtualPrint` of the machine (its
    states, noise-free outputs at ν_ref with the shutter ignored, processes); ``camera_line``
    (T, 2) the true line at the print time of what each frame saw.
    """

    record: PrintRecord
    plan: JobPlan
    line_speed_law: dict
    virtual: object
    camera_line: np.ndarray


def read_job(program, process_speed_mm_s=None, rapid_speed_mm_s=None, speed_schedule=None):
    """A :class:`~ajtwin.job.Job` from a program path (or a Job, returned as it is) and the
    path its ``job`` metadata names; ``speed_schedule``: process speeds per layer, stroke or
    feature (:class:`ajtwin.job.SpeedSchedule`)."""

    if isinstance(program, Job):
        return program, None
    # nothing to print: refused before the machine runs
    job = read_printing(
        lambda: read_program(
            program, process_speed_mm_s, rapid_speed_mm_s, speed_schedule=speed_schedule
        )
    )
    return job, Path(program)


def run_job_print(
    program,
    scenario="exp1",
    seed: int = 0,
    duration_min: float | None = None,
    overrides: dict | None = None,
    continue_from: PrintRecord | None = None,
    machine=None,
    machine_seed: int | None = None,
    truth_generator: str = "model",
    camera: CameraSettings | None = None,
    job_settings: JobSettings | None = None,
) -> JobPrint:
    """Print a job on the virtual printer; see :func:`simulate_job` for the parameters."""

    settings = job_settings or JobSettings()
    job, path = read_job(
        program, settings.process_speed_mm_s, settings.rapid_speed_mm_s, settings.speed_schedule
    )
    camera = camera or CameraSettings()
    base = load_scenario(scenario, overrides)
    print_s = base.duration_s if duration_min is None else int(round(duration_min * 60.0))
    plan = plan_job_print(job, print_s, camera, settings.repeat_pitch_mm)
    plan.program_meta = program_meta(job, path)
    # the machine runs on through the inspection pass, inputs held at their last set-points
    virtual = run_virtual_print(
        scenario,
        seed,
        plan.n_rows / 60.0,
        overrides,
        continue_from,
        machine=machine,
        machine_seed=machine_seed,
        truth_generator=truth_generator,
    )
    inherited = None
    if continue_from is not None and machine is None and machine_seed is None:
        inherited = continue_from.meta.get("truth_draws", {}).get("line_speed")
    law = truth_line_speed(virtual.scenario, seed, truth_generator, machine_seed, inherited)
    params = load_parameters()
    camera_line = line_at_print_times(
        plan.camera_printed_at_s,
        plan.camera_speed_mm_s,
        virtual.states,
        virtual.processes.head_inputs,
        virtual.outputs_true,
        params,
        virtual.line_coefficients,
        virtual.machine,
        law,
    )
    if truth_generator == "alt":

        def measurement(truth):
            return alt_measure(virtual.scenario, virtual.processes, truth, int(seed))
    else:

        def measurement(truth):
            return measure(virtual.scenario, virtual.processes, truth, make_streams(seed))

    inputs, outputs, printed_at = measure_job_outputs(
        measurement, virtual.outputs_true, camera_line, plan
    )
    line_truth = nozzle_line(plan, virtual.outputs_true, law)
    data = job_table(plan, inputs, outputs, printed_at, virtual.states, line_truth)
    meta = dict(virtual.record.meta)
    extra = job_meta(plan, law, len(data))
    meta["truth_draws"] = {**meta.get("truth_draws", {}), "line_speed": extra.pop("line_speed_law")}
    meta.update(extra)
    meta["source"] = meta["source"].replace("virtual printer", "virtual printer, job print", 1)
    return JobPrint(PrintRecord(data, meta), plan, law, virtual, camera_line)


def simulate_job(program, scenario="exp1", seed: int = 0, **kwargs) -> PrintRecord:
    """Print a machine program on the virtual printer (a format-2 record).

    Parameters
    ----------
    program : str, Path or ajtwin.job.Job
        The ``.prg`` program (or a job already read).
    scenario, seed
        As for :func:`ajtwin.simulation.simulate`: the machine's inputs, faults and truth.

    Other Parameters
    ----------------
    duration_min : float, optional
        Length of the print [min] (default: the scenario's); the job is looped to it.
    overrides, continue_from, machine, machine_seed, truth_generator : optional
        As for :func:`ajtwin.simulation.simulate`.
    camera : CameraSettings, optional
        Mode and offset of the alignment camera (default ``data/virtual_camera.toml``).
    job_settings : JobSettings, optional
        The GUI's speeds for the program and how its loop is laid out (default: the
        program's own speeds, each run printed over the last).

    Returns
    -------
    PrintRecord
        Format 2: the straight-line record's columns plus ``shutter_open``,
        ``platen_speed_mm_s``, ``printed_at_s``, ``true_linewidth_um``,
        ``true_overspray_um``; metadata ``job`` and ``camera`` (docs/reference/record-format.md).
    """
    return run_job_print(program, scenario, seed, **kwargs).record
