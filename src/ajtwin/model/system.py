"""The assembled digital model: transition f and output g (paper §6, model reference §4–5).

State, input and output vectors are in display units (model reference §3):

* x = [d_a µm, V_l mL, ΔR_T µm, ΔR_N µm, φ_A]
* u = [I_A mA, Q_c sccm, Q_s sccm]
* y = [L_w µm, L_o µm, P_c Pa, P_s Pa, Q_m mL/s]
* θ = [θ_da, θ_Vl, θ_RT, θ_RN, θ_φA] in 1/s

The pure functions here (:func:`transition_rates`, :func:`output_function`,
:func:`euler_step`, :func:`rk4_step`) take the parameters as pytrees and can be
``jit``-ed, ``vmap``-ed and differentiated; the estimators use them directly.
:class:`DigitalModel` wraps them for users with input checks and NumPy I/O.

The transition is linear in θ: f(x, u; θ) = f(x, u; 0) + θ ⊙ x — which is
what gives the EM M-step its closed form (model reference §7).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ajtwin import units
from ajtwin._aot import exported_jit
from ajtwin._jax import jax, jnp
from ajtwin.model.atomizer import aerosol_fraction_rate, net_droplet_generation, vial_volume_rate
from ajtwin.model.calibration import CalibratedCoefficients, apply_calibration
from ajtwin.model.droplets import QUADRATURE_ORDER
from ajtwin.model.fluidics import carrier_pressure, sheath_pressure
from ajtwin.model.limits import INPUT_LIMITS
from ajtwin.model.line_output import line_feature, material_flow
from ajtwin.model.line_speed import apply_line_speed, load_line_speed_law
from ajtwin.model.names import (
    INPUT_NAMES,
    N_INPUTS,
    N_STATES,
    STATE_NAMES,
)
from ajtwin.model.parameters import (
    OutputCoefficients,
    PhysicalParameters,
    load_output_coefficients,
    load_parameters,
)
from ajtwin.model.transport import (
    CRITICAL_RADIUS_NEWTON_STEPS,
    nozzle_deposition_rate,
    tube_deposition_rate,
)


def coefficient_matrix(coefficients: OutputCoefficients) -> np.ndarray:
    """Output coefficients as a (2, 8) array: rows L_w, L_o (pytree-friendly)."""
    return np.array([list(coefficients.linewidth), list(coefficients.overspray)], dtype=float)


def transition_rates(
    x,
    u,
    theta,
    params: PhysicalParameters,
    *,
    quadrature_order: int = QUADRATURE_ORDER,
    newton_steps: int = CRITICAL_RADIUS_NEWTON_STEPS,
):
    """Continuous-time transition f(x, u; θ): per-second rates in display units.

    dd_a/dt  = θ_da d_a
    dV_l/dt  = −φ_A Q_c + θ_Vl V_l
    dΔR_T/dt = θ_RT ΔR_T + Q_d ∫(1 − P_grav) p dd / (2π (r_T0 − ΔR_T) L_T)
    dΔR_N/dt = θ_RN ΔR_N + Q_d ∫(1 − P_diff) p dd / (2π (r_N0 − ΔR_N) L_N)
    dφ_A/dt  = (H − φ_A Q_c + φ_A dV_l/dt)/(V_v − V_l) + θ_φA φ_A

    Parameters
    ----------
    x : array (..., 5)
        States [µm, mL, µm, µm, –].
    u : array (..., 3)
        Inputs [mA, sccm, sccm].
    theta : array (5,) or (..., 5)
        Drift parameters [1/s].
    params : PhysicalParameters
        SI parameters.
    quadrature_order, newton_steps : int, keyword-only, static
        Resolution of the droplet integrals and of the critical radius x_c
        (defaults: converged over the operating box; raise them for a reference).

    Returns
    -------
    array (..., 5)
        [µm/s, mL/s, µm/s, µm/s, 1/s].
    """
    x = jnp.asarray(x)
    u = jnp.asarray(u)
    theta = jnp.asarray(theta)
    droplet_um, vial_ml, tube_um, nozzle_um, aerosol = (x[..., i] for i in range(N_STATES))
    current_ma, carrier_sccm, sheath_sccm = (u[..., i] for i in range(N_INPUTS))

    carrier_ml_s = units.sccm_to_ml_per_s(carrier_sccm)
    carrier_m3_s = units.sccm_to_m3_per_s(carrier_sccm)
    sheath_m3_s = units.sccm_to_m3_per_s(sheath_sccm)
    droplet_m = units.um_to_m(droplet_um)

    d_droplet = theta[..., 0] * droplet_um
    d_vial = vial_volume_rate(aerosol, carrier_ml_s, vial_ml, theta[..., 1])
    d_tube = theta[..., 2] * tube_um + units.m_to_um(
        tube_deposition_rate(
            aerosol, droplet_m, units.um_to_m(tube_um), carrier_m3_s, params, quadrature_order
        )
    )
    d_nozzle = theta[..., 3] * nozzle_um + units.m_to_um(
        nozzle_deposition_rate(
            aerosol,
            droplet_m,
            units.um_to_m(nozzle_um),
            carrier_m3_s,
            sheath_m3_s,
            params,
            quadrature_order,
            newton_steps,
        )
    )
    generation = net_droplet_generation(carrier_sccm, vial_ml, current_ma, params.generation_fit)
    d_aerosol = aerosol_fraction_rate(
        aerosol,
        generation,
        carrier_ml_s,
        vial_ml,
        d_vial,
        units.m3_to_ml(params.vial_volume),
        theta[..., 4],
    )
    return jnp.stack([d_droplet, d_vial, d_tube, d_nozzle, d_aerosol], axis=-1)


def output_function(
    x, u, params: PhysicalParameters, coefficients, platen_speed_mm_s=None, speed_law=None
):
    """Output model g(x, u[, ν]): [L_w µm, L_o µm, P_c Pa, P_s Pa, Q_m mL/s].

    Parameters
    ----------
    x : array (..., 5), u : array (..., 3)
        Display units.
    params : PhysicalParameters
    coefficients : array (2, 8) or CalibratedCoefficients
        :func:`coefficient_matrix` of the output coefficients, or that matrix with a
        machine's :class:`~ajtwin.model.calibration.Calibration` (model reference §11), which is
        then applied to the nominal outputs.
    platen_speed_mm_s : array (...) or float, optional
        Platen speed ν [mm/s], a known input (model reference §12): L_w and L_o of the
        calibrated line are scaled by the speed law (:mod:`ajtwin.model.line_speed`);
        P_c, P_s, Q_m do not depend on ν. ``None`` (or ν = ν_ref): the line at ν_ref,
        exactly the output model without ν.
    speed_law : LineSpeedLaw, optional
        The law's constants; default: ``data/line_speed.toml``.
    """
    if platen_speed_mm_s is not None:
        law = load_line_speed_law() if speed_law is None else speed_law
        return apply_line_speed(output_function(x, u, params, coefficients), platen_speed_mm_s, law)
    if isinstance(coefficients, CalibratedCoefficients):
        nominal = output_function(x, u, params, coefficients.line)
        return apply_calibration(nominal, x, u, params, coefficients.calibration)
    x = jnp.asarray(x)
    u = jnp.asarray(u)
    coefficients = jnp.asarray(coefficients)
    droplet_um, _, tube_um, nozzle_um, aerosol = (x[..., i] for i in range(N_STATES))
    _, carrier_sccm, sheath_sccm = (u[..., i] for i in range(N_INPUTS))
    carrier_m3_s = units.sccm_to_m3_per_s(carrier_sccm)
    sheath_m3_s = units.sccm_to_m3_per_s(sheath_sccm)

    features = [
        line_feature(coefficients[row], droplet_um, aerosol, nozzle_um, carrier_sccm, sheath_sccm)
        for row in (0, 1)
    ]
    p_carrier = carrier_pressure(
        carrier_m3_s, sheath_m3_s, units.um_to_m(tube_um), nozzle_um, params
    )
    p_sheath = sheath_pressure(carrier_m3_s, sheath_m3_s, nozzle_um, params)
    q_material = material_flow(
        aerosol, units.sccm_to_ml_per_s(carrier_sccm), params.silver_volume_fraction
    )
    return jnp.stack([features[0], features[1], p_carrier, p_sheath, q_material], axis=-1)


def euler_step(x, u, theta, params, dt=1.0):
    """Euler-discretized transition f_d(x, u; θ) = x + Δt f(x, u; θ) (paper §6)."""
    return x + dt * transition_rates(x, u, theta, params)


def rk4_step(x, u, theta, params, dt=1.0):
    """Classical Runge–Kutta step with the input held over the step."""
    k1 = transition_rates(x, u, theta, params)
    k2 = transition_rates(x + 0.5 * dt * k1, u, theta, params)
    k3 = transition_rates(x + 0.5 * dt * k2, u, theta, params)
    k4 = transition_rates(x + dt * k3, u, theta, params)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def steady_aerosol_fraction(u, vial_volume_ml, params, theta_aerosol=0.0):
    """φ_A where dφ_A/dt = 0 for given inputs and vial level (θ_Vl = 0).

    With dV_l/dt = −φ Q_c the balance is H − φ Q_c − φ² Q_c + θ_φA φ (V_v − V_l) = 0;
    φ² Q_c is ~1e-7 of φ Q_c, so φ ≈ H / (Q_c − θ_φA (V_v − V_l)).
    """
    u = jnp.asarray(u)
    carrier_ml_s = units.sccm_to_ml_per_s(u[..., 1])
    generation = net_droplet_generation(u[..., 1], vial_volume_ml, u[..., 0], params.generation_fit)
    headspace = vial_headspace_ml(vial_volume_ml, params)
    return generation / (carrier_ml_s - theta_aerosol * headspace)


def settled_outputs(u, vial_volume_ml, params, coefficients):
    """(φ_A in balance at inputs u (3,) and vial level V_l, the outputs (5,) of the clean
    nominal state x = (3.5 µm, V_l, 0, 0, φ_A) there): what a record's scale is checked
    against and where the initial fit starts.
    """
    phi = steady_aerosol_fraction(u, vial_volume_ml, params)
    x = jnp.stack([3.5, vial_volume_ml, 0.0, 0.0, phi])
    return phi, output_function(x, u, params, coefficients)


# kept on disk (ajtwin._aot): every command that reads a record asks it once
settled_outputs = exported_jit(settled_outputs)


def vial_headspace_ml(vial_volume_ml, params):
    """V_v − V_l [mL]: the vial's gas space above the ink."""
    return units.m3_to_ml(params.vial_volume) - vial_volume_ml


