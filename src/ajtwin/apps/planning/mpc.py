"""Model-predictive control of linewidth from the twin's state (closed loop).

From the twin's current state estimate (mean x̂, covariance P) and θ, choose the atomizer
current I_A, carrier flow Q_c and sheath flow Q_s over a horizon so that the line holds a
target width while overspray stays low and the moves stay smooth.

The plan
--------
Move blocking: ``M`` piecewise-constant moves v_0 … v_{M−1} (3 inputs each) start at
``move_starts_s`` and hold to the end of the horizon H (default 60 s, moves at 0/10/30 s;
why: ``data/control.toml``). The model is the twin's own: the EKF prediction
(x̂ ← f_d(x̂, u; θ), P ← F P Fᵀ + Σ_ξ, :func:`ajtwin.apps.planning.forecast._forecast_scan`) runs
second by second over the horizon, giving L̂_w,k ± σ_k and L̂_o,k. The cost (all terms
dimensionless) is

    J = 1/H Σ_k [ w_t ((L̂_w,k − r)/tol)² + w_b max(0, (|L̂_w,k − r| + 2σ_k − tol)/tol)²
                  + w_o (L̂_o,k / L_o,ref)² + w_l max(0, L̂_o,k − L_o,max)² ]
        + w_m Σ_j ‖(v_j − v_{j−1}) / (ρ Δt_j)‖²

with v_{−1} the command in force, ρ the rate limits and Δt_j the time between moves.
The band term keeps L_w's 2σ band inside ±tol where the mean alone would not.

Constraints (hard): lo ≤ v_j ≤ hi (the machine's limits ∩ the validity range of H's fit,
:func:`ajtwin.apps.planning.advice.effective_bounds`) and |v_j − v_{j−1}| ≤ ρ Δt_j (rate limits).
Optimiser: SciPy SLSQP on inputs scaled to [0, 1], value and gradient from one jitted
``jax.value_and_grad``; warm-started from the previous plan shifted by one period.

Safety (:func:`safety_check`, :meth:`MPC.command`)
--------------------------------------------------
* every command is clipped to the limits and the rate limits, then asserted;
* no command (hold the one in force, say why) while the twin reports a model–machine
  mismatch (:func:`mismatch_reasons`) or an alarm that makes acting unsafe (``hold_causes``:
  a fault of the inputs, a model that does not fit, a deposit beyond the model's range; or
  ``hold_detectors``: raised by the filter's own consistency test, whatever its cause);
  through any other alarm it keeps acting and says so;
* a bounded step when L_w's 1σ exceeds ``uncertainty_sigma_um``: the rate limits are
  scaled by σ_max/σ.

Examples
--------
Not run in the suite: the MPC's first solve compiles its horizon (~10-30 s).

>>> from ajtwin.estimation import Twin
>>> twin = Twin.default()
>>> mpc = MPC(twin)                                            # doctest: +SKIP
>>> x = np.array([3.5, 1.0, 0.0, 0.0, 4.6e-7]); P = np.diag([1e-2, 1e-4, 1e-8, 1e-4, 1e-16])
>>> sol = mpc.solve(x, P, np.zeros(5), np.array([375.0, 23.0, 50.0]), 70.0)  # doctest: +SKIP
>>> sol.command                                                # [mA, sccm, sccm]  # doctest: +SKIP
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy import optimize

from ajtwin._jax import jax, jnp
from ajtwin.apps.planning.advice import effective_bounds
from ajtwin.apps.planning.forecast import _forecast_scan
from ajtwin.config import load_toml
from ajtwin.estimation.vial import ink_volume_drawn_ml
from ajtwin.model import INPUT_NAMES
from ajtwin.model.droplet_dynamics import input_response

# --------------------------------------------------------------------------- #
# Settings
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class ControlSettings:
    """MPC tuning, rate limits, safety rules and the PI baseline (``data/control.toml``)."""

    period_s: int = 10
    horizon_s: int = 60
    move_starts_s: tuple = (0, 10, 30)
    tolerance_um: float = 2.0
    weight_tracking: float = 1.0
    weight_band: float = 4.0
    weight_overspray: float = 0.05
    overspray_scale_um: float = 10.0
    weight_move: float = 0.02
    weight_overspray_limit: float = 100.0
    max_linearisations: int = 2
    max_iterations: int = 30
    solver_tolerance: float = 1e-6
    rate_limits: tuple = (2.0, 0.1, 0.2)  # per second [mA/s, sccm/s, sccm/s]
    uncertainty_sigma_um: float = 1.0
    nis_window_s: int = 120
    nis_ratio_max: float = 3.0
    warmup_s: int = 60
    hold_causes: tuple = ("carrier_leak", "model_machine_mismatch", "nozzle_cleaning")
    hold_detectors: tuple = ("windowed NIS",)
    pi_closed_loop_time_s: float = 120.0
    # PI on a job print, per camera mode: closed-loop time and the share of the camera's
    # median delay taken as SIMC's dead time (tuned by `python -m ajtwin.studies.control tune-pi`)
    pi_job_closed_loop_time_s: tuple = ()  # ((mode, seconds), …)
    pi_job_delay_fraction: tuple = ()  # ((mode, fraction), …)
    ink_stop_vial_ml: float = 0.5
    ink_stop_lead_min: float = 10.0
    source: str = "defaults"

    @classmethod
    def load(cls, path: str | Path | None = None, **overrides) -> ControlSettings:
        """Settings from ``data/control.toml`` (or a user's file of the same form)."""
        source = "ajtwin/data/control.toml" if path is None else str(path)
        raw = load_toml(path, "data/control.toml", what="control settings")
        try:
            mpc, rates, safety, pi = raw["mpc"], raw["rate_limits"], raw["safety"], raw["pi"]
            ink = raw["ink"]
            values = dict(
                period_s=int(mpc["period_s"]),
                horizon_s=int(mpc["horizon_s"]),
                move_starts_s=tuple(int(v) for v in mpc["move_starts_s"]),
                tolerance_um=float(mpc["tolerance_um"]),
                weight_tracking=float(mpc["weight_tracking"]),
                weight_band=float(mpc["weight_band"]),
                weight_overspray=float(mpc["weight_overspray"]),
                overspray_scale_um=float(mpc["overspray_scale_um"]),
                weight_move=float(mpc["weight_move"]),
                weight_overspray_limit=float(mpc["weight_overspray_limit"]),
                max_linearisations=int(mpc["max_linearisations"]),
                max_iterations=int(mpc["max_iterations"]),
                solver_tolerance=float(mpc["solver_tolerance"]),
                rate_limits=tuple(float(rates[name]) for name in INPUT_NAMES),
                uncertainty_sigma_um=float(safety["uncertainty_sigma_um"]),
                nis_window_s=int(safety["nis_window_s"]),
                nis_ratio_max=float(safety["nis_ratio_max"]),
                warmup_s=int(safety["warmup_s"]),
                hold_causes=tuple(safety["hold_causes"]),
                hold_detectors=tuple(safety["hold_detectors"]),
                pi_closed_loop_time_s=float(pi["closed_loop_time_s"]),
                pi_job_closed_loop_time_s=tuple(
                    (str(k), float(v))
                    for k, v in pi.get("job_print", {}).get("closed_loop_time_s", {}).items()
                ),
                pi_job_delay_fraction=tuple(
                    (str(k), float(v))
                    for k, v in pi.get("job_print", {}).get("delay_fraction", {}).items()
                ),
                ink_stop_vial_ml=float(ink["stop_vial_ml"]),
                ink_stop_lead_min=float(ink["stop_lead_min"]),
            )
        except KeyError as exc:
            raise ValueError(f"{source}: missing key {exc}") from None
        settings = cls(**values, source=source)

        settings = replace(settings, **overrides)
        settings.validate()
        return settings

    def pi_tuning(self, camera_mode: str | None) -> tuple[float, float]:
        """PI's (closed-loop time [s], share of the camera's delay taken as dead time) for a
        print under a camera of ``camera_mode`` (None: a straight line, the camera at the
        nozzle: ``closed_loop_time_s``, no delay)."""
        if camera_mode is None:
            return self.pi_closed_loop_time_s, 1.0
        closed = dict(self.pi_job_closed_loop_time_s).get(camera_mode, self.pi_closed_loop_time_s)
        return float(closed), float(dict(self.pi_job_delay_fraction).get(camera_mode, 1.0))

    def validate(self) -> None:
        """Raise ValueError for inconsistent settings (move starts, horizon, limits)."""
        starts = self.move_starts_s
        if not starts or starts[0] != 0 or any(b <= a for a, b in zip(starts, starts[1:])):
            raise ValueError(f"move_starts_s must start at 0 and increase; got {starts}")
        if starts[-1] >= self.horizon_s:
            raise ValueError(
                f"the last move ({starts[-1]} s) must start inside the horizon ({self.horizon_s} s)"
            )
        if self.period_s < 1 or self.period_s > self.horizon_s:
            raise ValueError(f"period_s = {self.period_s} must be in [1, horizon_s]")
        if not all(r > 0 for r in self.rate_limits):
            raise ValueError(f"rate limits must be positive; got {self.rate_limits}")
        if not self.tolerance_um > 0:
            raise ValueError(f"tolerance_um must be > 0; got {self.tolerance_um}")
        if self.max_linearisations < 1 or self.max_iterations < 1:
            raise ValueError("max_linearisations and max_iterations must be ≥ 1")
        if not self.solver_tolerance > 0:
            raise ValueError(f"solver_tolerance must be > 0; got {self.solver_tolerance}")
        if not (np.isfinite(self.ink_stop_vial_ml) and self.ink_stop_vial_ml >= 0):
            raise ValueError(f"[ink] stop_vial_ml must be ≥ 0 mL; got {self.ink_stop_vial_ml}")
        for mode, value in (*self.pi_job_closed_loop_time_s, *self.pi_job_delay_fraction):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"[pi.job_print] {mode} = {value!r} must be a number >= 0")
        if not self.ink_stop_lead_min >= 0:
            raise ValueError(f"[ink] stop_lead_min must be ≥ 0; got {self.ink_stop_lead_min}")


