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
from ajtwin.estimation.filters import (
    AJ_EULER,
    FilterResult,
    ModelFunctions,
    ModelSpec,
    SmootherResult,
    ekf,
    rts_smoother,
)


class EMStep(NamedTuple):
    theta: np.ndarray  # (5,)
    iterations: int
    converged: bool
    log_likelihood: float  # of the window under the final θ's E-step
    filtered: FilterResult  # of the last E-step
    smoothed: SmootherResult


def m_step(
    spec: ModelSpec,
    smoothed: SmootherResult,
    inputs,
    process_cov,
    theta_prior_precision,
    functions: ModelFunctions = AJ_EULER,
):
    """Closed-form M-step: θ maximising the expected complete-data log-likelihood.

    With the step written x_{j+1} = a(x_j) + B(x_j) θ + ξ (B = ∂f_d/∂θ), the
    expected normal equations under the smoothed Gaussian are, to first order,

        E[BᵀWB] ≈ B̂ᵀWB̂ + Σ_mn P_mn (∂B/∂x_m)ᵀ W (∂B/∂x_n)
        E[BᵀWr] ≈ B̂ᵀWr̂ + Σ_m (∂B/∂x_m)ᵀ W Cov(x_m, r),
        Cov(x_j, r_j) = Cov(x_j, x_{j+1}) − P_j Aᵀ,  A = ∂a/∂x,

    exact when B is linear in x (the AJ model: B = Δt·diag(x) plus the θ_Vl
    coupling into φ_A).

    Parameters
    ----------
    smoothed : SmootherResult over T steps
    inputs : array (T, n_u)
    process_cov : array (n, n) Σ_ξ (display units)
    theta_prior_precision : array (n_θ,) 1/σ_θ² (0: flat prior)

    Returns
    -------
    array (n_θ,)
    """
    params = spec.params
    dt = spec.dt
    means = smoothed.means
    covs = smoothed.covariances
    lag = smoothed.lag_one_covariances
    u = jnp.asarray(inputs)
    precision = jnp.asarray(theta_prior_precision)
    theta_zero = jnp.zeros(precision.shape[0])
    weight = jnp.linalg.inv(jnp.asarray(process_cov))

    def base(x, u_j):
        return functions.step(x, u_j, theta_zero, params, dt)

    def b_matrix(x, u_j):
        return jax.jacfwd(lambda th: functions.step(x, u_j, th, params, dt))(theta_zero)

    def per_step(x_j, x_next, p_j, c_next_j, u_j):
        residual = x_next - base(x_j, u_j)
        b = b_matrix(x_j, u_j)  # (n, n_θ)
        db = jax.jacfwd(b_matrix)(x_j, u_j)  # (n, n_θ, n): ∂B/∂x_m
        a_jac = jax.jacfwd(base)(x_j, u_j)
        cov_x_r = c_next_j.T - p_j @ a_jac.T  # (n, n): Cov(x_m, r_i)
        normal = b.T @ weight @ b + jnp.einsum("ikm,mn,jln,ij->kl", db, p_j, db, weight)
        rhs = b.T @ weight @ residual + jnp.einsum("ikm,ij,mj->k", db, weight, cov_x_r)
        return normal, rhs

    normals, rhss = jax.vmap(per_step)(means[:-1], means[1:], covs[:-1], lag, u[:-1])
    normal = normals.sum(axis=0) + jnp.diag(precision)
    rhs = rhss.sum(axis=0)
    # equilibrate before solving: the columns of B differ by ~10 orders of magnitude
    scale = jnp.sqrt(jnp.maximum(jnp.diag(normal), 1e-300))
    return jnp.linalg.solve(normal / jnp.outer(scale, scale), rhs / scale) / scale


m_step = jax.jit(m_step, static_argnames=("functions",))


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
    functions: ModelFunctions = AJ_EULER,
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
        theta_prior_precision = np.zeros(np.asarray(theta0).shape[-1])
    precision = jnp.asarray(theta_prior_precision, dtype=float)
    theta = jnp.asarray(theta0, dtype=float)
    n_steps = np.asarray(inputs).shape[0]
    args = (prior_mean, prior_cov, inputs, measurements)
    noise = (process_cov, measurement_cov, gate)
    converged = False
    iterations = 0
    filtered, smoothed, log_lik = e_step(spec, *args, theta, *noise, functions=functions)
    log_lik = float(log_lik)
    for iteration in range(1, max_iterations + 1):
        iterations = iteration
        theta_new = m_step(spec, smoothed, inputs, process_cov, precision, functions)
        filtered_new, smoothed_new, log_lik_new = e_step(
            spec, *args, theta_new, *noise, functions=functions
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
    functions=AJ_EULER,
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
        functions=functions,
    )
    return filtered, rts_smoother(spec, filtered), jnp.sum(filtered.log_likelihood)


e_step = jax.jit(e_step, static_argnames=("functions",))
