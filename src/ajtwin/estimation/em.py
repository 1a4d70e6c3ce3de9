"""Expectation–maximisation of the drift parameters θ (paper Algorithm 2, model reference §7).

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

from ajtwin._aot import exported_jit
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


class EMSettings(NamedTuple):
    """How EM iterates over a window (a pytree: one compiled loop for any values).

    Attributes
    ----------
    theta_prior_precision : array (5,)
        Precision of θ's MAP prior [s²] (0: flat).
    max_iterations : int
        M-steps at most.
    tolerance : float
        Stop when the window's log-likelihood changes less than this [nats per step].
    gate : float
        The filter's innovation gate in σ (inf: off).
    """

    theta_prior_precision: object = None
    max_iterations: int = 10
    tolerance: float = 1e-3
    gate: float = np.inf


class EMStep(NamedTuple):
    """The result of EM over one window.

    Attributes
    ----------
    theta : array (5,)
        The drift parameters θ [1/s].
    iterations : int
    converged : bool
    log_likelihood : float
        Of the window under the final θ's E-step.
    filtered : FilterResult
        Of the last E-step.
    smoothed : SmootherResult
    """

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
    transitions=None,
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
    transitions : array (T − 1,) bool, optional
        Which transitions j → j+1 the sums take (None: all). The others are left out
        whatever their terms hold (NaN included): a window padded at its end
        (:func:`em_loop`) sums its own transitions only.

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

    def value_and_b(x, u_j):
        # f_d is linear in θ: its value at θ = 0 is a(x), its θ-Jacobian is B(x)
        def f_theta(th):
            value = functions.step(x, u_j, th, params, dt)
            return value, value

        b, a = jax.jacfwd(f_theta, has_aux=True)(theta_zero)
        return (b, a), (b, a)

    def per_step(x_j, x_next, p_j, c_next_j, u_j):
        # one nested forward pass gives a, B and their x-Jacobians ∂B/∂x_m and A = ∂a/∂x
        (db, a_jac), (b, a) = jax.jacfwd(value_and_b, has_aux=True)(x_j, u_j)  # db: (n, n_θ, n)
        residual = x_next - a
        cov_x_r = c_next_j.T - p_j @ a_jac.T  # (n, n): Cov(x_m, r_i)
        normal = b.T @ weight @ b + jnp.einsum("ikm,mn,jln,ij->kl", db, p_j, db, weight)
        rhs = b.T @ weight @ residual + jnp.einsum("ikm,ij,mj->k", db, weight, cov_x_r)
        return normal, rhs

    normals, rhss = jax.vmap(per_step)(means[:-1], means[1:], covs[:-1], lag, u[:-1])
    if transitions is not None:
        normals = jnp.where(transitions[:, None, None], normals, 0.0)
        rhss = jnp.where(transitions[:, None], rhss, 0.0)
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
    settings: EMSettings | None = None,
    functions: ModelFunctions = AJ_EULER,
    line_factors=None,
    padded_steps: int | None = None,
) -> EMStep:
    """EM over one window (paper Algorithm 2).

    Iterates E-step (EKF + RTS with θ⁽ⁱ⁾) and M-step until the change of the
    window's log-likelihood is below ``settings.tolerance`` (absolute, nats per step)
    or ``settings.max_iterations`` is reached. A non-finite θ or log-likelihood ends the
    iterations and keeps the last good θ. The whole loop is one compiled
    function (:func:`em_loop`), so a new process loads one executable from the
    compilation cache instead of tracing every iteration's pieces. ``line_factors``
    (T, 4): a job print's per-step line factors (:func:`ajtwin.estimation.filters.ekf`).

    ``padded_steps``: the length every window is run at, so that windows of any length
    up to it share one compiled program (the twin's early windows and its full ones). A
    shorter window gets steps without measurements appended (inputs and line factors
    held from its last step); they weigh nothing in θ, ℓ or the convergence test and the
    smoother does not look past the window (:func:`em_loop`), so the result is the
    window's own, returned at the window's length. None: the window's own length.

    Returns
    -------
    EMStep
        Final θ, iterations used, convergence flag, and the final E-step
        (filter and smoother under the returned θ).
    """
    args, kwargs, n = _em_arguments(
        spec, prior_mean, prior_cov, inputs, measurements, theta0, process_cov,
        measurement_cov, settings, functions, line_factors, padded_steps,
    )  # fmt: skip
    theta, iterations, converged, log_lik, filtered, smoothed = em_loop(*args, **kwargs)
    # back to the window's length (on the host: slicing dispatches no JAX operation)
    filtered = FilterResult(*(np.asarray(a)[:n] for a in filtered))
    smoothed = SmootherResult(
        np.asarray(smoothed.means)[:n],
        np.asarray(smoothed.covariances)[:n],
        np.asarray(smoothed.lag_one_covariances)[: n - 1],
    )
    return EMStep(
        np.asarray(theta), int(iterations), bool(converged), float(log_lik), filtered, smoothed
    )


def prefetch_em(*args, **kwargs) -> None:
    """Start loading the kept EM program that :func:`run_em` with these arguments (their
    shapes: the values do not matter) will run, in the background (:mod:`ajtwin._aot`):
    a 2 MB executable whose load then overlaps the start's fit and the first filtering."""
    call_args, call_kwargs, _ = _em_arguments(*args, **kwargs)
    em_loop.prefetch(*call_args, **call_kwargs)


def _em_arguments(
    spec,
    prior_mean,
    prior_cov,
    inputs,
    measurements,
    theta0,
    process_cov,
    measurement_cov,
    settings: EMSettings | None = None,
    functions: ModelFunctions = AJ_EULER,
    line_factors=None,
    padded_steps: int | None = None,
):
    """:func:`em_loop`'s arguments for :func:`run_em`'s (the window padded to
    ``padded_steps``), and the window's own length."""
    settings = settings or EMSettings()
    precision = settings.theta_prior_precision
    if precision is None:
        precision = np.zeros(np.asarray(theta0).shape[-1])
    settings = EMSettings(
        np.asarray(precision, dtype=float),
        np.asarray(settings.max_iterations, dtype=int),
        np.asarray(settings.tolerance, dtype=float),
        np.asarray(settings.gate, dtype=float),
    )
    inputs = np.asarray(inputs, dtype=float)
    measurements = np.asarray(measurements, dtype=float)
    line = None if line_factors is None else np.asarray(line_factors, dtype=float)
    n = inputs.shape[0]
    length = n if padded_steps is None else int(padded_steps)
    if n > length:
        raise ValueError(f"an EM window of {n} steps is longer than padded_steps={length}")
    # the appended steps: inputs (and line factors) held, nothing measured
    held = np.repeat(inputs[-1:], length - n, axis=0)
    inputs = np.concatenate([inputs, held])
    measurements = np.concatenate(
        [measurements, np.full((length - n, measurements.shape[1]), np.nan)]
    )
    if line is not None:
        line = np.concatenate([line, np.repeat(line[-1:], length - n, axis=0)])
    args = (
        spec,
        np.asarray(prior_mean, dtype=float),
        np.asarray(prior_cov, dtype=float),
        inputs,
        measurements,
        np.asarray(theta0, dtype=float),
        np.asarray(process_cov, dtype=float),
        np.asarray(measurement_cov, dtype=float),
        settings,
        line,
    )
    return args, {"window_steps": np.asarray(n), "functions": functions}, n


def em_loop(
    spec,
    prior_mean,
    prior_cov,
    inputs,
    measurements,
    theta0,
    process_cov,
    measurement_cov,
    settings: EMSettings,
    line_factors=None,
    window_steps=None,
    functions=AJ_EULER,
):
    """The EM iterations of :func:`run_em` as a ``lax.while_loop`` (pure, jit-able).

    Pass j of the loop runs the M-step from the accepted smoother (pass 0: θ₀
    instead) and then the E-step under that θ, so the compiled loop holds one E-step
    and one M-step (an E-step before the loop would be a second copy to compile). The
    new iterate is accepted when θ and ℓ are finite (pass 0: always); the loop stops
    on a rejected iterate, on |Δℓ|/n < ``tolerance``, or after ``max_iterations``
    M-steps.

    The window is the first n = ``window_steps`` (a traced integer; None: all T) of the
    T steps; the steps after it are padding without measurements. The M-step weighs
    only the transitions inside the window, ℓ sums only its steps and the smoother
    starts its backward pass at its last step (:func:`e_step`), so θ, ℓ, the iterations
    and the filter and smoother at steps < n are those of the window alone: the filter
    runs forward, and steps without measurements leave the smoothed steps before them
    unchanged in exact arithmetic — here by construction, whatever the padding's
    predictions do.

    Returns
    -------
    (θ (n_θ,), iterations, converged, ℓ, FilterResult, SmootherResult)
        The filter and smoother over all T steps (at the padding: not the window's).
    """
    theta_prior_precision, max_iterations, tolerance, gate = settings
    n_total, n_states = inputs.shape[0], prior_mean.shape[0]
    n_steps = n_total if window_steps is None else window_steps
    in_window = jnp.arange(n_total) < n_steps
    inside = in_window[1:]  # transition j → j+1 within the window
    data = (prior_mean, prior_cov, inputs, measurements)
    noise = (process_cov, measurement_cov, gate)
    false = jnp.asarray(False)

    def keep_going(state):
        passes, _, _, _, _, stop, _ = state
        return ~stop & (passes <= max_iterations)  # passes − 1 M-steps done so far

    def one_pass(state):
        passes, theta, filtered, smoothed, log_lik, _, _ = state
        first = passes == 0
        theta_new = jax.lax.cond(
            first,
            lambda: theta0,
            lambda: m_step(
                spec, smoothed, inputs, process_cov, theta_prior_precision, functions, inside
            ),
        )
        filtered_new, smoothed_new, log_lik_new = e_step(
            spec, *data, theta_new, *noise, line_factors, in_window, functions=functions
        )
        finite = jnp.isfinite(log_lik_new) & jnp.all(jnp.isfinite(theta_new))
        accept = first | finite
        converged = ~first & finite & (jnp.abs(log_lik_new - log_lik) / n_steps < tolerance)

        def pick(new, old):
            return jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), new, old)

        return (
            passes + 1,
            pick(theta_new, theta),
            pick(filtered_new, filtered),
            pick(smoothed_new, smoothed),
            pick(log_lik_new, log_lik),
            ~accept | converged,
            converged,
        )

    state = (
        jnp.asarray(0),
        theta0,
        _empty_filter_result(n_total, n_states, measurements.shape[1]),
        _empty_smoother_result(n_total, n_states),
        jnp.zeros(()),
        false,
        false,
    )
    passes, theta, filtered, smoothed, log_lik, _, converged = jax.lax.while_loop(
        keep_going, one_pass, state
    )
    return theta, passes - 1, converged, log_lik, filtered, smoothed


