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

A *consider* state (``ModelSpec.update_mask`` 0: V_l in the twin) gets a zero gain row
(Schmidt–Kalman): its mean follows the model, its covariance stays exact.

A job print (model reference §12) adds a known input per step, ``line`` =
(F_w, F_o, v_w, v_o): the speed law's factors on L_w, L_o at the platen speed the
measured trace was printed at, and the variance factors of a camera measurement that
combines several frames of that second (:mod:`ajtwin.estimation.print_time`):

    g_k(x) = diag(F_w, F_o, 1, 1, 1) g(x, u_k)
    Σ_w,k  = diag(v_w σ²_Lw, v_o σ²_Lo, σ²_Pc, σ²_Ps, σ²_Qm)

Without it (``line=None``, every record without a job) the step is exactly the one above.

Missing measurements (NaN) drop their rows (H row 0, innovation 0, unit
variance), so the update uses only what was measured; optional per-output
innovation gating drops outliers the same way. A divergence guard replaces a
non-finite or non-positive-definite posterior by the prior covariance P₀ at the
predicted mean and flags the step.

The EKF's step is the public pure function :func:`ekf_step` (carry in, carry
and one step's outputs out), a streaming engine calls it per sample; it wraps
:func:`ekf_step_in_loop`, the same step with the per-run constants taken out and
results in scaled coordinates, which :func:`ekf` scans over a print. One math path.

RTS (paper App. E): J_k = P_k F_kᵀ P_{k+1|k}⁻¹,
x̂_{k|N} = x̂_k + J_k (x̂_{k+1|N} − x̂_{k+1|k}),
P_{k|N} = P_k + J_k (P_{k+1|N} − P_{k+1|k}) J_kᵀ; the lag-one cross-covariance
P_{k+1,k|N} = P_{k+1|N} J_kᵀ is returned for the EM M-step.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from ajtwin._aot import exported_jit
from ajtwin._jax import jax, jnp
from ajtwin.model.line_speed import apply_line_factors
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
    """Scales that make the filter's arithmetic well conditioned.

    Attributes
    ----------
    state : array (5,)
        Typical size of each state (display units).
    output : array (5,)
        Typical size of each output.
    """

    state: jnp.ndarray  # (5,)
    output: jnp.ndarray  # (5,)


# NumPy constants: made at import without dispatching a JAX operation
DEFAULT_SCALING = Scaling(STATE_SCALE, OUTPUT_SCALE)


class ModelSpec(NamedTuple):
    """Everything the filter needs about the model (a pytree)."""

    params: object  # PhysicalParameters
    coefficients: jnp.ndarray  # (2, 8)
    scaling: Scaling
    dt: float = 1.0
    #: (5,) 1 = the measurements update the state, 0 = a *consider* state (Schmidt–Kalman):
    #: its gain row is zero, so its mean follows the model alone while its covariance and
    #: cross-covariances stay exact (Joseph form holds for any gain). None: update all.
    update_mask: jnp.ndarray | None = None


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
    """The RTS smoother over a print.

    Attributes
    ----------
    means : array (T, 5)
        x̂_{k|N}.
    covariances : array (T, 5, 5)
        P_{k|N}.
    lag_one_covariances : array (T − 1, 5, 5)
        Cov(x_{k+1}, x_k | all data).
    """

    means: jnp.ndarray  # (T, 5) x̂_{k|N}
    covariances: jnp.ndarray  # (T, 5, 5) P_{k|N}
    lag_one_covariances: jnp.ndarray  # (T-1, 5, 5) Cov(x_{k+1}, x_k | all)


def _scaled_functions(spec: ModelSpec, functions: ModelFunctions, line=None):
    s, r = spec.scaling.state, spec.scaling.output

    def f_scaled(z, u, theta):
        return functions.step(z * s, u, theta, spec.params, spec.dt) / s

    def g_scaled(z, u):
        y = functions.output(z * s, u, spec.params, spec.coefficients)
        if line is not None:  # the line at the speed it was printed (a job print)
            y = apply_line_factors(y, line[0], line[1])
        return y / r

    return f_scaled, g_scaled


def line_variance_factors(line, n_outputs: int):
    """(n_outputs,) factors on Σ_w's diagonal of a job step ``line`` = (F_w, F_o, v_w, v_o):
    v_w, v_o on L_w, L_o (a combined camera measurement), 1 on the other outputs."""
    return jnp.concatenate([jnp.asarray(line[2:4], dtype=float), jnp.ones(n_outputs - 2)])


