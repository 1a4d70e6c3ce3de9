"""Droplet-size distribution and single-droplet aerosol physics (paper App. B).

All functions are pure JAX, SI units in and out unless a name says otherwise.

* :func:`lognormal_quadrature` — Gauss–Hermite nodes in ln d for the
  log-normal droplet distribution p(d) with median d_a and a 25 % coefficient
  of variation (σ_ln = sqrt(ln(1 + CV²)), model reference §4); 8 nodes by default
  (:data:`QUADRATURE_ORDER`).
* :func:`cunningham_slip_correction` — C_c = 1 + Kn (1.257 + 0.4 e^{−1.1/Kn}),
  Kn = 2λ/d.
* :func:`settling_velocity` — Stokes terminal velocity with slip,
  v_ts = ρ_p d² g C_c / (18 η_settle).
* :func:`diffusion_coefficient` — Stokes–Einstein, D = k_B T C_c / (3π η_gas d)
  (the paper prints 2π, a typo; model reference §4).
"""

from __future__ import annotations

import functools

import numpy as np

from ajtwin._jax import jnp

#: Gauss–Hermite order for integrals over p(d). The integrands (settling and
#: diffusion losses over a log-normal with σ_ln = 0.246) are smooth over the
#: operating box: 8 nodes agree with a 64-node reference to ≤ 3e-12 relative
#: there and ≤ 1e-9 for d_a in 0.5–15 µm (tests/test_model_accuracy.py), at a
#: quarter of the 32-node cost per EKF step.
QUADRATURE_ORDER = 8


@functools.cache
def _hermite(order: int) -> tuple[np.ndarray, np.ndarray]:
    return np.polynomial.hermite.hermgauss(order)


def lognormal_sigma(coefficient_of_variation):
    """σ of ln d for a log-normal with the given coefficient of variation.

    σ_ln = sqrt(ln(1 + CV²)); CV = 0.25 gives σ_ln = 0.2462.
    """
    return jnp.sqrt(jnp.log1p(coefficient_of_variation**2))


def lognormal_quadrature(median_diameter, coefficient_of_variation=0.25, order=QUADRATURE_ORDER):
    """Nodes and weights that integrate over the log-normal droplet distribution.

    ∫ φ(d) p(d) dd ≈ Σ_i w_i φ(d_i), with d_i = d_a exp(√2 σ_ln t_i) and
    w_i = ω_i / √π for the Gauss–Hermite pairs (t_i, ω_i).

    Parameters
    ----------
    median_diameter : array (...)
        d_a, any length unit (nodes come back in the same unit).
    coefficient_of_variation : float
        Standard deviation / mean of d (paper: 1/4).
    order : int
        Number of nodes n (static; default :data:`QUADRATURE_ORDER`).

    Returns
    -------
    nodes : array (..., n)
        Droplet diameters.
    weights : array (n,)
        Probability weights; they sum to 1.

    Examples
    --------
    >>> d, w = lognormal_quadrature(3.5)
    >>> float(w.sum())
    1.0
    """
    sigma = lognormal_sigma(coefficient_of_variation)
    hermite_nodes, hermite_weights = _hermite(int(order))
    nodes = jnp.asarray(median_diameter)[..., None] * jnp.exp(
        jnp.sqrt(2.0) * sigma * jnp.asarray(hermite_nodes)
    )
    weights = jnp.asarray(hermite_weights) / jnp.sqrt(jnp.pi)
    return nodes, weights


def cunningham_slip_correction(diameter, mean_free_path):
    """Cunningham slip correction C_c for a droplet of diameter d (same units as λ).

    C_c = 1 + Kn (1.257 + 0.4 exp(−1.1/Kn)), Kn = 2λ/d.
    """
    knudsen = 2.0 * mean_free_path / diameter
    return 1.0 + knudsen * (1.257 + 0.4 * jnp.exp(-1.1 / knudsen))


def slip_log_slope(diameter, mean_free_path):
    """∂ln C_c/∂ln d of the Cunningham correction (same units for d and λ).

    With Kn = 2λ/d and C_c = 1 + Kn (1.257 + 0.4 e^{−1.1/Kn}):
    ∂ln C_c/∂ln d = −Kn (1.257 + 0.4 e^{−1.1/Kn} (1 + 1.1/Kn)) / C_c
    (0 for large droplets, → −1 in the free-molecular limit).
    """
    knudsen = 2.0 * mean_free_path / diameter
    decay = 0.4 * jnp.exp(-1.1 / knudsen)
    slip = 1.0 + knudsen * (1.257 + decay)
    return -knudsen * (1.257 + decay * (1.0 + 1.1 / knudsen)) / slip


def settling_velocity(diameter, droplet_density, gravity, settling_viscosity, mean_free_path):
    """Terminal settling velocity v_ts [m/s] of a droplet of diameter d [m].

    v_ts = ρ_p d² g C_c / (18 η_settle). η_settle is the paper's effective
    (calibrated) viscosity, not N₂'s (model reference §6).
    """
    slip = cunningham_slip_correction(diameter, mean_free_path)
    return droplet_density * diameter**2 * gravity * slip / (18.0 * settling_viscosity)


def diffusion_coefficient(diameter, temperature, gas_viscosity, mean_free_path, boltzmann):
    """Brownian diffusion coefficient D [m²/s] of a droplet of diameter d [m].

    Stokes–Einstein with slip: D = k_B T C_c / (3π η_gas d).
    """
    slip = cunningham_slip_correction(diameter, mean_free_path)
    return boltzmann * temperature * slip / (3.0 * jnp.pi * gas_viscosity * diameter)
