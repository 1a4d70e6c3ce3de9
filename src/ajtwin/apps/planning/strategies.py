"""Control strategies for linewidth: the inputs held (open loop), a PI loop on the measured
linewidth, and the MPC on the nominal model — each sees only what a real controller
would (the reported inputs and the measured outputs of the last period) and issues the
next command (:class:`Decision`). All start from the same inputs: the advice for the
target on the nominal model (:func:`start_inputs`). The MPC on the streaming twin is the
engine's (:class:`ajtwin.apps.planning.twin_control.MPCTwin`).

``open_loop``
    the start inputs, held for the whole print;
``pi``
    a PI loop on the period-mean of measured L_w acting on Q_c (the measurement-feedback
    baseline; SIMC tuning from the nominal model's static gain, ``data/control.toml``);
``mpc_nominal``
    the MPC on the nominal model without the twin's state updates: the twin's initial fit
    over the first samples, then propagated open loop (θ = 0) under its own commands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ajtwin import units
from ajtwin.apps.planning.advice import advise, effective_bounds
from ajtwin.apps.planning.job_preview import JobPreview
from ajtwin.apps.planning.mpc import (
    MPC,
    TargetError,
    check_target,
    reachable_linewidth,
    steady_linewidths,
)
from ajtwin.estimation.twin import predict
from ajtwin.model.droplet_dynamics import next_response
from ajtwin.model.limits import StateLimits


def nominal_state(twin, u):
    """The nominal model's state at inputs u: d_a 3.5 µm, a full 1 mL vial, clean, φ_A steady."""
    phi = float(twin.model.steady_aerosol_fraction(np.asarray(u, dtype=float), 1.0))
    mean = np.array([3.5, 1.0, 0.0, 0.0, phi])
    c = twin.config
    cov = np.diag(
        [
            0.15**2,
            c.vial_fill_std_ml**2,
            c.tube_prior_std_um**2,
            c.nozzle_prior_std_um**2,
            (0.05 * phi) ** 2,
        ]
    )
    return mean, cov


def start_inputs(twin, target_um, limits=None, max_overspray_um=None):
    """The recipe every strategy starts from: ``ajtwin advise`` for the target on the nominal
    model's state (what an operator sets from the datasheet). Raises :class:`TargetError`
    with the reachable range when the target cannot be reached."""
    bounds = effective_bounds(limits)
    u_ref = np.array([375.0, 23.0, 50.0])
    mean, cov = nominal_state(twin, u_ref)
    reach = reachable_linewidth(twin, mean, cov, bounds)
    check_target(target_um, reach)
    advice = advise(
        twin,
        mean,
        cov,
        u_ref,
        float(target_um),
        max_overspray_um=max_overspray_um,
        limits=limits,
    )
    if not advice.reachable:
        raise TargetError(
            f"target linewidth {target_um:g} µm: {advice.message}; "
            f"reachable {reach[0]:.1f}–{reach[1]:.1f} µm"
        )
    return advice.inputs, reach


@dataclass
class Decision:
    """A controller's decision for the next period.

    Attributes
    ----------
    command : array (3,)
        Inputs to set [mA, sccm, sccm].
    status : str
        ``act``, ``hold``, ``warm-up`` or ``stop`` (latched: the ink ran low).
    reason : str
    solve_s : float
        CPU seconds of the MPC solve (NaN: none).
    predicted_linewidth_um, predicted_linewidth_std_um : float
        The MPC's prediction at the horizon's end.
    step_scale : float
        Fraction of the rate limit allowed (< 1 when L_w is uncertain).
    solve_wall_s : float
        Wall-clock seconds of the MPC solve (NaN: none).
    """

    command: np.ndarray
    status: str = "act"  # act | hold | warm-up | stop (latched: the ink ran low)
    reason: str = ""
    solve_s: float = float("nan")
    predicted_linewidth_um: float = float("nan")
    predicted_linewidth_std_um: float = float("nan")
    step_scale: float = 1.0
    solve_wall_s: float = float("nan")


class OpenLoop:
    """The start inputs, held for the whole print (the baseline without feedback)."""

    name = "open_loop"

    def __init__(self, **_):
        pass

    def observe(self, chunk):
        """Nothing to learn from a period's data."""
        pass

    def decide(self, t, u):
        """Hold the inputs."""
        return Decision(u.copy(), "hold", "open loop: inputs fixed at the start")


