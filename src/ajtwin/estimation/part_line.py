"""The printed line at any print time and speed, from the twin's states (model reference §7, §12).

A part map asks how wide every stroke was along its length, not only where the camera
looked. The twin's states are known per second with their covariance (filtered, or
smoothed over the whole print); the line printed at a time τ at platen speed ν is the
output model there:

    x(τ) = x_k + w (x_{k+1} − x_k),   P(τ) = (1 − w) P_k + w P_{k+1},   w = τ − t_k ∈ [0, 1)
    L(τ, ν) = f(ν) ⊙ g_line(x(τ), u_k)                      (u held over the second, as printed)
    Var L  = diag(H P(τ) Hᵀ) + (L ln(ν_ref/ν))² σ_b²           (H = ∂L/∂x at x(τ))

f(ν) is the twin's speed law (:mod:`ajtwin.model.line_speed`); the second term is what the
law's own uncertainty adds away from ν_ref (σ_b: a quarter of the exponents' bracketed range
in ``data/line_speed.toml``, i.e. the range as ±2σ; 0 at ν_ref). P includes what the
calibration's uncertainty adds when the twin knows it (:class:`~ajtwin.estimation.TwinRun`).
The camera's noise is not in it: this is the line on the part, not a measurement of it.

Examples
--------
>>> from ajtwin.simulation import simulate
>>> from ajtwin.estimation import Twin
>>> run = Twin.default(em=False).run(simulate("exp1", seed=1, duration_min=1), smooth=True)
>>> line = run.line_at([30.2, 41.7], [2.0, 4.0])      # τ [s], ν [mm/s]
>>> bool(line.linewidth_um[1] < line.linewidth_um[0])  # faster: a thinner line
True
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.model.line_speed import (
    LineSpeedLaw,
    apply_line_speed,
    load_line_speed_law,
    read_line_speed_file,
)


class LineModel(NamedTuple):
    """What evaluating the line needs besides the states: the twin's output model and law.

    Attributes
    ----------
    params : PhysicalParameters
    coefficients : array (2, 8) or CalibratedCoefficients
        The twin's (calibrated) output coefficients.
    output : callable
        ``output(x, u, params, coefficients) -> y`` (the twin's ``ModelFunctions.output``).
    speed_law : LineSpeedLaw
    exponent_std : ndarray (2,)
        σ of the law's exponents b, c (the law's uncertainty; zeros to leave it out).
    """

    params: object
    coefficients: object
    output: object
    speed_law: LineSpeedLaw
    exponent_std: np.ndarray


class LineEstimate(NamedTuple):
    """The line at the asked print times and speeds (display units), each (n,)."""

    linewidth_um: np.ndarray
    overspray_um: np.ndarray
    linewidth_std_um: np.ndarray
    overspray_std_um: np.ndarray


@functools.cache
def law_exponent_std() -> tuple[float, float]:
    """σ of (b, c): a quarter of each bracketed range of ``data/line_speed.toml``."""
    ranges = read_line_speed_file()["uncertainty"]
    return tuple(
        (float(ranges[name][1]) - float(ranges[name][0])) / 4.0
        for name in ("linewidth_exponent_range", "overspray_exponent_range")
    )


def line_model(params, coefficients, output, speed_law=None, with_law_uncertainty=True):
    """A :class:`LineModel` (the packaged law, its uncertainty unless told otherwise)."""
    law = speed_law or load_line_speed_law()
    std = np.asarray(law_exponent_std()) if with_law_uncertainty else np.zeros(2)
    return LineModel(params, coefficients, output, law, std)


def _line_and_jacobian(x, u, speed, params, coefficients, law, output):
    def line(z):
        value = apply_line_speed(output(z, u, params, coefficients), speed, law)[:2]
        return value, value

    return jax.jacfwd(line, has_aux=True)(x)


def _lines(x, u, speed, params, coefficients, law, output):
    """:func:`_line_and_jacobian` over n print times (x (n, 5), u (n, 3), speed (n,))."""
    return jax.vmap(
        lambda xi, ui, si: _line_and_jacobian(xi, ui, si, params, coefficients, law, output)
    )(x, u, speed)


_lines = jax.jit(_lines, static_argnames=("output",))


def line_at(model: LineModel, time_s, means, covariances, inputs, times, speeds) -> LineEstimate:
    """The line printed at print times ``times`` [s] and speeds ``speeds`` [mm/s].

    Parameters
    ----------
    model : LineModel
    time_s : array (T,)
        The twin's steps t_k (1 s apart).
    means, covariances : array (T, 5), (T, 5, 5)
        States per step and their covariance (smoothed for a finished print).
    inputs : array (T, 3)
        u_k [mA, sccm, sccm].
    times, speeds : array_like (n,)
        τ (clipped to the steps' span) and ν at τ [mm/s].
    """
    t = np.asarray(time_s, dtype=float)
    x = np.asarray(means, dtype=float)
    p = np.asarray(covariances, dtype=float)
    u = np.asarray(inputs, dtype=float)[:, :3]
    tau = np.atleast_1d(np.asarray(times, dtype=float))
    nu = np.broadcast_to(np.asarray(speeds, dtype=float), tau.shape)
    if tau.size == 0:
        empty = np.zeros(0)
        return LineEstimate(empty, empty, empty, empty)
    if not (np.isfinite(tau).all() and np.isfinite(nu).all() and (nu >= 0).all()):
        raise ValueError("print times and speeds must be finite numbers (speeds >= 0 mm/s)")
    position = np.clip(tau - t[0], 0.0, float(len(t) - 1))
    k = np.minimum(np.floor(position).astype(np.int64), max(len(t) - 2, 0))
    w = (position - k)[:, None]
    k1 = np.minimum(k + 1, len(t) - 1)
    x_tau = x[k] + w * (x[k1] - x[k])
    p_tau = (1.0 - w[:, :, None]) * p[k] + w[:, :, None] * p[k1]
    jac, value = _lines(
        jnp.asarray(x_tau),
        jnp.asarray(u[k]),
        jnp.asarray(nu, dtype=float),
        model.params,
        model.coefficients,
        model.speed_law,
        output=model.output,
    )
    jac, value = np.asarray(jac), np.asarray(value)
    variance = np.einsum("nij,njk,nik->ni", jac, p_tau, jac)
    law = model.speed_law
    clipped = np.clip(nu, law.min_speed_mm_s, law.max_speed_mm_s)
    log_ratio = np.log(law.reference_speed_mm_s / clipped)[:, None]
    variance = variance + (value * log_ratio * np.asarray(model.exponent_std)[None, :]) ** 2
    std = np.sqrt(np.maximum(variance, 0.0))
    return LineEstimate(value[:, 0], value[:, 1], std[:, 0], std[:, 1])
