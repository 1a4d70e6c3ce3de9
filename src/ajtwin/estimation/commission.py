"""Commissioning: fit a machine's calibration from a commissioning print (model reference §11).

A commissioning print starts from a cleaned nozzle and a weighed fill and steps the
inputs across the operating window (scenario ``commissioning``). The calibration c
(:mod:`ajtwin.model.calibration`, 11 parameters) is estimated jointly with the states by
an EKF on the augmented state z = [x, c] with dc/dt = 0:

    z_{k+1} = [f_d(x_k, u_k; θ), c_k] + [ξ_k, 0],   y_k = g_c(x_k, u_k) + w_k

started from the priors of ``data/commissioning.toml`` (overridden by ``known`` states)
and iterated: each pass re-linearises around the previous pass's calibration. The
final covariance of c gives the standard errors; a parameter whose posterior σ is not
below ``determined_ratio`` × its prior σ is reported as *not determined by the print*
(its value is then the prior's). Confounded by construction (model reference §11): the line
offsets with d_a, the Q_m gain with φ_A — give ``known`` values to pin them.

**φ_A's level.** The filter holds φ_A at the generation model's prediction φ̂ (it relaxes
to H/Q_c within seconds), so the Q_m gain it fits is the product p = g·λ of the CNN's
true gain g and the atomizer's level λ = φ_A/φ̂. :func:`aerosol_level_posterior` splits
it: with nothing else, λ = 1 ± the generation prior (``aerosol_fraction_relative_std``)
and φ_A is known only relative to the generation model; a known gain
(``material_flow_gain`` from a profilometer-calibrated CNN), the ink the print drew
(the vial weighed before and after: ``vial_used_ml``) or a measured φ_A pins λ. A
pinned level refits the print with the aerosol row held at λ·H (:func:`aerosol_level_theta`)
so the line offsets, which also see φ_A, are fitted at the true level.

Examples
--------
Not run in the suite: a 20-min commissioning print fitted twice (~25 s).

>>> from ajtwin.simulation import simulate
>>> rec = simulate("commissioning", seed=1, machine_seed=3)        # doctest: +SKIP
>>> result = commission(rec, known={"droplet_diameter_um": (3.4, 0.2)})  # doctest: +SKIP
>>> result.calibration.linewidth_offset_um                           # doctest: +SKIP
>>> pinned = commission(rec, known={"material_flow_gain": (1.0, 0.03)})  # doctest: +SKIP
>>> pinned.aerosol_level["pinned_by"]                                     # doctest: +SKIP
['material_flow_gain']
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ajtwin import units
from ajtwin._jax import jnp
from ajtwin.config import packaged_toml
from ajtwin.estimation.filters import DEFAULT_SCALING, ModelFunctions, ModelSpec, Scaling, ekf
from ajtwin.estimation.twin import TwinConfig
from ajtwin.model import DigitalModel
from ajtwin.model.calibration import (
    CALIBRATION_NAMES,
    IDENTITY,
    PARAMETER_OUTPUT,
    CalibratedCoefficients,
    Calibration,
    calibration_from_vector,
    write_calibration_file,
)
from ajtwin.model.names import N_STATES, OUTPUT_NAMES, STATE_NAMES
from ajtwin.model.system import (
    aerosol_level_theta,
    check_input,
    euler_step,
    output_function,
    steady_aerosol_fraction,
)

N_CAL = len(CALIBRATION_NAMES)
GAIN = CALIBRATION_NAMES.index("material_flow_gain")
#: a weighed ink use this many times off the modelled one is a weighing error, not the atomizer
LEVEL_PLAUSIBLE = (0.1, 10.0)


class CommissioningError(ValueError):
    """A print that cannot determine the calibration (too short, no steps, no camera)."""


def load_commissioning_settings() -> dict:
    """Commissioning's priors and checks with their provenance (``data/commissioning.toml``)."""
    return packaged_toml("data/commissioning.toml")


def _augmented_step(z, u, theta, params, dt):
    """[f_d(x, u; θ), c]: the calibration is constant."""
    x_next = euler_step(z[:N_STATES], u, theta[:N_STATES], params, dt)
    return jnp.concatenate([x_next, z[N_STATES:]])


