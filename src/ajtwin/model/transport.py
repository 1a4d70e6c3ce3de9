"""Aerosol transport losses and ink build-up in the tube and nozzle (paper App. B).

* :func:`settling_survival` — Thomas (1958) survival of gravitational settling
  in a horizontal tube, P_grav = (2/π)(αβ + asin β − 2α³β),
  α = (3 L v_ts / (8 ū R))^{1/3} (clipped to ≤ 1), β = sqrt(1 − α²).
* :func:`diffusion_survival` — survival of diffusion to the wall,
  P_diff = x_c²(2 − x_c²), (1 − x_c)²(1 − x_c²) = π L D / Q.
* :func:`tube_deposition_rate` — dΔR_T/dt = Q_d ∫(1 − P_grav) p dd / (2π (r_T0 − ΔR_T) L_T).
* :func:`nozzle_deposition_rate` — dΔR_N/dt = Q_d ∫(1 − P_diff) p dd / (2π (r_N0 − ΔR_N) L_N).

SI units throughout (m, m³/s, m/s).

Derivatives of the droplet integrals
------------------------------------
The two integrals F_T = ∫(1 − P_grav) p dd and F_N = ∫(1 − P_diff) p dd are most of
a transition step's cost, and the EKF needs f's Jacobian at every step. Automatic
forward mode would differentiate every operation inside them — the Newton
iterations for x_c, the cube roots, the arcsine. They are ``custom_jvp`` functions
whose rule uses closed forms instead, sharing the integrals' own intermediates
(the state enters through d_a and, for the tube, R = r_T0 − ΔR_T; the inputs
through Q):

* settling: α = (3π L_T v_ts R / (8 Q))^{1/3}, and with β² = 1 − α²,
  dP_grav/dα = −(16/π) α² β, so ∂F_T/∂ln α_i = w_i (16/π) α_i³ β_i (0 once α ≥ 1);
  ln α = (ln v_ts + ln R − ln Q)/3 + const, and ∂ln v_ts/∂ln d = 2 + ∂ln C_c/∂ln d;
* diffusion: 1 − P_diff = (ε(2 − ε))² with ε = 1 − x_c, ε³(2 − ε) = μ = π L_N D / Q
  (implicit function theorem at the converged root), so
  μ ∂(1 − P_diff)/∂μ = 2ε²(2 − ε)²(1 − ε)/(3 − 2ε); ∂ln μ/∂ln d = ∂ln C_c/∂ln d − 1;
* the nodes d_i = d_a exp(√2 σ t_i) give ∂ln d_i/∂ln d_a = 1.

A derivative with respect to the parameters (rare: sensitivity studies) takes the
automatic path. ``tests/test_model_accuracy.py`` holds the closed forms to automatic
differentiation of the plain integrals over the operating box.
"""

from __future__ import annotations

from functools import partial

from ajtwin._jax import jax, jnp
from ajtwin.model.droplets import (
    QUADRATURE_ORDER,
    diffusion_coefficient,
    lognormal_quadrature,
    settling_velocity,
    slip_log_slope,
)

#: Newton steps for the critical radius. The start ε₀ (one fixed-point step of
#: ε = (μ/2)^{1/3}(1 − ε/2)^{−1/3}) is within 4e-5 relative of the root for the
#: operating box's μ ≤ 1e-4 and within 6 % for any μ ∈ (0, 1], so 3 quadratic
#: steps reach machine precision (≤ 1e-14 relative, tests/test_model_accuracy.py);
#: the former start μ^{1/3} (26 % off) needed 5–6.
CRITICAL_RADIUS_NEWTON_STEPS = 3


def _settling_alpha_beta(settling_speed, mean_gas_speed, tube_length, tube_radius):
    """Thomas's α = (3 L v_ts / (8 ū R))^{1/3} ≤ 1 and β = sqrt(1 − α²)."""
    alpha = jnp.cbrt(3.0 * tube_length * settling_speed / (8.0 * mean_gas_speed * tube_radius))
    alpha = jnp.minimum(alpha, 1.0)
    # double-where keeps the gradient finite where α hits 1 (β = 0, dβ/dα = ∞)
    one_minus = 1.0 - alpha**2
    inside = one_minus > 1e-15
    beta = jnp.where(inside, jnp.sqrt(jnp.where(inside, one_minus, 1.0)), 0.0)
    return alpha, beta