# --------------------------------------------------------------------------- #
# Targets and the reachable range
# --------------------------------------------------------------------------- #


class TargetError(ValueError):
    """A target linewidth that is not a number, not positive or not reachable."""


def reachable_linewidth(twin, mean, cov, bounds, settle_s: int = 60, grid: int = 5):
    """Steady linewidth range [min, max] µm reachable with constant inputs inside ``bounds``.

    Each of grid³ constant input settings is forecast ``settle_s`` seconds from (mean, cov)
    with the twin's model and θ (the same EKF prediction as the forecast); the range is the
    least and largest L_w reached. L_w is monotone in each input over the admissible box
    (Q_c and I_A raise it through φ_A, Q_s narrows the line), so the extremes sit on its
    corners, which the grid contains.
    """
    axes = [np.linspace(lo, hi, grid) for lo, hi in bounds]
    settings = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    lw = np.asarray(steady_linewidths(twin, mean, cov, settings, settle_s))
    return float(lw.min()), float(lw.max())


def steady_linewidths(twin, mean, cov, settings, settle_s):
    """The linewidth [µm] ``settle_s`` seconds after each input setting, from the twin's state.

    Parameters
    ----------
    twin : Twin
    mean : array (5,), cov : array (5, 5)
        The state now (display units).
    settings : array (N, 3)
        Input settings [mA, sccm, sccm].
    settle_s : int
        Seconds held.

    Returns
    -------
    array (N,)
    """
    fn = _steady_fn(settle_s)
    return fn(
        twin.spec,
        jnp.asarray(mean, dtype=float),
        jnp.asarray(cov, dtype=float),
        jnp.asarray(settings, dtype=float),
        jnp.asarray(twin.theta, dtype=float),
        jnp.asarray(twin.process_cov),
        functions=getattr(twin, "functions", None),
    )