def _is_valid_covariance(p):
    """Finite, positive diagonal and eig_min > −1e-9 · max diag (a Cholesky test).

    The Cholesky factor of sym + 1e-9 · max|diag| · I exists exactly when
    eig_min(sym) > −1e-9 · max|diag|: the same test as an eigenvalue decomposition
    at a fraction of the cost. It is written out as symmetric Gaussian elimination
    (the pivots of LDLᵀ, all > 0 ⇔ positive definite) in plain element-wise ops:
    a LAPACK call is a custom call, which keeps XLA:CPU from compiling the
    filter's ``lax.scan`` into one kernel (see ``ajtwin._jax``), and for a 5×5
    matrix the call's overhead exceeds the arithmetic.
    """
    n = p.shape[0]
    sym = 0.5 * (p + p.T)
    finite = jnp.all(jnp.isfinite(sym))
    safe = jnp.where(finite, sym, jnp.eye(n))
    shift = 1e-9 * jnp.max(jnp.abs(jnp.diag(safe)))
    a = safe + shift * jnp.eye(n)
    positive = jnp.asarray(True)
    for _ in range(n):  # static: eliminate the first row/column, keep the trailing block
        pivot = a[0, 0]
        positive = positive & (pivot > 0)
        column = a[1:, 0]
        a = a[1:, 1:] - jnp.outer(column, column) / pivot
    return finite & positive & jnp.all(jnp.diag(sym) > 0)


class EKFCarry(NamedTuple):
    """What the EKF carries from one step to the next, in *scaled* coordinates.

    Build it with :func:`ekf_init`; the divergence guard falls back to the
    reset pair (the prior) when a posterior is not a valid covariance.
    """

    predicted_mean: jnp.ndarray  # (5,) z_{k|k-1} = x̂_{k|k-1} / s
    predicted_cov: jnp.ndarray  # (5, 5) P_{k|k-1} / (s sᵀ)
    reset_mean: jnp.ndarray  # (5,) z₀
    reset_cov: jnp.ndarray  # (5, 5) P₀ / (s sᵀ)


class EKFStepOutput(NamedTuple):
    """One EKF step's results (the per-step rows of :class:`FilterResult`)."""

    mean: jnp.ndarray  # (5,) x̂_k, display units
    covariance: jnp.ndarray  # (5, 5) P_k, display units
    predicted_mean: jnp.ndarray  # (5,) x̂_{k|k-1}
    predicted_covariance: jnp.ndarray  # (5, 5)
    transition_jacobian: jnp.ndarray  # (5, 5) F_k, scaled coordinates
    predicted_output: jnp.ndarray  # (5,) g(x̂_{k|k-1}, u_k)
    innovation_variance: jnp.ndarray  # (5,) diag S_k, display units²
    log_likelihood: jnp.ndarray  # ()
    nis: jnp.ndarray  # ()
    n_measured: jnp.ndarray  # ()
    reinitialised: jnp.ndarray  # () bool


def ekf_init(spec: ModelSpec, prior_mean, prior_cov) -> EKFCarry:
    """The EKF's carry before step 0: x̂_{0|−1} = prior, scaled; also the reset pair.

    On the host (no traced argument) in NumPy: a run's start and restarts dispatch no JAX
    operation."""
    traced = any(isinstance(a, jax.core.Tracer) for a in (prior_mean, prior_cov, *spec.scaling))
    xp = jnp if traced else np
    s = xp.asarray(spec.scaling.state)
    z0 = xp.asarray(prior_mean, dtype=float) / s
    p0 = xp.asarray(prior_cov, dtype=float) / xp.outer(s, s)
    return EKFCarry(z0, p0, z0, p0)


class StepConstants(NamedTuple):
    """What every EKF step of a run shares, in *scaled* coordinates (:func:`step_constants`).

    Computed once per run, outside the loop, so the step inside ``lax.scan`` does
    only per-sample work.
    """

    process_cov: jnp.ndarray  # (5, 5) Σ_ξ / (s sᵀ)
    measurement_var: jnp.ndarray  # (5,) diag Σ_w / r²
    log_output_scale: jnp.ndarray  # (5,) log r: the log-likelihood back in display units
    gate: jnp.ndarray  # () innovation gate in σ (inf: off)


def step_constants(spec: ModelSpec, process_cov, measurement_var, gate=jnp.inf) -> StepConstants:
    """Σ_ξ, diag Σ_w (display units) and the gate as the in-loop step wants them."""
    s, r = spec.scaling.state, spec.scaling.output
    return StepConstants(
        jnp.asarray(process_cov, dtype=float) / jnp.outer(s, s),
        jnp.asarray(measurement_var, dtype=float) / r**2,
        jnp.log(r),
        jnp.asarray(gate, dtype=float),
    )


