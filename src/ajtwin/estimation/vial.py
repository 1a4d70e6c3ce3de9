"""The vial observer: the ink volume V_l told apart from the atomizer's efficiency.

No output of the twin measures V_l. Its only signature is the droplet generation
H(V_l, Q_c, I_A) (model reference §4) behind the measured material flow: at the aerosol's steady
state (φ_A relaxes in ~5 s) Q_m = g φ_m η H, with g the machine's Q_m gain and η the
atomizer's efficiency relative to the generation fit. Q_m alone sees only the product
η H(V_l). What separates the two is *how* they may change:

* the vial starts at a known fill and can only drain — by the aerosol it gives off
  (η H, the integral of the measured Q_m / (g φ_m)) and by an unmodelled loss r
  (evaporation, a leak) that is slow and persistent;
* the efficiency has an unknown offset for the print (c) and wanders about it within a
  few per cent (w, mean-reverting over ~30 min); it can also fail at once (a dropout).

So a persistent fall of Q_m beyond the efficiency's plausible wander is the vial; a
sudden drop is the atomizer. A small EKF over x = [V_l mL, r mL/h, c, w] does this
bookkeeping (parameters: ``data/vial.toml``)::

    V_{k+1} = V_k − Δt (η_k H(V_k, u_k) + r_k / 3600) + ξ_V,     ln η = c + w
    r_{k+1} = r_k + ξ_r,    c_{k+1} = c_k,    w_{k+1} = a w_k + ξ_w,  a = e^{−Δt/τ_w}
    z_k = ln(Q_m,k / (g φ_m)) = ln H(V_k, u_k) + c_k + w_k + ε_k,   ε ~ N(0, σ_ε²)

with V_0 ~ N(fill, σ_fill²), r_0 ~ N(0, σ_r²), c_0 ~ N(0, σ_c²), w_0 ~ N(0, σ_w²).
A *step* of Q_m is not read as the vial: a two-sided CUSUM on the normalised
innovations (allowance k, threshold h) holds the observer (no update) while it is above
h, and single samples beyond the gate are not used. Without the hold, a Gaussian
filter explains a step more cheaply by re-reading the level ridge V_l ↔ c (the level
is known only to ±σ_r·t) than by w, whose per-step moves are tiny: 5 min of atomizer
dropout made the vial "fall" 0.7 mL. While held, the vial follows the model (its band
widens) and :attr:`VialEstimate.held` says so.

The
step is one pure function (:func:`observer_step`): the batch :func:`observe_vial` scans
it and :class:`VialObserver` calls it per sample (the live detectors).

Parameters (of :func:`observe_vial`)
-----------------------------------
inputs : (T, 3) [mA, sccm, sccm];  material_flow : (T,) measured Q_m [mL/s], NaN = none;
fill_ml, fill_std_ml : the vial's known fill and its σ [mL]; material_flow_gain : g.

Returns
-------
:class:`VialEstimate`: V_l, r, η with σ per second, and the 'running low' flag.

Example
-------
>>> import numpy as np
>>> from ajtwin.model import load_parameters
>>> from ajtwin.model.atomizer import net_droplet_generation
>>> params = load_parameters()
>>> u = np.tile([375.0, 23.0, 50.0], (600, 1))
>>> q = 0.087 * float(net_droplet_generation(23.0, 0.8, 375.0, params.generation_fit))
>>> est = observe_vial(u, np.full(600, q), fill_ml=0.8, fill_std_ml=3e-3)
>>> bool(abs(est.vial_ml[-1] - 0.8) < 0.01), bool(est.running_low[-1])
(True, False)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ajtwin._aot import exported_jit
from ajtwin._jax import jax, jnp
from ajtwin.config import load_toml
from ajtwin.model.atomizer import net_droplet_generation
from ajtwin.model.parameters import PhysicalParameters, load_parameters

N_OBSERVER = 4  # V_l, r, c, w
#: smallest generation used inside the log [mL/s] (H of the fit can go ≤ 0 far outside it)
_MIN_GENERATION = 1e-12


def load_vial_settings(path=None) -> dict:
    """``data/vial.toml`` as ``{"twin": {...}, "observer": {...}, "low": {...}}`` of values."""
    raw = load_toml(path, "data/vial.toml", what="vial settings")
    out = {}
    for group in ("twin", "observer", "low"):
        if group not in raw:
            raise ValueError(f"{path or 'vial.toml'}: missing table [{group}]")
        out[group] = {name: entry["value"] for name, entry in raw[group].items()}
    return out


@dataclass(frozen=True)
class VialSettings:
    """Priors and noise of the observer (``data/vial.toml`` [observer] and [low])."""

    efficiency_offset_std: float = 0.10
    efficiency_wander_std: float = 0.05
    efficiency_wander_time_s: float = 1800.0
    loss_rate_std_mL_per_h: float = 0.10
    loss_rate_walk_mL_per_h_per_sqrt_h: float = 0.02
    vial_walk_mL_per_sqrt_s: float = 1e-6
    material_flow_log_std: float = 0.17
    innovation_gate_sigma: float = 4.0
    step_allowance_sigma: float = 1.0
    step_threshold_sigma: float = 8.0
    vial_low_mL: float = 0.5
    horizon_min: float = 30.0
    loss_significance_z: float = 3.0

    @classmethod
    def load(cls, path=None) -> VialSettings:
        """The observer's and the low-vial rule's settings from ``data/vial.toml`` (or a user's
        file)."""
        raw = load_vial_settings(path)
        return cls(**raw["observer"], **raw["low"])


class ObserverModel(NamedTuple):
    """What the observer's step needs (a pytree of arrays)."""

    generation_fit: jnp.ndarray  # (8,) H's coefficients
    silver_fraction: float  # φ_m
    decay: float  # a = e^{−Δt/τ_w}
    process_var: jnp.ndarray  # (4,) per-step variances
    measurement_var: float  # σ_ε²
    gate: float  # |ν|/√S above this: no update (a sudden atomizer fault is not the vial)
    step_allowance: float  # k of the step CUSUM on the normalised innovations
    step_threshold: float  # h: above it the observer holds (a step of Q_m: the atomizer)
    dt: float = 1.0