def aerosol_level_theta_std(u, vial_volume_ml, params, relative_std):
    """σ of θ_φA [1/s] that moves the steady aerosol fraction by ``relative_std``.

    From φ* ≈ H / (Q_c − θ_φA (V_v − V_l)) (:func:`steady_aerosol_fraction`, θ_φA small):
    δφ*/φ* ≈ δθ_φA (V_v − V_l) / Q_c, so σ_θ = relative_std · Q_c / (V_v − V_l).
    """
    carrier_ml_s = units.sccm_to_ml_per_s(np.asarray(u)[..., 1])  # host-side: no JAX dispatch
    return relative_std * carrier_ml_s / vial_headspace_ml(vial_volume_ml, params)


def aerosol_level_theta(u, vial_volume_ml, params, level):
    """θ_φA [1/s] at which the steady aerosol fraction is ``level`` × the generation model's.

    From φ* = H / (Q_c − θ_φA (V_v − V_l)) (:func:`steady_aerosol_fraction`):
    φ* = level · H/Q_c when θ_φA = (1 − 1/level) Q_c / (V_v − V_l). An atomizer that
    delivers a known factor of H is, to the model, this drift of the aerosol row.

    >>> from ajtwin.model.parameters import load_parameters
    >>> p = load_parameters()
    >>> u = jnp.array([375.0, 23.0, 50.0])
    >>> theta = aerosol_level_theta(u, 1.0, p, 0.8)
    >>> held, nominal = (steady_aerosol_fraction(u, 1.0, p, t) for t in (theta, 0.0))
    >>> round(float(held / nominal), 6)
    0.8
    """
    carrier_ml_s = units.sccm_to_ml_per_s(jnp.asarray(u)[..., 1])
    return (1.0 - 1.0 / level) * carrier_ml_s / vial_headspace_ml(vial_volume_ml, params)