def ekf_step_in_loop(
    spec: ModelSpec,
    carry: EKFCarry,
    u,
    eta,
    theta,
    constants: StepConstants,
    functions: ModelFunctions = AJ_EULER,
    line=None,
) -> tuple[EKFCarry, EKFStepOutput]:
    """One EKF step in scaled coordinates: the body of :func:`ekf`'s ``lax.scan``.

    The math of :func:`ekf_step` (which wraps this function) with everything that
    is the same at every step taken out: the noise is scaled once
    (:func:`step_constants`), the measurement comes in scaled (η = y / r), and the
    step's results go out scaled — :func:`to_display_units` converts them, once per
    run on the stacked arrays in :func:`ekf`, per sample in :func:`ekf_step`. ``line``
    (4,): a job step's speed and variance factors (module docstring); None: none.

    Returns
    -------
    (EKFCarry, EKFStepOutput)
        The carry for step k+1 and step k's results in scaled coordinates
        (``mean`` z_k, ``covariance`` P_k / (s sᵀ), ``predicted_output`` ĝ / r,
        ``innovation_variance`` diag S_k / r²; the other fields as in display units).
    """
    f_s, g_s = _scaled_functions(spec, functions, line)
    q, r_diag = constants.process_cov, constants.measurement_var
    if line is not None:
        r_diag = r_diag * line_variance_factors(line, r_diag.shape[0])
    z_pred, p_pred, z0, p0 = carry

    # --- update with y_k: one scalar update per output (Σ_w is diagonal) --------------
    measured = jnp.isfinite(eta)
    # value and Jacobian from one forward-mode pass (the primal is not evaluated twice)
    h, y_hat = jax.jacfwd(lambda z: (g_s(z, u), g_s(z, u)), has_aux=True)(z_pred)
    innovation = jnp.where(measured, eta - y_hat, 0.0)
    s_diag = jnp.einsum("ij,jk,ik->i", h, p_pred, h) + r_diag  # diag(H P Hᵀ + Σ_w)
    # per-output gate on the marginal innovation
    keep = measured & (innovation**2 <= constants.gate**2 * s_diag)
    # outputs not used at k become dummies h_i = 0, r_i = 1, ν_i = 0: their scalar update
    # is then exactly the identity (k_i = 0, s_i = 1), with no select per output
    h_k = jnp.where(keep[:, None], h, 0.0)
    r_k = jnp.where(keep, r_diag, 1.0)
    nu_k = jnp.where(keep, innovation, 0.0)
    z_post, p_post = z_pred, p_pred
    nis = jnp.zeros(())
    variances = []
    for i in range(h.shape[0]):
        # y_i given y_<i: innovation ν_i = η_i − h_i z^(i−1), variance s_i = h_i P^(i−1) h_iᵀ + r_i
        h_i = h_k[i]
        ph = p_post @ h_i
        s_i = h_i @ ph + r_k[i]
        nu_i = nu_k[i] - h_i @ (z_post - z_pred)
        k_i = ph / s_i
        if spec.update_mask is not None:
            k_i = k_i * spec.update_mask
        z_post = z_post + k_i * nu_i
        # Joseph form for a scalar update: (I − k hᵀ) P (I − k hᵀ)ᵀ + r k kᵀ
        m = p_post - jnp.outer(k_i, ph)
        p_post = m - jnp.outer(m @ h_i, k_i) + r_k[i] * jnp.outer(k_i, k_i)
        nis = nis + nu_i**2 / s_i
        variances.append(s_i)
    p_post = 0.5 * (p_post + p_post.T)
    # log det S = Σ_i log s_i as one vector log, not five scalar ones (~0.1 µs a step)
    log_det = jnp.sum(jnp.log(jnp.stack(variances)))
    n_meas = jnp.sum(keep)
    log_lik = -0.5 * (nis + log_det + n_meas * jnp.log(2.0 * jnp.pi)) - jnp.sum(
        jnp.where(keep, constants.log_output_scale, 0.0)
    )

    # --- divergence guard --------------------------------------------------------
    ok = jnp.all(jnp.isfinite(z_post)) & _is_valid_covariance(p_post)
    fallback = jnp.where(jnp.all(jnp.isfinite(z_pred)), z_pred, z0)
    z_post = jnp.where(ok, z_post, fallback)
    p_post = jnp.where(ok, p_post, p0)

    # --- predict to k+1 ------------------------------------------------------------
    f_jac, z_next = jax.jacfwd(lambda z: (f_s(z, u, theta), f_s(z, u, theta)), has_aux=True)(z_post)
    p_next = f_jac @ p_post @ f_jac.T + q
    p_next = 0.5 * (p_next + p_next.T)

    out = EKFStepOutput(
        mean=z_post,
        covariance=p_post,
        predicted_mean=z_pred,
        predicted_covariance=p_pred,
        transition_jacobian=f_jac,
        predicted_output=y_hat,
        innovation_variance=s_diag,
        log_likelihood=log_lik,
        nis=nis,
        n_measured=n_meas,
        reinitialised=~ok,
    )
    return EKFCarry(z_next, p_next, z0, p0), out


