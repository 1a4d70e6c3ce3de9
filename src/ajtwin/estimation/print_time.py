"""A job print's measurements at their print time (model reference §7, §12).

On a job print the camera's frame at row time t_k measures the trace printed at τ ≤ t_k
(``printed_at_s``): an *out-of-sequence* measurement. The twin files it at the 1 Hz step
that holds τ, with the line at the speed the trace was printed, and runs the ordinary
EKF over the filed steps. A measurement of step j can arrive until H steps after it (the
*horizon*); after that step j is *final* and the filter, the detectors, EM and the
registry take it. The batch twin (:meth:`ajtwin.estimation.Twin.run`) and the live engine
(:class:`ajtwin.engine.stream.TwinStream`) pass their rows through the same
:class:`PrintTimeBins`, in the same order: the same steps, the same drops, the same
numbers (docs/explanation/out-of-sequence-camera.md says why roll back rather than an
exact OOSM update or a lag-augmented state).

Filing
------
* Step j holds the print times τ with |τ − t_j| ≤ ½ s (the nearest second:
  j = ⌊τ − t_0 + ½⌋). A measurement whose step lies more than H steps back when its row
  arrives (k − j > H) is dropped and counted (``late``); one printed before the record
  starts (j < 0) likewise (``before_start``); one the program says was printed with the
  shutter closed (``not_printed``) too, and one of a dot printed while the stage stood still
  with the shutter open (``dwell``: below the speed law's validity range, not a line).
* The pressures and Q_m of row k belong to step k; Q_m only while the shutter is open at
  t_k (nothing reaches the substrate otherwise). L_w and L_o of a step come only from
  the camera, at their τ.
* Speed: ν(τ) from the program when it is known, else the rows' ``platen_speed_mm_s``
  interpolated linearly at τ between the two rows around it that were *printing* (shutter
  open, stage moving): a line was printed at τ, and a 1 Hz log interleaves printing rows
  with rapid rows and still ones (the shutter's open dwell) where strokes turn. When only
  one of the two was printing its speed stands alone; when neither was, the job's process
  speed (``fallback_speed_mm_s``, the record's ``job.process_speed_mm_s``), else ν_ref.
  The twin's speed law gives f_i = (ν_ref/ν_i)^b per measurement
  (:mod:`ajtwin.model.line_speed`).
* Several measurements y_i = f_i L + w_i (w_i ~ N(0, σ²)) of one step are replaced by
  their sufficient statistic (weighted least squares for the one L they share)::

      ȳ = Σ f_i y_i / Σ f_i,   F = Σ f_i² / Σ f_i,   v = Σ f_i² / (Σ f_i)²

  so ȳ = F L + w̄ with Var w̄ = v σ²; equal speeds give the mean and σ²/n. The update with
  (ȳ, F, v) equals the update with every y_i stacked, H fixed at the prior (the scalar
  updates of :func:`ajtwin.estimation.filters.ekf_step` are sequential): no information
  is lost or counted twice. One measurement is passed as it is (F = f, v = 1).
* A step with no camera measurement predicts the line printed at t_j: F = f(ν(t_j))
  while the shutter is open, 1 (the line at ν_ref) while it is closed.

Each final step is a :class:`FiledStep`: its time, inputs, outputs (L_w, L_o filed, NaN
where none) and ``line`` = (F_w, F_o, v_w, v_o) — the known input of the output model
(:func:`ajtwin.estimation.filters.ekf_step`).

Examples
--------
>>> import numpy as np
>>> bins = PrintTimeBins(horizon_s=3.0)
>>> out = []
>>> for k in range(6):                          # from row 3 on, the camera sees what was
...     seen = k >= 3                            # printed 2.2 s before
...     y = [40.0 if seen else np.nan, 30.0 if seen else np.nan, 5600.0, 5600.0, 1e-9]
...     out += bins.add(float(k), [375.0, 23.0, 50.0], y, 1.0, 2.0, k - 2.2 if seen else np.nan)
>>> [step.time_s for step in out]          # steps 0..2 are final once row 5 is in
[0.0, 1.0, 2.0]
>>> float(out[1].outputs[0])               # row 3's frame (τ = 0.8 s) is filed at step 1
40.0
>>> np.isnan(out[0].outputs[0])
np.True_
"""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ajtwin.config import packaged_toml
from ajtwin.io.records import PrintRecord
from ajtwin.job import (
    Job,
    LoopedJob,
    SpeedSchedule,
    decode_program,
    loop_job,
    read_printing,
    read_program_bytes,
    read_program_text,
)
from ajtwin.job.agreement import JobEvidence, check_record_agrees, sample_rows
from ajtwin.model.line_speed import LineSpeedLaw, line_speed_factors, load_line_speed_law

