"""How uncertain the states are because the machine's calibration is (honest bands).

Commissioning knows the calibration c only to its covariance Σ_c (the line offset to a
few µm, say). The twin runs with the fitted c as if it were exact, so its filter
covariance P_k misses a systematic part: a line offset off by δo makes d_a off by
about δo / (g α^da) for the whole print, however many samples arrive.

For a constant calibration error δc the filter settles where its gain-weighted
innovations vanish, K_k (G_k δc − H_k δx) = 0, so

    δx_k = A_k δc,   A_k = (K_k H_k)⁺ K_k G_k,   C_k = A_k Σ_c A_kᵀ,

with H_k = ∂g/∂x, G_k = ∂g/∂c at the filtered state, K_k = P_{k|k−1} Hᵀ S⁻¹ the filter's
gain, ⁺ a pseudo-inverse that drops the directions the outputs do not see (those states
are not moved by a calibration error). The vial, seen by no output, integrates the
aerosol (dV_l/dt = −φ_A Q_c), so its row is A_k[V_l] = −Σ_{j<k} A_j[φ_A] Q_c,j Δt.
The reported covariance is P_k + C_k.
Computed in the filter's scaled coordinates (states span 15 orders of magnitude).
"""

from __future__ import annotations

import numpy as np

from ajtwin import units
from ajtwin._jax import jax, jnp
from ajtwin.model.calibration import (
    CalibratedCoefficients,
    calibration_from_vector,
    calibration_vector,
)

#: Singular values of K H below this fraction of the largest are treated as unseen.
RCOND = 1e-4


def calibration_state_covariance(
    spec,
    filtered,
    inputs,
    measurement_var,
    calibration_cov,
    functions,
    line_factors=None,
    carry=None,
) -> np.ndarray:
    """C_k (T, 5, 5), display units: the state covariance the calibration error adds.

    Parameters
    ----------
    spec : ModelSpec
        With ``CalibratedCoefficients`` (the fitted calibration).
    filtered : FilterResult
    inputs : (T, 3)
    measurement_var : (5,)
        Σ_w diagonal the filter used.
    calibration_cov : (11, 11)
        Σ_c from commissioning (display units).
    functions : ModelFunctions
    line_factors : (T, 4), optional
        A job print's (F_w, F_o, v_w, v_o) per step: the filter's g_k and Σ_w,k
        (:func:`ajtwin.estimation.filters.ekf_step`).
    carry : dict, optional
        A run taken in chunks (``filtered`` one chunk of it): the vial's drain so far
        (``carry["drain"]``, none at the first chunk) is added, and updated for the next.
    """
    coefficients = spec.coefficients
    if not isinstance(coefficients, CalibratedCoefficients):
        raise ValueError("calibration_state_covariance needs a calibrated ModelSpec")
    s = np.asarray(spec.scaling.state)
    r = np.asarray(spec.scaling.output)
    c0 = calibration_vector(coefficients.calibration)
    line = coefficients.line

    def g(x, u, c):
        return functions.output(
            x, u, spec.params, CalibratedCoefficients(line, calibration_from_vector(c))
        )

    means = jnp.asarray(filtered.means)
    u = jnp.asarray(inputs, dtype=float)
    h = np.asarray(jax.vmap(jax.jacfwd(g, argnums=0), in_axes=(0, 0, None))(means, u, c0))
    gc = np.asarray(jax.vmap(jax.jacfwd(g, argnums=2), in_axes=(0, 0, None))(means, u, c0))
    # scaled coordinates: z = x/s, η = y/r
    h_s = h * s[None, None, :] / r[None, :, None]
    g_s = gc / r[None, :, None]
    p_pred = np.asarray(filtered.predicted_covariances) / np.outer(s, s)[None]
    r_diag = np.tile(np.asarray(measurement_var, float) / r**2, (len(p_pred), 1))
    if line_factors is not None:  # a job print: L_w, L_o at their speed, combined frames
        line = np.asarray(line_factors, dtype=float)
        factor = np.concatenate([line[:, :2], np.ones((len(line), len(r) - 2))], axis=1)
        h_s, g_s = h_s * factor[:, :, None], g_s * factor[:, :, None]
        r_diag[:, :2] *= line[:, 2:4]
    cal_cov = np.asarray(calibration_cov, dtype=float)
    sensitivity = np.zeros((len(p_pred), len(s), cal_cov.shape[0]))  # A_k, scaled states
    for k in range(len(p_pred)):
        hk, pk = h_s[k], p_pred[k]
        gain = np.linalg.solve(hk @ pk @ hk.T + np.diag(r_diag[k]), hk @ pk).T  # K = P Hᵀ S⁻¹
        sensitivity[k] = np.linalg.pinv(gain @ hk, rcond=RCOND) @ gain @ g_s[k]
    # the vial is seen by no output, but it integrates the aerosol: dV_l/dt = −φ_A Q_c, so
    # a calibration error that biases φ_A drains the estimated vial by Σ δφ_A Q_c Δt
    carrier_ml_s = np.asarray(units.sccm_to_ml_per_s(np.asarray(inputs, dtype=float)[:, 1]))
    dt = float(spec.dt)
    drain = np.cumsum(sensitivity[:, 4, :] * (s[4] * carrier_ml_s * dt)[:, None], axis=0)
    drain = np.concatenate([np.zeros_like(drain[:1]), drain[:-1]])
    if carry is not None:
        before = carry.get("drain", 0.0)
        carry["drain"] = before + drain[-1] + sensitivity[-1, 4, :] * (s[4] * carrier_ml_s[-1] * dt)
        drain = drain + before
    sensitivity[:, 1, :] -= drain / s[1]
    out = np.einsum("tic,cd,tjd->tij", sensitivity, cal_cov, sensitivity)
    return out * np.outer(s, s)[None]