_STEADY_CACHE: dict = {}


def _steady_fn(settle_s: int):
    if settle_s not in _STEADY_CACHE:

        def run(spec, mean, cov, settings, theta, process_cov, functions=None):
            def one(u):
                inputs = model_inputs(jnp.broadcast_to(u, (settle_s, 3)), functions)
                _, _, y, _ = _forecast_scan(spec, mean, cov, inputs, theta, process_cov, functions)
                return y[-1, 0]

            return jax.vmap(one)(settings)

        _STEADY_CACHE[settle_s] = jax.jit(run, static_argnames=("functions",))
    return _STEADY_CACHE[settle_s]


def check_target(target_um, reachable: tuple[float, float] | None = None) -> float:
    """A valid target linewidth [µm] or a :class:`TargetError` naming the reachable range."""
    hint = ""
    if reachable is not None:
        hint = f"; reachable now: {reachable[0]:.1f}–{reachable[1]:.1f} µm"
    try:
        value = float(target_um)
    except (TypeError, ValueError):
        raise TargetError(f"target linewidth {target_um!r} is not a number{hint}") from None
    if not np.isfinite(value):
        raise TargetError(f"target linewidth {target_um!r} is not a finite number{hint}")
    if value <= 0:
        raise TargetError(f"target linewidth must be > 0 µm, got {value:g}{hint}")
    if reachable is not None and not (reachable[0] <= value <= reachable[1]):
        raise TargetError(
            f"target linewidth {value:g} µm is not reachable within the machine's limits from "
            f"the current state{hint} (ajtwin advise shows the closest settings)"
        )
    return value


