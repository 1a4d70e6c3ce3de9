"""The MPC on the streaming twin, and a strategy run in closed loop with the virtual printer.

:class:`MPCTwin` feeds every sample to the streaming twin
(:class:`ajtwin.engine.stream.TwinStream`: the batch twin's EKF step, EM over a moving
window, the anomaly detectors) and starts the MPC from its filtered state, covariance
and θ, under the safety rules of :mod:`ajtwin.apps.planning.mpc`; the live control link
(:mod:`ajtwin.live.control_link`) runs the same class beside a real machine.
:func:`simulate_strategy` runs any of the four strategies (open loop, PI, the MPC on the
nominal model, the MPC on the twin) in closed loop with the virtual printer.

Examples
--------
>>> run = simulate_strategy("exp1", 1, "pi", 65.0, duration_min=10)   # doctest: +SKIP
>>> run.metrics["rms_error_um"]                                      # doctest: +SKIP
"""

from __future__ import annotations

import functools

import numpy as np

from ajtwin.apps.detection.causes import CAUSES
from ajtwin.apps.planning.advice import effective_bounds
from ajtwin.apps.planning.closed_loop import (
    STRATEGIES,
    ClosedLoopRun,
    resolve_scenario,
    run_closed_loop,
)
from ajtwin.apps.planning.mpc import (
    ControlSettings,
    check_target,
    ink_supply_status,
    mismatch_reasons,
    vial_level_from_material_flow,
)
from ajtwin.apps.planning.strategies import (
    Decision,
    MPCNominal,
    MPCStrategy,
    OpenLoop,
    PIController,
    linewidth_variance,
    start_inputs,
)
from ajtwin.engine.stream import TwinStream
from ajtwin.estimation import print_time
from ajtwin.estimation.print_time import PrintContext
from ajtwin.estimation.samples import Sample
from ajtwin.estimation.twin import Twin
from ajtwin.simulation.stepper import SteppedPrinter