def observer_model(
    settings: VialSettings, params: PhysicalParameters | None = None, dt: float = 1.0
) -> ObserverModel:
    """The vial observer's linear-Gaussian model for one step of ``dt`` seconds.

    Parameters
    ----------
    settings : VialSettings
    params : PhysicalParameters, optional
        Default: the packaged parameters.
    dt : float
        Step [s].
    """
    params = params or load_parameters()
    s = settings
    decay = float(np.exp(-dt / s.efficiency_wander_time_s))
    process_var = np.array(
        [
            s.vial_walk_mL_per_sqrt_s**2 * dt,
            s.loss_rate_walk_mL_per_h_per_sqrt_h**2 * dt / 3600.0,
            0.0,
            s.efficiency_wander_std**2 * (1.0 - decay**2),
        ]
    )
    return ObserverModel(
        np.asarray(params.generation_fit, dtype=float),
        float(params.silver_volume_fraction),
        decay,
        np.asarray(process_var, dtype=float),
        float(s.material_flow_log_std**2),
        float(s.innovation_gate_sigma),
        float(s.step_allowance_sigma),
        float(s.step_threshold_sigma),
        float(dt),
    )


def _log_generation(vial_ml, u, model: ObserverModel):
    h = net_droplet_generation(u[1], vial_ml, u[0], model.generation_fit)
    return jnp.log(jnp.maximum(h, _MIN_GENERATION))


def _transition(x, u, model: ObserverModel):
    vial, rate, offset, wander = (x[i] for i in range(N_OBSERVER))
    drawn = jnp.exp(offset + wander + _log_generation(vial, u, model))  # mL/s of ink
    vial_next = vial - model.dt * (drawn + rate / 3600.0)
    return jnp.stack([vial_next, rate, offset, model.decay * wander])


def _observation(x, u, model: ObserverModel):
    return _log_generation(x[0], u, model) + x[2] + x[3]