# --------------------------------------------------------------------------- #
# Safety
# --------------------------------------------------------------------------- #


def mismatch_reasons(mean, nis=None, n_measured=None, *, limits=None, settings=None, status=None):
    """Why the twin does not describe the machine now (empty list: it does).

    Parameters
    ----------
    mean : (5,) current state estimate (display units)
    nis, n_measured : (W,) the last steps' NIS and measured-output counts, optional
    limits : ajtwin.model.limits.StateLimits, optional
    settings : ControlSettings
    status : object, optional
        A model–machine mismatch status from the machine's twin, when it has one: anything
        with ``mismatch`` (bool) and ``reason`` (str) attributes, or a (bool, str) pair.
        Taken as given when present; the checks below always run too.

    Returns
    -------
    list of str
        States outside the physical range (``model/limits.py``), a windowed mean NIS per
        measured output above ``nis_ratio_max`` over the last ``nis_window_s`` steps, and
        the given status's reason.
    """
    settings = settings or ControlSettings()
    reasons = []
    if status is not None:
        flag, why = (
            (status.mismatch, getattr(status, "reason", ""))
            if hasattr(status, "mismatch")
            else tuple(status)
        )
        if flag:
            reasons.append(f"the twin reports a model–machine mismatch: {why}".rstrip(": "))
    if limits is not None:
        reasons += limits.violations(mean)
    elif not np.all(np.isfinite(mean)):
        reasons.append("the state estimate is not finite")
    if nis is not None and n_measured is not None and len(nis):
        w = int(settings.nis_window_s)
        nis_w = np.asarray(nis, dtype=float)[-w:]
        n_w = np.asarray(n_measured, dtype=float)[-w:]
        if len(nis_w) >= w and n_w.sum() > 0:
            ratio = float(np.nansum(nis_w) / n_w.sum())
            if not ratio <= settings.nis_ratio_max:
                reasons.append(
                    f"windowed NIS {ratio:.1f} per measured output over the last {w} s "
                    f"(> {settings.nis_ratio_max:g}: the model no longer explains the data)"
                )
    return reasons


# --------------------------------------------------------------------------- #
# Ink supply: a vial running dry is not controllable with I_A, Q_c, Q_s
# --------------------------------------------------------------------------- #


def vial_level_from_material_flow(
    material_flow, fill_ml: float, material_flow_gain: float = 1.0, params=None, dt: float = 1.0
) -> float:
    """The controller's own ink balance: fill − Σ Q_m Δt / (g φ_m) [mL].

    The ink that left the vial as aerosol per the measured material flow (NaN samples
    count as nothing drawn). It sees only the aerosol draw — an unmodelled loss
    (evaporation, a leak) is the vial observer's to find — so it is an upper bound on
    the level: when even this is below the stop level, the vial is low.
    """

    if not (np.isfinite(fill_ml) and fill_ml >= 0):
        raise ValueError(f"vial fill = {fill_ml!r} mL must be a non-negative number")
    drawn = ink_volume_drawn_ml(material_flow, material_flow_gain, params, dt)
    return float(fill_ml) - drawn


@dataclass
class InkSupply:
    """What the controller concludes about the ink (see :func:`ink_supply_status`)."""

    status: str  # ok | low (warn, keep steering) | stop (hold for the rest of the print)
    reason: str
    balance_ml: float
    observer_ml: float = float("nan")
    minutes_to_low: float = float("inf")