# seconds of a camera's delays asked of the job at once (the trace query's arrays)
_DELAY_SECONDS = 20_000

#: Row times within this of the 1 s grid count as on it [s].
GRID_TOLERANCE_S = 1e-6
#: A print time up to this after its row is the row's own time (rounding of a log) [s].
PRINTED_AFTER_ROW_TOLERANCE_S = 1e-6
#: Counters of measurements that were not filed (:attr:`PrintTimeBins.dropped`).
DROP_REASONS = ("late", "before_start", "not_printed", "dwell", "after_row")


@functools.cache
def load_print_time_settings() -> dict:
    """``data/print_time.toml`` as {name: value} (the horizon rule and the camera's view)."""
    content = packaged_toml("data/print_time.toml")
    return {
        name: float(entry["value"])
        for table in ("horizon", "camera")
        for name, entry in content[table].items()
    }


class FiledStep(NamedTuple):
    """One final 1 Hz step of a job print as the filter takes it.

    Attributes
    ----------
    time_s : float
        t_j [s].
    inputs : ndarray (3,)
        u_j [mA, sccm, sccm].
    outputs : ndarray (5,)
        y_j: L_w, L_o filed from the camera frames printed at this step (combined when
        several), P_c, P_s measured at t_j, Q_m at t_j while the shutter was open; NaN = none.
    line : ndarray (4,)
        (F_w, F_o, v_w, v_o): speed-law factors and variance factors (module docstring).
    n_camera : ndarray (2,) of int
        Frames filed here for L_w and L_o.
    """

    time_s: float
    inputs: np.ndarray
    outputs: np.ndarray
    line: np.ndarray
    n_camera: np.ndarray


@dataclass
class _Bin:
    """A step whose camera measurements may still arrive (sums of the combination)."""

    time_s: float
    inputs: np.ndarray
    outputs: np.ndarray  # (5,) L_w, L_o NaN until filed
    idle_factors: np.ndarray  # (2,) F of the line printed at t_j (1 with the shutter closed)
    count: np.ndarray  # (2,) frames filed
    sum_f: np.ndarray  # (2,) Σ f_i
    sum_ff: np.ndarray  # (2,) Σ f_i²
    sum_fy: np.ndarray  # (2,) Σ f_i y_i
    first: np.ndarray  # (2, 2) (y, f) of the first frame: one frame is passed as it is

    def filed(self) -> FiledStep:
        """The step as the filter takes it: the frames combined (module docstring)."""
        y = self.outputs.copy()
        line = np.array([self.idle_factors[0], self.idle_factors[1], 1.0, 1.0])
        for i in range(2):
            n = int(self.count[i])
            if n == 1:
                y[i], line[i] = self.first[i]
            elif n > 1:
                y[i] = self.sum_fy[i] / self.sum_f[i]
                line[i] = self.sum_ff[i] / self.sum_f[i]
                line[2 + i] = self.sum_ff[i] / self.sum_f[i] ** 2
        return FiledStep(self.time_s, self.inputs, y, line, self.count.astype(np.int64))