class ObserverCarry(NamedTuple):
    """The vial observer's state between steps.

    Attributes
    ----------
    mean : array (4,)
        x̂_{k|k−1}: V_l [mL], loss rate r [mL/h], efficiency offset c and wander w.
    cov : array (4, 4)
    step_low, step_high : array ()
        CUSUMs of a downward and an upward step of Q_m against the prediction.
    """

    mean: jnp.ndarray  # (4,) x̂_{k|k−1}
    cov: jnp.ndarray  # (4, 4)
    step_low: jnp.ndarray  # () CUSUM of a downward step of Q_m against the prediction
    step_high: jnp.ndarray  # () and of an upward one


def observer_step(model: ObserverModel, carry: ObserverCarry, u, material_flow, gain):
    """Update with Q_m,k (NaN or ≤ 0: no update), then predict to k+1 (pure, jit-able).

    A sample beyond ``model.gate`` σ is not used, and no sample is used while the step
    CUSUM is above its threshold (module docstring): a sudden change of Q_m is a fault
    for the detectors, not evidence about the vial, which cannot fall that fast.

    Returns the carry for k+1 and (x̂_k (4,), P_k (4, 4), normalised innovation, held).
    """
    mean, cov, step_low, step_high = carry
    y = material_flow / (gain * model.silver_fraction)
    measured = jnp.isfinite(y) & (y > 0)
    z = jnp.log(jnp.where(measured, y, 1.0))
    h_row, z_hat = jax.jacfwd(lambda x: (_observation(x, u, model),) * 2, has_aux=True)(mean)
    s = h_row @ cov @ h_row + model.measurement_var
    e = jnp.where(measured, (z - z_hat) / jnp.sqrt(s), jnp.nan)
    e0 = jnp.where(measured, jnp.clip(e, -model.step_threshold, model.step_threshold), 0.0)
    k, h = model.step_allowance, model.step_threshold
    # capped at 2h: once a step is over, the hold ends within ~h/k samples
    step_low = jnp.where(measured, jnp.clip(step_low - e0 - k, 0.0, 2 * h), step_low)
    step_high = jnp.where(measured, jnp.clip(step_high + e0 - k, 0.0, 2 * h), step_high)
    held = (step_low > h) | (step_high > h)
    used = measured & (jnp.abs(e) <= model.gate) & ~held
    gain_k = jnp.where(used, cov @ h_row / s, 0.0)
    nu = jnp.where(used, z - z_hat, 0.0)
    mean_post = mean + gain_k * nu
    m = cov - jnp.outer(gain_k, h_row @ cov)
    cov_post = m - jnp.outer(m @ h_row, gain_k) + model.measurement_var * jnp.outer(gain_k, gain_k)
    cov_post = 0.5 * (cov_post + cov_post.T)
    f_jac, mean_next = jax.jacfwd(lambda x: (_transition(x, u, model),) * 2, has_aux=True)(
        mean_post
    )
    cov_next = f_jac @ cov_post @ f_jac.T + jnp.diag(model.process_var)
    cov_next = 0.5 * (cov_next + cov_next.T)
    return ObserverCarry(mean_next, cov_next, step_low, step_high), (mean_post, cov_post, e, held)


_step_jit = jax.jit(observer_step)


def _scan(model, carry, inputs, material_flow, gain):
    def body(c, inp):
        u, q = inp
        return observer_step(model, c, u, q, gain)

    return jax.lax.scan(body, carry, (inputs, material_flow))


_scan_jit = exported_jit(_scan)


def initial_carry(settings: VialSettings, fill_ml: float, fill_std_ml: float) -> ObserverCarry:
    """The prior before the first sample (module docstring)."""
    if not (np.isfinite(fill_ml) and fill_ml > 0):
        raise ValueError(f"vial fill = {fill_ml!r} mL must be a positive number")
    if not (np.isfinite(fill_std_ml) and fill_std_ml > 0):
        raise ValueError(f"vial fill σ = {fill_std_ml!r} mL must be a positive number")
    s = settings
    # NumPy, not jnp: built on the host before the compiled scan, it dispatches no
    # JAX operation of its own (each would be traced and lowered in every new process)
    mean = np.array([float(fill_ml), 0.0, 0.0, 0.0])
    cov = np.diag(
        [
            fill_std_ml**2,
            s.loss_rate_std_mL_per_h**2,
            s.efficiency_offset_std**2,
            s.efficiency_wander_std**2,
        ]
    )
    return ObserverCarry(mean, cov, np.zeros(()), np.zeros(()))