def ink_supply_status(balance_ml: float, observer=None, settings=None) -> InkSupply:
    """Whether the vial still feeds the line in the range the model was fitted on.

    Parameters
    ----------
    balance_ml : the controller's ink balance (:func:`vial_level_from_material_flow`)
    observer : ajtwin.estimation.vial.VialStatus, optional
        The vial observer's latest status (level, projected minutes to its low level,
        the latched ``running_low`` flag).
    settings : ControlSettings (its ``[ink]`` table)

    Returns
    -------
    InkSupply
        ``stop`` when the balance or the observer's level is below ``stop_vial_ml``
        (the low end of H's fit: below it the model the MPC plans with extrapolates, and
        an empty vial gives no aerosol at any current or flow), or the observer projects
        reaching its low level within ``stop_lead_min``; ``low`` when the observer says
        'running low' earlier than that (refill soon; the model still holds, so keep
        steering); ``ok`` otherwise.
    """
    s = settings or ControlSettings()
    stop_ml = s.ink_stop_vial_ml
    if np.isfinite(balance_ml) and balance_ml < stop_ml:
        return InkSupply(
            "stop",
            f"ink_low: ink balance {balance_ml:.3f} mL < {stop_ml:g} mL (fill − aerosol drawn)",
            float(balance_ml),
        )
    if observer is None:
        return InkSupply("ok", "", float(balance_ml))
    level, minutes = float(observer.vial_ml), float(observer.minutes_to_low)
    found = dict(balance_ml=float(balance_ml), observer_ml=level, minutes_to_low=minutes)
    if level < stop_ml:
        why = f"ink_low: vial observer {level:.3f} ± {observer.vial_std_ml:.3f} mL < {stop_ml:g} mL"
        return InkSupply("stop", why, **found)
    if observer.running_low and minutes <= s.ink_stop_lead_min:
        why = (
            f"ink_low: vial observer projects {level:.3f} mL to reach its low level in "
            f"{minutes:.0f} min (≤ {s.ink_stop_lead_min:g}; "
            f"loss {observer.loss_rate_ml_per_h:.2f} mL/h)"
        )
        return InkSupply("stop", why, **found)
    if observer.running_low:
        why = (
            f"ink running low: vial observer {level:.3f} mL, ~{minutes:.0f} min to its "
            "low level; refill"
        )
        return InkSupply("low", why, **found)
    return InkSupply("ok", "", **found)


def clip_command(u, u_prev, bounds, max_step):
    """Clip a command into the limits and within ``max_step`` of ``u_prev``; asserted.

    When ``u_prev`` lies outside the limits (an operator's setting) so far that no step of
    ``max_step`` reaches them, the command moves towards them by ``max_step``. A
    non-finite command holds ``u_prev``.
    """
    lo = np.array([b[0] for b in bounds], dtype=float)
    hi = np.array([b[1] for b in bounds], dtype=float)
    u = np.asarray(u, dtype=float)
    u_prev = np.asarray(u_prev, dtype=float)
    max_step = np.asarray(max_step, dtype=float)
    if not np.all(np.isfinite(u)):
        u = u_prev.copy()
    low = np.maximum(lo, u_prev - max_step)
    high = np.minimum(hi, u_prev + max_step)
    reachable = low <= high
    # out of reach: the end of the rate-limited window nearest the box
    toward = np.where(u_prev > hi, u_prev - max_step, u_prev + max_step)
    out = np.where(reachable, np.clip(u, low, np.maximum(low, high)), toward)
    assert np.all(np.abs(out - u_prev) <= max_step * (1 + 1e-12) + 1e-12), (out, u_prev)
    assert np.all(~reachable | ((out >= lo) & (out <= hi))), (out, lo, hi)
    return out


# --------------------------------------------------------------------------- #
# The MPC
# --------------------------------------------------------------------------- #


@dataclass
class MPCSolution:
    """The MPC's answer at one period.

    Attributes
    ----------
    command : array (3,)
        The input to apply now [mA, sccm, sccm].
    plan : array (M, 3)
        The planned moves.
    predicted_linewidth, predicted_linewidth_std, predicted_overspray : array (H,)
        L̂_w ± σ and L̂_o over the horizon under the plan [µm].
    cost : float
    solve_s : float
        CPU seconds of the solve (process time, every thread of the process).
    solve_wall_s : float
        Wall-clock seconds of the solve (what a real-time loop waits; longer on a loaded
        machine).
    """

    command: np.ndarray  # (3,) the input to apply now [mA, sccm, sccm]
    plan: np.ndarray  # (M, 3) the planned moves
    predicted_linewidth: np.ndarray  # (H,) L̂_w over the horizon under the plan [µm]
    predicted_linewidth_std: np.ndarray  # (H,)
    predicted_overspray: np.ndarray  # (H,)
    cost: float
    solve_s: float  # CPU seconds of the solve (process time)
    iterations: int
    success: bool
    message: str = ""
    step_scale: float = 1.0  # < 1 when the step was bounded for uncertainty
    notes: list = field(default_factory=list)
    solve_wall_s: float = float("nan")  # wall-clock seconds of the solve


class _PlanArrays(NamedTuple):
    """The static shape of a plan as arrays (a pytree: one compilation for every MPC)."""

    lo: jnp.ndarray  # (3,) lower input limits
    span: jnp.ndarray  # (3,) upper − lower
    block_index: jnp.ndarray  # (H,) which move holds at each second of the horizon
    rates: jnp.ndarray  # (3,) rate limits per second
    gaps: jnp.ndarray  # (M,) seconds between a move and the one before it
    weights: jnp.ndarray  # (7,) w_t, w_b, w_o, L_o,ref, w_m, w_l, tol


