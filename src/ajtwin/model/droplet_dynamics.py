"""Optional droplet-size dynamics of the transition model (paper's future work).

The paper's transition holds the droplet size by a pure drift, dd_a/dt = θ_da d_a
(model reference §4): over a forecast horizon that drift extrapolates exponentially, and the
droplet size cannot follow an input change. ``data/transition.toml`` offers variants
that change only the d_a row of the transition (the other rows are
:func:`ajtwin.model.system.transition_rates`):

``paper``
    dd_a/dt = θ_da d_a.
``mean_reverting`` (a drift that saturates)
    dd_a/dt = θ_da d_ref + (d_eq(u) − d_a)/τ,
    d_eq(u) = d_ref + c_c (Q_c − Q_c,ref) + c_I (I_A − I_A,ref).
    θ_da moves the equilibrium by θ_da d_ref τ instead of compounding; the inputs move it
    by c Δu, with the same time constant τ.
``input_following`` (droplet size = slow level + fast input response)
    d_a = ℓ + r,  dr/dt = (c·Δu − r)/τ_u,  dℓ/dt = θ_da d_a,
    i.e. dd_a/dt = θ_da d_a + (c·Δu − r)/τ_u. The response r depends on the inputs only,
    so it is not a state: :func:`augment_inputs` computes it from the input sequence
    (past and planned) and appends it as a 4th input column; the level keeps the paper's
    random walk and θ_da, whose MAP prior the variant may tighten (``theta_prior_std``,
    a bounded drift). Fed plain 3-column inputs, the step has no response term (the
    paper's row).

θ enters linearly in every form (∂f/∂θ_da is d_ref or d_a), so the EM M-step keeps its
closed form.

Parameters (``data/transition.toml``, one table per variant, with provenance)
-----------------------------------------------------------------------------
form : ``"paper"``, ``"mean_reverting"`` or ``"input_following"``
relaxation_time_s : τ [s] (mean_reverting); response_time_s : τ_u [s] (input_following)
reference_um : d_ref [µm]
carrier_um_per_sccm, current_um_per_mA : c_c [µm/sccm], c_I [µm/mA]
reference_carrier_sccm, reference_current_mA : Q_c,ref [sccm], I_A,ref [mA]
theta_prior_std : MAP prior σ of θ_da [1/s] (0 = keep noise.toml's)
forecast_droplet_std_um : σ of d_a's process noise per 1 s step in open-loop forecasts
    [µm] (0 = the filter's σ_da). The filter's σ_da is a short-horizon tuning (it must let
    the filter follow the droplet size within seconds); over a forecast horizon the level
    wanders less than a random walk with that σ.
forecast_aerosol_wander_per_sqrt_h : relative σ per √hour of the aerosol level (the
    atomizer's efficiency) in open-loop forecasts (0 = none): θ_φA, which holds the level
    the print has shown, becomes a random walk over the horizon, so φ_A's band (and L_o's,
    Q_m's) widens as the efficiency may move (apps.forecast).

Examples
--------
>>> import numpy as np
>>> from ajtwin.model import load_parameters
>>> step = DropletStep(load_droplet_dynamics("mean_reverting"), "euler")
>>> x = np.array([3.5, 1.0, 0.0, 0.0, 4.6e-7])
>>> u = np.array([375.0, 23.0, 50.0])      # at the reference inputs d_eq = d_ref
>>> float(step(x, u, np.zeros(5), load_parameters())[0])
3.5
>>> dyn = load_droplet_dynamics("input_following")
>>> r = augment_inputs(np.array([[375.0, 23.0, 50.0], [375.0, 25.0, 50.0]]), dyn)[:, 3]
>>> float(r[0])                              # starts in equilibrium with the first input
0.0
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.config import load_toml
from ajtwin.model.names import N_INPUTS
from ajtwin.model.system import transition_rates

FORMS = ("paper", "mean_reverting", "input_following")


@dataclass(frozen=True)
class DropletDynamics:
    """One variant of ``transition.toml`` (floats; hashable, so a static jit argument)."""

    name: str = "paper"
    form: str = "paper"
    relaxation_time_s: float = 600.0
    response_time_s: float = 60.0
    reference_um: float = 3.5
    carrier_um_per_sccm: float = 0.0
    current_um_per_mA: float = 0.0
    reference_carrier_sccm: float = 23.0
    reference_current_mA: float = 375.0
    theta_prior_std: float = 0.0
    forecast_droplet_std_um: float = 0.0
    forecast_aerosol_wander_per_sqrt_h: float = 0.0
    provenance: str = ""

    @property
    def is_paper(self) -> bool:
        """Whether this is the paper's droplet row (no input dependence)."""
        return self.form == "paper"

    @property
    def follows_inputs(self) -> bool:
        """The step reads a 4th input column (the input response r)."""
        return self.form == "input_following"

    def input_shift_um(self, u):
        """c_c (Q_c − Q_c,ref) + c_I (I_A − I_A,ref) [µm] for inputs u (..., ≥3) (NumPy in,
        NumPy out: host code never dispatches a JAX operation for it)."""
        if not isinstance(u, np.ndarray | list | tuple):
            u = jnp.asarray(u)
        else:
            u = np.asarray(u, dtype=float)
        return self.carrier_um_per_sccm * (
            u[..., 1] - self.reference_carrier_sccm
        ) + self.current_um_per_mA * (u[..., 0] - self.reference_current_mA)

    def equilibrium_um(self, u):
        """d_eq(u) = d_ref + c·Δu [µm] (mean_reverting)."""
        return self.reference_um + self.input_shift_um(u)


