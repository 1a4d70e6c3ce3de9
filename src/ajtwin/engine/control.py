"""A print under the MPC: samples → the machine's twin → the controller → what to write.

:class:`ControlledPrint` wires live control and computes nothing itself: the machine's
samples go to its twin (the live engine's stream, stored and published, or a stream of its
own), the MPC on the twin (:class:`ajtwin.apps.planning.twin_control.MPCTwin`) decides
each period under the supervisor's rules (:class:`ajtwin.apps.planning.supervisor.
Supervisor`), and what is to be written comes back to the link (``ajtwin.live``), which
only talks to the machine. On a job print the program and the camera fill each sample's
job columns (:class:`ajtwin.engine.job_samples.JobColumns`) and the twin files the
camera's frames at their print times.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from ajtwin.apps.planning.advice import effective_bounds
from ajtwin.apps.planning.supervisor import ControlTarget, Supervisor
from ajtwin.apps.planning.twin_control import MPCTwin
from ajtwin.engine.job_samples import JobColumns, live_loop
from ajtwin.engine.stream import TwinStream
from ajtwin.estimation import Twin
from ajtwin.estimation.print_time import PrintContext, camera_horizon_s

log = logging.getLogger("ajtwin.control")


@dataclass(frozen=True)
class CameraOnJob:
    """The machine's camera on a job print: ``trailing`` (its view ``offset_mm`` (x, y)
    from the nozzle [mm]) or ``at_nozzle``."""

    mode: str = "trailing"
    offset_mm: tuple = (0.0, 0.0)

    def __post_init__(self):
        if self.mode not in ("trailing", "at_nozzle"):
            raise ValueError(
                f"camera {self.mode!r}: live control follows a trailing camera or one at the "
                "nozzle (an inspection pass comes after the print)"
            )


class ControlledPrint:
    """One machine's print under the MPC (module docstring).

    Parameters
    ----------
    machine : str
    target : ControlTarget
    job : ajtwin.job.Job, optional
        The program the machine prints (run again over the same part when it ends).
    camera : CameraOnJob, optional
        The camera on a job print.
    engine : ajtwin.engine.fleet.LiveEngine, optional
        The live engine whose stream of the machine the controller plans from (its print
        stored with the job, every step published); default a stream of its own.
    """

    def __init__(
        self,
        machine: str,
        target: ControlTarget,
        *,
        job=None,
        camera: CameraOnJob | None = None,
        engine=None,
    ):
        self.machine = machine
        self.target = target.resolved()
        self.job, self.engine = job, engine
        self.camera = camera or CameraOnJob()
        self.columns: JobColumns | None = None
        self.controller: MPCTwin | None = None
        self.supervisor: Supervisor | None = None
        self.last_time = -np.inf

    def prepare(self) -> None:
        """Build the twin and the MPC (and compile them)."""
        if self.controller is not None:
            return
        t = self.target
        fill = {} if t.vial_fill_ml is None else {"vial_fill_ml": float(t.vial_fill_ml)}
        twin, context, looped = Twin.default(**fill), None, None
        if self.job is not None:
            looped = live_loop(self.job)
            # the horizon from two runs of the program (its delays repeat run after run)
            camera = {"mode": self.camera.mode, "offset_mm": list(self.camera.offset_mm)}
            two_runs = live_loop(self.job, 2 * self.job.duration_s)
            horizon = camera_horizon_s(camera, two_runs)
            process = self.job.summary()["process_speed_mm_s"]
            context = PrintContext(horizon, self.camera.mode, looped, process)
            self.columns = JobColumns(looped, self.camera.mode, self.camera.offset_mm)
            log.info("%s: job print, camera %s, horizon %g s", self.machine, camera, horizon)
        if self.engine is not None:
            stream = self.engine.open(self.machine, source="control", print_context=context)
            twin, feed = stream.twin, functools.partial(self.engine.feed, self.machine)
        else:
            stream = TwinStream(self.machine, twin, asynchronous=False, print_context=context)
            feed = None
        bounds = effective_bounds(t.limits)
        self.controller = MPCTwin(
            twin=twin,
            settings=t.settings,
            bounds=bounds,
            u0=np.array([np.mean(b) for b in bounds]),
            target=t.target_um,
            limits=t.limits,
            max_overspray_um=t.max_overspray_um,
            job=looped,
            stream=stream,
            feed=feed,
        )
        self.supervisor = Supervisor(self.controller, t)

    def feed(self, samples) -> int:
        """The machine's new samples (:class:`~ajtwin.estimation.samples.Sample`, in order)
        to the twin; how many."""
        if not samples:
            return 0
        time_s = np.array([x.time_s for x in samples], dtype=float)
        chunk = SimpleNamespace(
            time_s=time_s,
            inputs=np.array([x.inputs for x in samples], dtype=float),
            outputs=np.array([x.outputs for x in samples], dtype=float),
            printed_at_s=None,
        )
        if self.columns is not None:
            columns = self.columns.fill(chunk.time_s, chunk.outputs)
            chunk.outputs = columns.pop("outputs")
            for name, values in columns.items():
                setattr(chunk, name, values)
        self.controller.observe(chunk)
        self.supervisor.saw(float(time_s[0]))
        self.last_time = float(time_s[-1])
        return len(samples)

    @property
    def due(self) -> bool:
        """Whether a decision is due."""
        return self.supervisor is not None and self.supervisor.due(self.last_time)

    def decide(self, u, machine_now_s: float):
        """The period's decision from the command in force ``u`` (3,) and the machine's
        clock (:meth:`Supervisor.decide`; the target checked once the twin has a state)."""
        reach = self.supervisor.reachable
        if self.supervisor.check_reachable() is not None and reach is None:
            log.info("%s: reachable L_w %.1f–%.1f µm", self.machine, *self.supervisor.reachable)
        return self.supervisor.decide(self.last_time + 1, u, machine_now_s)

    def close(self) -> int | None:
        """The print ended: stored with its job by the engine (its id; None without)."""
        if self.engine is None or self.controller is None:
            return None
        return self.engine.close(self.machine)