class PrintTimeBins:
    """The delay line in front of the filter: rows in, final steps out (module docstring).

    Parameters
    ----------
    horizon_s : float
        H: a step is final H rows after its own (0: at once; ``inf``: at :meth:`finish`).
        Measurements more than H steps late are dropped and counted.
    speed_law : LineSpeedLaw, optional
        The twin's speed law (default ``data/line_speed.toml``).
    job : ajtwin.job.Job, optional
        The program as printed (looped as the record's was): ν(τ) and the shutter at τ
        come from it; without it ν(τ) is the rows' speed interpolated at τ.
    fallback_speed_mm_s : float, optional
        ν(τ) without the program when neither row around τ was printing (default ν_ref).
    """

    def __init__(
        self,
        horizon_s: float,
        speed_law: LineSpeedLaw | None = None,
        job=None,
        fallback_speed_mm_s: float | None = None,
    ):
        horizon = float(horizon_s)
        if not (horizon >= 0) or (math.isfinite(horizon) and not horizon.is_integer()):
            raise ValueError(f"horizon_s = {horizon_s!r}: a whole number of seconds >= 0, or inf")
        self.horizon_s = horizon
        self.speed_law = speed_law or load_line_speed_law()
        self.job = job
        self.fallback_speed_mm_s = float(fallback_speed_mm_s or self.speed_law.reference_speed_mm_s)
        self.start_time_s: float | None = None
        self.n_rows = 0
        self.first_open = 0  # oldest step not yet final
        self._bins: dict[int, _Bin] = {}
        self._speeds: dict[int, float] = {}  # row speeds kept for interpolation at τ
        self.dropped = {reason: 0 for reason in DROP_REASONS}
        self.filed = 0  # camera frames filed
        self.closed_material_flow = 0  # Q_m values of shutter-closed rows not used
        self._changed_from: int | None = None  # oldest step changed since take_changed()

    # ------------------------------------------------------------------ #
    def add(self, time_s, inputs, outputs, shutter_open, platen_speed_mm_s, printed_at_s):
        """Take row k (the next second); returns the steps that became final, in order.

        Parameters
        ----------
        time_s : float
            t_k, on the 1 s grid of the first row (gaps are the caller's: fill them with
            rows of NaN outputs).
        inputs : array (3,)
        outputs : array (5,)
            As measured in the row (the camera's L_w, L_o from the frame at t_k).
        shutter_open : float
            At t_k (0/1; NaN: unknown, taken as open).
        platen_speed_mm_s : float
            At t_k (NaN: unknown, the law's reference speed).
        printed_at_s : float
            τ of the row's camera measurement (NaN with a camera measurement: τ = t_k).
        """
        t = float(time_s)
        k = self.n_rows
        if self.start_time_s is None:
            self.start_time_s = t
        elif abs(t - (self.start_time_s + k)) > GRID_TOLERANCE_S:
            raise ValueError(
                f"row {k + 1} at t = {t:g} s is not on the 1 s grid from "
                f"t = {self.start_time_s:g} s (expected {self.start_time_s + k:g} s)"
            )
        self.n_rows += 1
        y = np.array(outputs, dtype=float).reshape(5)
        shutter = float(shutter_open)
        speed = float(platen_speed_mm_s)
        speed = self.speed_law.reference_speed_mm_s if not np.isfinite(speed) else speed
        is_open = not (shutter == 0.0)
        self._speeds[k] = (speed, is_open and speed > 0.0)
        row = y.copy()
        row[:2] = np.nan
        if not is_open and np.isfinite(row[4]):
            row[4] = np.nan  # nothing reaches the substrate: no material flow measured
            self.closed_material_flow += 1
        idle = np.asarray(self._factors(speed)) if is_open else np.ones(2)
        self._bins[k] = _Bin(
            t,
            np.array(inputs, dtype=float).reshape(3),
            row,
            idle,
            np.zeros(2),
            np.zeros(2),
            np.zeros(2),
            np.zeros(2),
            np.full((2, 2), np.nan),
        )
        self._mark_changed(k)
        camera = np.isfinite(y[:2])
        if camera.any():
            tau = float(printed_at_s)
            self._file(k, t, t if not np.isfinite(tau) else tau, y[:2], camera)
        self._forget_speeds(k)
        if math.isinf(self.horizon_s):
            return []
        return self._pop_until(k - int(self.horizon_s))

    def finish(self) -> list[FiledStep]:
        """End of the print: every step left is final."""
        return self._pop_until(self.n_rows - 1)

    @property
    def n_pending(self) -> int:
        """Steps not final yet."""
        return len(self._bins)

    def pending(self) -> list[FiledStep]:
        """The steps not final yet, as filed so far (what a provisional estimate runs on)."""
        return [self._bins[j].filed() for j in range(self.first_open, self.n_rows)]

    @property
    def counts(self) -> dict:
        """Frames filed, dropped by reason, and Q_m values of shutter-closed rows not used."""
        return {
            "filed": self.filed,
            **{f"dropped_{reason}": n for reason, n in self.dropped.items()},
            "material_flow_shutter_closed": self.closed_material_flow,
        }

    # ------------------------------------------------------------------ #
    def _file(self, k: int, t: float, tau: float, values: np.ndarray, camera: np.ndarray):
        if tau > t + PRINTED_AFTER_ROW_TOLERANCE_S:
            self.dropped["after_row"] += 1
            return
        j = int(math.floor(tau - self.start_time_s + 0.5))
        if j < 0:
            self.dropped["before_start"] += 1
            return
        if k - j > self.horizon_s or j < self.first_open:
            self.dropped["late"] += 1
            return
        speed = self._speed_at(tau)
        if speed is None:
            self.dropped["not_printed"] += 1
            return
        if speed < self.speed_law.min_speed_mm_s:
            # a still stage with the shutter open prints a dot, not a line: the law there is
            # its edge value held, and a dot read as a line would pull the states by whatever
            # the law's extrapolation to a stop misses
            self.dropped["dwell"] += 1
            return
        f = np.asarray(self._factors(speed))
        b = self._bins[j]
        for i in np.flatnonzero(camera):
            if b.count[i] == 0:
                b.first[i] = (values[i], f[i])
            b.count[i] += 1
            b.sum_f[i] += f[i]
            b.sum_ff[i] += f[i] * f[i]
            b.sum_fy[i] += f[i] * values[i]
        self.filed += 1
        self._mark_changed(j)

    def _mark_changed(self, j: int) -> None:
        self._changed_from = j if self._changed_from is None else min(self._changed_from, j)

    def take_changed(self) -> int | None:
        """The oldest step added or filed into since the last call (None: none), then reset:
        a provisional re-run need not go back further."""
        changed, self._changed_from = self._changed_from, None
        return changed

    def _speed_at(self, tau: float) -> float | None:
        """ν(τ): the program's (None: its shutter was closed then), else the rows' interpolated."""
        if self.job is not None:
            # a spot at the very end of a stroke is printed as the shutter closes: look just before
            state = self.job.state_at(np.array([tau, tau - PRINTED_AFTER_ROW_TOLERANCE_S]))
            if not state.shutter_open.any():
                return None
            return float(state.speed_mm_s[0] if state.shutter_open[0] else state.speed_mm_s[1])
        x = tau - self.start_time_s
        k0 = min(max(int(math.floor(x)), 0), self.n_rows - 1)
        w = x - k0
        s0, printing0 = self._speeds[k0]
        s1, printing1 = self._speeds[min(k0 + 1, self.n_rows - 1)]
        if printing0 and printing1:
            return s0 + w * (s1 - s0)
        if printing0 or printing1:
            return s0 if printing0 else s1
        return self.fallback_speed_mm_s

    def _factors(self, speed: float):
        f_w, f_o = line_speed_factors(speed, self.speed_law)
        return float(f_w), float(f_o)

    def _forget_speeds(self, k: int) -> None:
        """Drop row speeds no τ still to come can need: all of them when the program gives
        ν(τ), else those below the oldest step a measurement may still reach (τ ≥ t_{k−H} − ½)."""
        if self.job is not None:
            self._speeds.pop(k, None)
        elif math.isfinite(self.horizon_s):
            self._speeds.pop(k - int(self.horizon_s) - 2, None)

    def _pop_until(self, last: int) -> list[FiledStep]:
        out = []
        while self.first_open <= last:
            out.append(self._bins.pop(self.first_open).filed())
            self.first_open += 1
        return out


