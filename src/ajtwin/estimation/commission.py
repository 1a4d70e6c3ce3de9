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

Examples
--------
>>> from ajtwin.simulation import simulate
>>> rec = simulate("commissioning", seed=1, machine_seed=3)        # doctest: +SKIP
>>> result = commission(rec, known={"droplet_diameter_um": (3.4, 0.2)})  # doctest: +SKIP
>>> result.calibration.linewidth_offset_um                           # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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
)
from ajtwin.model.names import N_STATES, STATE_NAMES
from ajtwin.model.system import check_input, euler_step, output_function, steady_aerosol_fraction

N_CAL = len(CALIBRATION_NAMES)


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


def parse_known(items) -> dict:
    """``["droplet_diameter_um=3.5±0.2", ...]`` → {name: (mean, std)} (``+-`` works too)."""
    known = {}
    for item in items or ():
        if "=" not in item:
            raise ValueError(
                f"--known {item!r}: write NAME=VALUE±STD, e.g. droplet_diameter_um=3.5±0.2"
            )
        name, value = item.split("=", 1)
        name = name.strip()
        if name not in STATE_NAMES:
            raise ValueError(
                f"--known {item!r}: unknown state {name!r} (known: {', '.join(STATE_NAMES)})"
            )
        text = value.replace("+-", "±").replace("+/-", "±")
        mean_text, _, std_text = text.partition("±")
        try:
            mean = float(mean_text)
            std = float(std_text) if std_text else None
        except ValueError:
            raise ValueError(f"--known {item!r}: VALUE and STD must be numbers") from None
        if std is None or not std > 0:
            raise ValueError(
                f"--known {item!r}: give a positive uncertainty, e.g. {name}={mean}±0.1"
            )
        known[name] = (mean, std)
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
        State name → (mean, std) known at the start, e.g. ``{"droplet_diameter_um":
        (3.5, 0.2)}`` from a droplet sizer; overrides the priors.
    vial_fill_ml : float
        The weighed fill [mL].
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
        The print is too short, has no input steps, or lacks camera/pressure data.
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
    unknown = sorted(set(known) - set(STATE_NAMES))
    if unknown:
        raise ValueError(f"known: unknown state(s) {unknown} (use {', '.join(STATE_NAMES)})")
    priors = state_priors(settings, inputs[0], vial_fill_ml, model, known)
    cal_prior_std = np.array(
        [float(settings["calibration_prior_std"][n]) for n in CALIBRATION_NAMES]
    )
    result, cal_mean = _augmented_filter(
        model, priors, cal_prior_std, inputs, measurements, process_std, measurement_std,
        int(checks["passes"]), where,
    )  # fmt: skip
    end = np.asarray(result.means[-1])
    end_cov = np.asarray(result.covariances[-1])
    aerosol_std = None if "aerosol_fraction" in known else (
        settings["state_prior"]["aerosol_fraction_relative_std"]["value"]
    )  # fmt: skip
    cal_std, calibration_cov = _calibration_errors(result, measurements, cal_mean, aerosol_std)
    ratio = float(checks["determined_ratio"])
    nis = np.asarray(result.nis)
    n_meas = np.maximum(np.asarray(result.n_measured), 1)
    return CommissioningResult(
        calibration=Calibration(*(float(v) for v in cal_mean)),
        std=dict(zip(CALIBRATION_NAMES, cal_std.tolist(), strict=True)),
        prior_std=dict(zip(CALIBRATION_NAMES, cal_prior_std.tolist(), strict=True)),
        determined={
            n: bool(cal_std[i] < ratio * cal_prior_std[i]) for i, n in enumerate(CALIBRATION_NAMES)
        },
        priors={k: list(v) for k, v in priors.items()},
        n_samples=len(inputs),
        mean_nis=float(np.mean(nis / n_meas)),
        end_state=end[:N_STATES],
        end_state_std=np.sqrt(np.maximum(np.diag(end_cov)[:N_STATES], 0.0)),
        end_state_cov=end_cov[:N_STATES, :N_STATES],
        calibration_cov=calibration_cov,
        noise_factors=noise_factors(result, measurements),
        notes=_confounding_notes(priors, known, aerosol_std),
    )


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
    relative = prior["aerosol_fraction_relative_std"]["value"]
    priors["aerosol_fraction"] = (aerosol, relative * aerosol)
    priors.update({k: (float(m), float(s)) for k, (m, s) in known.items()})
    return {name: priors[name] for name in STATE_NAMES}