class PIController:
    """PI on the period-mean of measured L_w, acting on Q_c (SIMC tuning).

    SIMC (Skogestad 2003) for K e^{−θs}/(τ₁ s + 1): K the nominal model's static gain
    dL_w/dQ_c at the start inputs, τ₁ φ_A's head-space time constant, θ half a period plus
    a share of the camera's delay; K_p = τ₁ / (K (τ_c + θ)), T_i = min(τ₁, 4 (τ_c + θ)).

    Parameters
    ----------
    camera_delay_s : float
        How late the camera sees a trace after it was printed (a job print's camera: the
        program's median delay; 0 at the nozzle).
    camera_mode : str, optional
        A job print's camera mode: τ_c and the share of the delay from ``[pi.job_print]``
        of ``control.toml`` (:meth:`ControlSettings.pi_tuning`); None: a straight line.
    closed_loop_time_s, delay_fraction : float, optional
        Override the settings' (the tuning study's grid).
    """

    name = "pi"

    def __init__(
        self,
        twin,
        settings,
        bounds,
        u0,
        target,
        camera_delay_s: float = 0.0,
        camera_mode: str | None = None,
        closed_loop_time_s: float | None = None,
        delay_fraction: float | None = None,
        **_,
    ):
        self.settings = settings
        self.bounds = bounds
        self.target = target
        self.u0 = np.asarray(u0, dtype=float)
        mean, cov = nominal_state(twin, u0)
        # static gain dL_w/dQ_c of the nominal model at the start inputs [µm/sccm]
        dq = 0.5
        u_hi, u_lo = self.u0.copy(), self.u0.copy()
        u_hi[1] += dq
        u_lo[1] -= dq
        lw = np.asarray(steady_linewidths(twin, mean, cov, np.stack([u_hi, u_lo]), 60))
        self.gain = float(lw[0] - lw[1]) / (2 * dq)
        # SIMC (Skogestad 2003) for K e^{-θs}/(τ1 s + 1): τ1 = φ_A's head-space time
        # constant (V_v − V_l)/Q_c, θ = half a period (sample and hold)
        vial_ml = 1.0
        head_ml = float(units.m3_to_ml(twin.model.params.vial_volume)) - vial_ml
        tau1 = head_ml / float(units.sccm_to_ml_per_s(self.u0[1]))
        tau_c, fraction = settings.pi_tuning(camera_mode)
        tau_c = tau_c if closed_loop_time_s is None else float(closed_loop_time_s)
        fraction = fraction if delay_fraction is None else float(delay_fraction)
        theta = settings.period_s / 2.0 + fraction * float(camera_delay_s)
        self.tuning = {"closed_loop_time_s": tau_c, "dead_time_s": theta}
        self.kp = tau1 / (self.gain * (tau_c + theta))
        self.ti = min(tau1, 4.0 * (tau_c + theta))
        self.integral = 0.0
        self.measured = []

    def observe(self, chunk):
        """Keep the period's measured linewidth."""
        self.measured.append(chunk.outputs[:, 0])

    def decide(self, t, u):
        """Q_c from the PI law on the period-mean linewidth error (anti-windup at the limits)."""
        y = np.concatenate(self.measured) if self.measured else np.array([])
        self.measured = []
        if not np.isfinite(y).any():
            return Decision(u.copy(), "hold", "no linewidth measured in the last period")
        error = self.target - float(np.nanmean(y))
        dt = self.settings.period_s
        lo, hi = self.bounds[1]
        trial = self.integral + self.kp * dt / self.ti * error
        q_c = self.u0[1] + self.kp * error + trial
        # conditional integration (anti-windup): keep the integral when saturated outward
        if lo < q_c < hi or (q_c >= hi and error < 0) or (q_c <= lo and error > 0):
            self.integral = trial
        q_c = self.u0[1] + self.kp * error + self.integral
        command = u.copy()
        command[1] = q_c
        return Decision(command, "act")