# --------------------------------------------------------------------------- #
# A record's job, its camera and the horizon
# --------------------------------------------------------------------------- #


def is_job_record(record: PrintRecord) -> bool:
    """A format-2 record with the job columns: the twin files its camera at print times.

    A version-1 record (its reader fills the columns with defaults: the speed is only the
    metadata's, 1 mm/s for a bare log) and a record without the columns are read as
    before: the line at the law's reference speed, measured as printed.
    """
    return record.has_job and int(record.meta.get("format_version", 2)) >= 2


#: What a print's job settings say about how it ran the program (a record's ``job``
#: metadata and the settings the registry keeps with a print share these keys).
PRINTED_AS = (
    "process_speed_mm_s",
    "rapid_speed_mm_s",
    "repeat_to_s",
    "repeat_pitch_mm",
    "process_speed_schedule",
)


def job_as_printed(
    program,
    settings: dict | None = None,
    *,
    name: str | None = None,
    print_duration_s: float | None = None,
    held: bool = True,
    **overrides,
) -> Job | LoopedJob:
    """The job as a print ran it: the program read at the print's speeds and looped as the
    print looped it (side by side when it was). The one place a program is read "as
    printed": from a record's metadata (:func:`program_for_record`), from what the registry
    keeps with a print, and for a live print.

    Parameters
    ----------
    program : str, Path or bytes
        The ``.prg`` file, or its bytes (then ``name`` is its file name).
    settings : dict, optional
        A format-2 record's ``job`` metadata, or the settings the registry keeps with a
        print: ``sha256`` (checked: another program is refused), and
        :data:`PRINTED_AS` — ``process_speed_mm_s``, ``rapid_speed_mm_s``, ``repeat_to_s``
        (the print looped the program to this many seconds) and ``repeat_pitch_mm``
        ([dx, dy]: the runs placed side by side, :meth:`ajtwin.job.Job.repeat`) and
        ``process_speed_schedule`` (speeds per layer, stroke or feature: a
        :class:`ajtwin.job.SpeedSchedule` or its :meth:`~ajtwin.job.SpeedSchedule.to_meta`).
    print_duration_s : float, optional
        How long the print ran [s]: when nothing says how it looped and it outlasted the
        program, the program ran again over the same part (as the live map assumes).
    held : bool
        A looped job as :meth:`ajtwin.job.Job.repeat` holds it (every run's segments), for
        what asks the whole part; False: a :class:`ajtwin.job.LoopedJob`, which answers
        where the stage is and what lies under a point without growing with the loop (a
        print's camera filing).
    **overrides
        Any of :data:`PRINTED_AS` given by the user instead of ``settings`` (None: not given).
        Without either the program runs at the GUI's default speeds (``stage.toml``), once.

    Raises
    ------
    ValueError
        The program is not the one the settings name (its SHA-256 differs), or an unknown
        override.
    ajtwin.job.ProgramError
        A program that cannot be read, naming its line.
    """
    unknown = set(overrides) - set(PRINTED_AS)
    if unknown:
        raise TypeError(f"job_as_printed: unknown settings {sorted(unknown)}")
    raw = program if isinstance(program, bytes) else read_program_bytes(program)
    name = name if name is not None else str(program)
    given = dict(settings or {})
    expected = given.get("sha256")
    digest = hashlib.sha256(raw).hexdigest()
    if expected and digest != expected:
        raise ValueError(
            f"{name}: sha256 {digest[:12]}… is not the program this print ran "
            f"({given.get('program', '?')}, sha256 {str(expected)[:12]}…); give the same file"
        )
    value = {key: overrides.get(key) if overrides.get(key) is not None else given.get(key)
             for key in PRINTED_AS}  # fmt: skip
    schedule = value["process_speed_schedule"]
    if not isinstance(schedule, SpeedSchedule):
        schedule = SpeedSchedule.from_meta(schedule)
    # a job that prints nothing has no part, no camera, no map: refused
    job = read_printing(
        lambda: read_program_text(
            decode_program(raw, name),
            None if value["process_speed_mm_s"] is None else float(value["process_speed_mm_s"]),
            None if value["rapid_speed_mm_s"] is None else float(value["rapid_speed_mm_s"]),
            path=name,
            speed_schedule=schedule,
        )
    )
    loop, pitch = value["repeat_to_s"], value["repeat_pitch_mm"]
    if loop is None and print_duration_s is not None and print_duration_s > job.duration_s:
        loop = print_duration_s
    if loop is not None and float(loop) > 0:
        pitch = None if pitch is None else tuple(float(v) for v in pitch)
        job = (
            job.repeat(float(loop), pitch_mm=pitch)
            if held
            else loop_job(job, float(loop), pitch_mm=pitch)
        )
    return job