def _transition_file(path: str | Path | None) -> dict:
    return load_toml(path, "data/transition.toml", what="transition")


def transition_variants(path: str | Path | None = None) -> tuple[str, ...]:
    """Names of the variants in ``transition.toml`` (or the file at ``path``)."""
    return tuple(_transition_file(path)["variants"])


def default_transition(path: str | Path | None = None) -> str:
    """The variant the twin runs when none is named (``default`` of ``transition.toml``)."""
    raw = _transition_file(path)
    variant = str(raw.get("default", "paper"))
    if variant not in raw.get("variants", {}):
        where = str(path) if path is not None else "ajtwin/data/transition.toml"
        raise ValueError(f"{where}: default = {variant!r} is not one of its [variants]")
    return variant


def load_droplet_dynamics(variant: str = "paper", path: str | Path | None = None):
    """The droplet-dynamics variant ``variant`` of ``transition.toml``.

    Raises ValueError naming the file and the variant or key that is wrong.
    """
    where = str(path) if path is not None else "ajtwin/data/transition.toml"
    raw = _transition_file(path)
    variants = raw.get("variants", {})
    if variant not in variants:
        raise ValueError(f"{where}: no transition variant {variant!r}; choose {sorted(variants)}")
    table = dict(variants[variant])
    form = table.pop("form", "paper")
    if form not in FORMS:
        raise ValueError(f"{where} [variants.{variant}]: form = {form!r}; choose one of {FORMS}")
    provenance = str(table.pop("provenance", ""))
    known = set(DropletDynamics.__dataclass_fields__) - {"name", "form", "provenance"}
    unknown = set(table) - known
    if unknown:
        raise ValueError(f"{where} [variants.{variant}]: unknown keys {sorted(unknown)}")
    values = {key: float(value) for key, value in table.items()}
    for key in ("relaxation_time_s", "response_time_s"):
        if key in values and not values[key] > 0:
            raise ValueError(f"{where} [variants.{variant}]: {key} must be > 0")
    return DropletDynamics(name=variant, form=form, provenance=provenance, **values)


def input_response(inputs, dynamics: DropletDynamics, response0=None, dt=1.0):
    """The droplet size's input response r_k over inputs (T, 3) [µm] (jit-able).

    r_{k+1} = r_k + Δt (c·Δu_k − r_k)/τ_u (the same Euler step as the transition, so
    d_a's response increment is exactly r_{k+1} − r_k); r_0 = ``response0``, default the
    equilibrium c·Δu_0 (inputs steady before the record starts).
    """
    target = jnp.asarray(dynamics.input_shift_um(inputs))
    gain = dt / dynamics.response_time_s
    r0 = target[0] if response0 is None else jnp.asarray(response0, dtype=target.dtype)
    return _response_scan(target, r0, jnp.asarray(gain, dtype=target.dtype))


@jax.jit
def _response_scan(target, r0, gain):
    """r_k for k = 0 … T−1 from r_0 (one compiled scan per length: a start value baked
    into an unjitted scan compiled it anew for every piece of a print read in pieces)."""

    def step(r, target_k):
        return response_step(r, target_k, gain), r

    return jax.lax.scan(step, r0, target)[1]