def _augmented_output(z, u, params, coefficients):
    calibration = calibration_from_vector(z[N_STATES:])
    return output_function(
        z[:N_STATES], u, params, CalibratedCoefficients(coefficients, calibration)
    )


AUGMENTED = ModelFunctions(_augmented_step, _augmented_output)


@dataclass
class CommissioningResult:
    """What commissioning found (display units)."""

    calibration: Calibration
    std: dict  # parameter -> standard error
    prior_std: dict
    determined: dict  # parameter -> bool
    priors: dict  # state priors used (mean, std)
    n_samples: int
    mean_nis: float
    end_state: np.ndarray
    end_state_std: np.ndarray
    end_state_cov: np.ndarray = None  # (5, 5): the machine's state when commissioning ended
    calibration_cov: np.ndarray = None  # (11, 11): Σ_c with the standard errors above
    # (5,): this machine's output noise σ / the tuned σ (its camera, gauges, CNN)
    noise_factors: np.ndarray = None
    notes: list = field(default_factory=list)
    #: φ_A's level relative to the generation model (:func:`aerosol_level_posterior`):
    #: ``relative`` λ, ``relative_std``, ``pinned_by`` (what pinned it; [] = only the
    #: generation prior), ``theta_per_s`` (θ_φA that holds λ at the print's last inputs),
    #: ``generation_prior_std``
    aerosol_level: dict = field(default_factory=dict)

    def write_toml(self, path, provenance: dict):
        """Write the calibration (with covariance, noise factors and φ_A's level) as TOML
        (:func:`~ajtwin.model.calibration.write_calibration_file`); the path written."""
        return write_calibration_file(
            path,
            self.calibration,
            self.std,
            provenance,
            covariance=self.calibration_cov,
            noise_factors=dict(zip(OUTPUT_NAMES, np.asarray(self.noise_factors).tolist())),
            aerosol_level=self.aerosol_level,
        )

    def table(self) -> list[dict]:
        """One row per parameter: value, standard error, prior σ, determined."""
        values = self.calibration._asdict()
        return [
            {
                "parameter": name,
                "value": float(values[name]),
                "std_error": float(self.std[name]),
                "prior_std": float(self.prior_std[name]),
                "determined": bool(self.determined[name]),
            }
            for name in CALIBRATION_NAMES
        ]


def parse_amount(text: str, what: str) -> tuple[float, float]:
    """``"3.5±0.2"`` (or ``+-``, ``+/-``) → (3.5, 0.2); a clear error naming ``what``."""
    value = str(text).replace("+/-", "±").replace("+-", "±")
    mean_text, _, std_text = value.partition("±")
    try:
        mean = float(mean_text)
        std = float(std_text) if std_text else None
    except ValueError:
        raise ValueError(f"{what} {text!r}: VALUE and STD must be numbers") from None
    if not np.isfinite(mean):
        raise ValueError(f"{what} {text!r}: VALUE must be finite")
    if std is None or not (std > 0 and np.isfinite(std)):
        raise ValueError(f"{what} {text!r}: give a positive uncertainty, e.g. {mean}±0.1")
    return mean, std


def parse_known(items) -> dict:
    """``["droplet_diameter_um=3.5±0.2", ...]`` → {name: (mean, std)} (``+-`` works too).

    A name is a state (:data:`STATE_NAMES`) known at the start or a calibration parameter
    (:data:`CALIBRATION_NAMES`) known from elsewhere, e.g. ``material_flow_gain=1.00±0.03``
    from a CNN calibrated against a profilometer.
    """
    known = {}
    for item in items or ():
        if "=" not in item:
            raise ValueError(
                f"--known {item!r}: write NAME=VALUE±STD, e.g. droplet_diameter_um=3.5±0.2"
            )
        name, value = item.split("=", 1)
        name = name.strip()
        if name not in STATE_NAMES and name not in CALIBRATION_NAMES:
            raise ValueError(
                f"--known {item!r}: unknown state or calibration parameter {name!r} (states: "
                f"{', '.join(STATE_NAMES)}; calibration: {', '.join(CALIBRATION_NAMES)})"
            )
        if value.replace("+/-", "±").replace("+-", "±").partition("±")[1] == "":
            raise ValueError(
                f"--known {item!r}: give a positive uncertainty, e.g. {name}={value}±0.1"
            )
        known[name] = parse_amount(value, f"--known {name}")
    return known