def to_display_units(spec: ModelSpec, out: EKFStepOutput) -> EKFStepOutput:
    """:func:`ekf_step_in_loop`'s scaled results in display units (one step or stacked)."""
    s, r = spec.scaling.state, spec.scaling.output
    ss = jnp.outer(s, s)
    return out._replace(
        mean=out.mean * s,
        covariance=out.covariance * ss,
        predicted_mean=out.predicted_mean * s,
        predicted_covariance=out.predicted_covariance * ss,
        predicted_output=out.predicted_output * r,
        innovation_variance=out.innovation_variance * r**2,
    )


def ekf_step(
    spec: ModelSpec,
    carry: EKFCarry,
    u,
    y,
    theta,
    process_cov,
    measurement_var,
    gate=jnp.inf,
    functions: ModelFunctions = AJ_EULER,
    line=None,
) -> tuple[EKFCarry, EKFStepOutput]:
    """One EKF step: update with y_k at x̂_{k|k-1}, then predict to k+1 (pure, jit-able).

    A streaming engine calls this once per sample; the batch filter :func:`ekf`
    scans :func:`ekf_step_in_loop`, which this function wraps: one math path.

        H = ∂g/∂x at x̂_{k|k-1},  S = H P Hᵀ + Σ_w,  K = P Hᵀ S⁻¹
        x̂_k = x̂_{k|k-1} + K (y_k − g(x̂_{k|k-1}, u_k))
        P_k = (I − K H) P (I − K H)ᵀ + K Σ_w Kᵀ              (Joseph form)
        x̂_{k+1|k} = f_d(x̂_k, u_k; θ),  F = ∂f_d/∂x,  P_{k+1|k} = F P_k Fᵀ + Σ_ξ

    Σ_w is diagonal, so the update is done as one scalar update per measured
    output with H fixed at x̂_{k|k-1} (sequential processing): in exact
    arithmetic the same x̂_k and P_k, and Σ_i ν_i²/s_i and Σ_i log s_i of the
    sequential innovations are νᵀS⁻¹ν and log det S (the chain rule of
    p(y_k)). No matrix factorisation: half the cost of the batch form.

    NaN entries of y are not measured (their H rows drop out); entries whose
    innovation exceeds ``gate`` marginal standard deviations are dropped the
    same way. A non-finite or non-PSD posterior is replaced by the reset pair
    (guard; ``reinitialised`` flags it).

    Parameters
    ----------
    spec : ModelSpec
    carry : EKFCarry
        From :func:`ekf_init` or the previous step.
    u : array (3,)
        u_k [mA, sccm, sccm]; drives k → k+1.
    y : array (5,)
        y_k, NaN where not measured.
    theta : array (5,)
        θ for the step k → k+1 [1/s].
    process_cov : array (5, 5)
        Σ_ξ, display units.
    measurement_var : array (5,)
        diag Σ_w, display units.
    gate : float
        Innovation gate in σ (inf: off).
    functions : ModelFunctions (static)
    line : array (4,), optional
        A job step's (F_w, F_o, v_w, v_o): L_w, L_o at the speed they were printed and the
        variance factors of a combined camera measurement (model reference §12); None for a
        record without a job.

    Returns
    -------
    (EKFCarry, EKFStepOutput)
        The carry for step k+1 and step k's results.
    """
    constants = step_constants(spec, process_cov, measurement_var, gate)
    eta = jnp.asarray(y, dtype=float) / spec.scaling.output
    carry, out = ekf_step_in_loop(spec, carry, u, eta, theta, constants, functions, line)
    return carry, to_display_units(spec, out)