def settling_survival(settling_speed, mean_gas_speed, tube_length, tube_radius):
    """Fraction of droplets surviving gravitational settling in a horizontal tube.

    Thomas (1958): P_grav = (2/π)(αβ + asin β − 2α³β), with
    α = (3 L v_ts / (8 ū R))^{1/3} clipped to ≤ 1 and β = sqrt(1 − α²).
    P_grav → 1 as v_ts → 0 and is 0 for α ≥ 1 (every droplet settles).

    Parameters
    ----------
    settling_speed : array
        v_ts [m/s].
    mean_gas_speed : array
        ū = Q/(πR²) [m/s].
    tube_length, tube_radius : float
        L [m], R [m] (R = r_T0 − ΔR_T).

    Returns
    -------
    array
        Survival probability in [0, 1].
    """
    alpha, beta = _settling_alpha_beta(settling_speed, mean_gas_speed, tube_length, tube_radius)
    survival = (2.0 / jnp.pi) * (alpha * beta + jnp.arcsin(beta) - 2.0 * alpha**3 * beta)
    return jnp.clip(survival, 0.0, 1.0)


def critical_radius(loss_parameter, newton_steps=CRITICAL_RADIUS_NEWTON_STEPS):
    """Solve (1 − x_c)²(1 − x_c²) = μ for x_c ∈ [0, 1] with fixed Newton steps.

    In ε = 1 − x_c the equation is ε³(2 − ε) = μ, i.e. the fixed point of
    ε = a (1 − ε/2)^{−1/3}, a = (μ/2)^{1/3}. One fixed-point step from ε = a
    gives ε₀ = a (1 − a/2)^{−1/3} (clipped to 1), left of the root and within
    4e-5 relative of it for μ ≤ 1e-4 (6 % at worst, μ → 1); ε³(2 − ε) is
    increasing and convex on [0, 1], so Newton from there overshoots once and
    then converges monotonically.
    μ ≥ 1 gives x_c = 0 (no survivors). ``newton_steps`` is static.
    """
    mu = jnp.asarray(loss_parameter)
    a = jnp.cbrt(0.5 * mu)
    eps = jnp.minimum(a * (1.0 - 0.5 * jnp.minimum(a, 1.0)) ** (-1.0 / 3.0), 1.0)
    for _ in range(newton_steps):
        residual = eps**3 * (2.0 - eps) - mu
        slope = 6.0 * eps**2 - 4.0 * eps**3
        eps = jnp.clip(eps - residual / jnp.where(slope > 0, slope, 1.0), 0.0, 1.0)
    return 1.0 - eps


def diffusion_loss(diffusivity, flow_rate, length, newton_steps=CRITICAL_RADIUS_NEWTON_STEPS):
    """Fraction of droplets lost to the wall by diffusion, 1 − P_diff.

    1 − x_c²(2 − x_c²) = (1 − x_c²)², evaluated in that factored form so the
    small loss (~1e-4 at AJ conditions) keeps full precision.
    """
    x_c = critical_radius(jnp.pi * length * diffusivity / flow_rate, newton_steps)
    return (1.0 - x_c**2) ** 2


def diffusion_survival(diffusivity, flow_rate, length):
    """Fraction of droplets surviving diffusion to the wall of a straight channel.

    P_diff = x_c²(2 − x_c²) with (1 − x_c)²(1 − x_c²) = π L D / Q.

    Parameters
    ----------
    diffusivity : array
        D [m²/s].
    flow_rate : array
        Q [m³/s] through the channel (nozzle: Q_c + Q_s).
    length : float
        L [m].

    Returns
    -------
    array
        Survival probability in [0, 1].
    """
    x_c = critical_radius(jnp.pi * length * diffusivity / flow_rate)
    return x_c**2 * (2.0 - x_c**2)


