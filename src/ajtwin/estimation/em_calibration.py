"""EM for what may drift slowly between commissionings: line offsets and output noise.

The paper's EM (Algorithm 2, :mod:`ajtwin.estimation.em`) learns θ; its future work asks
for the covariances too. This module adds an M-step on the *output* side, using the same
E-step (EKF + RTS over the window, the machine's calibration inside g):

* **line-model offsets** o_w, o_o (camera refocus, substrate change): with smoothed
  residuals r_k = y_k − g_c(x̂_{k|N}, u_k) and a Gaussian prior N(o_c, σ_o²) centred on
  the commissioned offset (how far a line may drift between commissionings),

      o_new = (o_c/σ_o² + Σ_k (o + r_k)/R) / (1/σ_o² + n/R)         (per output, MAP)

* **output noise variances** R_j = mean_k [ (r_kj − Δo_j)² + (H_k P_{k|N} H_kᵀ)_jj ]
  for L_w, L_o and Q_m, clipped to ``noise_bounds`` × the tuned value.

Nothing about the pressures is learned online (model reference §11): a pressure offset is
indistinguishable from nozzle deposition, so a learned one would hide a clog — and so
would a pressure noise variance learned from a window with a clog in it (tried: the
clog went undetected). Pressures change only at commissioning or maintenance.

Examples
--------
>>> settings = load_em_calibration_settings()
>>> settings["offset_drift_std_um"]
[5.0, 5.0]
"""

from __future__ import annotations

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.config import packaged_toml
from ajtwin.model.calibration import CalibratedCoefficients, Calibration

#: Outputs whose offset may be learned online: L_w, L_o (never the pressures).
LEARNABLE_OFFSETS = {0: "linewidth_offset_um", 1: "overspray_offset_um"}
#: Outputs whose noise variance may be learned online: not the pressures either — a clog's
#: rising pressure misfit learned as "noise" would blunt the clog detectors just the same.
LEARNABLE_NOISE = (0, 1, 4)


def load_em_calibration_settings() -> dict:
    """Which output parameters EM may learn online, with their provenance
    (``data/em_calibration.toml``)."""
    return packaged_toml("data/em_calibration.toml")["em_calibration"]


def _as_calibrated(spec):
    coefficients = spec.coefficients
    if isinstance(coefficients, CalibratedCoefficients):
        return coefficients.line, coefficients.calibration
    return coefficients, Calibration.identity()


def output_m_step(
    spec,
    smoothed,
    inputs,
    measurements,
    measurement_var,
    commissioned: Calibration,
    *,
    functions,
    learn_offsets: bool = True,
    learn_noise: bool = True,
    tuned_var=None,
    settings: dict | None = None,
):
    """One output-side M-step (module docstring).

    Parameters
    ----------
    spec : ModelSpec
        With the current calibration inside (``CalibratedCoefficients``) or a bare matrix.
    smoothed : SmootherResult
        The E-step over the window (display units).
    inputs : (T, 3), measurements : (T, 5)
    measurement_var : (5,)
        Current Σ_w diagonal.
    commissioned : Calibration
        The centre of the offset prior.
    tuned_var : (5,), optional
        The tuned Σ_w the noise is bounded around (default: ``measurement_var``).

    Returns
    -------
    (Calibration, array (5,))
        The updated calibration (only the line offsets change) and Σ_w diagonal.
    """
    cfg = settings or load_em_calibration_settings()
    line, calibration = _as_calibrated(spec)
    means = jnp.asarray(smoothed.means)
    covs = jnp.asarray(smoothed.covariances)
    u = jnp.asarray(inputs, dtype=float)
    y = np.asarray(measurements, dtype=float)
    coefficients = CalibratedCoefficients(line, calibration)

    def g(x, uk):
        return functions.output(x, uk, spec.params, coefficients)

    predicted = np.asarray(jax.vmap(g)(means, u))
    jac = jax.vmap(jax.jacfwd(g))(means, u)  # (T, 5, 5) in display units
    spread = np.asarray(jnp.einsum("tij,tjk,tik->ti", jac, covs, jac))
    residual = y - predicted
    measured = np.isfinite(residual)
    var = np.asarray(measurement_var, dtype=float).copy()
    tuned = var if tuned_var is None else np.asarray(tuned_var, dtype=float)
    values = calibration._asdict()
    shift = np.zeros(5)
    if learn_offsets:
        prior_std = np.asarray(cfg["offset_drift_std_um"], dtype=float)
        for j, name in LEARNABLE_OFFSETS.items():
            n = int(measured[:, j].sum())
            if n == 0:
                continue
            current = float(values[name])
            centre = float(commissioned._asdict()[name])
            total = float(np.sum(residual[measured[:, j], j]))
            precision = 1.0 / prior_std[j] ** 2 + n / var[j]
            new = (centre / prior_std[j] ** 2 + (n * current + total) / var[j]) / precision
            shift[j] = new - current
            values[name] = new
    if learn_noise:
        low, high = cfg["noise_bounds"]
        for j in LEARNABLE_NOISE:
            if measured[:, j].sum() < cfg["min_samples"]:
                continue
            r = residual[measured[:, j], j] - shift[j]
            estimate = float(np.mean(r**2 + spread[measured[:, j], j]))
            var[j] = float(np.clip(estimate, low * tuned[j], high * tuned[j]))
    return Calibration(**values), var