def model_inputs(inputs, functions=None):
    """Inputs (H, 3) as the twin's transition reads them (jit-able).

    A transition variant that follows the inputs (``input_following``,
    :mod:`ajtwin.model.droplet_dynamics`) reads a 4th column, the droplet size's input
    response r; it is filtered here from the plan as :func:`augment_inputs` does, starting
    at its equilibrium with the first input (as :func:`ajtwin.apps.planning.forecast.forecast`).
    Any other variant reads the three inputs unchanged.
    """

    dynamics = getattr(getattr(functions, "step", None), "dynamics", None)
    if dynamics is None or not dynamics.follows_inputs:
        return inputs
    # Δt = 1 s, the forecast's step
    return jnp.concatenate([inputs, input_response(inputs, dynamics)[:, None]], axis=1)


def plan_trajectory(z, plan, spec, mean, cov, theta, process_cov, functions=None):
    """Moves (M, 3) from scaled z (3M,), and over the horizon outputs (H, 5), variances (H, 5).

    ``functions``: the twin's model (discretisation, transition variant; ``twin.functions``),
    the one its θ was learned on; None = the paper's Euler step.
    """
    n_moves = plan.gaps.shape[0]
    moves = plan.lo + z.reshape(n_moves, 3) * plan.span
    inputs = model_inputs(moves[plan.block_index], functions)
    _, _, y, var = _forecast_scan(spec, mean, cov, inputs, theta, process_cov, functions)
    return moves, y, var


def plan_outputs(z, plan, spec, mean, cov, theta, process_cov, functions=None):
    """[L̂_w (H,), L̂_o (H,), var L_w (H,)] stacked: what the cost needs of the model."""
    _, y, var = plan_trajectory(z, plan, spec, mean, cov, theta, process_cov, functions)
    return jnp.concatenate([y[:, 0], y[:, 1], var[:, 0]])


def plan_cost(z, outputs, plan, u_prev, target, max_overspray, line):
    """The cost J (module docstring) of moves z given the model's outputs over H.

    ``line`` (H, 3): per second of the horizon the printed length relative to a second at
    ν_ref (ℓ_k; 0 with the shutter closed: the width there costs nothing) and the speed
    law's factors f_w, f_o of the line printed then (:class:`ajtwin.apps.planning.job_preview.
    JobPreview`); ones without a job.
    """
    w_t, w_b, w_o, lo_ref, w_m, w_l, tol = (plan.weights[i] for i in range(7))
    h = plan.block_index.shape[0]
    n_moves = plan.gaps.shape[0]
    moves = plan.lo + z.reshape(n_moves, 3) * plan.span
    length, f_w, f_o = line[:, 0], line[:, 1], line[:, 2]
    # the line printed at each second: the model's line at ν_ref scaled by the speed law
    lw, lo_ = outputs[:h] * f_w, outputs[h : 2 * h] * f_o
    sd = f_w * jnp.sqrt(jnp.maximum(outputs[2 * h :], 0.0) + 1e-12)
    err = (lw - target) / tol
    # |e| smoothed (1e-3 µm) so the gradient exists on target
    band = jnp.maximum(0.0, (jnp.sqrt((lw - target) ** 2 + 1e-6) + 2.0 * sd - tol) / tol)
    over = jnp.maximum(0.0, lo_ - max_overspray)
    stage = w_t * err**2 + w_b * band**2 + w_o * (lo_ / lo_ref) ** 2 + w_l * over**2
    previous = jnp.concatenate([u_prev[None], moves[:-1]], axis=0)
    step = (moves - previous) / (plan.rates * plan.gaps[:, None])
    return jnp.mean(length * stage) + w_m * jnp.sum(step**2)


def _linearise(z, plan, spec, mean, cov, theta, process_cov, functions=None):
    args = (plan, spec, mean, cov, theta, process_cov, functions)
    return plan_outputs(z, *args), jax.jacfwd(plan_outputs)(z, *args)


def _linear_cost(z, z0, out0, jac, plan, u_prev, target, max_overspray, line):
    """The cost on the model linearised at z0 (outputs ≈ out0 + J (z − z0))."""
    return plan_cost(z, out0 + jac @ (z - z0), plan, u_prev, target, max_overspray, line)


def _exact_cost(
    z,
    plan,
    spec,
    mean,
    cov,
    theta,
    process_cov,
    u_prev,
    target,
    max_overspray,
    line,
    functions=None,
):
    outputs = plan_outputs(z, plan, spec, mean, cov, theta, process_cov, functions)
    return plan_cost(z, outputs, plan, u_prev, target, max_overspray, line)