def _augmented_filter(
    model, priors, cal_prior_std, inputs, measurements, process_std, measurement_std, passes, where
):
    """The EKF over [x, c] (the calibration c as constant states), ``passes`` times, each
    pass starting c where the last ended. Returns (the last filter result, c at its end)."""
    x_mean = np.array([priors[n][0] for n in STATE_NAMES])
    x_std = np.array([priors[n][1] for n in STATE_NAMES])
    cal_mean = np.array(IDENTITY, dtype=float)
    scaling = Scaling(
        jnp.concatenate([DEFAULT_SCALING.state, jnp.asarray(cal_prior_std)]),
        DEFAULT_SCALING.output,
    )
    spec = ModelSpec(model.params, jnp.asarray(model.coefficient_matrix), scaling)
    process_cov = np.zeros((N_STATES + N_CAL, N_STATES + N_CAL))
    process_cov[:N_STATES, :N_STATES] = np.diag(process_std**2)
    prior_cov = np.diag(np.concatenate([x_std, cal_prior_std]) ** 2)
    thetas = np.zeros(N_STATES + N_CAL)
    result = None
    for _ in range(passes):
        result = ekf(
            spec,
            np.concatenate([x_mean, cal_mean]),
            prior_cov,
            inputs,
            measurements,
            thetas,
            process_cov,
            measurement_std**2,
            functions=AUGMENTED,
        )
        end = np.asarray(result.means[-1])
        if not np.all(np.isfinite(end)):
            raise CommissioningError(f"{where}: the commissioning filter diverged")
        cal_mean = end[N_STATES:]
    return result, cal_mean


def _calibration_errors(result, measurements, cal_mean, aerosol_relative_std):
    """Standard errors (11,) and covariance Σ_c (11, 11) of the fitted calibration.

    The filter's σ inflated by the residuals' misfit per output; the Q_m gain's σ also
    carries the generation model's uncertainty (``aerosol_relative_std``, None when φ_A
    was known): φ_A is held near H/Q_c by the model, so the filter's σ of the gain ignores
    it. Σ_c keeps the filter's correlations with these standard errors.
    """
    end_cov = np.asarray(result.covariances[-1])
    inflation = residual_inflation(result, measurements)
    cal_std = (
        np.sqrt(np.maximum(np.diag(end_cov)[N_STATES:], 0.0)) * inflation[list(PARAMETER_OUTPUT)]
    )
    if aerosol_relative_std is not None:
        gain_index = CALIBRATION_NAMES.index("material_flow_gain")
        cal_std[gain_index] = np.hypot(
            cal_std[gain_index], aerosol_relative_std * cal_mean[gain_index]
        )
    block = end_cov[N_STATES:, N_STATES:]
    raw_std = np.sqrt(np.maximum(np.diag(block), 1e-300))
    correlation = block / np.outer(raw_std, raw_std)
    return cal_std, correlation * np.outer(cal_std, cal_std)


def _confounding_notes(priors: dict, known: dict, aerosol_relative_std) -> list[str]:
    """What the print could not separate, and which prior decided it instead."""
    notes = []
    if "droplet_diameter_um" not in known:
        mean, std = priors["droplet_diameter_um"]
        notes.append(
            f"linewidth_offset_um rests on the droplet-size prior ({mean}±{std} µm): "
            "d_a and the line offsets are confounded (model reference §11)"
        )
    if aerosol_relative_std is not None:
        notes.append(
            "material_flow_gain rests on the aerosol-fraction prior (the generation model, "
            f"±{aerosol_relative_std:.0%}): φ_A and the Q_m gain are confounded "
            "(model reference §11)"
        )
    return notes