def _settling_terms(quadrature_order, median_diameter, tube_radius, carrier_flow, params):
    """F_T and Σ_i ∂F_T/∂ln α_i, Σ_i ∂F_T/∂ln α_i · ∂ln v_ts/∂ln d at d_i (module docstring)."""
    d, w = lognormal_quadrature(median_diameter, params.droplet_cv, quadrature_order)
    v_ts = settling_velocity(
        d,
        params.droplet_density,
        params.gravity,
        params.settling_viscosity,
        params.mean_free_path,
    )
    radius = jnp.asarray(tube_radius)[..., None]
    speed = jnp.asarray(carrier_flow / (jnp.pi * tube_radius**2))[..., None]
    survival = settling_survival(v_ts, speed, params.tube_length, radius)
    value = jnp.sum(w * (1.0 - survival), axis=-1)
    alpha, beta = _settling_alpha_beta(v_ts, speed, params.tube_length, radius)
    per_log_alpha = w * (16.0 / jnp.pi) * alpha**3 * beta
    per_log_speed = 2.0 + slip_log_slope(d, params.mean_free_path)
    return value, jnp.sum(per_log_alpha, axis=-1), jnp.sum(per_log_alpha * per_log_speed, axis=-1)


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def settled_fraction(quadrature_order, median_diameter, tube_radius, carrier_flow, params):
    """F_T = ∫(1 − P_grav(d; Q_c, R)) p(d) dd: the share of the droplets settling in the tube.

    Parameters: quadrature order (static), d_a [m], R = r_T0 − ΔR_T [m], Q_c [m³/s],
    params (SI). Differentiated in closed form (module docstring).
    """
    return _settling_terms(quadrature_order, median_diameter, tube_radius, carrier_flow, params)[0]


def _settled_fraction_jvp(quadrature_order, primals, tangents):
    median_diameter, tube_radius, carrier_flow, params = primals
    d_diameter, d_radius, d_flow = (_dense(t) for t in tangents[:3])
    d_params = tangents[3]
    value, per_log_alpha, per_log_diameter = _settling_terms(
        quadrature_order, median_diameter, tube_radius, carrier_flow, params
    )
    # ln α = (ln v_ts + ln R − ln Q)/3 + const
    tangent = (
        per_log_diameter * d_diameter / median_diameter
        + per_log_alpha * (d_radius / tube_radius - d_flow / carrier_flow)
    ) / 3.0
    tangent = tangent + _parameter_tangent(
        lambda p: _settling_terms(quadrature_order, median_diameter, tube_radius, carrier_flow, p)[
            0
        ],
        params,
        d_params,
    )
    return value, tangent


def _diffusion_terms(quadrature_order, newton_steps, median_diameter, total_flow, params):
    """F_N and Σ_i μ_i ∂(1 − P_diff)/∂μ_i · ∂ln μ/∂ln d at d_i, Σ_i μ_i ∂(1 − P_diff)/∂μ_i."""
    d, w = lognormal_quadrature(median_diameter, params.droplet_cv, quadrature_order)
    diffusivity = diffusion_coefficient(
        d, params.temperature, params.gas_viscosity, params.mean_free_path, params.boltzmann
    )
    flow = jnp.asarray(total_flow)[..., None]
    x_c = critical_radius(jnp.pi * params.nozzle_length * diffusivity / flow, newton_steps)
    eps = 1.0 - x_c
    loss = (1.0 - x_c**2) ** 2  # the factored form of diffusion_loss
    per_log_mu = w * 2.0 * eps**2 * (2.0 - eps) ** 2 * (1.0 - eps) / (3.0 - 2.0 * eps)
    per_log_diameter = per_log_mu * (slip_log_slope(d, params.mean_free_path) - 1.0)
    return (
        jnp.sum(w * loss, axis=-1),
        jnp.sum(per_log_diameter, axis=-1),
        jnp.sum(per_log_mu, axis=-1),
    )


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def diffused_fraction(quadrature_order, newton_steps, median_diameter, total_flow, params):
    """F_N = ∫(1 − P_diff(d; Q)) p(d) dd: the share of the droplets reaching the nozzle wall.

    Parameters: quadrature order and Newton steps (static), d_a [m], Q = Q_c + Q_s [m³/s],
    params (SI). Differentiated in closed form (module docstring).
    """
    return _diffusion_terms(quadrature_order, newton_steps, median_diameter, total_flow, params)[0]