def _empty_filter_result(n_steps, n, m):
    """Zeros shaped like an E-step's FilterResult (the loop's state before pass 0)."""
    vec, mat = jnp.zeros((n_steps, n)), jnp.zeros((n_steps, n, n))
    scalar = jnp.zeros(n_steps)
    return FilterResult(
        vec,
        mat,
        vec,
        mat,
        mat,
        jnp.zeros((n_steps, m)),
        jnp.zeros((n_steps, m)),
        scalar,
        scalar,
        jnp.zeros(n_steps, dtype=jnp.sum(jnp.zeros(1, dtype=bool)).dtype),
        jnp.zeros(n_steps, dtype=bool),
    )


def _empty_smoother_result(n_steps, n):
    return SmootherResult(
        jnp.zeros((n_steps, n)), jnp.zeros((n_steps, n, n)), jnp.zeros((n_steps - 1, n, n))
    )


em_loop = exported_jit(
    em_loop, static_argnames=("functions",), constant_fields=(("spec", "params"),)
)


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
    line_factors=None,
    in_window=None,
    functions=AJ_EULER,
):
    """E-step: EKF then RTS under θ; returns (filtered, smoothed, log-likelihood).

    ``in_window`` (T,) bool, a run of True then False (None: all True): the steps after
    the window are padding. ℓ sums the window's steps, and the smoother sees the padding
    inert (:func:`_inert_padding`), so its backward pass starts at the window's last step.
    """
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
        line_factors=line_factors,
    )
    if in_window is None:
        in_window = jnp.ones(inputs.shape[0], dtype=bool)
    smoothed = rts_smoother(spec, _inert_padding(filtered, in_window))
    return filtered, smoothed, jnp.sum(jnp.where(in_window, filtered.log_likelihood, 0.0))


