"""Initial-state fit (paper §7.1, model reference §7).

    x̂₀ = argmin Σ_{k=1..n} ‖y_k − g(x₀, u_k)‖²_{Σ_w⁻¹}   s.t.  ΔR_T = ΔR_N = 0,

over the first n = 10 samples, with physical bounds. g does not depend on the
vial level V_l at all, so the data cannot fix it: V_l is held at the operator's
fill level (``vial_fill_ml``) with a prior standard deviation, which is also
what the returned covariance says about it. Missing samples are skipped.

A machine without a camera logs no L_w, L_o or Q_m: nothing then constrains d_a and φ_A.
Given priors (``droplet_prior_um`` ± ``droplet_prior_std_um`` from ``noise.toml``), the
fit starts them from those instead of refusing the print — d_a at its prior, φ_A at the
generation model's steady state φ_ss(u₀, V_l) with a relative σ — and says so in
``states_from_prior``; the deposits keep their priors as always (the pressures find them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ajtwin._aot import exported_jit
from ajtwin._jax import jax, jnp
from ajtwin.model.system import output_function, settled_outputs, steady_aerosol_fraction


class InitialFit(NamedTuple):
    """The initial-state fit.

    Attributes
    ----------
    mean : array (5,)
        Display units.
    covariance : array (5, 5)
    cost : float
        ½ Σ weighted squared residuals at the optimum.
    n_samples : int
    success : bool
    message : str
    states_from_prior : tuple of str
        States no early sample constrained (their start is the prior's).
    """

    mean: np.ndarray  # (5,) display units
    covariance: np.ndarray  # (5, 5)
    cost: float  # ½ Σ weighted squared residuals at the optimum
    n_samples: int
    success: bool
    message: str
    states_from_prior: tuple = ()  # states no early sample constrained (prior start)


_PHI_SCALE = 1e-7


def _residuals_impl(p, params, coefficients, u, y, measured, sigma, vial_ml):
    """Weighted residuals (y − g(x₀, u_k))/σ of the first samples, 0 where missing."""
    x = jnp.stack([p[0], vial_ml, 0.0, 0.0, p[1] * _PHI_SCALE])
    pred = jax.vmap(lambda uk: output_function(x, uk, params, coefficients))(u)
    return jnp.where(measured, (y - pred) / sigma, 0.0).ravel()


def _residual_jacobian_impl(p, params, coefficients, u, y, measured, sigma, vial_ml):
    """∂ residuals / ∂p (forward mode)."""
    return jax.jacfwd(_residuals_impl)(p, params, coefficients, u, y, measured, sigma, vial_ml)


#: Bounds of the fitted states (d_a µm, φ_A): physical, generous.
DROPLET_BOUNDS_UM = (0.5, 10.0)
AEROSOL_BOUNDS = (1e-10, 1e-4)


def _residuals_and_jacobian_impl(p, params, coefficients, u, y, measured, sigma, vial_ml):
    """The residuals and their Jacobian ∂r/∂p at p (one program: one call per iteration)."""
    data = (params, coefficients, u, y, measured, sigma, vial_ml)
    return _residuals_impl(p, *data), _residual_jacobian_impl(p, *data)


# kept on disk (ajtwin._aot): every command that starts a print fits the start
_residuals_and_jacobian = exported_jit(_residuals_and_jacobian_impl)


def gauss_newton_box(residuals_and_jacobian, start, lower, upper, max_iterations: int = 100):
    """min ½‖r(p)‖² over lower ≤ p ≤ upper: Gauss–Newton steps (a parameter at its bound
    held there while its step points out), projected on the box and halved until the cost
    does not rise.

    Two parameters and a program that gives r and ∂r/∂p together need no more; this keeps
    ``scipy.optimize`` (0.16 s to import) and a compiled BFGS (1.1 MB to load) off every
    command that starts a print. Stops when a step changes the cost by less than 1e-12 of
    it (or p by less than 1e-12 of it), or when no halving of the step (down to 2⁻⁴⁰) keeps
    the cost from rising.

    Parameters
    ----------
    residuals_and_jacobian : callable
        p (n,) → (r (m,), ∂r/∂p (m, n)).
    start, lower, upper : array (n,)

    Returns
    -------
    p : array (n,)
    r, jacobian : arrays (m,), (m, n) at p
    iterations : int
    converged : bool

    Examples
    --------
    >>> import numpy as np
    >>> f = lambda p: (np.array([p[0] - 1.0, 10 * (p[1] - p[0] ** 2)]),
    ...                np.array([[1.0, 0.0], [-20 * p[0], 10.0]]))
    >>> p, r, j, n, ok = gauss_newton_box(f, np.array([-1.2, 1.0]), np.full(2, -2.0),
    ...                                   np.array([2.0, 0.5]))
    >>> np.round(p, 5).tolist(), ok  # scipy.optimize.least_squares: 0.70856, 0.5
    ([0.70856, 0.5], True)
    """
    p = np.clip(np.asarray(start, dtype=float), lower, upper)
    r, jac = (np.asarray(a) for a in residuals_and_jacobian(p))
    cost = 0.5 * float(r @ r)
    for iteration in range(1, max_iterations + 1):
        step = np.linalg.lstsq(jac, -r, rcond=None)[0]
        # a parameter at its bound whose step points out of the box stays there; the others
        # take the Gauss–Newton step of the problem without it
        held = ((p <= lower) & (step < 0)) | ((p >= upper) & (step > 0))
        if held.any():
            step = np.zeros_like(p)
            step[~held] = np.linalg.lstsq(jac[:, ~held], -r, rcond=None)[0]
        for _ in range(41):
            trial = np.clip(p + step, lower, upper)
            r_t, jac_t = (np.asarray(a) for a in residuals_and_jacobian(trial))
            cost_t = 0.5 * float(r_t @ r_t)
            if cost_t <= cost:
                break
            step = step / 2
        else:
            return p, r, jac, iteration, True  # no step lowers the cost: p is the minimum
        small = cost - cost_t <= 1e-12 * cost or np.all(np.abs(trial - p) <= 1e-12 * np.abs(p))
        p, r, jac, cost = trial, r_t, jac_t, cost_t
        if small:
            return p, r, jac, iteration, True
    return p, r, jac, max_iterations, False


@dataclass(frozen=True)
class StartPriors:
    """What the initial fit assumes beyond the data (display units).

    Attributes
    ----------
    n_samples : int
        The first samples the fit uses.
    vial_fill_ml, vial_fill_std_ml : float
        The vial level the operator loaded, and how well it is known.
    tube_prior_std_um, nozzle_prior_std_um : float
        Prior σ of the deposits, which the fit holds at 0 (A x₀ = 0): the EKF's initial
        covariance uses them so a machine whose nozzle is not clean can still be found from
        the pressures.
    droplet_prior_um, droplet_prior_std_um, aerosol_prior_relative_std : float, optional
        Priors for a print with no line output in the first samples (module docstring);
        without them such a print is refused.
    """

    n_samples: int = 10
    vial_fill_ml: float = 1.0
    vial_fill_std_ml: float = 0.05
    tube_prior_std_um: float = 1e-3
    nozzle_prior_std_um: float = 0.05
    droplet_prior_um: float | None = None
    droplet_prior_std_um: float | None = None
    aerosol_prior_relative_std: float | None = None


def fit_initial_state(
    params,
    coefficients,
    inputs,
    measurements,
    measurement_std,
    priors: StartPriors | None = None,
    line_factors=None,
) -> InitialFit:
    """Weighted least-squares fit of x₀ over the first ``n_samples`` samples.

    Parameters
    ----------
    params, coefficients
        Model parameters (SI pytree) and the (2, 8) output coefficients.
    inputs : array (T, 3), measurements : array (T, 5)
        The print's first samples (more are ignored); NaN = not measured.
    measurement_std : array (5,)
        σ of each output (display units).
    priors : StartPriors, optional
        The samples used and the priors (default :class:`StartPriors`).
    line_factors : array (T, 4), optional
        A job print's (F_w, F_o, v_w, v_o) per sample (:func:`_at_reference_speed`).

    Returns
    -------
    InitialFit
        Mean, covariance (Gauss–Newton inverse for d_a, φ_A; priors for the
        rest), cost and the optimiser's status.
    """
    p = priors or StartPriors()
    n_samples, vial_fill_ml, vial_fill_std_ml = p.n_samples, p.vial_fill_ml, p.vial_fill_std_ml
    tube_prior_std_um, nozzle_prior_std_um = p.tube_prior_std_um, p.nozzle_prior_std_um
    droplet_prior_um, droplet_prior_std_um = p.droplet_prior_um, p.droplet_prior_std_um
    aerosol_prior_relative_std = p.aerosol_prior_relative_std
    u = np.asarray(inputs, dtype=float)[:n_samples]
    line = None if line_factors is None else np.asarray(line_factors, dtype=float)[:n_samples]
    y = np.asarray(measurements, dtype=float)[:n_samples]
    y, sigma = _at_reference_speed(y, np.asarray(measurement_std, dtype=float), line)
    measured = np.isfinite(y)
    if not measured[:, [0, 1, 4]].any() and droplet_prior_um is not None:
        return _prior_start(
            params,
            u,
            n_samples=len(y),
            vial_fill_ml=vial_fill_ml,
            vial_fill_std_ml=vial_fill_std_ml,
            tube_prior_std_um=tube_prior_std_um,
            nozzle_prior_std_um=nozzle_prior_std_um,
            droplet_prior_um=droplet_prior_um,
            droplet_prior_std_um=droplet_prior_std_um,
            aerosol_prior_relative_std=aerosol_prior_relative_std,
        )
    if not measured[:, [0, 1, 4]].any():
        raise ValueError(
            f"no linewidth, overspray or material-flow measurement in the first {len(y)} samples:"
            " the initial droplet size and aerosol fraction cannot be fitted"
        )
    y_filled = np.where(measured, y, 0.0)
    phi_scale = _PHI_SCALE
    data = (
        params,
        coefficients,
        np.asarray(u, dtype=float),
        np.asarray(y_filled, dtype=float),
        np.asarray(measured),
        np.asarray(sigma, dtype=float),
        float(vial_fill_ml),
    )

    phi_start = float(
        settled_outputs(np.asarray(u[0]), float(vial_fill_ml), params, coefficients)[0]
    )
    phi_start = float(np.clip(phi_start, AEROSOL_BOUNDS[0] * 10, AEROSOL_BOUNDS[1] / 10))
    lower = np.array([DROPLET_BOUNDS_UM[0], AEROSOL_BOUNDS[0] / phi_scale])
    upper = np.array([DROPLET_BOUNDS_UM[1], AEROSOL_BOUNDS[1] / phi_scale])
    x, r, jacobian, iterations, converged = gauss_newton_box(
        lambda p: _residuals_and_jacobian(p, *data),
        np.array([3.5, phi_start / phi_scale]),
        lower,
        upper,
    )
    mean, cov = _fitted_start(
        x, jacobian, vial_fill_ml, (vial_fill_std_ml, tube_prior_std_um, nozzle_prior_std_um)
    )
    fit = InitialFit(
        mean=mean,
        covariance=cov,
        cost=0.5 * float(r @ r),
        n_samples=int(len(y)),
        success=converged,
        message=f"Gauss–Newton {'converged' if converged else 'stopped'} after {iterations} "
        "iterations",
    )
    if not measured[:, :2].any():  # Q_m alone: it sees φ_A, not the droplet size
        return _droplet_from_prior(fit, droplet_prior_um, droplet_prior_std_um)
    return fit


def _fitted_start(x, jac, vial_fill_ml: float, prior_stds) -> tuple[np.ndarray, np.ndarray]:
    """x₀ and its covariance from the least-squares fit of (d_a, φ_A/scale): the Gauss–Newton
    inverse for those two (x (2,) = d_a, φ_A/scale; jac (m, 2) = ∂r/∂x there), the priors
    (``prior_stds``: V_l, ΔR_T, ΔR_N) for the rest."""
    info = jac.T @ jac
    try:
        cov_fit = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        cov_fit = np.linalg.pinv(info)
    mean = np.array([x[0], vial_fill_ml, 0.0, 0.0, x[1] * _PHI_SCALE])
    cov = np.zeros((5, 5))
    scale = np.array([1.0, _PHI_SCALE])
    cov[np.ix_([0, 4], [0, 4])] = cov_fit * np.outer(scale, scale)
    for i, std in zip((1, 2, 3), prior_stds):
        cov[i, i] = std**2
    return mean, cov


def _droplet_from_prior(fit: InitialFit, prior_um, prior_std_um) -> InitialFit:
    """The fit with d_a from its prior: the first samples measured Q_m (φ_A) but no line,
    so nothing constrained d_a (the fit's information on it is zero; a pseudo-inverse would
    call it exact). A job print whose first seconds' traces the camera never saw (printed
    over, or seen only by a later inspection pass) starts so."""
    if prior_um is None or not (prior_std_um and prior_std_um > 0):
        raise ValueError(
            f"no linewidth or overspray measurement in the first {fit.n_samples} samples: "
            "the initial droplet size cannot be fitted (give a droplet prior)"
        )
    mean, cov = fit.mean.copy(), fit.covariance.copy()
    mean[0] = float(prior_um)
    cov[0, :] = cov[:, 0] = 0.0
    cov[0, 0] = float(prior_std_um) ** 2
    message = (
        f"no linewidth or overspray measurement in the first {fit.n_samples} samples: the "
        "droplet diameter starts from its prior (the aerosol fraction is fitted to Q_m)"
    )
    return fit._replace(
        mean=mean, covariance=cov, message=message, states_from_prior=("droplet_diameter_um",)
    )


def _at_reference_speed(y, sigma, line):
    """(y, σ) of the samples as the line at ν_ref: y_w = F_w L_w + w with Var w = v_w σ² is
    fitted as y_w/F_w against L_w with σ√v_w/F_w (the same residual); F, v of ``line``
    (n, 4) of a job print (:mod:`ajtwin.estimation.print_time`); unchanged without one."""
    if line is None:
        return y, sigma
    y = y.copy()
    y[:, :2] = y[:, :2] / line[:, :2]
    sigma = np.tile(sigma, (len(y), 1))
    sigma[:, :2] = sigma[:, :2] * np.sqrt(line[:, 2:4]) / line[:, :2]
    return y, sigma


def _prior_start(
    params,
    u,
    *,
    n_samples,
    vial_fill_ml,
    vial_fill_std_ml,
    tube_prior_std_um,
    nozzle_prior_std_um,
    droplet_prior_um,
    droplet_prior_std_um,
    aerosol_prior_relative_std,
) -> InitialFit:
    """x₀ from priors alone: d_a ~ N(prior, σ²), φ_A ~ N(φ_ss(u₀, V_l), (rel σ · φ_ss)²)."""
    if not (droplet_prior_std_um and droplet_prior_std_um > 0):
        raise ValueError("a prior start needs droplet_prior_std_um > 0")
    if not (aerosol_prior_relative_std and aerosol_prior_relative_std > 0):
        raise ValueError("a prior start needs aerosol_prior_relative_std > 0")
    phi = float(steady_aerosol_fraction(jnp.asarray(u[0]), vial_fill_ml, params))
    if not (np.isfinite(phi) and AEROSOL_BOUNDS[0] <= phi <= AEROSOL_BOUNDS[1]):
        raise ValueError(
            f"the generation model's steady aerosol fraction {phi:.3g} at the first inputs "
            f"{u[0].tolist()} is outside [{AEROSOL_BOUNDS[0]:g}, {AEROSOL_BOUNDS[1]:g}]: "
            "no prior start"
        )
    mean = np.array([float(droplet_prior_um), vial_fill_ml, 0.0, 0.0, phi])
    cov = np.diag(
        [
            float(droplet_prior_std_um) ** 2,
            vial_fill_std_ml**2,
            tube_prior_std_um**2,
            nozzle_prior_std_um**2,
            (float(aerosol_prior_relative_std) * phi) ** 2,
        ]
    )
    return InitialFit(
        mean=mean,
        covariance=cov,
        cost=0.0,
        n_samples=int(n_samples),
        success=True,
        message=(
            f"no linewidth, overspray or material-flow measurement in the first {n_samples} "
            "samples: droplet diameter and aerosol fraction start from their priors"
        ),
        states_from_prior=("droplet_diameter_um", "aerosol_fraction"),
    )