def ekf_continue(
    spec: ModelSpec,
    carry: EKFCarry,
    inputs,
    measurements,
    thetas,
    process_cov,
    measurement_cov,
    gate: float = jnp.inf,
    functions: ModelFunctions = AJ_EULER,
    line_factors=None,
    n_steps=None,
) -> tuple[EKFCarry, FilterResult]:
    """The EKF over T steps from ``carry``: ``lax.scan`` of :func:`ekf_step_in_loop`.

    What :func:`ekf` runs from a prior, and what the twin's core
    (:mod:`ajtwin.estimation.online`) runs on each block of a print as it comes: the carry
    returned continues the filter exactly where it stopped (its divergence-guard pair
    included), so a print filtered in blocks is the print filtered whole.

    Only the first ``n_steps`` of the T rows are steps (None: all): the rest pad the
    arrays to a length already compiled, and the carry returned is the one after step
    ``n_steps − 1`` (the padding's results are to be dropped).

    Parameters
    ----------
    spec : ModelSpec
    carry : EKFCarry
        From :func:`ekf_init` or the previous block.
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
    line_factors : array (T, 4), optional
        A job print's per-step (F_w, F_o, v_w, v_o) (:func:`ekf_step`); None: no job.
    n_steps : int, optional
        The real steps among the T rows (a traced value: one compiled program for every
        count).

    Returns
    -------
    (EKFCarry, FilterResult)
        The carry after the last real step and the T steps' results (display units).
    """
    inputs = jnp.asarray(inputs, dtype=float)
    measurements = jnp.asarray(measurements, dtype=float)
    n_rows = inputs.shape[0]
    n_theta = jnp.asarray(thetas).shape[-1]
    thetas = jnp.broadcast_to(jnp.asarray(thetas, dtype=float), (n_rows, n_theta))
    constants = step_constants(spec, process_cov, measurement_cov, gate)
    real = jnp.arange(n_rows) < (n_rows if n_steps is None else n_steps)

    def body(carry, inp):
        u, eta, theta, line, is_step = inp
        new, out = ekf_step_in_loop(spec, carry, u, eta, theta, constants, functions, line)
        # a padding row leaves the carry as the last real step left it
        kept = jax.tree_util.tree_map(lambda a, b: jnp.where(is_step, a, b), new, carry)
        return kept, out

    eta = measurements / spec.scaling.output
    lines = None if line_factors is None else jnp.asarray(line_factors, dtype=float)
    carry, out = jax.lax.scan(body, carry, (inputs, eta, thetas, lines, real))
    return carry, FilterResult(*to_display_units(spec, out))


ekf_continue = exported_jit(
    ekf_continue, static_argnames=("functions",), constant_fields=(("spec", "params"),)
)


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
    line_factors=None,
) -> FilterResult:
    """Run the EKF over a print from a prior: :func:`ekf_continue` from :func:`ekf_init`.

    Parameters
    ----------
    spec : ModelSpec
    prior_mean : array (5,)
        x̂ at k = 0 before the first measurement, display units.
    prior_cov : array (5, 5)
        Its covariance, display units.
    inputs : array (T, 3)
        u_k [mA, sccm, sccm] (as for :func:`ekf_continue`).
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
    line_factors : array (T, 4), optional
        A job print's per-step (F_w, F_o, v_w, v_o); None: no job.

    Returns
    -------
    FilterResult
    """
    carry = ekf_init(spec, prior_mean, prior_cov)
    return ekf_continue.__wrapped__(
        spec, carry, inputs, measurements, thetas, process_cov, measurement_cov, gate,
        functions, line_factors,
    )[1]  # fmt: skip


ekf = exported_jit(ekf, static_argnames=("functions",), constant_fields=(("spec", "params"),))


def ekf_fleet(
    spec: ModelSpec,
    prior_means,
    prior_covs,
    inputs,
    measurements,
    thetas,
    process_cov,
    measurement_cov,
    gate: float = jnp.inf,
    functions: ModelFunctions = AJ_EULER,
) -> FilterResult:
    """:func:`ekf` for M machines at once: every array gains a leading machine axis.

    ``prior_means`` (M, 5), ``prior_covs`` (M, 5, 5), ``inputs`` (M, T, 3),
    ``measurements`` (M, T, 5), ``thetas`` (M, 5) or (M, T, 5); the noise is shared.

    The machines are filtered one after the other (``lax.map``), not vectorised
    (``vmap``): one machine's scan is small enough for XLA:CPU to compile into a
    single kernel (``ajtwin._jax``), a vmapped scan over the fleet is not and runs
    op by op — about half the machine-steps per second (docs/explanation/performance.md). Same
    results as :func:`ekf` per machine.
    """

    def one(args):
        m0, p0, u, y, theta = args
        return ekf(spec, m0, p0, u, y, theta, process_cov, measurement_cov, gate, functions)

    return jax.lax.map(one, (prior_means, prior_covs, inputs, measurements, thetas))


