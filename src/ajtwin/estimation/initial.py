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


# kept on disk (ajtwin._aot): every command that starts a print fits the start
_residuals = exported_jit(_residuals_impl)
_residual_jacobian = exported_jit(_residual_jacobian_impl)

#: Bounds of the fitted states (d_a µm, φ_A): physical, generous.
DROPLET_BOUNDS_UM = (0.5, 10.0)
AEROSOL_BOUNDS = (1e-10, 1e-4)


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

    def fun(p):
        return _residuals(p, *data)

    def jac(p):
        return _residual_jacobian(p, *data)

    phi_start = float(
        settled_outputs(np.asarray(u[0]), float(vial_fill_ml), params, coefficients)[0]
    )
    phi_start = float(np.clip(phi_start, AEROSOL_BOUNDS[0] * 10, AEROSOL_BOUNDS[1] / 10))
    start = np.array([3.5, phi_start / phi_scale])
    lower = [DROPLET_BOUNDS_UM[0], AEROSOL_BOUNDS[0] / phi_scale]
    upper = [DROPLET_BOUNDS_UM[1], AEROSOL_BOUNDS[1] / phi_scale]
    from scipy.optimize import least_squares  # here: forecast and advise never fit a start

    result = least_squares(
        lambda p: np.asarray(fun(np.asarray(p, dtype=float))),
        start,
        jac=lambda p: np.asarray(jac(np.asarray(p, dtype=float))),
        bounds=(lower, upper),
        method="trf",
        x_scale="jac",
    )
    mean, cov = _fitted_start(
        result, vial_fill_ml, (vial_fill_std_ml, tube_prior_std_um, nozzle_prior_std_um)
    )
    fit = InitialFit(
        mean=mean,
        covariance=cov,
        cost=float(result.cost),
        n_samples=int(len(y)),
        success=bool(result.success),
        message=str(result.message),
    )
    if not measured[:, :2].any():  # Q_m alone: it sees φ_A, not the droplet size
        return _droplet_from_prior(fit, droplet_prior_um, droplet_prior_std_um)
    return fit


def _fitted_start(result, vial_fill_ml: float, prior_stds) -> tuple[np.ndarray, np.ndarray]:
    """x₀ and its covariance from the least-squares fit of (d_a, φ_A/scale): the Gauss–Newton
    inverse for those two, the priors (``prior_stds``: V_l, ΔR_T, ΔR_N) for the rest."""
    j = result.jac
    info = j.T @ j
    try:
        cov_fit = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        cov_fit = np.linalg.pinv(info)
    mean = np.array([result.x[0], vial_fill_ml, 0.0, 0.0, result.x[1] * _PHI_SCALE])
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
