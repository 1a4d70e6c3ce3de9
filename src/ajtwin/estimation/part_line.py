"""The printed line at any print time and speed, from the twin's states (model reference §7, §12).

A part map asks how wide every stroke was along its length, not only where the camera
looked. The twin's states are known per second with their covariance (filtered, or
smoothed over the whole print); the line printed at a time τ at platen speed ν is the
output model there:

    x(τ) = x_k + w (x_{k+1} − x_k),   P(τ) = (1 − w) P_k + w P_{k+1},
    w = (τ − t_k)/(t_{k+1} − t_k) ∈ [0, 1]                   (τ outside the steps: the nearest)
    L(τ, ν) = f(ν) ⊙ g_line(x(τ), u_k)                      (u held over the second, as printed)
    Var L  = diag(H P(τ) Hᵀ) + (L ln(ν_ref/ν))² σ_b²           (H = ∂L/∂x at x(τ))

f(ν) is the twin's speed law (:mod:`ajtwin.model.line_speed`); the second term is what the
law's own uncertainty adds away from ν_ref (σ_b: what the camera's readings at several speeds
left of it, :mod:`ajtwin.estimation.line_speed_fit`, or before any such print a quarter of
the exponents' bracketed range in ``data/line_speed.toml``, the range as ±2σ; 0 at ν_ref).
P includes what the calibration's uncertainty adds when the twin knows it
(:class:`~ajtwin.estimation.TwinRun`).
The camera's noise is not in it: this is the line on the part, not a measurement of it.

:func:`line_at` is the one evaluation of this line: the part map of a finished or stored
print, the live map and :meth:`~ajtwin.estimation.TwinRun.line_at` all call it. It works
in padded blocks (:func:`block_size`) so that asking for a different number of print times
— as the live map does at every step — does not compile the jitted function again.

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

from typing import NamedTuple

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.estimation.line_speed_fit import prior_exponents
from ajtwin.model.line_speed import (
    LineSpeedLaw,
    apply_line_speed,
    load_line_speed_law,
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


def law_exponent_std() -> tuple[float, float]:
    """σ of (b, c) of the packaged law: a quarter of each bracketed range of
    ``data/line_speed.toml`` (:func:`~ajtwin.estimation.line_speed_fit.prior_exponents`)."""
    return tuple(float(v) for v in prior_exponents().std)


def line_model(params, coefficients, output, speed_law=None, exponent_std=None):
    """A :class:`LineModel`: the packaged law unless given, σ of its exponents
    ``exponent_std`` (2,) (default the packaged law's, :func:`law_exponent_std`; zeros leave
    the law's uncertainty out)."""
    law = speed_law or load_line_speed_law()
    std = np.asarray(law_exponent_std() if exponent_std is None else exponent_std, dtype=float)
    return LineModel(params, coefficients, output, law, std)


#: Largest block of print times evaluated in one call [points].
MAX_BLOCK = 1 << 15
#: Smallest padded block [points].
MIN_BLOCK = 256


def block_size(n: int) -> int:
    """The padded size a block of ``n`` print times is evaluated at: the next power of two,
    between :data:`MIN_BLOCK` and :data:`MAX_BLOCK`.

    The jitted evaluation compiles once per shape, so a live map that asks for a different
    number of points at every update would otherwise compile at every update; with powers of
    two there are at most 8 shapes.

    >>> block_size(1), block_size(257), block_size(10**6) == MAX_BLOCK
    (256, 512, True)
    """
    return min(MAX_BLOCK, max(MIN_BLOCK, 1 << max(int(n) - 1, 0).bit_length()))


def _line_moments(x, p, u, speed, params, coefficients, law, exponent_std, output):
    """Mean (n, 2) and variance (n, 2) of [L_w, L_o] at n states (module docstring)."""

    def one(xi, pi, ui, si):
        def line(z):
            value = apply_line_speed(output(z, ui, params, coefficients), si, law)[:2]
            return value, value

        jac, value = jax.jacfwd(line, has_aux=True)(xi)
        nu = jnp.clip(si, law.min_speed_mm_s, law.max_speed_mm_s)
        law_share = (value * jnp.log(law.reference_speed_mm_s / nu) * exponent_std) ** 2
        return value, jnp.einsum("ij,jk,ik->i", jac, pi, jac) + law_share

    return jax.vmap(one)(x, p, u, speed)


_line_moments = jax.jit(_line_moments, static_argnames=("output",))


def _padded(array: np.ndarray, size: int) -> np.ndarray:
    """``array`` (m, ...) padded to ``size`` rows by repeating its last row."""
    pad = size - len(array)
    return np.concatenate([array, np.repeat(array[-1:], pad, axis=0)]) if pad else array


def interpolation(time_s, times):
    """Where print times τ fall between the steps t_k: (k, w, held), each (n,).

    x(τ) = x_k + w (x_{k+1} − x_k) with w ∈ [0, 1] (τ before the first step or after the
    last takes the nearest); ``held`` is the step whose inputs were held at τ (the second
    that holds it: k, or k + 1 from t_{k+1} on).
    """
    t = np.asarray(time_s, dtype=float)
    tau = np.asarray(times, dtype=float)
    if len(t) == 1:
        zero = np.zeros(tau.shape, dtype=np.int64)
        return zero, np.zeros(tau.shape), zero
    k = np.clip(np.searchsorted(t, tau, side="right") - 1, 0, len(t) - 2)
    span = t[k + 1] - t[k]
    w = np.clip((tau - t[k]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    held = np.where(tau >= t[k + 1], k + 1, k)
    return k, w, held


def line_at(
    model: LineModel, time_s, means, covariances, inputs, times, speeds, progress=None
) -> LineEstimate:
    """The line printed at print times ``times`` [s] and speeds ``speeds`` [mm/s].

    The one place the twin's line is evaluated from its states: the part map of a finished
    or stored print (smoothed states), the live map (filtered states) and
    :meth:`ajtwin.estimation.TwinRun.line_at` all call it. Print times are evaluated in
    blocks of at most :data:`MAX_BLOCK`, each padded to a power of two
    (:func:`block_size`), so the jitted evaluation compiles once per padded size.

    Parameters
    ----------
    model : LineModel
    time_s : array (T,)
        The twin's steps t_k [s], increasing (1 s apart for a print).
    means, covariances : array (T, 5), (T, 5, 5)
        States per step and their covariance (smoothed for a finished print).
    inputs : array (T, 3)
        u_k [mA, sccm, sccm], held over each second.
    times, speeds : array_like (n,)
        τ [s] (outside the steps: the nearest) and ν at τ [mm/s].
    progress : callable(int), optional
        Called with the number of print times done after each block.

    Returns
    -------
    LineEstimate
        Mean and σ of L_w and L_o [µm], each (n,).
    """
    t = np.asarray(time_s, dtype=float).ravel()
    x = np.asarray(means, dtype=float).reshape(-1, 5)
    p = np.asarray(covariances, dtype=float).reshape(-1, 5, 5)
    u = np.asarray(inputs, dtype=float).reshape(len(t), -1)[:, :3]
    tau = np.atleast_1d(np.asarray(times, dtype=float)).ravel()
    nu = np.broadcast_to(np.asarray(speeds, dtype=float), tau.shape).ravel()
    if not (len(t) == len(x) == len(p) >= 1):
        raise ValueError(
            f"steps, means and covariances must be as many (got {len(t)}, {len(x)}, {len(p)})"
        )
    if not (np.isfinite(tau).all() and np.isfinite(nu).all() and (nu >= 0).all()):
        raise ValueError("print times and speeds must be finite numbers (speeds >= 0 mm/s)")
    n = tau.size
    value, variance = np.zeros((n, 2)), np.zeros((n, 2))
    k, w, held = interpolation(t, tau)
    k1 = np.minimum(k + 1, len(t) - 1)
    std = jnp.asarray(model.exponent_std, dtype=float)
    for lo in range(0, n, MAX_BLOCK):
        sel = slice(lo, min(lo + MAX_BLOCK, n))
        kk, ww = k[sel], w[sel]
        size = block_size(len(kk))
        x_tau = x[kk] + ww[:, None] * (x[k1[sel]] - x[kk])
        p_tau = p[kk] + ww[:, None, None] * (p[k1[sel]] - p[kk])
        mean, var = _line_moments(
            jnp.asarray(_padded(x_tau, size)),
            jnp.asarray(_padded(p_tau, size)),
            jnp.asarray(_padded(u[held[sel]], size)),
            jnp.asarray(_padded(nu[sel], size)),
            model.params,
            model.coefficients,
            model.speed_law,
            std,
            output=model.output,
        )
        m = len(kk)
        value[sel], variance[sel] = np.asarray(mean)[:m], np.asarray(var)[:m]
        if progress:
            progress(sel.stop)
    sd = np.sqrt(np.maximum(variance, 0.0))
    return LineEstimate(value[:, 0], value[:, 1], sd[:, 0], sd[:, 1])