@dataclass
class VialStatus:
    """The vial at one moment: what a controller or an operator needs.

    ``running_low`` is True when V̂_l is below ``vial_low_mL`` or, with a loss rate
    significantly above zero, is projected to get there within ``horizon_min``.
    """

    vial_ml: float
    vial_std_ml: float
    loss_rate_ml_per_h: float  # unmodelled loss (evaporation, leak), beyond the aerosol drawn
    loss_rate_std_ml_per_h: float
    drain_ml_per_h: float  # the aerosol drawn off (η H)
    efficiency: float  # η = e^{c+w} relative to the generation fit
    efficiency_log_std: float
    minutes_to_low: float  # inf when not falling
    running_low: bool


def status_arrays(means, covs, inputs, model: ObserverModel, settings: VialSettings) -> dict:
    """Vectorised :class:`VialStatus` fields over (T, 4) means, (T, 4, 4) covs, (T, 3) inputs."""
    means = np.atleast_2d(np.asarray(means, dtype=float))
    covs = np.asarray(covs, dtype=float).reshape(-1, N_OBSERVER, N_OBSERVER)
    u = np.atleast_2d(np.asarray(inputs, dtype=float))
    vial, rate = means[:, 0], means[:, 1]
    log_eta = means[:, 2] + means[:, 3]
    fit = np.asarray(model.generation_fit)
    generation = np.maximum(net_droplet_generation(u[:, 1], vial, u[:, 0], fit), _MIN_GENERATION)
    drain = np.exp(log_eta) * generation * 3600.0
    rate_std = np.sqrt(np.maximum(covs[:, 1, 1], 0.0))
    significant = rate > settings.loss_significance_z * rate_std
    falling = drain + np.where(significant, rate, 0.0)
    low = settings.vial_low_mL
    with np.errstate(divide="ignore", invalid="ignore"):
        minutes = np.where(falling > 0, 60.0 * (vial - low) / falling, np.inf)
    minutes = np.maximum(minutes, 0.0)
    return {
        "vial_ml": vial,
        "vial_std_ml": np.sqrt(np.maximum(covs[:, 0, 0], 0.0)),
        "loss_rate_ml_per_h": rate,
        "loss_rate_std_ml_per_h": rate_std,
        "drain_ml_per_h": drain,
        "efficiency": np.exp(log_eta),
        "efficiency_log_std": np.sqrt(np.maximum(covs[:, 2:4, 2:4].sum(axis=(1, 2)), 0.0)),
        "minutes_to_low": minutes,
        "running_low": (vial < low) | (significant & (minutes < settings.horizon_min)),
    }


def vial_status(mean, cov, u, model: ObserverModel, settings: VialSettings) -> VialStatus:
    """:class:`VialStatus` from one observer estimate (mean (4,), cov (4, 4)) at inputs u."""
    row = status_arrays(mean, cov, u, model, settings)
    return VialStatus(
        **{k: float(v[0]) for k, v in row.items() if k != "running_low"},
        running_low=bool(row["running_low"][0]),
    )


@dataclass
class VialEstimate:
    """The observer over a print (per second, display units)."""

    means: np.ndarray  # (T, 4) V_l mL, r mL/h, c, w
    covariances: np.ndarray  # (T, 4, 4)
    normalised_innovations: np.ndarray  # (T,) of ln Q_m (NaN: not measured)
    held: np.ndarray  # (T,) bool: a step of Q_m held the observer (no update)
    running_low: np.ndarray  # (T,) bool, :func:`vial_status` per second, latched
    minutes_to_low: np.ndarray  # (T,)

    @property
    def vial_ml(self) -> np.ndarray:
        """V_l per step [mL]."""
        return self.means[:, 0]

    @property
    def vial_std_ml(self) -> np.ndarray:
        """σ of V_l per step [mL]."""
        return np.sqrt(np.maximum(self.covariances[:, 0, 0], 0.0))

    @property
    def loss_rate_ml_per_h(self) -> np.ndarray:
        """The vial's unmodelled loss rate per step [mL/h]."""
        return self.means[:, 1]

    @property
    def efficiency(self) -> np.ndarray:
        """The atomizer's efficiency exp(c + w) per step [–]."""
        return np.exp(self.means[:, 2] + self.means[:, 3])

    def first_running_low_s(self, time_s) -> float:
        """Time of the first 'running low' second (NaN: never)."""
        hits = np.flatnonzero(self.running_low)
        return float(np.asarray(time_s)[hits[0]]) if len(hits) else float("nan")


