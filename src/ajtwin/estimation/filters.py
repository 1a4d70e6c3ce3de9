"""Extended Kalman filter and Rauch–Tung–Striebel smoother (paper Alg. 1, App. E).

Pure JAX, ``lax.scan`` loops, in *scaled* coordinates: the raw states span
15 orders of magnitude (φ_A ~ 1e-7, d_a ~ 3 µm), so the filter runs on
z = x / s and η = y / r with the scales of :class:`Scaling`; the results are
converted back to display units at the boundary.

Model (discrete, Δt = 1 s):

    x_{k+1} = f_d(x_k, u_k; θ_k) + ξ_k,   ξ_k ~ N(0, Σ_ξ)
    y_k     = g(x_k, u_k) + w_k,          w_k ~ N(0, Σ_w)

EKF step k (paper Algorithm 1, with the measurement at k taken after the
prediction to k):

    x̂_{k|k-1} = f_d(x̂_{k-1}, u_{k-1}),  F_{k-1} = ∂f_d/∂x,  P_{k|k-1} = F P Fᵀ + Σ_ξ
    H_k = ∂g/∂x at x̂_{k|k-1},  S = H P Hᵀ + Σ_w,  K = P Hᵀ S⁻¹
    x̂_k = x̂_{k|k-1} + K (y_k − g(x̂_{k|k-1}, u_k))
    P_k = (I − K H) P (I − K H)ᵀ + K Σ_w Kᵀ          (Joseph form: stays PSD)

Missing measurements (NaN) drop their rows (H row 0, innovation 0, unit
variance), so the update uses only what was measured; optional per-output
innovation gating drops outliers the same way. A divergence guard replaces a
non-finite or non-positive-definite posterior by the prior covariance P₀ at the
predicted mean and flags the step.

RTS (paper App. E): J_k = P_k F_kᵀ P_{k+1|k}⁻¹,
x̂_{k|N} = x̂_k + J_k (x̂_{k+1|N} − x̂_{k+1|k}),
P_{k|N} = P_k + J_k (P_{k+1|N} − P_{k+1|k}) J_kᵀ; the lag-one cross-covariance
P_{k+1,k|N} = P_{k+1|N} J_kᵀ is returned for the EM M-step.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.model.system import euler_step, output_function, rk4_step

#: Typical magnitudes of the states [µm, mL, µm, µm, –] and outputs
#: [µm, µm, Pa, Pa, mL/s]: the filter works on x/s and y/r.
STATE_SCALE = np.array([1.0, 1.0, 1e-3, 1e-2, 1e-7])
OUTPUT_SCALE = np.array([1.0, 1.0, 1.0, 1.0, 1e-9])


class ModelFunctions(NamedTuple):
    """The model the filters run on (static, hashable).

    ``step(x, u, theta, params, dt) -> x_next`` and
    ``output(x, u, params, coefficients) -> y``, display units. The transition
    must be linear in θ for the closed-form M-step.
    """

    step: object
    output: object


AJ_EULER = ModelFunctions(euler_step, output_function)
AJ_RK4 = ModelFunctions(rk4_step, output_function)


def model_functions(method: str) -> ModelFunctions:
    """The AJ model with the Euler (default) or RK4 discretisation."""
    if method not in ("euler", "rk4"):
        raise ValueError(f"method {method!r}; choose 'euler' or 'rk4'")
    return AJ_RK4 if method == "rk4" else AJ_EULER


class Scaling(NamedTuple):
    state: jnp.ndarray  # (5,)
    output: jnp.ndarray  # (5,)


DEFAULT_SCALING = Scaling(jnp.asarray(STATE_SCALE), jnp.asarray(OUTPUT_SCALE))


class ModelSpec(NamedTuple):
    """Everything the filter needs about the model (a pytree)."""

    params: object  # PhysicalParameters
    coefficients: jnp.ndarray  # (2, 8)
    scaling: Scaling
    dt: float = 1.0


class FilterResult(NamedTuple):
    """EKF output, display units. T = number of time steps."""

    means: jnp.ndarray  # (T, 5) filtered x̂_k
    covariances: jnp.ndarray  # (T, 5, 5) P_k
    predicted_means: jnp.ndarray  # (T, 5) x̂_{k|k-1} (k = 0: the prior)
    predicted_covariances: jnp.ndarray  # (T, 5, 5)
    transition_jacobians: jnp.ndarray  # (T, 5, 5) F_k = ∂f_d/∂x at (x̂_k, u_k), scaled coords
    predicted_outputs: jnp.ndarray  # (T, 5) g(x̂_{k|k-1}, u_k)
    innovation_variances: jnp.ndarray  # (T, 5) diag of S_k (display units²)
    log_likelihood: jnp.ndarray  # (T,) log N(y_k; ŷ_k, S_k) over the measured entries
    nis: jnp.ndarray  # (T,) normalised innovation squared νᵀ S⁻¹ ν
    n_measured: jnp.ndarray  # (T,) number of outputs used at k
    reinitialised: jnp.ndarray  # (T,) divergence guard fired at k


class SmootherResult(NamedTuple):
    means: jnp.ndarray  # (T, 5) x̂_{k|N}
    covariances: jnp.ndarray  # (T, 5, 5) P_{k|N}
    lag_one_covariances: jnp.ndarray  # (T-1, 5, 5) Cov(x_{k+1}, x_k | all)


def _scaled_functions(spec: ModelSpec, functions: ModelFunctions):
    s, r = spec.scaling.state, spec.scaling.output

    def f_scaled(z, u, theta):
        return functions.step(z * s, u, theta, spec.params, spec.dt) / s

    def g_scaled(z, u):
        return functions.output(z * s, u, spec.params, spec.coefficients) / r

    return f_scaled, g_scaled


def _is_valid_covariance(p):
    sym = 0.5 * (p + p.T)
    finite = jnp.all(jnp.isfinite(sym))
    eig_min = jnp.min(jnp.linalg.eigvalsh(jnp.where(finite, sym, jnp.eye(sym.shape[0]))))
    return finite & (eig_min > -1e-9 * jnp.max(jnp.abs(jnp.diag(sym)))) & jnp.all(jnp.diag(sym) > 0)


class EKFCarry(NamedTuple):
    """What the EKF carries from one step to the next (scaled coordinates z = x / s).

    ``prior_*`` is where the divergence guard restarts (the start of the run).
    """

    predicted_mean: jnp.ndarray  # (5,) z_{k|k-1}
    predicted_cov: jnp.ndarray  # (5, 5)
    prior_mean: jnp.ndarray  # (5,) z₀
    prior_cov: jnp.ndarray  # (5, 5)


class EKFStep(NamedTuple):
    """One EKF step's results, display units (one row of :class:`FilterResult`)."""

    mean: jnp.ndarray  # (5,)
    covariance: jnp.ndarray  # (5, 5)
    predicted_mean: jnp.ndarray  # (5,)
    predicted_covariance: jnp.ndarray  # (5, 5)
    transition_jacobian: jnp.ndarray  # (5, 5) scaled coords
    predicted_output: jnp.ndarray  # (5,)
    innovation_variance: jnp.ndarray  # (5,)
    log_likelihood: jnp.ndarray  # ()
    nis: jnp.ndarray  # ()
    n_measured: jnp.ndarray  # ()
    reinitialised: jnp.ndarray  # ()