def _inert_padding(filtered: FilterResult, in_window) -> FilterResult:
    """The filter's results as the smoother should see a window followed by padding.

    Every padding step holds the window's last filtered mean and covariance, as its
    filtered and its predicted values, and the transitions out of the window's last
    step and on are zero: the smoother's gains J_k = P_k Fₖᵀ P_{k+1|k}⁻¹ there are
    exactly 0 and nothing of the padding (a NaN or a divergence-guard reset of its
    predictions included) reaches the window. With no padding nothing changes (the last
    step's F is not used by the smoother).
    """
    last = jnp.sum(in_window) - 1
    padding = ~in_window

    def held(field, at_last):
        mask = padding.reshape((-1,) + (1,) * (field.ndim - 1))
        return jnp.where(mask, at_last, field)

    mean, cov = filtered.means[last], filtered.covariances[last]
    leaving = (jnp.arange(in_window.shape[0]) >= last)[:, None, None]
    return filtered._replace(
        means=held(filtered.means, mean),
        covariances=held(filtered.covariances, cov),
        predicted_means=held(filtered.predicted_means, mean),
        predicted_covariances=held(filtered.predicted_covariances, cov),
        transition_jacobians=jnp.where(leaving, 0.0, filtered.transition_jacobians),
    )


e_step = jax.jit(e_step, static_argnames=("functions",))