def _step_size(values: np.ndarray) -> float:
    """Spread between the low and high levels an input visited (robust to jitter)."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0
    return float(np.percentile(finite, 95) - np.percentile(finite, 5))


def check_commissioning_print(inputs, measurements, checks: dict, where: str = "print") -> None:
    """Refuse a print that cannot determine the calibration (clear message)."""
    n = len(inputs)
    problems = []
    if n < checks["min_duration_s"]:
        problems.append(
            f"it is {n} s long; commissioning needs at least {checks['min_duration_s']} s "
            "(use the `commissioning` scenario: 20 min of input steps)"
        )
    carrier_step = _step_size(inputs[:, 1])
    sheath_step = _step_size(inputs[:, 2])
    if carrier_step < checks["min_carrier_step_sccm"]:
        problems.append(
            f"carrier flow varies only {carrier_step:.2f} sccm (needs steps ≥ "
            f"{checks['min_carrier_step_sccm']} sccm): the line gains and the carrier-line "
            "factor cannot be told from the offsets"
        )
    if sheath_step < checks["min_sheath_step_sccm"]:
        problems.append(
            f"sheath flow varies only {sheath_step:.2f} sccm (needs steps ≥ "
            f"{checks['min_sheath_step_sccm']} sccm): the sheath-line factor cannot be told "
            "from the gauge gain"
        )
    camera = np.isfinite(measurements[:, 0]).sum()
    if camera < checks["min_camera_samples"]:
        problems.append(
            f"the camera columns (linewidth_um) hold {camera} finite samples (needs ≥ "
            f"{checks['min_camera_samples']}): the line model cannot be calibrated"
        )
    for column, name in ((2, "carrier_pressure_Pa"), (3, "sheath_pressure_Pa")):
        count = np.isfinite(measurements[:, column]).sum()
        if count < checks["min_pressure_samples"]:
            problems.append(
                f"column {name} holds {count} finite samples (needs ≥ "
                f"{checks['min_pressure_samples']})"
            )
    if problems:
        raise CommissioningError(f"{where} cannot commission this machine: " + "; ".join(problems))


def noise_factors(result, measurements, bounds=(0.5, 3.0)) -> np.ndarray:
    """Per-output factor (5,) on the tuned σ_w that makes this machine's innovations unit.

    A machine's camera, gauges and CNN have their own noise (a line printed 1.4× wider
    carries 1.4× the relative camera noise): σ_w,machine = σ_w · sqrt(mean ν²/S), bounded.
    Learned at commissioning only; online only the line outputs may adapt (em_calibration).
    """
    predicted = np.asarray(result.predicted_outputs)
    variance = np.asarray(result.innovation_variances)
    nu2 = (np.asarray(measurements) - predicted) ** 2 / np.maximum(variance, 1e-300)
    factors = np.ones(nu2.shape[1])
    for j in range(nu2.shape[1]):
        finite = np.isfinite(nu2[:, j])
        if finite.sum() >= 10:
            factors[j] = np.sqrt(np.mean(nu2[finite, j]))
    return np.clip(factors, *bounds)


def residual_inflation(result, measurements) -> np.ndarray:
    """Per-output factor (5,) by which the filter's standard errors understate the truth.

    The EKF takes the output noise as white with the tuned variance; a real machine's
    residuals are larger (mean NIS > 1) and correlated in time (MFC jitter, slow line
    noise), so fewer independent samples back the calibration. With ν the normalised
    innovations of one output and ρ their lag-1 autocorrelation, the variance of a mean
    of AR(1) residuals grows by (1 + ρ)/(1 − ρ); the factor is
    sqrt(max(mean ν², 1) · (1 + ρ)/(1 − ρ)), ρ clipped to [0, 0.95].
    """
    predicted = np.asarray(result.predicted_outputs)
    variance = np.asarray(result.innovation_variances)
    nu = (np.asarray(measurements) - predicted) / np.sqrt(np.maximum(variance, 1e-300))
    factors = np.ones(nu.shape[1])
    for j in range(nu.shape[1]):
        series = nu[:, j]
        ok = np.isfinite(series[1:]) & np.isfinite(series[:-1])
        if ok.sum() < 10:
            continue
        a, b = series[1:][ok], series[:-1][ok]
        rho = float(np.clip(np.corrcoef(a, b)[0, 1], 0.0, 0.95))
        power = float(np.nanmean(series**2))
        factors[j] = np.sqrt(max(power, 1.0) * (1.0 + rho) / (1.0 - rho))
    return factors


def commission(
    record=None,
    *,
    inputs=None,
    measurements=None,
    known: dict | None = None,
    vial_fill_ml: float = 1.0,
    vial_used_ml: tuple | None = None,
    settings: dict | None = None,
    model: DigitalModel | None = None,
    process_std=None,
    measurement_std=None,
    where: str | None = None,
) -> CommissioningResult:
    """Fit a machine's calibration from a commissioning print (see module docstring).

    Parameters
    ----------
    record : PrintRecord, optional
        The commissioning print; or ``inputs`` (T, 3) and ``measurements`` (T, 5).
    known : dict, optional
        Name → (mean, std) known from elsewhere: a state at the start, e.g.
        ``{"droplet_diameter_um": (3.5, 0.2)}`` from a droplet sizer (overrides its prior),
        or a calibration parameter, e.g. ``{"material_flow_gain": (1.0, 0.03)}`` from a
        profilometer-calibrated CNN (pins φ_A's level; others replace their prior).
    vial_fill_ml : float
        The weighed fill [mL].
    vial_used_ml : (mean, std), optional
        The ink the print drew from the vial [mL] (weighed before and after): pins the
        print's mean φ_A through dV_l/dt = −φ_A Q_c.
    settings : dict, optional
        Replaces ``data/commissioning.toml``.
    process_std, measurement_std : array (5,), optional
        Filter tuning (default: the twin's ``noise.toml`` "calibrated" profile).

    Returns
    -------
    CommissioningResult

    Raises
    ------
    CommissioningError
        The print is too short, has no input steps, lacks camera/pressure data, or its
        weighed ink use is implausible.
    """
    if record is not None:
        inputs, measurements = record.inputs, record.outputs
        where = where or str(record.meta.get("source_file", "the commissioning print"))
    where = where or "the commissioning print"
    inputs = np.asarray(inputs, dtype=float)
    measurements = np.asarray(measurements, dtype=float)
    if inputs.ndim != 2 or inputs.shape[1] != 3 or measurements.shape != (len(inputs), 5):
        raise CommissioningError(
            f"{where}: inputs must be (T, 3) and measurements (T, 5); got {inputs.shape}, "
            f"{measurements.shape}"
        )
    settings = settings or load_commissioning_settings()
    checks = settings["checks"]
    check_commissioning_print(inputs, measurements, checks, where)
    inputs = check_input(inputs)
    model = model or DigitalModel.default()
    config = TwinConfig.default(model)
    process_std = np.asarray(config.process_std if process_std is None else process_std, float)
    measurement_std = np.asarray(
        config.measurement_std if measurement_std is None else measurement_std, float
    )
    known = dict(known or {})
    unknown = sorted(set(known) - set(STATE_NAMES) - set(CALIBRATION_NAMES))
    if unknown:
        raise ValueError(
            f"known: unknown name(s) {unknown} (states {', '.join(STATE_NAMES)}; calibration "
            f"{', '.join(CALIBRATION_NAMES)})"
        )
    state_known = {k: v for k, v in known.items() if k in STATE_NAMES}
    priors = state_priors(settings, inputs[0], vial_fill_ml, model, state_known)
    cal_prior_mean, cal_prior_std, fixed = _calibration_prior(settings, known)
    run = _CommissioningRun(
        model, priors, cal_prior_mean, cal_prior_std, fixed, inputs, measurements,
        process_std, measurement_std, int(checks["passes"]), where,
    )  # fmt: skip
    result, cal_mean = run.filter(thetas=None)
    data_std, correlation = _calibration_errors(result, measurements)
    generation_std = float(settings["state_prior"]["aerosol_fraction_relative_std"]["value"])
    pins = _level_pins(known, vial_used_ml, result, inputs, model, where)
    mean, cov = aerosol_level_posterior(
        cal_mean[GAIN], data_std[GAIN] / abs(cal_mean[GAIN]), generation_std, **pins
    )
    level, level_std = float(np.exp(mean[1])), float(np.sqrt(cov[1, 1]))
    thetas = None
    if any(v is not None for v in pins.values()):
        # refit with the aerosol row at the pinned level: the line offsets see φ_A too
        vial_path = np.asarray(result.means)[:, 1]
        thetas = np.zeros((len(inputs), N_STATES + N_CAL))
        thetas[:, 4] = np.asarray(aerosol_level_theta(inputs, vial_path, model.params, level))
        result, cal_mean = run.filter(thetas=thetas)
        data_std, correlation = _calibration_errors(result, measurements)
    reported_std = data_std.copy()
    reported_std[GAIN] = abs(cal_mean[GAIN]) * float(np.sqrt(cov[0, 0]))
    aerosol_level = {
        "relative": level,
        "relative_std": level_std,
        "pinned_by": [PIN_NAMES[name] for name, v in pins.items() if v is not None],
        "theta_per_s": 0.0 if thetas is None else float(thetas[-1, 4]),
        "generation_prior_std": generation_std,
    }
    return _result(
        result, measurements, cal_mean, reported_std, cal_prior_std,
        correlation * np.outer(data_std, data_std), priors, known, aerosol_level,
        float(checks["determined_ratio"]),
    )  # fmt: skip


def _result(
    result, measurements, cal_mean, std, prior_std, cal_cov, priors, known, level, ratio
) -> CommissioningResult:
    """The :class:`CommissioningResult` of the last filter pass: its end state (φ_A's band
    widened by the level's uncertainty), the calibration with its standard errors, the
    fit's NIS and noise factors, and the notes."""
    end = np.asarray(result.means[-1])
    end_cov = np.asarray(result.covariances[-1])[:N_STATES, :N_STATES].copy()
    end_cov[4, 4] += (level["relative_std"] * end[4]) ** 2  # φ_A's level is as uncertain as λ
    nis = np.asarray(result.nis)
    n_meas = np.maximum(np.asarray(result.n_measured), 1)
    return CommissioningResult(
        calibration=Calibration(*(float(v) for v in cal_mean)),
        std=dict(zip(CALIBRATION_NAMES, std.tolist(), strict=True)),
        prior_std=dict(zip(CALIBRATION_NAMES, prior_std.tolist(), strict=True)),
        determined={
            name: bool(std[i] < ratio * prior_std[i]) for i, name in enumerate(CALIBRATION_NAMES)
        },
        priors={k: list(v) for k, v in priors.items()},
        n_samples=len(measurements),
        mean_nis=float(np.mean(nis / n_meas)),
        end_state=end[:N_STATES],
        end_state_std=np.sqrt(np.maximum(np.diag(end_cov), 0.0)),
        end_state_cov=end_cov,
        calibration_cov=cal_cov,
        noise_factors=noise_factors(result, measurements),
        notes=_confounding_notes(priors, known, level),
        aerosol_level=level,
    )


#: how each pin of φ_A's level is named to the user
PIN_NAMES = {
    "gain": "material_flow_gain",
    "ink_used": "vial weighing",
    "aerosol": "aerosol_fraction",
}


def aerosol_level_posterior(
    product, product_relative_std, prior_relative_std, gain=None, ink_used=None, aerosol=None
):
    """Split the Q_m gain a commissioning print determines into the CNN's gain and φ_A's level.

    The commissioning filter holds φ_A at the generation model's φ̂, so the gain it fits is
    the product p = g·λ of the true Q_m gain g and the atomizer's level λ = φ_A/φ̂. In
    logarithms a = ln g, b = ln λ everything is linear and Gaussian (relative σ → σ of
    the logarithm, first order):

        ln p = a + b   ± r_p          (the print's Q_m)
        b    = 0       ± s            (the generation prior)
        a    = ln m    ± r_m          (``gain``: a known Q_m gain m ± σ_m)
        b    = ln ρ    ± r_ρ          (``ink_used`` or ``aerosol``: a measured level ρ ± σ_ρ)

    and the posterior is the weighted least-squares solution: precision Λ = Σ hᵢhᵢᵀ/rᵢ²,
    mean Λ⁻¹ Σ hᵢ yᵢ/rᵢ². The gain has no prior of its own here: without a pin, b stays
    at its prior and a = ln p − b.

    Parameters
    ----------
    product : float
        p, the Q_m gain the filter fitted.
    product_relative_std : float
        Its relative standard error from the data.
    prior_relative_std : float
        s, the generation model's relative error.
    gain, ink_used, aerosol : (value, relative std), optional
        The pins: m (the gain), ρ (measured over modelled ink use, or φ_A over φ̂).

    Returns
    -------
    mean : array (2,)
        (a, b).
    cov : array (2, 2)

    Examples
    --------
    >>> mean, cov = aerosol_level_posterior(0.8, 0.01, 0.35)
    >>> round(float(np.exp(mean[1])), 6), round(float(np.sqrt(cov[1, 1])), 3)
    (1.0, 0.35)
    >>> mean, cov = aerosol_level_posterior(0.8, 0.01, 0.35, gain=(1.0, 0.03))
    >>> round(float(np.exp(mean[1])), 2), round(float(np.sqrt(cov[1, 1])), 3)
    (0.8, 0.031)
    """
    rows = [((1.0, 1.0), np.log(product), product_relative_std)]
    rows.append(((0.0, 1.0), 0.0, prior_relative_std))
    if gain is not None:
        rows.append(((1.0, 0.0), np.log(gain[0]), gain[1]))
    for level in (ink_used, aerosol):
        if level is not None:
            rows.append(((0.0, 1.0), np.log(level[0]), level[1]))
    precision = np.zeros((2, 2))
    information = np.zeros(2)
    for h, y, r in rows:
        h = np.asarray(h)
        precision += np.outer(h, h) / r**2
        information += h * y / r**2
    cov = np.linalg.inv(precision)
    return cov @ information, cov


def modelled_ink_drawn(aerosol_fraction, inputs, dt: float = 1.0) -> float:
    """The ink the model draws from the vial over a print [mL]: Σ φ̂_A,k Q_c,k Δt
    (dV_l/dt = −φ_A Q_c), with the filter's φ̂_A (T,) and the inputs (T, 3)."""
    carrier = np.asarray(units.sccm_to_ml_per_s(np.asarray(inputs, dtype=float)[:, 1]))
    return float(np.sum(np.asarray(aerosol_fraction, dtype=float) * carrier) * dt)


def _level_pins(known, vial_used_ml, result, inputs, model, where) -> dict:
    """The pins of φ_A's level as :func:`aerosol_level_posterior` takes them (None: absent)."""
    pins = {"gain": None, "ink_used": None, "aerosol": None}
    if "material_flow_gain" in known:
        mean, std = known["material_flow_gain"]
        if not mean > 0:
            raise ValueError(f"known material_flow_gain = {mean}: a gain must be positive")
        pins["gain"] = (mean, std / mean)
    aerosol_path = np.asarray(result.means)[:, 4]
    if vial_used_ml is not None:
        used, used_std = (float(v) for v in vial_used_ml)
        modelled = modelled_ink_drawn(aerosol_path, inputs)
        ratio = used / modelled if used > 0 else 0.0
        if not LEVEL_PLAUSIBLE[0] <= ratio <= LEVEL_PLAUSIBLE[1]:
            raise CommissioningError(
                f"{where}: the vial lost {used:.3g} mL but the generation model draws "
                f"{modelled:.3g} mL over this print ({ratio:.3g}×): check the weighing (mL of "
                "ink, not g; an evaporation blank subtracted) before pinning φ_A with it"
            )
        pins["ink_used"] = (ratio, used_std / used)
    if "aerosol_fraction" in known:
        mean, std = known["aerosol_fraction"]
        modelled = float(aerosol_path[0])
        if not (mean > 0 and LEVEL_PLAUSIBLE[0] <= mean / modelled <= LEVEL_PLAUSIBLE[1]):
            raise CommissioningError(
                f"{where}: the known aerosol fraction {mean:.3g} is {mean / modelled:.3g}× the "
                f"generation model's {modelled:.3g}: check its units (a volume fraction)"
            )
        pins["aerosol"] = (mean / modelled, std / mean)
    return pins


def state_priors(settings: dict, u0, vial_fill_ml: float, model, known: dict) -> dict:
    """The start state's prior {name: (mean, std)} (display units) of a commissioning print.

    Parameters
    ----------
    settings : dict
        ``data/commissioning.toml`` (its ``state_prior`` table).
    u0 : array (3,)
        The print's first inputs [mA, sccm, sccm] (φ_A's mean: the generation model there).
    vial_fill_ml : float
        The weighed fill [mL].
    model : DigitalModel
    known : dict
        States known at the start {name: (mean, std)}; they replace the priors.
    """
    prior = settings["state_prior"]
    aerosol = float(steady_aerosol_fraction(u0, vial_fill_ml, model.params))
    priors = {
        name: (prior[name]["mean"], prior[name]["std"])
        for name in ("droplet_diameter_um", "tube_deposition_um", "nozzle_deposition_um")
    }
    priors["vial_volume_mL"] = (vial_fill_ml, prior["vial_volume_std_mL"]["value"])
    # the start's transient only: φ_A's level is the generation prior's, split off after the fit
    relative = prior["aerosol_fraction_start_relative_std"]["value"]
    priors["aerosol_fraction"] = (aerosol, relative * aerosol)
    priors.update({k: (float(m), float(s)) for k, (m, s) in known.items()})
    return {name: priors[name] for name in STATE_NAMES}


def _calibration_prior(settings: dict, known: dict):
    """(prior mean (11,), prior σ (11,), indices held at a known value in every pass).

    A known calibration parameter replaces its prior — except the Q_m gain, which pins
    φ_A's level after the fit (:func:`aerosol_level_posterior`) instead: the filter holds
    φ_A at the generation model, so a gain fixed in it would contradict Q_m.
    """
    mean = np.array(IDENTITY, dtype=float)
    std = np.array([float(settings["calibration_prior_std"][n]) for n in CALIBRATION_NAMES])
    fixed = []
    for i, name in enumerate(CALIBRATION_NAMES):
        if name in known and name != "material_flow_gain":
            mean[i], std[i] = known[name]
            fixed.append(i)
    return mean, std, tuple(fixed)


@dataclass
class _CommissioningRun:
    """The augmented EKF over one commissioning print (everything but θ fixed)."""

    model: DigitalModel
    priors: dict
    cal_prior_mean: np.ndarray
    cal_prior_std: np.ndarray
    fixed: tuple
    inputs: np.ndarray
    measurements: np.ndarray
    process_std: np.ndarray
    measurement_std: np.ndarray
    passes: int
    where: str

    def filter(self, thetas=None):
        """The EKF over [x, c] (c as constant states), ``passes`` times, each pass starting c
        where the last ended (known parameters stay at their value). ``thetas`` (T, 16):
        the drift per step (None: 0). Returns (the last filter result, c at its end)."""
        x_mean = np.array([self.priors[n][0] for n in STATE_NAMES])
        x_std = np.array([self.priors[n][1] for n in STATE_NAMES])
        cal_mean = self.cal_prior_mean.copy()
        scaling = Scaling(
            jnp.concatenate([DEFAULT_SCALING.state, jnp.asarray(self.cal_prior_std)]),
            DEFAULT_SCALING.output,
        )
        spec = ModelSpec(self.model.params, jnp.asarray(self.model.coefficient_matrix), scaling)
        process_cov = np.zeros((N_STATES + N_CAL, N_STATES + N_CAL))
        process_cov[:N_STATES, :N_STATES] = np.diag(self.process_std**2)
        prior_cov = np.diag(np.concatenate([x_std, self.cal_prior_std]) ** 2)
        thetas = np.zeros(N_STATES + N_CAL) if thetas is None else thetas
        result = None
        for _ in range(self.passes):
            result = ekf(
                spec,
                np.concatenate([x_mean, cal_mean]),
                prior_cov,
                self.inputs,
                self.measurements,
                thetas,
                process_cov,
                self.measurement_std**2,
                functions=AUGMENTED,
            )
            end = np.asarray(result.means[-1])
            if not np.all(np.isfinite(end)):
                raise CommissioningError(f"{self.where}: the commissioning filter diverged")
            cal_mean = end[N_STATES:].copy()
            cal_mean[list(self.fixed)] = self.cal_prior_mean[list(self.fixed)]
        return result, end[N_STATES:]


def _calibration_errors(result, measurements):
    """Standard errors (11,) and correlation (11, 11) of the fitted calibration.

    The filter's σ inflated by the residuals' misfit per output; the correlations are the
    filter's. These are the errors given φ_A's level (the Q_m gain's alone); what the level
    adds is kept apart (:attr:`CommissioningResult.aerosol_level`).
    """
    end_cov = np.asarray(result.covariances[-1])
    inflation = residual_inflation(result, measurements)
    cal_std = (
        np.sqrt(np.maximum(np.diag(end_cov)[N_STATES:], 0.0)) * inflation[list(PARAMETER_OUTPUT)]
    )
    block = end_cov[N_STATES:, N_STATES:]
    raw_std = np.sqrt(np.maximum(np.diag(block), 1e-300))
    return cal_std, block / np.outer(raw_std, raw_std)


def unpinned_aerosol_level(settings: dict | None = None) -> dict:
    """φ_A's level of a calibration that does not say (stored before levels were kept):
    the generation model's, ± its prior (``aerosol_fraction_relative_std``)."""
    settings = settings or load_commissioning_settings()
    std = float(settings["state_prior"]["aerosol_fraction_relative_std"]["value"])
    return {
        "relative": 1.0,
        "relative_std": std,
        "pinned_by": [],
        "theta_per_s": 0.0,
        "generation_prior_std": std,
    }


#: what is said of φ_A on a machine that was never commissioned
UNCOMMISSIONED_AEROSOL_NOTE = (
    "φ_A's level takes the nominal Q_m scale as exact (the machine is not commissioned): "
    "relative to the generation model and the CNN's nominal calibration"
)


def aerosol_level_note(aerosol_level: dict | None) -> str:
    """One line on how well φ_A's level is known (for commands, pages and files).

    ``aerosol_level``: a calibration's (:attr:`CommissioningResult.aerosol_level`);
    None or {}: no commissioning (or one stored before levels were kept).
    """
    if not aerosol_level:
        return UNCOMMISSIONED_AEROSOL_NOTE
    std = aerosol_level["relative_std"]
    if not aerosol_level.get("pinned_by"):
        return (
            f"φ_A is known only relative to the generation model (±{std:.0%}): its level and "
            "the Q_m gain are confounded; pin them with --known material_flow_gain=…±… (a "
            "profilometer-calibrated CNN) or --vial-used-ml …±… (the vial weighed before and "
            "after the commissioning print)"
        )
    return (
        f"φ_A pinned by {' and '.join(aerosol_level['pinned_by'])}: the atomizer delivers "
        f"{aerosol_level['relative']:.2f} ± {std:.2f} × the generation model"
    )


def _confounding_notes(priors: dict, known: dict, aerosol_level: dict) -> list[str]:
    """What the print could not separate, and which prior decided it instead."""
    notes = []
    if "droplet_diameter_um" not in known:
        mean, std = priors["droplet_diameter_um"]
        notes.append(
            f"linewidth_offset_um rests on the droplet-size prior ({mean}±{std} µm): "
            "d_a and the line offsets are confounded (docs/reference/model.md §11)"
        )
    notes.append(aerosol_level_note(aerosol_level) + " (docs/reference/model.md §11)")
    return notes