def _diffused_fraction_jvp(quadrature_order, newton_steps, primals, tangents):
    median_diameter, total_flow, params = primals
    d_diameter, d_flow = (_dense(t) for t in tangents[:2])
    d_params = tangents[2]
    value, per_log_diameter, per_log_mu = _diffusion_terms(
        quadrature_order, newton_steps, median_diameter, total_flow, params
    )
    # ln μ = ln D(d) − ln Q + const
    tangent = per_log_diameter * d_diameter / median_diameter - per_log_mu * d_flow / total_flow
    tangent = tangent + _parameter_tangent(
        lambda p: _diffusion_terms(quadrature_order, newton_steps, median_diameter, total_flow, p)[
            0
        ],
        params,
        d_params,
    )
    return value, tangent


def _is_zero(tangent) -> bool:
    return isinstance(tangent, jax.custom_derivatives.SymbolicZero)


def _dense(tangent):
    """A tangent as an array; a symbolic zero (argument not differentiated) as 0."""
    return 0.0 if _is_zero(tangent) else tangent


def _parameter_tangent(of_params, params, d_params):
    """The tangent through the parameters, automatic; 0 when they are not differentiated.

    Zero tangents arrive symbolic (``symbolic_zeros=True``), so the common case — the
    state or the inputs differentiated, the parameters not — costs nothing here.
    """
    leaves = jax.tree.leaves(d_params, is_leaf=_is_zero)
    if all(_is_zero(leaf) for leaf in leaves):
        return 0.0
    dense = jax.tree.map(
        lambda t, p: jnp.zeros_like(jnp.asarray(p, dtype=float)) if _is_zero(t) else t,
        d_params,
        params,
        is_leaf=_is_zero,
    )
    return jax.jvp(of_params, (params,), (dense,))[1]


settled_fraction.defjvp(_settled_fraction_jvp, symbolic_zeros=True)
diffused_fraction.defjvp(_diffused_fraction_jvp, symbolic_zeros=True)


def tube_deposition_rate(
    aerosol_fraction,
    median_diameter,
    tube_deposition,
    carrier_flow,
    params,
    quadrature_order=QUADRATURE_ORDER,
):
    """dΔR_T/dt [m/s]: radial ink build-up in the transport tube by settling.

    dΔR_T/dt = Q_d ∫(1 − P_grav(d; Q_c, ΔR_T)) p(d) dd / (2π (r_T0 − ΔR_T) L_T),
    Q_d = φ_A Q_c. (θ_RT ΔR_T is added by the assembled transition model.)

    Parameters
    ----------
    aerosol_fraction : φ_A [-]
    median_diameter : d_a [m]
    tube_deposition : ΔR_T [m]
    carrier_flow : Q_c [m³/s]
    params : PhysicalParameters (SI)
    quadrature_order : int (static)
    """
    radius = params.tube_radius - tube_deposition
    deposited_fraction = settled_fraction(
        quadrature_order, median_diameter, radius, carrier_flow, params
    )
    droplet_flow = aerosol_fraction * carrier_flow
    return droplet_flow * deposited_fraction / (2.0 * jnp.pi * radius * params.tube_length)


def nozzle_deposition_rate(
    aerosol_fraction,
    median_diameter,
    nozzle_deposition,
    carrier_flow,
    sheath_flow,
    params,
    quadrature_order=QUADRATURE_ORDER,
    newton_steps=CRITICAL_RADIUS_NEWTON_STEPS,
):
    """dΔR_N/dt [m/s]: radial ink build-up in the nozzle by diffusion.

    dΔR_N/dt = Q_d ∫(1 − P_diff(d; Q_c + Q_s)) p(d) dd / (2π (r_N0 − ΔR_N) L_N),
    Q_d = φ_A Q_c. The nozzle is vertical, so settling does not act there.

    Parameters
    ----------
    aerosol_fraction : φ_A [-]
    median_diameter : d_a [m]
    nozzle_deposition : ΔR_N [m]
    carrier_flow, sheath_flow : Q_c, Q_s [m³/s]
    params : PhysicalParameters (SI)
    quadrature_order, newton_steps : int (static)
    """
    deposited_fraction = diffused_fraction(
        quadrature_order, newton_steps, median_diameter, carrier_flow + sheath_flow, params
    )
    droplet_flow = aerosol_fraction * carrier_flow
    radius = params.nozzle_radius - nozzle_deposition
    return droplet_flow * deposited_fraction / (2.0 * jnp.pi * radius * params.nozzle_length)