def program_for_record(record: PrintRecord, program, **overrides) -> Job | LoopedJob:
    """The program ``program`` (a ``.prg`` path) read and looped as ``record``'s print ran
    it (:func:`job_as_printed` with the record's ``job`` metadata and its length).

    A format-2 record names the program's SHA-256 (another file is refused with a
    ValueError naming both), the speeds and the looping; ``overrides`` (any of
    :data:`PRINTED_AS`) replace them, and ``held`` is :func:`job_as_printed`'s. A bare
    machine log names nothing: the GUI's speeds, time 0 = the program's start, the program
    run again whenever the log outlasts it.
    """
    info = record.meta.get("job")
    return job_as_printed(
        program,
        info if isinstance(info, dict) else None,
        print_duration_s=record_duration_s(record),
        **overrides,
    )


def record_duration_s(record: PrintRecord) -> float:
    """How long a record's print ran [s]: one second per row (the last row's second
    included)."""
    return float(record.duration_s + 1.0)


def trailing_delays(job: Job | LoopedJob, offset_mm, duration_s: float) -> np.ndarray:
    """Delays t − τ [s] of a camera trailing at ``offset_mm`` over whole seconds of ``job``.

    The frame at t sees the trace printed last before t within the view's field
    (``field_radius_mm`` of ``data/print_time.toml``) around p(t) + offset (the geometry
    of model reference §12, asked of :meth:`ajtwin.job.Job.locate`); seconds that see
    nothing are left out.
    """
    radius = load_print_time_settings()["field_radius_mm"]
    seconds = int(math.ceil(min(duration_s, job.duration_s)))
    delays = []
    for first in range(0, max(seconds, 1), _DELAY_SECONDS):  # a week's seconds in pieces
        t = np.arange(first, min(first + _DELAY_SECONDS, seconds), dtype=float)
        state = job.state_at(t)
        hits = job.locate(
            state.x_mm + float(offset_mm[0]), state.y_mm + float(offset_mm[1]), radius, before_s=t
        )
        delays.append((t - hits.print_time_s)[hits.found])
    return np.concatenate(delays)