ekf_fleet = jax.jit(ekf_fleet, static_argnames=("functions",))


def ekf_fleet_threaded(
    spec: ModelSpec,
    prior_means,
    prior_covs,
    inputs,
    measurements,
    thetas,
    process_cov,
    measurement_cov,
    gate: float = jnp.inf,
    functions: ModelFunctions = AJ_EULER,
    workers: int | None = None,
) -> FilterResult:
    """:func:`ekf_fleet` on several cores: the fleet split into ``workers`` blocks of
    machines, each block one call of the same compiled :func:`ekf_fleet` from its own
    thread (XLA runs a call without holding Python's GIL, so the blocks run at once).

    A host-side shell, not jit-able; the math is :func:`ekf_fleet`'s and the results
    are the same bit for bit (each machine's filter is the same kernel either way).
    ``workers``: default ``os.cpu_count()``, at most one block per machine. Returns
    NumPy arrays with the leading machine axis.
    """

    arrays = [np.asarray(a) for a in (prior_means, prior_covs, inputs, measurements, thetas)]
    n_machines = arrays[0].shape[0]
    n_blocks = max(1, min(int(workers or os.cpu_count() or 1), n_machines))
    edges = np.linspace(0, n_machines, n_blocks + 1).astype(int)

    def block(i):
        part = [a[edges[i] : edges[i + 1]] for a in arrays]
        result = ekf_fleet(
            spec, *part, process_cov, measurement_cov, gate=gate, functions=functions
        )
        return jax.tree_util.tree_map(np.asarray, result)

    if n_blocks == 1:
        return block(0)
    with ThreadPoolExecutor(n_blocks, thread_name_prefix="ekf_fleet") as pool:
        parts = list(pool.map(block, range(n_blocks)))
    return FilterResult(*(np.concatenate(fields) for fields in zip(*parts)))


def rts_smoother(spec: ModelSpec, filtered: FilterResult) -> SmootherResult:
    """Rauch–Tung–Striebel smoothing of an EKF run (paper App. E).

    Uses the EKF's own linearisations F_k, so it is the exact RTS smoother of
    the linearised model the filter saw. Consider states (``spec.update_mask`` 0) keep
    their filtered values: their rows of J_k are zero, so later data do not reach them
    through the backward pass either.
    """
    s = spec.scaling.state
    ss = jnp.outer(s, s)
    z_f = filtered.means / s
    p_f = filtered.covariances / ss
    z_p = filtered.predicted_means / s
    p_p = filtered.predicted_covariances / ss
    f_jacs = filtered.transition_jacobians

    # J_k = P_k Fᵀ P_{k+1|k}⁻¹ depends on the filter's output only, not on the backward
    # pass: all gains in one batched solve, outside the scan (a per-step solve inside
    # the scan costs a factorisation call per step)
    gains = jnp.swapaxes(jnp.linalg.solve(p_p[1:], f_jacs[:-1] @ p_f[:-1]), -1, -2)  # (T-1, 5, 5)
    if spec.update_mask is not None:
        gains = gains * spec.update_mask[None, :, None]

    def body(carry, inp):
        z_next_s, p_next_s = carry
        z_k, p_k, gain, z_next_p, p_next_p = inp
        z_s = z_k + gain @ (z_next_s - z_next_p)
        p_s = p_k + gain @ (p_next_s - p_next_p) @ gain.T
        p_s = 0.5 * (p_s + p_s.T)
        lag_one = p_next_s @ gain.T
        return (z_s, p_s), (z_s, p_s, lag_one)

    last = (z_f[-1], p_f[-1])
    seq = (z_f[:-1], p_f[:-1], gains, z_p[1:], p_p[1:])
    _, (z_s, p_s, lag) = jax.lax.scan(body, last, seq, reverse=True)
    z_s = jnp.concatenate([z_s, z_f[-1:]], axis=0)
    p_s = jnp.concatenate([p_s, p_f[-1:]], axis=0)
    return SmootherResult(means=z_s * s, covariances=p_s * ss, lag_one_covariances=lag * ss)


rts_smoother = jax.jit(rts_smoother)