def aerosol_level_covariance(
    means, inputs, relative_std, dt: float = 1.0, carry: dict | None = None
) -> np.ndarray:
    """(T, 5, 5), display units: what an unknown level of φ_A adds to the states' covariance.

    The atomizer's output relative to the generation model is known only to a relative σ
    (commissioning's ``aerosol_level``, model reference §11): one systematic factor (1 + ε),
    ε ~ N(0, σ²), on φ_A for the whole print, which the outputs cannot see once the Q_m gain
    has absorbed it. With v_k = [0, −σ Σ_{j<k} φ̂_j Q_c,j Δt, 0, 0, σ φ̂_k] (the vial drains
    by the same factor), the addition is v_k v_kᵀ. ``carry``: a dict kept between the chunks
    of one run (the sum so far), so chunks give the whole run's result.

    >>> means = np.tile([3.5, 1.0, 0.0, 0.0, 4.6e-7], (3, 1))
    >>> c = aerosol_level_covariance(means, np.tile([375.0, 23.0, 50.0], (3, 1)), 0.35)
    >>> round(float(np.sqrt(c[1, 4, 4]) / 4.6e-7), 3)
    0.35
    """
    means = np.asarray(means, dtype=float)
    carrier_ml_s = np.asarray(units.sccm_to_ml_per_s(np.asarray(inputs, dtype=float)[:, 1]))
    aerosol = relative_std * means[:, 4]
    # a chunk of a run starts from what the vial drained before it (``carry``, updated)
    before = 0.0 if carry is None else carry.get("aerosol_level_drained", 0.0)
    steps = np.cumsum(aerosol * carrier_ml_s * dt)
    drained = before + np.concatenate([[0.0], steps[:-1]])
    if carry is not None and len(steps):
        carry["aerosol_level_drained"] = before + float(steps[-1])
    v = np.zeros_like(means)
    v[:, 1] = -drained
    v[:, 4] = aerosol
    return v[:, :, None] * v[:, None, :]