def response_step(response, target, gain):
    """r_{k+1} = r_k + g (c·Δu_k − r_k), g = Δt/τ_u: the one Euler step of the input
    response, for whole sequences (:func:`input_response`) and sample by sample
    (:func:`next_response`, the live engine)."""
    return response + gain * (target - response)


def augment_inputs(inputs, dynamics: DropletDynamics, response0: float | None = None, dt=1.0):
    """Inputs (T, 3) → (T, 4) with the input response r_k (:func:`input_response`) as
    4th column [µm]. A variant that does not follow the inputs returns ``inputs`` unchanged.
    """
    inputs = np.asarray(inputs, dtype=float)
    if not dynamics.follows_inputs:
        return inputs
    if inputs.ndim != 2 or inputs.shape[1] != N_INPUTS:
        raise ValueError(f"inputs must be (T, {N_INPUTS}); got {inputs.shape}")
    # on the host, step by step (:func:`response_step`, the recursion :func:`input_response`
    # scans): a scan compiled per length cost more than the arithmetic of a print
    target = dynamics.input_shift_um(inputs)
    gain = dt / dynamics.response_time_s
    response = np.empty(len(inputs))
    r = float(target[0]) if response0 is None else float(response0)
    for k, target_k in enumerate(target.tolist()):
        response[k] = r
        r = response_step(r, target_k, gain)
    return np.concatenate([inputs, response[:, None]], axis=1)


def next_response(response: float, u, dynamics: DropletDynamics, dt=1.0) -> float:
    """r after one step of input u (to continue :func:`augment_inputs` past a record)."""
    target = float(dynamics.input_shift_um(np.asarray(u, dtype=float)))
    return float(response_step(response, target, dt / dynamics.response_time_s))


def model_input(u, response: float | None, dynamics: DropletDynamics, dt=1.0):
    """One sample's input as the transition reads it, and r for the next sample.

    ``u`` (3,) [mA, sccm, sccm]; ``response`` r_k [µm], None at the first sample (then
    the equilibrium c·Δu_k, as :func:`augment_inputs` starts). Returns (u (4,) with r_k
    appended, r_{k+1}); a variant that does not follow the inputs returns (u, None).
    Fed sample by sample it gives :func:`augment_inputs`' rows (tested).
    """
    u = np.asarray(u, dtype=float)
    if not dynamics.follows_inputs:
        return u, None
    if response is None:
        response = float(dynamics.input_shift_um(u))
    return np.append(u, response), next_response(response, u, dynamics, dt)


def droplet_rate(x, u, theta, dynamics: DropletDynamics):
    """dd_a/dt [µm/s] of the variant (module docstring)."""
    x, u, theta = jnp.asarray(x), jnp.asarray(u), jnp.asarray(theta)
    droplet_um = x[..., 0]
    if dynamics.form == "mean_reverting":
        return (
            theta[..., 0] * dynamics.reference_um
            + (dynamics.equilibrium_um(u) - droplet_um) / dynamics.relaxation_time_s
        )
    rate = theta[..., 0] * droplet_um
    if dynamics.follows_inputs and u.shape[-1] > N_INPUTS:
        response = u[..., N_INPUTS]
        rate = rate + (dynamics.input_shift_um(u) - response) / dynamics.response_time_s
    return rate


def extended_transition_rates(x, u, theta, params, dynamics: DropletDynamics):
    """f(x, u; θ) with the d_a row of ``dynamics``; the other rows are the paper's."""
    rates = transition_rates(x, jnp.asarray(u)[..., :N_INPUTS], theta, params)
    if dynamics.is_paper:
        return rates
    return rates.at[..., 0].set(droplet_rate(x, u, theta, dynamics))


@dataclass(frozen=True)
class DropletStep:
    """f_d(x, u; θ) with a droplet variant: a hashable callable for ``ModelFunctions.step``.

    ``method`` "euler" (x + Δt f) or "rk4" (input, and the response column, held over
    the step). Linear in θ as the paper's steps are.
    """

    dynamics: DropletDynamics
    method: str = "euler"

    def __call__(self, x, u, theta, params, dt=1.0):
        def f(state):
            return extended_transition_rates(state, u, theta, params, self.dynamics)

        if self.method == "euler":
            return x + dt * f(x)
        k1 = f(x)
        k2 = f(x + 0.5 * dt * k1)
        k3 = f(x + 0.5 * dt * k2)
        k4 = f(x + dt * k3)
        return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