def ekf_init(spec: ModelSpec, prior_mean, prior_cov) -> EKFCarry:
    """The carry before the first step: prior x̂₀ (5,), P₀ (5, 5) in display units."""
    s = spec.scaling.state
    z0 = jnp.asarray(prior_mean, dtype=float) / s
    p0 = jnp.asarray(prior_cov, dtype=float) / jnp.outer(s, s)
    return EKFCarry(z0, p0, z0, p0)


def ekf_step(
    spec: ModelSpec,
    carry: EKFCarry,
    u,
    y,
    theta,
    process_cov,
    measurement_cov,
    gate=jnp.inf,
    functions: ModelFunctions = AJ_EULER,
) -> tuple[EKFCarry, EKFStep]:
    """One EKF step k: update with y_k, then predict to k+1 with u_k and θ_k.

    The pure per-step function of :func:`ekf` (its ``lax.scan`` body) and of the
    live engine; jit it with ``functions`` static, vmap it over machines.

    Parameters
    ----------
    spec : ModelSpec
    carry : EKFCarry
        x̂_{k|k-1}, P_{k|k-1} and the guard's restart point (from :func:`ekf_init`
        or the previous step).
    u : array (3,)
        u_k [mA, sccm, sccm].
    y : array (5,)
        y_k, NaN where not measured.
    theta : array (5,)
        θ of the step k → k+1.
    process_cov : array (5, 5)
        Σ_ξ, display units.
    measurement_cov : array (5,)
        Diagonal of Σ_w, display units.
    gate : float
        Per-output innovation gate in σ (inf: off).
    functions : ModelFunctions

    Returns
    -------
    carry : EKFCarry for step k+1
    step : EKFStep (display units)
    """
    s, r = spec.scaling.state, spec.scaling.output
    f_s, g_s = _scaled_functions(spec, functions)
    # value and Jacobian from one forward-mode pass (the primal is not evaluated twice)
    f_and_jac = jax.jacfwd(lambda z, u, th: (f_s(z, u, th), f_s(z, u, th)), has_aux=True)
    g_and_jac = jax.jacfwd(lambda z, u: (g_s(z, u), g_s(z, u)), has_aux=True)
    q = jnp.asarray(process_cov) / jnp.outer(s, s)
    r_diag = jnp.asarray(measurement_cov) / r**2
    z_pred, p_pred, z0, p0 = carry
    eye = jnp.eye(z_pred.shape[0])
    log_2pi = jnp.log(2.0 * jnp.pi)

    # update with y_k
    eta = y / r
    measured = jnp.isfinite(eta)
    h, y_hat = g_and_jac(z_pred, u)
    innovation = jnp.where(measured, eta - y_hat, 0.0)
    s_full = h @ p_pred @ h.T + jnp.diag(r_diag)
    # per-output gate on the marginal innovation
    keep = measured & (innovation**2 <= gate**2 * jnp.diag(s_full))
    h_k = jnp.where(keep[:, None], h, 0.0)
    nu = jnp.where(keep, innovation, 0.0)
    r_k = jnp.where(keep, r_diag, 1.0)
    s_k = h_k @ p_pred @ h_k.T + jnp.diag(r_k)
    chol = jax.scipy.linalg.cho_factor(s_k, lower=True)
    gain = jax.scipy.linalg.cho_solve(chol, h_k @ p_pred).T
    z_post = z_pred + gain @ nu
    i_kh = eye - gain @ h_k
    p_post = i_kh @ p_pred @ i_kh.T + gain @ jnp.diag(r_k) @ gain.T
    p_post = 0.5 * (p_post + p_post.T)
    weighted = jax.scipy.linalg.cho_solve(chol, nu)
    nis = nu @ weighted
    # unit-variance dummies contribute log 1 = 0 to the determinant
    log_det = 2.0 * jnp.sum(jnp.log(jnp.diag(chol[0])))
    n_meas = jnp.sum(keep)
    log_lik = -0.5 * (nis + log_det + n_meas * log_2pi) - jnp.sum(jnp.where(keep, jnp.log(r), 0.0))
    s_display = jnp.diag(s_full) * r**2

    # divergence guard
    ok = jnp.all(jnp.isfinite(z_post)) & _is_valid_covariance(p_post)
    fallback = jnp.where(jnp.all(jnp.isfinite(z_pred)), z_pred, z0)
    z_post, p_post, reinit = jnp.where(ok, z_post, fallback), jnp.where(ok, p_post, p0), ~ok

    # predict to k+1
    f_jac, z_next = f_and_jac(z_post, u, theta)
    p_next = f_jac @ p_post @ f_jac.T + q
    p_next = 0.5 * (p_next + p_next.T)
    ss = jnp.outer(s, s)
    step = EKFStep(
        z_post * s,
        p_post * ss,
        z_pred * s,
        p_pred * ss,
        f_jac,
        y_hat * r,
        s_display,
        log_lik,
        nis,
        n_meas,
        reinit,
    )
    return EKFCarry(z_next, p_next, z0, p0), step