def observe_vial(
    inputs,
    material_flow,
    fill_ml: float = 1.0,
    fill_std_ml: float = 3e-3,
    material_flow_gain: float = 1.0,
    settings: VialSettings | None = None,
    params: PhysicalParameters | None = None,
) -> VialEstimate:
    """Run the vial observer over a print (module docstring); ``lax.scan`` of the step."""
    settings = settings or VialSettings.load()
    model = observer_model(settings, params)
    inputs = np.asarray(inputs, dtype=float)
    q = np.asarray(material_flow, dtype=float)
    if inputs.ndim != 2 or inputs.shape[1] != 3 or q.shape != (len(inputs),):
        raise ValueError(f"inputs (T, 3) and material_flow (T,); got {inputs.shape}, {q.shape}")
    if not (np.isfinite(material_flow_gain) and material_flow_gain > 0):
        raise ValueError(f"material_flow_gain = {material_flow_gain!r} must be > 0")
    carry = initial_carry(settings, fill_ml, fill_std_ml)
    _, (means, covs, e, held) = _scan_jit(model, carry, inputs, q, float(material_flow_gain))
    means, covs = np.asarray(means), np.asarray(covs)
    status = status_arrays(means, covs, inputs, model, settings)
    return VialEstimate(
        means,
        covs,
        np.asarray(e),
        np.asarray(held),
        np.logical_or.accumulate(status["running_low"]),  # latched, see VialObserver
        status["minutes_to_low"],
    )


class VialObserver:
    """The observer one sample at a time (live detectors); same step as :func:`observe_vial`.

    ``running_low`` is latched: once raised it stays for the print (a vial does not refill
    itself; a refill is a maintenance event and a new print), so a controller does not
    see it flicker while the projection hovers at the horizon.
    """

    def __init__(
        self,
        fill_ml: float = 1.0,
        fill_std_ml: float = 3e-3,
        material_flow_gain: float = 1.0,
        settings: VialSettings | None = None,
        params: PhysicalParameters | None = None,
    ):
        self.settings = settings or VialSettings.load()
        self.model = observer_model(self.settings, params)
        self.gain = float(material_flow_gain)
        self.carry = initial_carry(self.settings, fill_ml, fill_std_ml)
        self.status: VialStatus | None = None
        self.held = False
        self.latched = False

    def update(self, u, material_flow: float) -> VialStatus:
        """One second: inputs u (3,) [mA, sccm, sccm] and the measured Q_m [mL/s] (NaN: not
        measured); the vial's status now ('running low' latches).
        """
        u = np.asarray(u, dtype=float)
        self.carry, (mean, cov, _, self.held) = _step_jit(
            self.model, self.carry, jnp.asarray(u), float(material_flow), self.gain
        )
        status = vial_status(mean, cov, u, self.model, self.settings)
        self.latched = self.latched or status.running_low
        status.running_low = self.latched
        self.status = status
        return status


def ink_volume_drawn_ml(material_flow, material_flow_gain=1.0, params=None, dt=1.0) -> float:
    """Ink that left the vial as aerosol per the measured Q_m: Σ Q_m Δt / (g φ_m) [mL]."""
    params = params or load_parameters()
    q = np.asarray(material_flow, dtype=float)
    return float(np.nansum(q) * dt / (material_flow_gain * params.silver_volume_fraction))


__all__ = [
    "ObserverModel",
    "VialEstimate",
    "VialObserver",
    "VialSettings",
    "VialStatus",
    "ink_volume_drawn_ml",
    "load_vial_settings",
    "observe_vial",
    "observer_step",
    "status_arrays",
    "vial_status",
]
