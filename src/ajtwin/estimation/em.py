"""Expectation–maximisation of the drift parameters θ (paper Algorithm 2, SPEC §7).

E-step: EKF + RTS over a window with θ⁽ⁱ⁾. M-step: minimise

    Σ_j E‖x_{j+1} − f_d(x_j, u_j; θ)‖²_{Σ_ξ⁻¹}

over θ. The transition is linear in θ, f_d(x, u; θ) = f_d(x, u; 0) + Δt D(x) θ,
with D = ∂f/∂θ (diag(x) plus the θ_Vl coupling into φ_A), so the M-step is the
weighted least-squares solve

    (Σ_j E[Dⱼᵀ W Dⱼ] Δt² + Λ) θ = Σ_j E[Dⱼᵀ W (x_{j+1} − f_d(x_j; 0))] Δt,

W = Σ_ξ⁻¹. The expectations use the smoothed Gaussian to first order: the
diagonal of Dᵀ W D gains the smoothed variances P_{j|N} and the right-hand
side the lag-one cross-covariances (so a state the data barely pins down, like
ΔR_T, does not get a wild θ from its noisy mean). Λ = diag(1/σ_θ²) is an
optional Gaussian prior on θ (MAP-EM) that keeps unidentifiable components at
zero; it is still a closed form.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.estimation.filters import FilterResult, ModelSpec, SmootherResult, ekf, rts_smoother
from ajtwin.model.system import transition_rates


class EMStep(NamedTuple):
    theta: np.ndarray  # (5,)
    iterations: int
    converged: bool
    log_likelihood: float  # of the window under the final θ's E-step
    filtered: FilterResult  # of the last E-step
    smoothed: SmootherResult


def m_step(spec: ModelSpec, smoothed: SmootherResult, inputs, process_cov, theta_prior_precision):
    """Closed-form M-step: θ maximising the expected complete-data log-likelihood.

    Parameters
    ----------
    smoothed : SmootherResult over T steps
    inputs : array (T, 3)
    process_cov : array (5, 5) Σ_ξ (display units, diagonal used)
    theta_prior_precision : array (5,) 1/σ_θ² (0: flat prior)

    Returns
    -------
    array (5,)
        θ [1/s].
    """
    dt = spec.dt
    params = spec.params
    means = smoothed.means
    covs = smoothed.covariances
    lag = smoothed.lag_one_covariances
    u = jnp.asarray(inputs)
    zeros = jnp.zeros(5)
    weight = 1.0 / jnp.diag(jnp.asarray(process_cov))

    def per_step(x_j, x_next, p_j, c_next_j, u_j):
        base = x_j + dt * transition_rates(x_j, u_j, zeros, params)
        d_mat = jax.jacfwd(transition_rates, argnums=2)(x_j, u_j, zeros, params)  # ∂f/∂θ
        f0_jac = jax.jacfwd(lambda x: x + dt * transition_rates(x, u_j, zeros, params))(x_j)
        residual = x_next - base
        normal = dt**2 * (d_mat.T * weight) @ d_mat
        rhs = dt * (d_mat.T * weight) @ residual
        # first-order expectation corrections on the diagonal part D = diag(x)
        normal = normal + dt**2 * jnp.diag(weight * jnp.diag(p_j))
        cross = jnp.diag(c_next_j) - jnp.diag(f0_jac @ p_j)
        rhs = rhs + dt * weight * cross
        return normal, rhs

    normals, rhss = jax.vmap(per_step)(means[:-1], means[1:], covs[:-1], lag, u[:-1])
    normal = normals.sum(axis=0) + jnp.diag(jnp.asarray(theta_prior_precision))
    rhs = rhss.sum(axis=0)
    # rows with no information (all zero) stay at θ = 0
    scale = jnp.sqrt(jnp.maximum(jnp.diag(normal), 1e-300))
    theta = jnp.linalg.solve(normal / jnp.outer(scale, scale), rhs / scale) / scale
    return theta


m_step = jax.jit(m_step)


def run_em(
    spec: ModelSpec,
    prior_mean,
    prior_cov,
    inputs,
    measurements,
    theta0,
    process_cov,
    measurement_cov,
    *,
    theta_prior_precision=None,
    max_iterations: int = 10,
    tolerance: float = 1e-3,
    gate: float = np.inf,
    method: str = "euler",
) -> EMStep:
    """EM over one window (paper Algorithm 2).

    Iterates E-step (EKF + RTS with θ⁽ⁱ⁾) and M-step until the change of the
    window's log-likelihood is below ``tolerance`` (absolute, nats per step)
    or ``max_iterations`` is reached.

    Returns
    -------
    EMStep
        Final θ, iterations used, convergence flag, and the final E-step
        (filter and smoother under the returned θ).
    """
    if theta_prior_precision is None:
        theta_prior_precision = np.zeros(5)
    precision = jnp.asarray(theta_prior_precision, dtype=float)
    theta = jnp.asarray(theta0, dtype=float)
    n_steps = np.asarray(inputs).shape[0]
    args = (prior_mean, prior_cov, inputs, measurements)
    noise = (process_cov, measurement_cov, gate)
    converged = False
    iterations = 0
    filtered, smoothed, log_lik = e_step(spec, *args, theta, *noise, method=method)
    log_lik = float(log_lik)
    for iterations in range(1, max_iterations + 1):
        theta_new = m_step(spec, smoothed, inputs, process_cov, precision)
        filtered_new, smoothed_new, log_lik_new = e_step(
            spec, *args, theta_new, *noise, method=method
        )
        log_lik_new = float(log_lik_new)
        if not np.isfinite(log_lik_new) or not np.all(np.isfinite(np.asarray(theta_new))):
            break  # keep the last good θ
        change = abs(log_lik_new - log_lik) / n_steps
        theta, filtered, smoothed, log_lik = theta_new, filtered_new, smoothed_new, log_lik_new
        if change < tolerance:
            converged = True
            break
    return EMStep(np.asarray(theta), iterations, converged, log_lik, filtered, smoothed)


def e_step(
    spec,
    prior_mean,
    prior_cov,
    inputs,
    measurements,
    theta,
    process_cov,
    measurement_cov,
    gate,
    method="euler",
):
    """E-step: EKF then RTS under θ; returns (filtered, smoothed, log-likelihood)."""
    filtered = ekf(
        spec,
        prior_mean,
        prior_cov,
        inputs,
        measurements,
        theta,
        process_cov,
        measurement_cov,
        gate,
        method=method,
    )
    return filtered, rts_smoother(spec, filtered), jnp.sum(filtered.log_likelihood)


e_step = jax.jit(e_step, static_argnames=("method",))