class MPCTwin(MPCStrategy):
    """MPC on the twin: the streaming twin fed every sample, safety rules applied.

    ``print_context`` (a job print): the twin files the camera's frames at their print times
    and the MPC plans from its provisional state now; ``stream``/``feed``: a live engine's
    stream of the machine and the engine's feed (default: the controller's own stream).

    Besides the safety rules of :mod:`ajtwin.apps.planning.mpc` it watches the ink supply
    (:func:`ajtwin.apps.planning.mpc.ink_supply_status`: its own ink balance from the measured
    Q_m and the twin's vial observer). A vial running dry is not controllable with these
    inputs, so on ``stop`` it latches: the inputs in force are held for the rest of the
    print (reason ``ink_low: …``) — a refill is maintenance and a new print.
    """

    name = "mpc_twin"

    def __init__(
        self,
        *args,
        print_context: PrintContext | None = None,
        stream: TwinStream | None = None,
        feed=None,
        **kwargs,
    ):
        super().__init__(*args, **kwargs)
        # a job print: the camera's frames filed at their print times through the engine's
        # delay line; the state now is the stream's provisional one. A live engine's stream
        # (``stream``, fed through ``feed``: the engine stores and publishes each step) or
        # the controller's own.
        self.stream = stream or TwinStream(
            "virtual", self.twin, asynchronous=False, print_context=print_context
        )
        # its own stream re-runs the provisional steps once per period, when it plans
        self._own_stream = feed is None
        self._feed = feed or functools.partial(self.stream.feed, provisional=False)
        self.holding = False
        # the ink balance starts from the fill the twin was told (weighed at the refill)
        self.vial_fill_ml = float(self.twin.config.vial_fill_ml)
        calibration = getattr(self.twin, "calibration", None)
        self.material_flow_gain = (
            float(calibration.material_flow_gain) if calibration is not None else 1.0
        )
        self.material_flow: list[np.ndarray] = []
        self.ink = None  # the latest InkSupply
        self.ink_stop: str | None = None  # the latched reason, once stopped

    def observe(self, chunk):
        """Feed every sample of the period to the streaming twin (with a job print's shutter,
        platen speed and the camera's print times when the chunk has them)."""
        job = getattr(chunk, "printed_at_s", None) is not None
        for k, (t, u, y) in enumerate(zip(chunk.time_s, chunk.inputs, chunk.outputs)):
            extra = {}
            if job:
                extra = dict(
                    shutter_open=float(chunk.shutter_open[k]),
                    platen_speed_mm_s=float(chunk.platen_speed_mm_s[k]),
                    printed_at_s=float(chunk.printed_at_s[k]),
                )
            self._feed(Sample(float(t), u, y, **extra))
        if self._own_stream:
            self.stream.refresh_provisional()
        self.material_flow.append(np.asarray(chunk.outputs, dtype=float)[:, 4])

    def state_now(self):
        """(mean, cov) the MPC plans from: the committed step's, or on a job print the
        provisional state of the newest row (the steps after the last final one re-run with
        what the camera has filed so far); None before the twin has a state."""
        core = self.stream.core
        provisional = self.stream.provisional
        if provisional is not None and (
            core.n_committed == 0 or provisional[0] > core.last_time_committed
        ):
            return provisional[1], provisional[2]
        if core.n_committed == 0:
            return None
        return core.last_mean, core.last_cov

    def ink_supply(self):
        """The ink supply now (:func:`ajtwin.apps.planning.mpc.ink_supply_status`)."""
        q = np.concatenate(self.material_flow) if self.material_flow else np.array([])
        balance = vial_level_from_material_flow(
            q, self.vial_fill_ml, self.material_flow_gain, self.twin.model.params
        )
        observer = getattr(getattr(self.stream, "detector", None), "vial_status", None)
        self.ink = ink_supply_status(balance, observer, self.settings)
        return self.ink

    def safety(self, mean=None):
        """Reasons not to act now (empty: act). ``mean``: the state the MPC plans from
        (default the committed one); before the first final step of a job print only its
        physical range can be checked (the detectors see steps H s after they are printed)."""
        core = self.stream.core
        if core.n_committed == 0:
            if mean is None:
                return ["the twin has not started (initial fit pending)"]
            return self.state_limits.violations(np.asarray(mean))
        mean = core.last_mean if mean is None else np.asarray(mean)
        window = self.settings.nis_window_s
        reasons = mismatch_reasons(
            mean,
            core.recent("nis", window),
            core.recent("n_measured", window),
            limits=self.state_limits,
            settings=self.settings,
            status=getattr(self.stream, "mismatch_status", None),
        )
        status, cause = self.stream.status()
        # 'ink running out' is the ink rule's (ink_supply): it keeps steering while the
        # vial is inside H's fit and stops for good before it leaves it — no on/off holds
        if status == "alarm" and cause not in (*self.settings.actionable_causes, "ink_low"):
            reasons.append(f"alarm the controller cannot act on: {CAUSES.get(cause, cause)}")
        return reasons

    def decide(self, t, u):
        """Stop for the ink, hold for a safety reason, else the MPC's command from the twin's
        state."""
        if self.ink_stop:
            # latched: nothing the controller does brings the ink back
            return Decision(u.copy(), "stop", self.ink_stop)
        state = self.state_now()
        if state is None:
            return Decision(u.copy(), "warm-up", "waiting for the twin's initial fit")
        mean, cov = state
        ink = self.ink_supply()
        if ink.status == "stop":
            self.ink_stop = f"{ink.reason}; inputs held for the rest of the print (refill)"
            self.mpc.reset()
            return Decision(u.copy(), "stop", self.ink_stop)
        reasons = self.safety(mean)
        if reasons:
            self.mpc.reset()
            return Decision(u.copy(), "hold", "; ".join(reasons))
        sigma = float(
            np.sqrt(max(linewidth_variance(self.twin.model.coefficient_matrix[0], mean, cov), 0.0))
        )
        decision = self._act(mean, cov, self.stream.theta, u, sigma, t=t)
        if ink.status == "low":
            decision.reason = "; ".join(r for r in (decision.reason, ink.reason) if r)
        return decision


STRATEGY_CLASSES = {
    "open_loop": OpenLoop,
    "pi": PIController,
    "mpc_nominal": MPCNominal,
    "mpc_twin": MPCTwin,
}


def simulate_strategy(
    scenario,
    seed: int,
    strategy: str,
    target_um: float,
    *,
    duration_min=None,
    settings: ControlSettings | None = None,
    limits: dict | None = None,
    max_overspray_um=None,
    u0=None,
    overrides=None,
    progress=None,
    truth: str = "model",
    vial_fill_ml: float | None = None,
    job=None,
    camera=None,
    repeat_pitch_mm=None,
    camera_horizon_s: float | None = None,
    controller_options: dict | None = None,
) -> ClosedLoopRun:
    """Run one strategy in closed loop with the virtual printer
    (:func:`ajtwin.apps.planning.closed_loop.run_closed_loop`).

    Parameters
    ----------
    scenario : str or Path
        A packaged scenario, one of the controller's own (``slow_clog``) or a file.
    seed : int
        The print's seed.
    strategy : str
        One of :data:`~ajtwin.apps.planning.closed_loop.STRATEGIES`.
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
    progress : callable(int), optional
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
    controller = STRATEGY_CLASSES[strategy](
        twin=twin,
        settings=settings,
        bounds=bounds,
        u0=u0,
        target=target_um,
        limits=limits,
        max_overspray_um=max_overspray_um,
        **job_print_setup(printer, camera_horizon_s),
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