def ekf(
    spec: ModelSpec,
    prior_mean,
    prior_cov,
    inputs,
    measurements,
    thetas,
    process_cov,
    measurement_cov,
    gate: float = jnp.inf,
    functions: ModelFunctions = AJ_EULER,
) -> FilterResult:
    """Run the EKF over a print (:func:`ekf_step` in a ``lax.scan``).

    Parameters
    ----------
    spec : ModelSpec
    prior_mean : array (5,)
        x̂ at k = 0 before the first measurement, display units.
    prior_cov : array (5, 5)
        Its covariance, display units.
    inputs : array (T, 3)
        u_k [mA, sccm, sccm]; u_k drives the step k → k+1.
    measurements : array (T, 5)
        y_k, NaN where nothing was measured.
    thetas : array (5,) or (T, 5)
        θ used in the step k → k+1.
    process_cov : array (5, 5)
        Σ_ξ per step, display units.
    measurement_cov : array (5,)
        Diagonal of Σ_w, display units.
    gate : float
        Per-output innovation gate in standard deviations (inf: off).
    functions : ModelFunctions
        The model (default: the AJ model, Euler steps).

    Returns
    -------
    FilterResult
    """
    inputs = jnp.asarray(inputs, dtype=float)
    measurements = jnp.asarray(measurements, dtype=float)
    n_steps = inputs.shape[0]
    n_theta = jnp.asarray(thetas).shape[-1]
    thetas = jnp.broadcast_to(jnp.asarray(thetas, dtype=float), (n_steps, n_theta))

    def body(carry, inp):
        u, y, theta = inp
        return ekf_step(spec, carry, u, y, theta, process_cov, measurement_cov, gate, functions)

    carry = ekf_init(spec, prior_mean, prior_cov)
    _, steps = jax.lax.scan(body, carry, (inputs, measurements, thetas))
    return FilterResult(*steps)


