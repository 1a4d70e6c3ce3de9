"""Forecast outputs with uncertainty under an input schedule (paper §4 simulation engine).

From a state estimate (mean, covariance) and θ, the EKF prediction step
(:func:`ajtwin.estimation.twin.predict`: x̂ ← f_d(x̂, u; θ), P ← F P Fᵀ + Σ_ξ) is iterated
over the planned inputs in a ``lax.scan``; outputs are g(x̂, u) with variance
G P Gᵀ (G = ∂g/∂x), optionally plus the measurement noise (a band for what the sensors
will read rather than for the true line).

Schedules are written the way an operator says them: ``carrier_flow_sccm=26@+60s``
(``Q_c`` to 26 sccm 60 s from now); names may be the column names or ``I_A``/``Q_c``/
``Q_s``; times ``+90s``, ``+5min``, ``+1.5h`` or plain seconds.

Examples
--------
>>> parse_change("Q_c=26@+1min")
Change(time_s=60.0, input_index=1, value=26.0)
>>> parse_duration("30min"), parse_duration("+90s"), parse_duration("2h")
(1800.0, 90.0, 7200.0)
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pandas as pd

from ajtwin import units
from ajtwin._aot import exported_jit
from ajtwin._jax import jax, jnp
from ajtwin.estimation.filters import model_functions
from ajtwin.estimation.twin import predict
from ajtwin.model import INPUT_NAMES, OUTPUT_NAMES, STATE_NAMES
from ajtwin.model.system import aerosol_level_theta_std, check_input, output_function

INPUT_ALIASES = {
    "i_a": 0,
    "current": 0,
    "atomizer_current": 0,
    "q_c": 1,
    "carrier": 1,
    "carrier_flow": 1,
    "q_s": 2,
    "sheath": 2,
    "sheath_flow": 2,
    **{name.lower(): i for i, name in enumerate(INPUT_NAMES)},
}
#: beyond these the forecast leaves the range the model was built for (model reference §3: ΔR_N
#: 0–0.1 µm typical; the virtual printer's clog reaches ~0.45 µm) — flagged, not clipped
MODEL_RANGE = {"nozzle_deposition_um": 0.5, "linewidth_um": 200.0}

_UNITS_S = {"": 1.0, "s": 1.0, "sec": 1.0, "min": 60.0, "m": 60.0, "h": 3600.0}


class Change(NamedTuple):
    """A planned input change.

    Attributes
    ----------
    time_s : float
        Seconds after the forecast's start.
    input_index : int
        0 I_A [mA], 1 Q_c [sccm], 2 Q_s [sccm].
    value : float
        The new value (display units).
    """

    time_s: float  # seconds after the forecast start
    input_index: int  # 0 I_A [mA], 1 Q_c [sccm], 2 Q_s [sccm]
    value: float  # display units


def parse_duration(text: str) -> float:
    """``"30min"``, ``"+90s"``, ``"1.5h"``, ``"45"`` → seconds."""
    m = re.fullmatch(r"\s*\+?\s*([0-9]*\.?[0-9]+)\s*([a-z]*)\s*", str(text).lower())
    if not m or m.group(2) not in _UNITS_S:
        raise ValueError(f"cannot read the duration {text!r} (use e.g. 90s, 30min, 1.5h)")
    return float(m.group(1)) * _UNITS_S[m.group(2)]


def parse_change(text: str) -> Change:
    """``NAME=VALUE@+TIME`` → :class:`Change` (``@TIME`` defaults to now)."""
    m = re.fullmatch(r"\s*([A-Za-z_]+)\s*=\s*([-+0-9.eE]+)\s*(?:@\s*(.+))?", text)
    if not m:
        raise ValueError(f"cannot read the input change {text!r} (use e.g. Q_c=26@+60s)")
    name = m.group(1).lower()
    if name not in INPUT_ALIASES:
        raise ValueError(
            f"unknown input {m.group(1)!r} in {text!r}; use one of {', '.join(INPUT_NAMES)} "
            "or I_A, Q_c, Q_s"
        )
    value = float(m.group(2))
    when = parse_duration(m.group(3)) if m.group(3) else 0.0
    return Change(when, INPUT_ALIASES[name], value)


def input_schedule(base_u, changes, horizon_s: float) -> np.ndarray:
    """Inputs (T, 3), one row per second of the horizon, base inputs then the changes.

    >>> u = input_schedule([375, 23, 50], [Change(2.0, 1, 26.0)], 4)
    >>> u[:, 1].tolist()
    [23.0, 23.0, 26.0, 26.0]
    """
    n = int(round(horizon_s))
    if n < 1:
        raise ValueError(f"horizon must be at least 1 s, got {horizon_s}")
    u = np.tile(np.asarray(base_u, dtype=float), (n, 1))
    for change in sorted(changes, key=lambda c: c.time_s):
        if change.time_s >= n:
            raise ValueError(
                f"change of {INPUT_NAMES[change.input_index]} at +{change.time_s:g} s is after "
                f"the horizon ({n} s)"
            )
        u[int(round(change.time_s)) :, change.input_index] = change.value
    return check_input(u)


@dataclass
class Forecast:
    """Forecast states and outputs, one row per second (t = 1 … T after the start)."""

    time_s: np.ndarray  # (T,)
    inputs: np.ndarray  # (T, 3)
    state_means: np.ndarray  # (T, 5)
    state_stds: np.ndarray  # (T, 5)
    output_means: np.ndarray  # (T, 5)
    output_stds: np.ndarray  # (T, 5)
    warnings: list = None  # texts: where the forecast leaves the model's range

    def __post_init__(self):
        if self.warnings is None:
            self.warnings = range_warnings(self)

    def to_frame(self) -> pd.DataFrame:
        """One row per second: time, inputs, output means and σ, state means and σ."""
        frame = pd.DataFrame({"time_s": self.time_s})
        for i, name in enumerate(INPUT_NAMES):
            frame[name] = self.inputs[:, i]
        for i, name in enumerate(OUTPUT_NAMES):
            frame[name] = self.output_means[:, i]
            frame[name + "_std"] = self.output_stds[:, i]
        for i, name in enumerate(STATE_NAMES):
            frame[name] = self.state_means[:, i]
            frame[name + "_std"] = self.state_stds[:, i]
        return frame


def range_warnings(fc) -> list[str]:
    """Where the forecast leaves :data:`MODEL_RANGE` (first time), as readable texts."""
    out = []
    checks = (
        ("nozzle_deposition_um", fc.state_means[:, 3], "ΔR_N", "µm"),
        ("linewidth_um", fc.output_means[:, 0], "L_w", "µm"),
    )
    for key, values, short, unit in checks:
        beyond = np.flatnonzero(~(values <= MODEL_RANGE[key]))
        if beyond.size:
            k = beyond[0]
            out.append(
                f"{short} passes {MODEL_RANGE[key]:g} {unit} at +{fc.time_s[k] / 60:.1f} min: "
                "beyond the range the output model was built for; later values are extrapolation"
            )
    return out


#: the transition variant's aerosol-level wander in forecasts (data/transition.toml)
WANDER_KEY = "forecast_aerosol_wander_per_sqrt_h"


def output_moments(spec, m, p, u, platen_speed_mm_s=None):
    """The outputs at state m and their variances diag(G P Gᵀ), G = ∂g/∂x (first order).

    The forecast's bands; the part map's line along a stroke uses the same function with
    the platen speed ν [mm/s] of the stroke (``None``: the line at ν_ref, model reference
    §12).
    """

    def g(x):
        return output_function(
            x, u, spec.params, spec.coefficients, platen_speed_mm_s=platen_speed_mm_s
        )

    jac = jax.jacfwd(g)(m)
    return g(m), jnp.einsum("ij,jk,ik->i", jac, p, jac)


def _forecast_scan(spec, mean, cov, inputs, theta, process_cov, functions=None):

    def body(carry, u):
        m, p = carry
        m, p = predict(spec, m, p, u, theta, process_cov, functions)
        y, var = output_moments(spec, m, p, u)
        return (m, p), (m, jnp.diagonal(p), y, var)

    _, out = jax.lax.scan(body, (mean, cov), inputs)
    return out


_forecast_scan = exported_jit(
    _forecast_scan, static_argnames=("functions",), constant_fields=(("spec", "params"),)
)


def _forecast_scan_level_walk(spec, mean, cov, inputs, theta, process_cov, level_var, functions):
    """:func:`_forecast_scan` with θ_φA (the aerosol level) a random walk over the horizon.

    The state is augmented with θ_φA (variance 0 at the start: EM's value), propagated by
    the same step as the filter's: with F = ∂f/∂x and b = ∂f/∂θ_φA,

        P ← [F b; 0 1] P [F b; 0 1]ᵀ + diag(Σ_ξ, q_θ),   q_θ = ``level_var`` per step,

    in the filter's scaled coordinates (θ_φA scaled by √q_θ). With q_θ → 0 the x block is
    :func:`ajtwin.estimation.twin.predict`'s covariance (tested).
    """

    step = (functions or model_functions("euler")).step
    s = spec.scaling.state
    theta_scale = jnp.sqrt(jnp.maximum(level_var, 1e-300))

    def f_scaled(z, level, u):
        th = theta.at[4].set(theta[4] + level * theta_scale)
        return step(z * s, u, th, spec.params, spec.dt) / s

    q = jnp.zeros((6, 6)).at[:5, :5].set(process_cov / jnp.outer(s, s)).at[5, 5].set(1.0)

    def body(carry, u):
        m, p = carry  # m display units (5,); p scaled (6, 6)
        z = m / s
        jac_x, jac_level = jax.jacfwd(f_scaled, argnums=(0, 1))(z, 0.0, u)
        a = jnp.zeros((6, 6)).at[:5, :5].set(jac_x).at[:5, 5].set(jac_level).at[5, 5].set(1.0)
        p = a @ p @ a.T + q
        m = f_scaled(z, 0.0, u) * s
        px = p[:5, :5] * jnp.outer(s, s)
        y, var = output_moments(spec, m, px, u)
        return (m, p), (m, jnp.diagonal(px), y, var)

    p0 = jnp.zeros((6, 6)).at[:5, :5].set(cov / jnp.outer(s, s))
    _, out = jax.lax.scan(body, (mean, p0), inputs)
    return out


_forecast_scan_level_walk = exported_jit(
    _forecast_scan_level_walk, static_argnames=("functions",), constant_fields=(("spec", "params"),)
)


def aerosol_level_variance(twin, mean, first_input, wander_per_sqrt_h: float) -> float:
    """q_θ [1/s² per step]: θ_φA's random-walk variance per step that makes the steady
    aerosol fraction wander by ``wander_per_sqrt_h`` (relative σ per √hour) at the forecast's
    first inputs and vial level (:func:`ajtwin.model.system.aerosol_level_theta_std`)."""

    per_sqrt_s = units.per_sqrt_h_to_per_sqrt_s(wander_per_sqrt_h)
    std = aerosol_level_theta_std(first_input, float(mean[1]), twin.spec.params, per_sqrt_s)
    return float(std) ** 2 * float(twin.spec.dt)


def forecast(
    twin,
    mean,
    cov,
    inputs,
    theta=None,
    *,
    include_measurement_noise: bool = False,
    input_response0: float | None = None,
    aerosol_wander_per_sqrt_h: float | None = None,
) -> Forecast:
    """Propagate (mean, cov) through the model under ``inputs`` (T, 3), one step per second.

    Parameters
    ----------
    twin : ajtwin.estimation.Twin
        Model, process noise Σ_ξ and (default) θ.
    mean : (5,) start state, display units; cov : (5, 5)
    inputs : (T, 3) inputs [mA, sccm, sccm]; row k drives the step k → k+1
    theta : (5,) θ [1/s], default ``twin.theta``
    include_measurement_noise : bool
        Add the sensors' σ² to the output variances.
    input_response0 : float, optional
        For a twin whose transition variant follows the inputs
        (:mod:`ajtwin.model.droplet_dynamics`): the droplet size's input response r [µm]
        at the start; default its equilibrium with the first planned input.
    aerosol_wander_per_sqrt_h : float, optional
        Relative σ per √h of the aerosol level over the horizon (θ_φA a random walk,
        :func:`_forecast_scan_level_walk`); default the transition variant's
        ``forecast_aerosol_wander_per_sqrt_h`` (data/transition.toml), 0 = none.

    Returns
    -------
    Forecast
    """
    inputs = check_input(np.asarray(inputs, dtype=float))
    theta = twin.theta if theta is None else theta
    model_inputs = inputs
    process_cov = np.array(twin.process_cov, dtype=float)
    if hasattr(twin, "model_inputs"):
        model_inputs = twin.model_inputs(inputs, input_response0)
        # a transition variant may set d_a's long-horizon wander for forecasts
        droplet_std = twin.droplet_dynamics.forecast_droplet_std_um
        if droplet_std > 0:
            process_cov[0, 0] = droplet_std**2
    # NumPy on the host: the compiled scan takes them as they are (a jnp conversion here
    # would be one more JAX program to trace in every new process)
    args = (
        twin.spec,
        np.asarray(mean, dtype=float),
        np.asarray(cov, dtype=float),
        np.asarray(model_inputs, dtype=float),
        np.asarray(theta, dtype=float),
        process_cov,
    )
    # the twin's own model (discretisation, transition variant): the one its θ was learned on
    functions = getattr(twin, "functions", None)
    wander = aerosol_wander_per_sqrt_h
    if wander is None:
        wander = getattr(getattr(twin, "droplet_dynamics", None), WANDER_KEY, 0.0) or 0.0
    wander = float(wander)
    if not (np.isfinite(wander) and wander >= 0):
        raise ValueError(f"aerosol_wander_per_sqrt_h = {wander}: a relative σ per √h, >= 0")
    if wander > 0:
        level_var = aerosol_level_variance(twin, mean, inputs[0], wander)
        m, pdiag, y, var = _forecast_scan_level_walk(
            *args, np.asarray(level_var), functions=functions
        )
    else:
        m, pdiag, y, var = _forecast_scan(*args, functions=functions)
    var = np.asarray(var)
    if include_measurement_noise:
        var = var + twin.measurement_var
    return Forecast(
        time_s=np.arange(1, len(inputs) + 1, dtype=float),
        inputs=inputs,
        state_means=np.asarray(m),
        state_stds=np.sqrt(np.maximum(np.asarray(pdiag), 0.0)),
        output_means=np.asarray(y),
        output_stds=np.sqrt(np.maximum(var, 0.0)),
    )


def plot_forecast(fc: Forecast, path, title: str = "Forecast", history=None):
    """L_w, L_o, P_c, P_s with ±2σ bands (and the recent history when given) → PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ("L_w [µm]", "L_o [µm]", "P_c [Pa]", "P_s [Pa]")
    fig, axes = plt.subplots(5, 1, figsize=(8, 10), sharex=True)
    t_min = fc.time_s / 60.0
    for i, ax in enumerate(axes[:4]):
        mu, sd = fc.output_means[:, i], fc.output_stds[:, i]
        if history is not None:
            th, yh = history
            ax.plot(np.asarray(th) / 60.0, np.asarray(yh)[:, i], ".", ms=1.5, color="0.6")
        ax.fill_between(t_min, mu - 2 * sd, mu + 2 * sd, alpha=0.3, label="±2σ")
        ax.plot(t_min, mu, lw=1.5, label="forecast")
        ax.set_ylabel(labels[i])
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    ax = axes[4]
    ax.plot(t_min, fc.inputs[:, 1], label="Q_c [sccm]")
    ax.plot(t_min, fc.inputs[:, 2], label="Q_s [sccm]")
    ax.plot(t_min, fc.inputs[:, 0] / 10.0, label="I_A / 10 [mA]")
    ax.set_ylabel("inputs")
    ax.set_xlabel("minutes from now")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