class MPCStrategy:
    """The MPC's part of a strategy: the solver, the uncertainty rule on the step, the
    physical state range, the job's seconds ahead; subclasses say where the state comes
    from.

    ``job`` (the job the machine prints, looped as it runs): the MPC's cost weighs each
    second ahead by the length printed then and reads the line at its planned speed
    (:class:`~ajtwin.apps.planning.job_preview.JobPreview`); None: a straight line at ν_ref.
    """

    def __init__(
        self,
        twin,
        settings,
        bounds,
        u0,
        target,
        limits=None,
        max_overspray_um=None,
        job=None,
        **_,
    ):
        self.twin = twin
        self.settings = settings
        self.target = target
        self.mpc = MPC(twin, settings, limits, max_overspray_um)
        self.mpc.warm_up()
        self.state_limits = StateLimits.load(twin.model.params)
        self.job = job
        self.preview = (
            None
            if job is None
            else JobPreview(job, settings.horizon_s, getattr(twin, "speed_law", None))
        )

    def line_ahead(self, t) -> np.ndarray | None:
        """The job's seconds t … t + H − 1 as the cost weighs them (None without a job)."""
        return None if self.preview is None else self.preview.line(t)

    def _act(self, mean, cov, theta, u, sigma_lw, notes="", t=0.0):
        s = self.settings
        scale = 1.0
        if sigma_lw > s.uncertainty_sigma_um:
            scale = s.uncertainty_sigma_um / sigma_lw
        sol = self.mpc.solve(
            mean, cov, theta, u, self.target, step_scale=scale, line=self.line_ahead(t)
        )
        reason = notes
        if scale < 1:
            reason = (
                f"L_w uncertain (1σ {sigma_lw:.2f} µm > {s.uncertainty_sigma_um:g}): "
                f"step bounded to {scale:.0%} of the rate limit"
            )
        return Decision(
            sol.command,
            "act",
            reason,
            sol.solve_s,
            float(sol.predicted_linewidth[-1]),
            float(sol.predicted_linewidth_std[-1]),
            scale,
            sol.solve_wall_s,
        )


class MPCNominal(MPCStrategy):
    """MPC on the nominal model: the initial fit, then open-loop prediction (θ = 0)."""

    name = "mpc_nominal"

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.mean = self.cov = None
        self.first_u, self.first_y = [], []
        self.theta = np.zeros(5)
        self.response = None  # input response r (input_following variants): equilibrium first

    def observe(self, chunk):
        """The initial fit once enough samples arrived, then the open-loop prediction under the
        inputs."""
        twin = self.twin
        if self.mean is None:
            self.first_u += list(chunk.inputs)
            self.first_y += list(chunk.outputs)
            if len(self.first_u) < twin.config.initial_samples:
                return
            fit = twin.initial_state(np.array(self.first_u), np.array(self.first_y))
            self.mean, self.cov = np.asarray(fit.mean), np.asarray(fit.covariance)
            inputs = np.array(self.first_u)  # the fit is the state at the first sample
        else:
            inputs = chunk.inputs
        # the twin's own model (transition variant), as the MPC plans with; a variant that
        # follows the inputs reads the response column, filtered as the forecast does
        if hasattr(twin, "model_inputs"):
            inputs = twin.model_inputs(inputs, self.response)
        for u in inputs:
            self.mean, self.cov = (
                np.asarray(a)
                for a in predict(
                    twin.spec, self.mean, self.cov, u, self.theta, twin.process_cov, twin.functions
                )
            )
        if inputs.shape[1] > 3:
            last = inputs[-1]
            self.response = next_response(float(last[3]), last[:3], twin.droplet_dynamics)

    def decide(self, t, u):
        """The MPC's command from the propagated nominal state (wait for the initial fit)."""
        if self.mean is None:
            return Decision(u.copy(), "warm-up", "waiting for the initial fit")
        g = self.twin.model.coefficient_matrix[0]
        sigma = float(np.sqrt(max(linewidth_variance(g, self.mean, self.cov), 0.0)))
        return self._act(self.mean, self.cov, self.theta, u, sigma, t=t)


def linewidth_variance(coefficients, mean, cov):
    """Var L_w = G P Gᵀ, G = ∂L_w/∂x of the output polynomial (d_a, φ_A, ΔR_N terms)."""
    c = np.asarray(coefficients, dtype=float)
    n = float(mean[3])
    g = np.array([c[0], 0.0, 0.0, c[2] + 2 * c[3] * n + 3 * c[4] * n**2, c[1]])
    return float(g @ np.asarray(cov) @ g)