ekf = jax.jit(ekf, static_argnames=("functions",))


def rts_smoother(spec: ModelSpec, filtered: FilterResult) -> SmootherResult:
    """Rauch–Tung–Striebel smoothing of an EKF run (paper App. E).

    Uses the EKF's own linearisations F_k, so it is the exact RTS smoother of
    the linearised model the filter saw.
    """
    s = spec.scaling.state
    ss = jnp.outer(s, s)
    z_f = filtered.means / s
    p_f = filtered.covariances / ss
    z_p = filtered.predicted_means / s
    p_p = filtered.predicted_covariances / ss
    f_jacs = filtered.transition_jacobians

    def body(carry, inp):
        z_next_s, p_next_s = carry
        z_k, p_k, f_k, z_next_p, p_next_p = inp
        # J = P_k Fᵀ P_{k+1|k}⁻¹ via a symmetric solve
        gain = jnp.linalg.solve(p_next_p, f_k @ p_k).T
        z_s = z_k + gain @ (z_next_s - z_next_p)
        p_s = p_k + gain @ (p_next_s - p_next_p) @ gain.T
        p_s = 0.5 * (p_s + p_s.T)
        lag_one = p_next_s @ gain.T
        return (z_s, p_s), (z_s, p_s, lag_one)

    last = (z_f[-1], p_f[-1])
    seq = (z_f[:-1], p_f[:-1], f_jacs[:-1], z_p[1:], p_p[1:])
    _, (z_s, p_s, lag) = jax.lax.scan(body, last, seq, reverse=True)
    z_s = jnp.concatenate([z_s, z_f[-1:]], axis=0)
    p_s = jnp.concatenate([p_s, p_f[-1:]], axis=0)
    return SmootherResult(means=z_s * s, covariances=p_s * ss, lag_one_covariances=lag * ss)


rts_smoother = jax.jit(rts_smoother)