def ink_flows(x, u, params):
    """Where the ink leaving the vial goes, per second [mL/s].

    Returns (out_of_vial, into_tube_deposit, into_nozzle_deposit, onto_substrate),
    with out_of_vial = Q_d = φ_A Q_c and the deposits the volume rates of the
    annular layers, 2π (r − ΔR) L dΔR/dt. The rest reaches the substrate.
    """
    x = jnp.asarray(x)
    u = jnp.asarray(u)
    zero_theta = jnp.zeros(N_STATES)
    rates = transition_rates(x, u, zero_theta, params)
    out_of_vial = x[..., 4] * units.sccm_to_ml_per_s(u[..., 1])
    tube_radius = params.tube_radius - units.um_to_m(x[..., 2])
    nozzle_radius = params.nozzle_radius - units.um_to_m(x[..., 3])
    into_tube = units.m3_to_ml(
        2 * jnp.pi * tube_radius * params.tube_length * units.um_to_m(rates[..., 2])
    )
    into_nozzle = units.m3_to_ml(
        2 * jnp.pi * nozzle_radius * params.nozzle_length * units.um_to_m(rates[..., 3])
    )
    return out_of_vial, into_tube, into_nozzle, out_of_vial - into_tube - into_nozzle


# --------------------------------------------------------------------------- #
# Input checking (the public API speaks display units and fails loudly)
# --------------------------------------------------------------------------- #


