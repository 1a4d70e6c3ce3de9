"""A virtual printer that takes set-point changes as it goes (closed-loop simulation).

:func:`ajtwin.simulation.run_virtual_print` makes a whole print from a set-point schedule
fixed in advance. A controller in the loop changes the set-points from what it measured,
so :class:`SteppedPrinter` advances the same truth a chunk at a time:

* the exogenous processes (MFC jitter, droplet-size process, generation wander, faults)
  are re-drawn from *fresh copies of the same seeded streams* for the schedule as it
  stands — no draw depends on the set-points and every process is causal in them, so the
  past is unchanged by a later command and the noise realisation is the batch printer's;
* the true states are integrated forward from the current true state with the batch
  printer's ``lax.scan`` (:mod:`ajtwin.simulation.truth`), one chunk of seconds at a time;
* the measurement layer is the batch printer's, evaluated on the chunk's rows.

With no set-point change, stepping a print through to its end gives
:func:`run_virtual_print`'s record (tested to 1e-12).

Parameters (of :class:`SteppedPrinter`)
----------
scenario : str, Path, Scenario or dict
    As for :func:`ajtwin.simulation.simulate`.
seed : int
duration_min : float, optional
    Override the scenario's duration [min].
overrides : dict, optional
    Scenario overrides.
truth : {"model", "alt"}
    The truth generator: the first (:mod:`ajtwin.simulation.truth`, which tuned the twin)
    or the second, structurally different one (:mod:`ajtwin.simulation.truth_alt`, for
    evaluation only), as ``simulate --truth``.
job : str, Path or ajtwin.job.Job, optional
    Print this machine program, looped to the duration, as ``simulate --job`` does
    (:mod:`ajtwin.simulation.job_print`): the chunks and the record then carry the shutter,
    the platen speed and the camera's print times, and stepping a job print through gives
    :func:`~ajtwin.simulation.job_print.run_job_print`'s record (nominal machine). An
    inspection pass (``camera`` mode ``"inspection"``) adds its rows after the print.
camera : CameraSettings, optional
    The job print's camera (default ``data/virtual_camera.toml``).

Examples
--------
>>> printer = SteppedPrinter("exp1", seed=1, duration_min=1.0)
>>> chunk = printer.advance(20)
>>> printer.set_setpoints([375.0, 22.0, 50.0])          # from t = 20 s on
>>> chunk = printer.advance(40)
>>> printer.done, printer.record().data.shape
(True, (60, 14))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from ajtwin import __version__
from ajtwin._jax import jnp
from ajtwin.io.records import (
    INPUT_COLUMNS,
    OUTPUT_COLUMNS,
    RECORD_COLUMNS,
    TIME_COLUMN,
    TRUTH_COLUMNS,
    UNITS,
    PrintRecord,
)
from ajtwin.model import coefficient_matrix, load_output_coefficients, load_parameters
from ajtwin.model.system import check_input
from ajtwin.simulation.job_print import (
    job_meta,
    job_table,
    line_at_print_times,
    measure_job_outputs,
    nozzle_line,
    plan_job_print,
    program_meta,
    read_job,
    truth_line_speed,
)
from ajtwin.simulation.machine import nominal_machine
from ajtwin.simulation.printer import (
    draw_line_coefficients,
    draw_processes,
    make_streams,
    measure,
    true_initial_state,
)
from ajtwin.simulation.scenarios import load_scenario
from ajtwin.simulation.truth import scan_truth_seconds
from ajtwin.simulation.truth_alt import (
    alt_measure,
    alt_processes,
    load_alt_settings,
    scan_alt_seconds,
)


@dataclass
class Chunk:
    """What one :meth:`SteppedPrinter.advance` produced, display units."""

    time_s: np.ndarray  # (n,)
    inputs: np.ndarray  # (n, 3) measured (reported) inputs
    outputs: np.ndarray  # (n, 5) measured outputs (NaN = missed)
    true_states: np.ndarray  # (n, 5)
    true_outputs: np.ndarray  # (n, 5) noise-free
    setpoints: np.ndarray  # (n, 3) the commands in force
    # a job print: shutter (0/1) and platen speed at t_k, the print time of the trace measured
    # in the row (NaN: none) and the true line printed at t_k (NaN with the shutter closed)
    shutter_open: np.ndarray | None = None  # (n,)
    platen_speed_mm_s: np.ndarray | None = None  # (n,)
    printed_at_s: np.ndarray | None = None  # (n,)
    true_line: np.ndarray | None = None  # (n, 2) L_w, L_o µm


class SteppedPrinter:
    """The virtual printer, advanced chunk by chunk under changing set-points."""

    def __init__(
        self,
        scenario="exp1",
        seed: int = 0,
        duration_min=None,
        overrides=None,
        truth="model",
        job=None,
        camera=None,
        repeat_pitch_mm=None,
    ):
        if truth not in ("model", "alt"):
            raise ValueError(f"truth generator {truth!r}: choose 'model' or 'alt'")
        self.truth = truth
        scenario = load_scenario(scenario, overrides)
        if duration_min is not None:
            scenario = scenario.with_duration(duration_min)
        if not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"seed = {seed!r} must be a non-negative integer")
        self.plan = None
        if job is not None:
            scenario = self._plan_job(job, scenario, camera, int(seed), repeat_pitch_mm)
        self.scenario = scenario
        self.seed = int(seed)
        self.params = load_parameters()
        self.n = scenario.duration_s
        self.schedule = scenario.setpoints(self.n).astype(float)
        streams = make_streams(self.seed)
        self._processes = self._draw(streams)
        nominal = coefficient_matrix(load_output_coefficients())
        self.line_factors, self.line_coefficients = draw_line_coefficients(
            scenario, streams, nominal, self.params
        )
        self._coefficients = jnp.asarray(self.line_coefficients)
        x0 = true_initial_state(scenario, self._processes, self.params, streams)
        self._carry = (jnp.asarray(x0, dtype=float), jnp.zeros(()))
        self.k = 0
        self._dirty = False
        self._true_states = np.full((self.n, 5), np.nan)
        self._true_outputs = np.full((self.n, 5), np.nan)
        self._substeps = int(scenario.config["truth"]["integration_substeps"])
        if truth == "alt":
            self._alt = load_alt_settings()
            dep = self._alt["deposition"]
            self._deposition = (
                float(dep["reference_um"]),
                float(dep["tube_size_exponent"]),
                float(dep["nozzle_size_exponent"]),
            )
            self._substeps = int(self._alt["measurement"]["substeps"])

    def _plan_job(self, job, scenario, camera, seed: int, pitch_mm=None):
        """Plan the job print (the scenario's duration = the print; runs side by side at
        ``pitch_mm`` when given) and extend the scenario over an inspection pass; returns the
        scenario to run."""

        the_job, path = read_job(job)
        self.plan = plan_job_print(the_job, scenario.duration_s, camera, pitch_mm)
        self.plan.program_meta = program_meta(the_job, path)
        scenario = scenario.with_duration(self.plan.n_rows / 60.0)
        self.line_speed_law = truth_line_speed(scenario, seed, self.truth)
        self._camera_line = np.full((self.plan.n_rows, 2), np.nan)
        return scenario

    def _draw(self, streams, setpoints=None):
        """The exogenous processes for a schedule (the alt truth replaces d_a and η)."""
        processes = draw_processes(self.scenario, streams, setpoints=setpoints)
        if self.truth == "alt":
            processes = alt_processes(self.scenario, processes, self.seed)
        return processes

    def _measure(self, processes, filled):
        if self.truth == "alt":
            return alt_measure(self.scenario, processes, filled, self.seed, self._alt)
        return measure(self.scenario, processes, filled, make_streams(self.seed))

    @property
    def done(self) -> bool:
        """Whether the print has ended."""
        return self.k >= self.n

    @property
    def processes(self):
        """The exogenous processes under the schedule as it stands now."""
        if self._dirty:
            self._processes = self._draw(make_streams(self.seed), setpoints=self.schedule)
            self._dirty = False
        return self._processes

    def set_setpoints(self, setpoints) -> None:
        """Command [I_A mA, Q_c sccm, Q_s sccm] from the current second to the end."""
        u = check_input(np.asarray(setpoints, dtype=float).reshape(3))
        if self.done:
            raise RuntimeError("the print is over; no more set-points")
        if not np.all(self.schedule[self.k :] == u):
            self.schedule[self.k :] = u
            self._dirty = True

    def set_input(self, index: int, value: float) -> None:
        """Command one input (0 = I_A mA, 1 = Q_c sccm, 2 = Q_s sccm) from now on; the
        other two keep their schedule (steps planned by the scenario included)."""
        if self.done:
            raise RuntimeError("the print is over; no more set-points")
        u = self.schedule[self.k].copy()
        u[index] = value
        check_input(u)
        if not np.all(self.schedule[self.k :, index] == value):
            self.schedule[self.k :, index] = value
            self._dirty = True

    def advance(self, seconds: int) -> Chunk:
        """Print ``seconds`` more seconds (fewer at the end of the print)."""
        seconds = int(seconds)
        if seconds < 1:
            raise ValueError(f"advance by at least 1 s, got {seconds}")
        if self.done:
            raise RuntimeError("the print is over")
        k0, k1 = self.k, min(self.k + seconds, self.n)
        p = self.processes
        droplet = p.droplet_um
        droplet_next = np.append(droplet[1:], droplet[-1])
        # pad to the requested length so every chunk of one size shares a compilation
        idx = np.minimum(np.arange(k0, k0 + seconds), k1 - 1)
        if self.truth == "alt":
            self._carry, emitted = scan_alt_seconds(
                self._carry,
                droplet[idx],
                droplet_next[idx],
                p.head_inputs[idx],
                p.drivers[idx],
                self.params,
                self._coefficients,
                self._deposition,
                substeps=self._substeps,
            )
        else:
            self._carry, emitted = scan_truth_seconds(
                self._carry,
                droplet[idx],
                droplet_next[idx],
                p.head_inputs[idx],
                p.drivers[idx],
                self.params,
                self._coefficients,
                substeps=self._substeps,
            )
        n_new = k1 - k0  # padding past the end of the print only ever moves a spent carry
        # (states, substrate ink, outputs[, generation]): the alt scan emits no generation
        states, outputs = (np.asarray(emitted[i])[:n_new] for i in (0, 2))
        self._true_states[k0:k1] = states
        self._true_outputs[k0:k1] = outputs
        if self.plan is not None:
            return self._advance_job(p, k0, k1, states, outputs)
        # the measurement layer on the print so far (rows are independent)
        filled = np.nan_to_num(self._true_outputs, nan=1.0)
        inputs, measured = self._measure(p, filled)
        self.k = k1
        return Chunk(
            time_s=np.arange(k0, k1, dtype=float),
            inputs=inputs[k0:k1],
            outputs=measured[k0:k1],
            true_states=states,
            true_outputs=outputs,
            setpoints=p.setpoints[k0:k1].copy(),
        )

    def _job_measurement(self, p):
        """Measured inputs, outputs and print times of the job print so far (all rows)."""

        return measure_job_outputs(
            lambda truth: self._measure(p, truth), self._true_outputs, self._camera_line, self.plan
        )

    def _advance_job(self, p, k0, k1, states, outputs) -> Chunk:
        """The job print's rows k0..k1: the camera's line at the print times, the measurement."""

        rows = slice(k0, k1)
        self._camera_line[rows] = line_at_print_times(
            self.plan.camera_printed_at_s[rows],
            self.plan.camera_speed_mm_s[rows],
            self._true_states,
            p.head_inputs,
            self._true_outputs,
            self.params,
            self.line_coefficients,
            nominal_machine(),
            self.line_speed_law,
        )
        inputs, measured, printed_at = self._job_measurement(p)
        self.k = k1
        return Chunk(
            time_s=np.arange(k0, k1, dtype=float),
            inputs=inputs[rows],
            outputs=measured[rows],
            true_states=states,
            true_outputs=outputs,
            setpoints=p.setpoints[rows].copy(),
            shutter_open=self.plan.shutter_open[rows].copy(),
            platen_speed_mm_s=self.plan.platen_speed_mm_s[rows].copy(),
            printed_at_s=printed_at[rows],
            true_line=nozzle_line(self.plan, self._true_outputs, self.line_speed_law, rows),
        )

    def record(self, extra_meta: dict | None = None) -> PrintRecord:
        """The print so far as a record (measured columns and truth), like ``simulate``."""
        k = self.k
        if k < 2:
            raise ValueError("a record needs at least 2 printed seconds")
        p = self.processes
        if self.plan is not None:
            return self._job_record(p, k, extra_meta)
        filled = np.nan_to_num(self._true_outputs, nan=1.0)
        inputs, outputs = self._measure(p, filled)
        columns = {TIME_COLUMN: np.arange(k, dtype=float)}
        columns.update({c: inputs[:k, i] for i, c in enumerate(INPUT_COLUMNS)})
        columns.update({c: outputs[:k, i] for i, c in enumerate(OUTPUT_COLUMNS)})
        columns.update({c: self._true_states[:k, i] for i, c in enumerate(TRUTH_COLUMNS)})
        data = pd.DataFrame({c: columns[c] for c in (*RECORD_COLUMNS, *TRUTH_COLUMNS)})
        meta = {**self._base_meta(p, k), **(extra_meta or {})}
        return PrintRecord(data, meta)

    def _base_meta(self, p, k: int) -> dict:
        cfg = self.scenario.config
        meta = {
            "machine_id": cfg["scenario"]["machine_id"],
            "scenario": self.scenario.name,
            "description": cfg["scenario"]["description"],
            "seed": self.seed,
            "platen_speed_mm_s": float(cfg["scenario"]["platen_speed_mm_s"]),
            "units": dict(UNITS),
            "fault_kind": cfg["fault"]["kind"],
            "fault_onset_s": self.scenario.fault_onset_s,
            "fault": dict(cfg["fault"]),
            "duration_s": k,
            "source": f"ajtwin {__version__} virtual printer, stepped ({self.scenario.source})",
            "truth_draws": {
                **p.draws,
                "line_coefficient_factors": self.line_factors.tolist(),
                "true_line_coefficients": self.line_coefficients.tolist(),
            },
        }
        if self.truth != "model":
            meta["truth_generator"] = self.truth
        return meta

    def _job_record(self, p, k: int, extra_meta: dict | None) -> PrintRecord:
        """The job print so far as a format-2 record (as :func:`run_job_print` writes)."""

        inputs, outputs, printed_at = self._job_measurement(p)
        rows = slice(0, k)
        line_truth = nozzle_line(self.plan, self._true_outputs, self.line_speed_law, rows)
        data = job_table(
            self.plan, inputs[rows], outputs[rows], printed_at[rows], self._true_states, line_truth
        )
        meta = self._base_meta(p, k)
        extra = job_meta(self.plan, self.line_speed_law, k)
        meta["truth_draws"]["line_speed"] = extra.pop("line_speed_law")
        meta.update(extra)
        meta["source"] = meta["source"].replace("virtual printer", "virtual printer, job print", 1)
        meta.update(extra_meta or {})
        return PrintRecord(data, meta)

    @property
    def true_outputs(self) -> np.ndarray:
        """Noise-free true outputs (k, 5) printed so far."""
        return self._true_outputs[: self.k]

    @property
    def true_states(self) -> np.ndarray:
        """The true states so far (k, 5), display units."""
        return self._true_states[: self.k]
