"""A control strategy in closed loop with the virtual printer (``ajtwin control simulate``).

:func:`simulate_strategy` runs one of the four strategies (open loop, PI, the MPC on the
nominal model, the MPC on the twin) against the virtual printer
(:func:`ajtwin.apps.planning.closed_loop.run_closed_loop`); the MPC on the twin plans from
the machine's twin as the live engine runs it (:class:`ajtwin.engine.stream.TwinStream`).

Examples
--------
>>> plan = ClosedLoopPlan("exp1", 1, 65.0, duration_min=10)
>>> run = simulate_strategy(plan, "pi")                 # doctest: +SKIP
>>> run.metrics["rms_error_um"]                         # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ajtwin.apps.planning.advice import effective_bounds
from ajtwin.apps.planning.closed_loop import (
    STRATEGIES,
    ClosedLoopRun,
    resolve_scenario,
    run_closed_loop,
)
from ajtwin.apps.planning.mpc import ControlSettings, check_target
from ajtwin.apps.planning.strategies import MPCNominal, OpenLoop, PIController, start_inputs
from ajtwin.apps.planning.twin_control import MPCTwin
from ajtwin.engine.stream import TwinStream
from ajtwin.estimation import print_time
from ajtwin.estimation.print_time import PrintContext
from ajtwin.estimation.twin import Twin
from ajtwin.simulation.stepper import SteppedPrinter

STRATEGY_CLASSES = {
    "open_loop": OpenLoop,
    "pi": PIController,
    "mpc_nominal": MPCNominal,
    "mpc_twin": MPCTwin,
}


@dataclass(frozen=True)
class ClosedLoopPlan:
    """One closed-loop print with the virtual printer: the print, the target, the limits.

    Attributes
    ----------
    scenario : str or Path
        A packaged scenario, one of the controller's own (``slow_clog``) or a file.
    seed : int
        The print's seed.
    target_um : float
        Target linewidth [µm].
    duration_min : float, optional
        Shorten the print [min].
    settings : ControlSettings, optional
        Default ``data/control.toml``.
    limits : dict, optional
        Input limits {name: [low, high]} (display units); default the registry's.
    max_overspray_um : float, optional
        Soft limit on L_o [µm].
    u0 : array (3,), optional
        Start inputs; default the advice for the target on the nominal model.
    overrides : dict, optional
        Scenario overrides.
    truth : str
        The virtual printer's truth generator, ``"model"`` (the first, which tuned the
        twin and the controller) or ``"alt"`` (the second, structurally different one:
        evaluation only).
    vial_fill_ml : float, optional
        The vial fill the twin is told (weighed at the refill, as ``ajtwin machine
        maintain --vial-refilled``); default the scenario's initial fill — the operator
        knows what was put in, not what evaporates later.
    job : ajtwin.job.Job, optional
        A job print: the printer runs this program (read with its speeds, e.g. per layer),
        looped to the print's length (:class:`~ajtwin.simulation.stepper.SteppedPrinter`);
        every strategy sees what its camera sees, the MPCs read the job's seconds ahead.
    camera : ajtwin.simulation.job_print.CameraSettings, optional
        The job print's camera (default ``data/virtual_camera.toml``).
    repeat_pitch_mm : (float, float), optional
        Loop the job as parts side by side at this pitch [mm].
    camera_horizon_s : float, optional
        The twin's camera horizon H (default: the rule of
        :func:`~ajtwin.estimation.print_time.camera_horizon_s` for the program and camera).
    controller_options : dict, optional
        More keywords of the strategy's class (e.g. PI's ``closed_loop_time_s``).
    """

    scenario: object
    seed: int
    target_um: float
    duration_min: float | None = None
    settings: ControlSettings | None = None
    limits: dict | None = None
    max_overspray_um: float | None = None
    u0: object = None
    overrides: dict | None = None
    truth: str = "model"
    vial_fill_ml: float | None = None
    job: object = None
    camera: object = None
    repeat_pitch_mm: object = None
    camera_horizon_s: float | None = None
    controller_options: dict | None = None


def simulate_strategy(plan: ClosedLoopPlan, strategy: str, progress=None) -> ClosedLoopRun:
    """Run one strategy in closed loop with the virtual printer
    (:func:`ajtwin.apps.planning.closed_loop.run_closed_loop`).

    Parameters
    ----------
    plan : ClosedLoopPlan
        The print, the target and the limits.
    strategy : str
        One of :data:`~ajtwin.apps.planning.closed_loop.STRATEGIES`.
    progress : callable(int), optional
    """
    p = plan
    scenario, seed, target_um, duration_min = p.scenario, p.seed, p.target_um, p.duration_min
    settings, limits, max_overspray_um, u0 = p.settings, p.limits, p.max_overspray_um, p.u0
    overrides, truth, vial_fill_ml, job, camera = (
        p.overrides,
        p.truth,
        p.vial_fill_ml,
        p.job,
        p.camera,
    )
    repeat_pitch_mm, camera_horizon_s = p.repeat_pitch_mm, p.camera_horizon_s
    controller_options = p.controller_options
    if strategy not in STRATEGY_CLASSES:
        raise ValueError(f"unknown strategy {strategy!r}; choose from {', '.join(STRATEGIES)}")
    settings = settings or ControlSettings.load()
    target_um = check_target(target_um)
    bounds = effective_bounds(limits)
    if u0 is None:
        u0, _ = start_inputs(Twin.default(), target_um, limits, max_overspray_um)
    u0 = np.asarray(u0, dtype=float)
    printer = SteppedPrinter(
        resolve_scenario(scenario),
        seed,
        duration_min,
        overrides,
        truth,
        job=job,
        camera=camera,
        repeat_pitch_mm=repeat_pitch_mm,
    )
    if vial_fill_ml is None:
        vial_fill_ml = float(printer.scenario.config["initial"]["vial_volume_mL"])
    twin = Twin.default(vial_fill_ml=float(vial_fill_ml))
    setup = job_print_setup(printer, camera_horizon_s)
    if strategy == "mpc_twin":
        context = setup.get("print_context")
        setup["stream"] = TwinStream("virtual", twin, asynchronous=False, print_context=context)
    controller = STRATEGY_CLASSES[strategy](
        twin=twin,
        settings=settings,
        bounds=bounds,
        u0=u0,
        target=target_um,
        limits=limits,
        max_overspray_um=max_overspray_um,
        **setup,
        **(controller_options or {}),
    )
    return run_closed_loop(
        printer,
        controller,
        strategy=strategy,
        target_um=target_um,
        u0=u0,
        settings=settings,
        bounds=bounds,
        seed=seed,
        truth=truth,
        vial_fill_ml=vial_fill_ml,
        progress=progress,
    )


def job_print_setup(printer, camera_horizon_s: float | None = None) -> dict:
    """What the strategies know of a virtual job print before it starts (empty without a
    job): the job as printed (``job``), the twin's :class:`PrintContext` (``print_context``:
    the camera's horizon H for this program and camera, its mode, the job) and the camera's
    median delay t − τ over the program (``camera_delay_s``: PI's dead time; the print's
    length for an inspection pass, 0 at the nozzle)."""
    plan = getattr(printer, "plan", None)
    if plan is None:
        return {}
    camera = plan.camera.meta()
    horizon = camera_horizon_s
    if horizon is None:
        horizon = print_time.camera_horizon_s(camera, plan.job, plan.n_print)
    delay = 0.0
    if camera["mode"] == "trailing":
        delays = print_time.trailing_delays(plan.job, camera["offset_mm"], plan.n_print)
        delay = float(np.median(delays)) if delays.size else float(plan.n_print)
    elif camera["mode"] == "inspection":
        delay = float(plan.n_print)
    process = plan.program_meta.get("process_speed_mm_s")
    context = PrintContext(
        float(horizon), camera["mode"], plan.job, None if process is None else float(process)
    )
    return {
        "job": plan.job,
        "print_context": context,
        "camera_delay_s": delay,
        "camera_mode": camera["mode"],
    }