_STATIC = ("functions",)
_linearise_jit = jax.jit(_linearise, static_argnames=_STATIC)
_linear_objective = jax.jit(jax.value_and_grad(_linear_cost))
_exact_cost_jit = jax.jit(_exact_cost, static_argnames=_STATIC)
_trajectory_jit = jax.jit(plan_trajectory, static_argnames=_STATIC)


class MPC:
    """Move-blocked MPC over the twin's model (see the module docstring).

    Parameters
    ----------
    twin : ajtwin.estimation.Twin
        Model, Σ_ξ and θ default.
    settings : ControlSettings, optional
    limits : dict, optional
        The machine's input limits {name: [low, high]} (registry); default limits otherwise.
    max_overspray_um : float, optional
        Soft upper limit on L_o over the horizon.
    """

    def __init__(self, twin, settings=None, limits=None, max_overspray_um=None):
        self.twin = twin
        self.settings = settings or ControlSettings.load()
        self.bounds = effective_bounds(limits)
        self.lo = np.array([b[0] for b in self.bounds])
        self.hi = np.array([b[1] for b in self.bounds])
        self.span = self.hi - self.lo
        self.max_overspray_um = max_overspray_um
        s = self.settings
        starts = np.asarray(s.move_starts_s)
        self.n_moves = len(starts)
        self.block_index = np.searchsorted(starts, np.arange(s.horizon_s), side="right") - 1
        # time between a move and the one before it (the first: one control period)
        self.move_gaps = np.diff(np.concatenate([[starts[0] - s.period_s], starts])).astype(float)
        self.rates = np.asarray(s.rate_limits, dtype=float)
        self.max_linearisations = int(s.max_linearisations)
        # the twin's own model (discretisation, transition variant), as its forecast uses
        self.functions = getattr(twin, "functions", None)
        self.plan_arrays = _PlanArrays(
            jnp.asarray(self.lo),
            jnp.asarray(self.span),
            jnp.asarray(self.block_index),
            jnp.asarray(self.rates),
            jnp.asarray(self.move_gaps),
            jnp.asarray(
                [
                    s.weight_tracking,
                    s.weight_band,
                    s.weight_overspray,
                    s.overspray_scale_um,
                    s.weight_move,
                    s.weight_overspray_limit,
                    s.tolerance_um,
                ]
            ),
        )
        self._warm: np.ndarray | None = None

    def _model_args(self, mean, cov, theta):
        return (
            self.plan_arrays,
            self.twin.spec,
            jnp.asarray(mean, dtype=float),
            jnp.asarray(cov, dtype=float),
            jnp.asarray(theta, dtype=float),
            jnp.asarray(self.twin.process_cov),
        )

    # -- the solve -----------------------------------------------------------------
    def rate_constraints(self, u_prev, scale: float = 1.0):
        """Linear inequalities A z ≥ b for |v_j − v_{j−1}| ≤ scale·ρ·Δt_j (scaled inputs)."""
        n = self.n_moves * 3
        rows, rhs = [], []
        z_prev = (np.asarray(u_prev) - self.lo) / self.span
        for j in range(self.n_moves):
            limit = scale * self.rates * self.move_gaps[j] / self.span
            for i in range(3):
                a = np.zeros(n)
                a[3 * j + i] = 1.0
                offset = z_prev[i] if j == 0 else 0.0
                if j > 0:
                    a[3 * (j - 1) + i] = -1.0
                # v − v_prev ≤ limit  →  −(v − v_prev) + limit ≥ 0 ; and the other side
                rows.append(-a)
                rhs.append(-(offset + limit[i]))
                rows.append(a)
                rhs.append(offset - limit[i])
        return np.array(rows), np.array(rhs)

    def solve(
        self,
        mean,
        cov,
        theta,
        u_prev,
        target_um: float,
        *,
        step_scale: float = 1.0,
        warm_start: bool = True,
        line=None,
    ) -> MPCSolution:
        """Optimise the moves from (mean, cov, θ) with the command in force ``u_prev``.

        ``line`` (H, 3): the job's seconds ahead as the cost weighs them (printed length
        relative to ν_ref, f_w, f_o; :meth:`ajtwin.apps.planning.job_preview.JobPreview.line`);
        default a straight line printed at ν_ref every second.
        """
        t0, wall0 = time.process_time(), time.perf_counter()
        s = self.settings
        u_prev = np.asarray(u_prev, dtype=float)
        model_args = self._model_args(mean, cov, theta)
        line = jnp.ones((s.horizon_s, 3)) if line is None else jnp.asarray(line, dtype=float)
        if line.shape != (s.horizon_s, 3):
            raise ValueError(f"line must be ({s.horizon_s}, 3), got {line.shape}")
        u_prev_j = jnp.asarray(u_prev)
        max_over = np.inf if self.max_overspray_um is None else float(self.max_overspray_um)
        plan = self.plan_arrays

        z_hold = np.clip((u_prev - self.lo) / self.span, 0.0, 1.0)
        if warm_start and self._warm is not None:
            z0 = np.concatenate([self._warm[1:], self._warm[-1:]]).ravel()
        else:
            z0 = np.tile(z_hold, self.n_moves)
        a, b = self.rate_constraints(np.clip(u_prev, self.lo, self.hi), step_scale)
        # start feasible: project the warm start onto the rate limits around u_prev
        z0 = self._feasible(z0, z_hold, step_scale)
        iterations, result = 0, None
        # real-time-iteration SQP: linearise the model along the plan, solve, repeat while
        # the plan still moves (the model is mildly nonlinear; the next solve, one period
        # later, re-linearises anyway)
        for _ in range(self.max_linearisations):
            out0, jac = _linearise_jit(jnp.asarray(z0), *model_args, functions=self.functions)
            lin_args = (
                jnp.asarray(z0),
                out0,
                jac,
                plan,
                u_prev_j,
                float(target_um),
                max_over,
                line,
            )

            def fun(z, lin_args=lin_args):
                value, grad = _linear_objective(jnp.asarray(z), *lin_args)
                return float(value), np.asarray(grad, dtype=float)

            result = optimize.minimize(
                fun,
                z0,
                jac=True,
                method="SLSQP",
                bounds=[(0.0, 1.0)] * (3 * self.n_moves),
                constraints=[{"type": "ineq", "fun": lambda z: a @ z - b, "jac": lambda z: a}],
                options={"maxiter": s.max_iterations, "ftol": s.solver_tolerance},
            )
            iterations += int(result.nit)
            z_new = self._feasible(result.x, z_hold, step_scale)
            moved = float(np.max(np.abs(z_new - z0)))
            z0 = z_new
            if moved < 1e-3:
                break
        z = z0
        self._warm = z.reshape(self.n_moves, 3)
        moves, y, var = _trajectory_jit(jnp.asarray(z), *model_args, functions=self.functions)
        moves = np.asarray(moves)
        command = clip_command(
            moves[0], u_prev, self.bounds, step_scale * self.rates * self.move_gaps[0]
        )
        return MPCSolution(
            command=command,
            plan=moves,
            predicted_linewidth=np.asarray(y[:, 0]),
            predicted_linewidth_std=np.sqrt(np.maximum(np.asarray(var[:, 0]), 0.0)),
            predicted_overspray=np.asarray(y[:, 1]),
            cost=float(
                _exact_cost_jit(
                    jnp.asarray(z),
                    *model_args,
                    u_prev_j,
                    float(target_um),
                    max_over,
                    line,
                    functions=self.functions,
                )
            ),
            solve_s=time.process_time() - t0,
            solve_wall_s=time.perf_counter() - wall0,
            iterations=iterations,
            success=bool(result.success),
            message=str(result.message),
            step_scale=float(step_scale),
        )

    def _feasible(self, z, z_hold, step_scale):
        """Clip moves in sequence so each is within the rate limit of the one before."""
        z = np.clip(np.asarray(z, dtype=float).reshape(self.n_moves, 3), 0.0, 1.0)
        prev = z_hold
        for j in range(self.n_moves):
            limit = step_scale * self.rates * self.move_gaps[j] / self.span
            z[j] = np.clip(z[j], prev - limit, prev + limit)
            prev = z[j]
        return z.ravel()

    def reset(self):
        """Forget the warm start (a new print, or after a hold)."""
        self._warm = None

    def warm_up(self):
        """Compile the solver's functions now (once per process), so solve times are solves."""
        u = (self.lo + self.hi) / 2.0
        phi = float(self.twin.model.steady_aerosol_fraction(u, 1.0))
        mean = np.array([3.5, 1.0, 0.0, 0.0, phi])
        cov = np.diag([1e-2, 1e-4, 1e-8, 1e-4, (0.05 * phi) ** 2])
        self.solve(mean, cov, np.zeros(5), u, 60.0, warm_start=False)
        self.reset()