def camera_horizon_s(
    camera: dict | None, job: Job | LoopedJob | None = None, duration_s=None
) -> float:
    """The horizon H [s] for a job print whose camera is ``camera`` (the record's metadata).

    * ``at_nozzle``: 0 (the camera sees the line as it is printed);
    * ``inspection``: ``inf`` (the pass comes after the print: steps are final at its end);
    * ``trailing``: with the program, the ``trailing_quantile`` of its own delays
      (:func:`trailing_delays` over ``duration_s``), rounded up, plus ``margin_s``;
      without it ``trailing_without_program_s``;
    * no camera metadata: ``unknown_camera_s``.
    """
    settings = load_print_time_settings()
    mode = None if not isinstance(camera, dict) else camera.get("mode")
    if mode == "at_nozzle":
        return 0.0
    if mode == "inspection":
        return math.inf
    if mode != "trailing":
        return settings["unknown_camera_s"]
    if job is None:
        return settings["trailing_without_program_s"]
    duration = job.duration_s if duration_s is None else float(duration_s)
    delays = trailing_delays(job, camera.get("offset_mm", (0.0, 0.0)), duration)
    if delays.size == 0:
        return settings["margin_s"]
    quantile = float(np.quantile(delays, settings["trailing_quantile"]))
    return float(math.ceil(quantile) + settings["margin_s"])


@dataclass(frozen=True)
class PrintContext:
    """What the twin knows about a job print before its rows arrive.

    Attributes
    ----------
    horizon_s : float
        H (:class:`PrintTimeBins`).
    camera_mode : str or None
        The record's camera mode (None: not stated).
    job : ajtwin.job.Job or None
        The program as printed (speeds at print times come from it).
    process_speed_mm_s : float or None
        The job's process speed: ν(τ) without the program where the rows cannot tell it.
    """

    horizon_s: float
    camera_mode: str | None = None
    job: object = None
    process_speed_mm_s: float | None = None

    def bins(self, speed_law: LineSpeedLaw | None = None) -> PrintTimeBins:
        """A fresh delay line for this print."""
        return PrintTimeBins(self.horizon_s, speed_law, self.job, self.process_speed_mm_s)


