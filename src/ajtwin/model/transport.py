"""Aerosol transport losses and ink build-up in the tube and nozzle (paper App. B).

* :func:`settling_survival` — Thomas (1958) survival of gravitational settling
  in a horizontal tube, P_grav = (2/π)(αβ + asin β − 2α³β),
  α = (3 L v_ts / (8 ū R))^{1/3} (clipped to ≤ 1), β = sqrt(1 − α²).
* :func:`diffusion_survival` — survival of diffusion to the wall,
  P_diff = x_c²(2 − x_c²), (1 − x_c)²(1 − x_c²) = π L D / Q.
* :func:`tube_deposition_rate` — dΔR_T/dt = Q_d ∫(1 − P_grav) p dd / (2π (r_T0 − ΔR_T) L_T).
* :func:`nozzle_deposition_rate` — dΔR_N/dt = Q_d ∫(1 − P_diff) p dd / (2π (r_N0 − ΔR_N) L_N).

SI units throughout (m, m³/s, m/s).
"""

from __future__ import annotations

from ajtwin._jax import jnp
from ajtwin.model.droplets import (
    QUADRATURE_ORDER,
    diffusion_coefficient,
    lognormal_quadrature,
    settling_velocity,
)

#: Newton steps for the critical radius. The start ε₀ (one fixed-point step of
#: ε = (μ/2)^{1/3}(1 − ε/2)^{−1/3}) is within 4e-5 relative of the root for the
#: operating box's μ ≤ 1e-4 and within 6 % for any μ ∈ (0, 1], so 3 quadratic
#: steps reach machine precision (≤ 1e-14 relative, tests/test_model_accuracy.py);
#: the former start μ^{1/3} (26 % off) needed 5–6.
CRITICAL_RADIUS_NEWTON_STEPS = 3


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
    alpha = jnp.cbrt(3.0 * tube_length * settling_speed / (8.0 * mean_gas_speed * tube_radius))
    alpha = jnp.minimum(alpha, 1.0)
    # double-where keeps the gradient finite where α hits 1 (β = 0, dβ/dα = ∞)
    one_minus = 1.0 - alpha**2
    inside = one_minus > 1e-15
    beta = jnp.where(inside, jnp.sqrt(jnp.where(inside, one_minus, 1.0)), 0.0)
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
    mean_speed = carrier_flow / (jnp.pi * radius**2)
    d, w = lognormal_quadrature(median_diameter, params.droplet_cv, quadrature_order)
    v_ts = settling_velocity(
        d,
        params.droplet_density,
        params.gravity,
        params.settling_viscosity,
        params.mean_free_path,
    )
    survival = settling_survival(
        v_ts,
        jnp.asarray(mean_speed)[..., None],
        params.tube_length,
        jnp.asarray(radius)[..., None],
    )
    deposited_fraction = jnp.sum(w * (1.0 - survival), axis=-1)
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
    d, w = lognormal_quadrature(median_diameter, params.droplet_cv, quadrature_order)
    diffusivity = diffusion_coefficient(
        d, params.temperature, params.gas_viscosity, params.mean_free_path, params.boltzmann
    )
    total_flow = jnp.asarray(carrier_flow + sheath_flow)[..., None]
    loss = diffusion_loss(diffusivity, total_flow, params.nozzle_length, newton_steps)
    deposited_fraction = jnp.sum(w * loss, axis=-1)
    droplet_flow = aerosol_fraction * carrier_flow
    radius = params.nozzle_radius - nozzle_deposition
    return droplet_flow * deposited_fraction / (2.0 * jnp.pi * radius * params.nozzle_length)