def _as_array(value, name, trailing):
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0 or arr.shape[-1] != trailing:
        raise ValueError(
            f"{name} must have shape ({trailing},) or (..., {trailing}); got {arr.shape}"
        )
    return arr


def _fail(name, value, allowed):
    raise ValueError(f"{name} = {value!r} is outside the allowed range {allowed}")


def check_state(x, params: PhysicalParameters) -> np.ndarray:
    """Validate a state array (..., 5) in display units; returns it as float array."""
    x = _as_array(x, "state x", N_STATES)
    for i, name in enumerate(STATE_NAMES):
        column = x[..., i]
        bad = ~np.isfinite(column)
        if bad.any():
            raise ValueError(f"{name} contains NaN/inf: {column[bad].ravel()[:3]}")
    vial_capacity = units.m3_to_ml(params.vial_volume)
    tube_radius_um = units.m_to_um(params.tube_radius)
    nozzle_radius_um = units.m_to_um(params.nozzle_radius)
    checks = [
        (0, lambda c: c > 0, "(0, inf) µm"),
        (
            1,
            lambda c: (c > 0) & (c < vial_capacity),
            f"(0, {vial_capacity:g}) mL (vial volume V_v)",
        ),
        (2, lambda c: np.abs(c) < tube_radius_um, f"(-{tube_radius_um:g}, {tube_radius_um:g}) µm"),
        (
            3,
            lambda c: np.abs(c) < nozzle_radius_um,
            f"(-{nozzle_radius_um:g}, {nozzle_radius_um:g}) µm",
        ),
        (4, lambda c: (c >= 0) & (c < 1), "[0, 1)"),
    ]
    for i, ok, allowed in checks:
        column = x[..., i]
        bad = ~ok(column)
        if bad.any():
            _fail(STATE_NAMES[i], float(column[bad].ravel()[0]), allowed)
    return x


def check_input(u) -> np.ndarray:
    """Validate an input array (..., 3) [mA, sccm, sccm]; returns it as float array."""
    u = _as_array(u, "input u", N_INPUTS)
    for i, name in enumerate(INPUT_NAMES):
        column = u[..., i]
        bad = ~np.isfinite(column)
        if bad.any():
            raise ValueError(f"{name} contains NaN/inf")
        low, high = INPUT_LIMITS[name]
        bad = (column <= low) | (column > high)
        if bad.any():
            value = float(column[bad].ravel()[0])
            hint = ""
            if name == "atomizer_current_mA" and value < 1:
                hint = " (the paper's '0.375 mA' means 375 mA)"
            if name != "atomizer_current_mA" and value <= 0:
                hint = " (flows must be positive)"
            raise ValueError(
                f"{name} = {value!r} is outside the allowed range ({low:g}, {high:g}]{hint}"
            )
    return u


def check_theta(theta) -> np.ndarray:
    """θ as a finite array (5,) [1/s]; None is θ = 0."""
    if theta is None:
        return np.zeros(N_STATES)
    theta = _as_array(theta, "theta", N_STATES)
    if not np.isfinite(theta).all():
        raise ValueError("theta contains NaN/inf")
    return theta


_jit_rates = jax.jit(transition_rates)
_jit_outputs = jax.jit(output_function)
_jit_euler = jax.jit(euler_step)
_jit_rk4 = jax.jit(rk4_step)