def job_evidence(record) -> JobEvidence:
    """What a job record (a :class:`PrintRecord` or a spooled one, read a column at a time)
    says of its program: its job columns over at most ``max_rows`` rows spread over the print,
    every camera row up to that many too, and its ``camera`` and ``job`` metadata."""
    rows = sample_rows(len(record))
    camera_rows = None
    columns = {}
    for name in ("shutter_open", "platen_speed_mm_s", "printed_at_s"):
        if hasattr(record, "data"):
            values = record.data[name].to_numpy(dtype=float)
        else:  # spooled: the raw column (a resampled shutter rounded as the reader does)
            values = np.asarray(record.column(name), dtype=float)
        if name == "printed_at_s":  # the camera's rows are few: keep them (up to the bound)
            seen = np.flatnonzero(np.isfinite(values))
            camera_rows = seen[sample_rows(seen.size)]
        columns[name] = values
    keep = np.union1d(rows, camera_rows)
    if hasattr(record, "data"):
        time_s = record.time_s[keep]
    else:  # spooled: a 1 Hz grid from its first row
        time_s = record.start_s + keep.astype(float)
    shutter = columns["shutter_open"][keep]
    camera = record.meta.get("camera") if isinstance(record.meta.get("camera"), dict) else {}
    info = record.meta.get("job") if isinstance(record.meta.get("job"), dict) else {}
    speed = info.get("process_speed_mm_s")
    return JobEvidence(
        where=str(record.meta.get("source_file", "the record")),
        time_s=time_s,
        row=keep + 1,
        shutter_open=np.where(np.isfinite(shutter), np.floor(shutter + 0.5), np.nan),
        platen_speed_mm_s=columns["platen_speed_mm_s"][keep],
        printed_at_s=columns["printed_at_s"][keep],
        camera_mode=camera.get("mode"),
        camera_offset_mm=tuple(float(v) for v in camera.get("offset_mm", (0.0, 0.0))),
        process_speed_mm_s=None if speed is None else float(speed),
    )


def check_job_record(record, job: Job | LoopedJob | None = None) -> None:
    """Refuse a job record that contradicts its program ``job`` (with the program: its
    speeds, shutter and print times; without: its speeds in the speed law's range),
    before anything is computed (:func:`ajtwin.job.agreement.check_record_agrees`)."""
    law = load_line_speed_law()
    check_record_agrees(
        job_evidence(record),
        job,
        speed_range_mm_s=(law.min_speed_mm_s, law.max_speed_mm_s),
    )


def print_context(record: PrintRecord, job: Job | None = None, horizon_s=None) -> PrintContext:
    """The :class:`PrintContext` of a job record (``horizon_s`` overrides the rule), once the
    record is found to agree with its program (:func:`check_job_record`: a record that
    contradicts it is refused here, where the batch and the spooled twin both start)."""
    check_job_record(record, job)
    camera = record.meta.get("camera")
    if horizon_s is None:
        horizon_s = camera_horizon_s(camera, job, len(record))
    mode = camera.get("mode") if isinstance(camera, dict) else None
    info = record.meta.get("job")
    process = info.get("process_speed_mm_s") if isinstance(info, dict) else None
    return PrintContext(float(horizon_s), mode, job, None if process is None else float(process))


class FiledPrint(NamedTuple):
    """A job record's rows filed at their print times: what the batch twin runs on.

    Attributes
    ----------
    inputs, measurements : ndarray (T, 3), (T, 5)
    line_factors : ndarray (T, 4)
    n_camera : ndarray (T, 2)
    counts : dict
        :attr:`PrintTimeBins.counts` and the horizon.
    """

    inputs: np.ndarray
    measurements: np.ndarray
    line_factors: np.ndarray
    n_camera: np.ndarray
    counts: dict


def file_record(
    record: PrintRecord, context: PrintContext, speed_law: LineSpeedLaw | None = None
) -> FiledPrint:
    """Every row of a job record through one :class:`PrintTimeBins`, as the live engine
    feeds them (the same order, the same drops)."""
    bins = context.bins(speed_law)
    steps = []
    columns = zip(
        record.time_s,
        record.inputs,
        record.outputs,
        record.shutter_open,
        record.platen_speed,
        record.printed_at,
    )
    for row in columns:
        steps += bins.add(*row)
    steps += bins.finish()
    counts = {**bins.counts, "horizon_s": context.horizon_s}
    return FiledPrint(
        np.array([s.inputs for s in steps]).reshape(-1, 3),
        np.array([s.outputs for s in steps]).reshape(-1, 5),
        np.array([s.line for s in steps]).reshape(-1, 4),
        np.array([s.n_camera for s in steps]).reshape(-1, 2),
        counts,
    )