@dataclass(frozen=True)
class DigitalModel:
    """The AJ digital model with packaged or user parameters.

    Examples
    --------
    >>> import numpy as np
    >>> m = DigitalModel.default()
    >>> y = m.outputs(np.array([3.5, 1.0, 0.0, 0.0, 4.6e-7]), np.array([375.0, 23.0, 50.0]))
    >>> round(float(y[2]))          # carrier pressure, Pa
    5661
    """

    params: PhysicalParameters
    coefficients: OutputCoefficients

    @classmethod
    def default(cls) -> DigitalModel:
        """Packaged parameters (model reference §6) and output coefficients (model reference §5)."""
        return cls(load_parameters(), load_output_coefficients())

    @classmethod
    def from_files(
        cls, parameters: str | Path | None = None, coefficients: str | Path | None = None
    ) -> DigitalModel:
        """A model from a user's parameter and/or coefficient TOML files."""
        return cls(load_parameters(parameters), load_output_coefficients(coefficients))

    @property
    def coefficient_matrix(self) -> np.ndarray:
        """The output coefficients as a (2, 8) array (rows L_w, L_o)."""
        return coefficient_matrix(self.coefficients)

    # -- public API in display units, NumPy in/out --------------------------------
    def derivative(self, x, u, theta=None) -> np.ndarray:
        """Per-second rates f(x, u; θ), same units as x (per second)."""
        x = check_state(x, self.params)
        u = check_input(u)
        return np.asarray(_jit_rates(x, u, check_theta(theta), self.params))

    def outputs(self, x, u, platen_speed_mm_s=None) -> np.ndarray:
        """Outputs g(x, u[, ν]) = [L_w µm, L_o µm, P_c Pa, P_s Pa, Q_m mL/s].

        ``platen_speed_mm_s`` (ν, mm/s): the line at that speed (model reference §12);
        without it, the line at the law's reference speed (2 mm/s).
        """
        x = check_state(x, self.params)
        u = check_input(u)
        if platen_speed_mm_s is None:
            return np.asarray(_jit_outputs(x, u, self.params, self.coefficient_matrix))
        speed = np.asarray(platen_speed_mm_s, dtype=float)
        if not np.isfinite(speed).all() or (speed < 0).any():
            raise ValueError(f"platen_speed_mm_s must be finite and >= 0 mm/s, got {speed}")
        return np.asarray(
            _jit_outputs(x, u, self.params, self.coefficient_matrix, speed, load_line_speed_law())
        )

    def step(self, x, u, theta=None, dt: float = 1.0, method: str = "euler") -> np.ndarray:
        """One discrete step x_{k+1} = f_d(x_k, u_k; θ) (Euler, or ``method="rk4"``)."""
        x = check_state(x, self.params)
        u = check_input(u)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt = {dt!r} must be a positive number of seconds")
        stepper = {"euler": _jit_euler, "rk4": _jit_rk4}.get(method)
        if stepper is None:
            raise ValueError(f"method = {method!r}; choose 'euler' or 'rk4'")
        return np.asarray(stepper(x, u, check_theta(theta), self.params, float(dt)))

    def steady_aerosol_fraction(self, u, vial_volume_ml: float = 1.0) -> float:
        """φ_A in balance with generation H at inputs u and vial level V_l."""
        u = check_input(u)
        return np.asarray(steady_aerosol_fraction(u, vial_volume_ml, self.params))

    def simulate(self, x0, inputs, theta=None, dt: float = 1.0, method: str = "euler"):
        """Open-loop run from x0 over an input sequence (T, 3); returns states (T+1, 5).

        Uses ``lax.scan``; states[k] is the state at time k·dt.
        """
        x0 = check_state(x0, self.params)
        inputs = check_input(inputs)
        if inputs.ndim != 2:
            raise ValueError(f"inputs must be a (T, 3) sequence; got {inputs.shape}")
        return np.asarray(
            simulate_open_loop(x0, inputs, check_theta(theta), self.params, dt, method)
        )


def simulate_open_loop(x0, inputs, theta, params, dt=1.0, method="euler"):
    """Pure open-loop trajectory, (T+1, 5), via ``lax.scan`` over inputs (T, 3)."""
    stepper = rk4_step if method == "rk4" else euler_step

    def body(x, u):
        x_next = stepper(x, u, theta, params, dt)
        return x_next, x_next

    _, xs = jax.lax.scan(body, jnp.asarray(x0), jnp.asarray(inputs))
    return jnp.concatenate([jnp.asarray(x0)[None], xs], axis=0)


simulate_open_loop = jax.jit(simulate_open_loop, static_argnames=("method",))
