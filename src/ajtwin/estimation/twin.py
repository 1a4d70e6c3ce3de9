"""The twin: model + estimators + state, run over a print (a thin shell).

:class:`Twin` ties the pure functions together the way the paper runs them:
initial-state fit (or the previous print's end state), the EKF over the print,
EM over a moving window (default T = 600 s every 300 s) that updates θ while
printing, and optionally an RTS pass over the whole print. On a job print (a format-2
record with the job columns) the camera's measurements are first filed at their print
times (:mod:`ajtwin.estimation.print_time`) and the line is read at the speed it was
printed; :meth:`TwinRun.line_at` gives the line at any print time and speed.

Examples
--------
>>> from ajtwin.simulation import simulate
>>> from ajtwin.estimation import Twin
>>> run = Twin.default().run(simulate("exp1", seed=1, duration_min=2))
>>> run.to_frame()[["time_s", "droplet_diameter_um"]].tail(1).round(1)
     time_s  droplet_diameter_um
119   119.0                  3.4
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from ajtwin._jax import jnp
from ajtwin.estimation.calibration_uncertainty import (
    aerosol_level_covariance,
    calibration_state_covariance,
)
from ajtwin.estimation.em_calibration import output_m_step
from ajtwin.estimation.filters import (
    DEFAULT_SCALING,
    FilterResult,
    ModelFunctions,
    ModelSpec,
    SmootherResult,
    ekf,
    model_functions,
    rts_smoother,
)
from ajtwin.estimation.initial import InitialFit, StartPriors, fit_initial_state
from ajtwin.estimation.line_speed_fit import SpeedExponents, prior_exponents
from ajtwin.estimation.online import (  # noqa: F401 — the schedule and predict, re-exported
    OnlineTwin,
    StepBlock,
    em_due,
    em_early_steps,
    first_em_update_time,
    next_em_boundary,
    predict,
)
from ajtwin.estimation.part_line import LineEstimate, line_at, line_model
from ajtwin.estimation.print_time import is_job_record, print_context
from ajtwin.estimation.record_checks import (
    SCALE_CHECKED_OUTPUTS,
    check_input_rows,
    check_model_inputs,
    check_output_medians,
    check_output_scales,
    check_print_length,
    finite_median,
    output_responds,
)
from ajtwin.estimation.vial import load_vial_settings, observe_vial
from ajtwin.io import spool
from ajtwin.io.schema import INPUT_COLUMNS, OUTPUT_COLUMNS
from ajtwin.model import OUTPUT_NAMES, STATE_NAMES, DigitalModel, load_noise
from ajtwin.model.calibration import CalibratedCoefficients, Calibration
from ajtwin.model.droplet_dynamics import (
    DropletStep,
    augment_inputs,
    default_transition,
    load_droplet_dynamics,
    next_response,
)
from ajtwin.model.limits import StateLimits
from ajtwin.model.line_speed import load_line_speed_law
from ajtwin.model.system import check_input, settled_outputs


@dataclass(frozen=True)
class TwinConfig:
    """Tuning of the estimators (display units, per 1 s step)."""

    process_std: tuple  # σ of ξ per step (5,)
    measurement_std: tuple  # σ of w (5,)
    em: bool = True
    window_s: int = 600
    every_s: int = 300
    # extra EM updates before the first full window, each over the print so far (steps
    # after the start; those >= window_s are dropped): θ_φA holds the print's atomizer
    # level from the first of them instead of from window_s on. Why 120 s: on held-out alt
    # machines the twin's φ_A level before the first EM left L_o and Q_m ±0.4…0.6σ off
    # for 10 min, the most common false alarm (9 of ~40 events; docs/explanation/detectors.md)
    early_em_s: tuple = (120,)
    em_max_iterations: int = 10
    em_tolerance: float = 1e-3  # nats per step
    # MAP prior σ on θ [1/s]; inf = flat. Keeps θ of states the data cannot see at 0.
    theta_prior_std: tuple = (1e-4, 1e-5, 1e-3, 1e-3, 0.1)  # θ_φA must absorb H offsets
    gate_sigma: float = np.inf
    initial_samples: int = 10
    vial_fill_ml: float = 1.0
    vial_fill_std_ml: float = 3e-3
    nozzle_prior_std_um: float = 0.05
    tube_prior_std_um: float = 1e-3
    # priors of d_a and φ_A for a print without line outputs (no camera); None = refuse it
    droplet_prior_um: float | None = None
    droplet_prior_std_um: float | None = None
    aerosol_prior_relative_std: float | None = None
    method: str = "euler"
    # V_l as a consider state (data/vial.toml [twin]): not updated from the confounded
    # generation signature; the vial observer (ajtwin.estimation.vial) estimates it from data
    vial_consider: bool = True
    # droplet-size dynamics: a variant of data/transition.toml ("paper" = model reference §4
    # unchanged); default: that file's ``default``
    transition: str = field(default_factory=default_transition)

    noise_tuning: str = "calibrated"
    # relative σ of φ_A's level that no output sees (commissioning's aerosol_level: the
    # generation model's error unless pinned); added to the reported covariance. 0: none
    # (an uncommissioned twin takes the nominal Q_m scale as exact)
    aerosol_level_std: float = 0.0
    # online EM of the output side (ajtwin.estimation.em_calibration; never the pressures)
    learn_line_offsets: bool = False
    learn_output_noise: bool = False
    # job prints: the horizon [s] after which a step is final and later camera measurements
    # of it are dropped (ajtwin.estimation.print_time); None: from the camera (data/print_time.toml)
    camera_horizon_s: float | None = None

    def start_priors(self) -> StartPriors:
        """What the initial fit assumes beyond the data (:class:`~ajtwin.estimation.initial.
        StartPriors`)."""
        return StartPriors(
            n_samples=self.initial_samples,
            vial_fill_ml=self.vial_fill_ml,
            vial_fill_std_ml=self.vial_fill_std_ml,
            tube_prior_std_um=self.tube_prior_std_um,
            nozzle_prior_std_um=self.nozzle_prior_std_um,
            droplet_prior_um=self.droplet_prior_um,
            droplet_prior_std_um=self.droplet_prior_std_um,
            aerosol_prior_relative_std=self.aerosol_prior_relative_std,
        )

    @classmethod
    def default(
        cls, model: DigitalModel | None = None, noise_tuning: str = "calibrated", **overrides
    ) -> TwinConfig:
        """Filter tuning from ``noise.toml``.

        ``noise_tuning="calibrated"`` (default) or ``"paper"`` (model reference §6 values,
        σ_Qm = 20 % of the nominal Q_m).
        """
        model = model or DigitalModel.default()
        noise = load_noise(tuning=noise_tuning)
        proc = noise["process"]
        meas = noise["measurement"]
        # nominal Q_m at the Exp 1 operating point (model reference §6: the paper's value is
        # unusable)
        u = np.array([375.0, 23.0, 50.0])
        q_m = float(
            np.asarray(settled_outputs(u, 1.0, model.params, model.coefficient_matrix)[1])[4]
        )
        process = tuple(proc[name] for name in STATE_NAMES)
        measurement = (
            meas["linewidth_um"],
            meas["overspray_um"],
            meas["carrier_pressure_Pa"],
            meas["sheath_pressure_Pa"],
            meas["material_flow_relative"] * q_m,
        )
        initial = {}
        if "vial_fill_std_mL" in noise["initial"]:
            initial["vial_fill_std_ml"] = noise["initial"]["vial_fill_std_mL"]
        if noise["theta_prior"]:
            initial["theta_prior_std"] = tuple(noise["theta_prior"][n] for n in STATE_NAMES)
        prior = noise["prior_initial"]
        if "tube_deposition_um" in prior:
            initial["tube_prior_std_um"] = prior["tube_deposition_um"]
        if "nozzle_deposition_um" in prior:
            initial["nozzle_prior_std_um"] = prior["nozzle_deposition_um"]
        if "droplet_diameter_mean_um" in prior:
            initial["droplet_prior_um"] = prior["droplet_diameter_mean_um"]
            initial["droplet_prior_std_um"] = prior["droplet_diameter_um"]
            initial["aerosol_prior_relative_std"] = prior["aerosol_fraction_relative"]

        initial["vial_consider"] = bool(load_vial_settings()["twin"]["vial_consider"])
        base = replace(cls(process, measurement, noise_tuning=noise_tuning, **initial), **overrides)
        if base.transition != "paper":
            dynamics = load_droplet_dynamics(base.transition)
            # the variant's bound on θ_da (its MAP prior), unless the caller set one
            if dynamics.theta_prior_std > 0 and "theta_prior_std" not in overrides:
                prior = list(base.theta_prior_std)
                prior[0] = dynamics.theta_prior_std
                base = replace(base, theta_prior_std=tuple(prior))
        return base


@dataclass
class TwinRun:
    """Everything a run of the twin over one print produced.

    Per second t_k (``time_s``): the filtered states and covariances (``filtered.means``,
    ``filtered.covariances``; ``stds`` adds the calibration's share), the smoothed ones
    (``smoothed``, with ``Twin.run(..., smooth=True)``), θ in force (``theta_per_step``),
    the inputs and the measurements the filter used. On a job print the measurements are
    the camera's filed at their print times (``n_camera`` frames per second,
    ``line_factors`` the speed law's factors, ``camera_counts`` what was filed and dropped)
    and :meth:`line_at` evaluates the printed line at any print time and speed — what a part
    map needs for every stroke portion::

        run = Twin.default().run(record, job=program_for_record(record, "part.prg"), smooth=True)
        line = run.line_at(t_mid, job.state_at(t_mid).speed_mm_s)   # mean, σ of L_w, L_o
    """

    time_s: np.ndarray
    filtered: FilterResult
    smoothed: SmootherResult | None
    theta_per_step: np.ndarray  # (T, 5) θ in force at each step (None: a run taken in chunks)
    theta_history: pd.DataFrame  # one row per EM update
    initial: InitialFit | None
    start_mean: np.ndarray
    start_cov: np.ndarray
    end_mean: np.ndarray = field(default=None)
    end_cov: np.ndarray = field(default=None)
    # (T, 5, 5): what the calibration's own uncertainty adds (None: exact / uncalibrated)
    calibration_covariances: np.ndarray = field(default=None)
    #: (T, 5) bool: some output measured at that second responds to the state
    #: (record_checks.observed_states); False rows run on the model and priors alone.
    seen: np.ndarray | None = None
    #: (T, 5) variance floor of states no data has constrained yet
    #: (:func:`never_seen_variance_floor`); None: every state fitted from data
    prior_floor: np.ndarray | None = None
    #: the vial observer over the print (ajtwin.estimation.vial; None: no Q_m measured):
    #: V_l from the data, apart from the atomizer's efficiency, and the 'running low' flag
    vial: object | None = None
    #: (T, 5) the measurements the filter used: the record's outputs, or on a job print the
    #: camera's filed at their print times (what the detectors compare with the predictions)
    measurements: np.ndarray | None = None
    #: (T, 3) the inputs u_k [mA, sccm, sccm]
    inputs: np.ndarray | None = None
    #: (T, 4) a job print's (F_w, F_o, v_w, v_o) per step (None: no job)
    line_factors: np.ndarray | None = None
    #: (T, 2) camera frames filed per step for L_w, L_o (None: no job)
    n_camera: np.ndarray | None = None
    #: a job print's filing: frames filed, dropped by reason, the horizon [s] ({} without)
    camera_counts: dict = field(default_factory=dict)
    #: the twin's output model and speed law (for :meth:`line_at`)
    line_model: object | None = None
    #: a run over a record held on disk (:meth:`Twin.run_streamed`), which keeps no (T, …)
    #: array: its steps, and per state the seconds no measured output saw it
    n_steps: int | None = None
    unseen_counts: np.ndarray | None = None

    def visibility_notes(self) -> list[str]:
        """Plain-language lines on what the data could not see (for the CLIs); [] if all seen."""
        notes = []
        if self.initial is not None and self.initial.states_from_prior:
            notes.append(f"warning: {self.initial.message}")
        n = len(self.time_s) if self.time_s is not None else int(self.n_steps)
        unseen = self.unseen_summary()
        never = [name for name, count in unseen.items() if count == n]
        sometimes = {name: count for name, count in unseen.items() if count < n}
        if never:
            notes.append(
                f"warning: no output in this record measures {', '.join(never)} (no linewidth, "
                "overspray or material flow): the twin cannot see them; their estimates follow "
                "the model from the priors and their bands stay wide (columns seen_* = 0)"
            )
        if sometimes:
            parts = ", ".join(f"{name} in {count} of {n} s" for name, count in sometimes.items())
            why = (
                "no camera frame of a trace printed then: shutter closed, no trace in view or "
                "a frame dropped"
                if self.line_factors is not None
                else "e.g. camera dropout"
            )
            notes.append(
                f"note: unmeasured ({why}) — {parts}: those seconds run on the "
                "model alone and the bands widen (columns seen_* = 0)"
            )
        return notes

    def unseen_summary(self) -> dict[str, int]:
        """State → seconds in which no measured output saw it (V_l, never measured, left out)."""
        if self.seen is not None:
            counts = (~np.asarray(self.seen)).sum(axis=0)
        elif self.unseen_counts is not None:
            counts = np.asarray(self.unseen_counts)
        else:
            return {}
        return {
            name: int(counts[i])
            for i, name in enumerate(STATE_NAMES)
            if counts[i] and name != "vial_volume_mL"
        }

    @property
    def means(self) -> np.ndarray:
        """Filtered state means (T, 5), display units."""
        return np.asarray(self.filtered.means)

    def _total_cov(self, covariances) -> np.ndarray:
        covariances = np.asarray(covariances)
        if self.calibration_covariances is not None:
            covariances = covariances + self.calibration_covariances
        if self.prior_floor is not None and self.prior_floor.any():
            # raising a diagonal entry keeps the matrix positive semi-definite
            covariances = covariances.copy()
            diagonal = np.einsum("tii->ti", covariances)
            np.maximum(diagonal, self.prior_floor, out=diagonal)
        return covariances

    def total_covariances(self, smoothed: bool = False) -> np.ndarray:
        """The state covariances (T, 5, 5) as the twin reports them: the filter's (or the
        smoother's) plus the calibration's share, the never-seen states' floor on the
        diagonal (what :attr:`stds` and :meth:`line_at` use)."""
        if smoothed and self.smoothed is None:
            raise ValueError("this run has no smoothed estimates (run with smooth=True)")
        src = self.smoothed if smoothed else self.filtered
        return self._total_cov(src.covariances)

    def line_at(self, times, speeds, smoothed: bool | None = None, progress=None) -> LineEstimate:
        """The line printed at print times ``times`` [s] at platen speeds ``speeds`` [mm/s].

        What a part map calls for every stroke portion: mean and σ of L_w and L_o from the
        states interpolated to τ (smoothed when this run has them, unless ``smoothed`` says
        otherwise) with their total covariance (the calibration's share and the prior floor
        included), through the output model and the twin's speed law with its uncertainty
        (:func:`ajtwin.estimation.part_line.line_at`).

        Parameters
        ----------
        times : array_like (n,)
            Print times τ [s] on the record's clock (clipped to the print).
        speeds : array_like (n,) or float
            Platen speed ν at τ [mm/s] (the program's, e.g. ``Job.state_at(τ).speed_mm_s``).
        smoothed : bool, optional
        progress : callable(int), optional
            Called with the number of print times done (they are evaluated in blocks).

        Returns
        -------
        LineEstimate
            ``linewidth_um``, ``overspray_um``, ``linewidth_std_um``, ``overspray_std_um`` (n,).

        Examples
        --------
        >>> run.line_at([120.4, 121.9], 2.0).linewidth_um          # doctest: +SKIP
        """
        if self.line_model is None or self.inputs is None:
            raise ValueError("this run has no output model attached (made by Twin.run)")
        use_smoothed = self.smoothed is not None if smoothed is None else smoothed
        covariances = self.total_covariances(use_smoothed)
        src = self.smoothed if use_smoothed else self.filtered
        return line_at(
            self.line_model,
            self.time_s,
            np.asarray(src.means),
            covariances,
            self.inputs,
            times,
            speeds,
            progress,
        )

    @property
    def stds(self) -> np.ndarray:
        """State σ (T, 5): the filter's, plus the calibration's share when known."""
        covariances = self._total_cov(self.filtered.covariances)
        return np.sqrt(np.maximum(np.diagonal(covariances, 0, 1, 2), 0))

    def to_frame(self, smoothed: bool | None = None) -> pd.DataFrame:
        """States with σ, one-step predicted outputs, NIS: the ``estimate`` CSV."""
        use_smoothed = self.smoothed is not None if smoothed is None else smoothed
        if use_smoothed and self.smoothed is None:
            raise ValueError("this run has no smoothed estimates (run with smooth=True)")
        src = self.smoothed if use_smoothed else self.filtered
        means = np.asarray(src.means)
        stds = np.sqrt(np.maximum(np.diagonal(self._total_cov(src.covariances), 0, 1, 2), 0))
        # columns gathered first: one DataFrame, not ~40 insertions (each copies the block)
        frame = {"time_s": self.time_s}
        for i, name in enumerate(STATE_NAMES):
            frame[name] = means[:, i]
            frame[name + "_std"] = stds[:, i]
        pred = np.asarray(self.filtered.predicted_outputs)
        for i, name in enumerate(OUTPUT_NAMES):
            frame["pred_" + name] = pred[:, i]
        frame["nis"] = np.asarray(self.filtered.nis)
        frame["n_measured"] = np.asarray(self.filtered.n_measured)
        frame["log_likelihood"] = np.asarray(self.filtered.log_likelihood)
        frame["reinitialised"] = np.asarray(self.filtered.reinitialised)
        if self.line_factors is not None:
            # a job print: each second's camera measurements filed at their print time, the
            # frames behind them and the speed law's factor of the line printed then
            for i, name in enumerate(("linewidth", "overspray")):
                frame[f"filed_{name}_um"] = np.asarray(self.measurements)[:, i]
                frame[f"camera_frames_{name}"] = np.asarray(self.n_camera)[:, i]
                frame[f"line_factor_{name}"] = self.line_factors[:, i]
        if self.seen is not None:
            for i, name in enumerate(STATE_NAMES):
                frame["seen_" + name] = np.asarray(self.seen)[:, i]
        if self.vial is not None:
            # V_l above is the twin's consider state (fill − modelled draw); these read it
            # from the measured Q_m with the atomizer's efficiency apart
            # (docs/explanation/vial-consider-state.md)
            frame["vial_observed_mL"] = self.vial.vial_ml
            frame["vial_observed_mL_std"] = self.vial.vial_std_ml
            frame["vial_loss_rate_mL_per_h"] = self.vial.loss_rate_ml_per_h
            frame["atomizer_efficiency"] = self.vial.efficiency
            frame["vial_running_low"] = self.vial.running_low
        return pd.DataFrame(frame)


def twin_functions(method: str = "euler", transition: str = "paper") -> ModelFunctions:
    """The model the estimators run: discretisation ``method`` and a ``transition`` variant.

    ``transition`` names a variant of ``data/transition.toml``
    (:mod:`ajtwin.model.droplet_dynamics`); ``"paper"`` is the paper's model itself.
    """
    functions = model_functions(method)
    if transition == "paper":
        return functions

    dynamics = load_droplet_dynamics(transition)
    if dynamics.is_paper:
        return functions
    return ModelFunctions(DropletStep(dynamics, method), functions.output)


#: rows a run over a record held on disk reads at a time (:meth:`Twin.run_streamed`), and a
#: run over a record in memory feeds the core at a time (its progress steps)
STREAM_READ_ROWS = 4096


class Twin:
    """A digital twin of one machine: model, tuning, θ and the current state.

    Parameters
    ----------
    model : DigitalModel
    config : TwinConfig
    theta : array (5,), optional
        Starting drift parameters (the machine's learned θ; default zeros).
    calibration : Calibration, optional
        The machine's calibration of the output model (model reference §11); None = the nominal
        machine (the packaged model exactly).
    calibration_cov : array (11, 11), optional
        Its covariance from commissioning: the reported state σ then include what the
        calibration's error adds (:mod:`ajtwin.estimation.calibration_uncertainty`).
    noise_factors : array (5,), optional
        This machine's output noise relative to the tuned σ_w (fitted at commissioning).
    """

    def __init__(
        self,
        model: DigitalModel,
        config: TwinConfig,
        theta=None,
        calibration=None,
        calibration_cov=None,
        noise_factors=None,
    ):
        self.model = model
        self.noise_factors = None if noise_factors is None else np.asarray(noise_factors, float)
        self.calibration_cov = None if calibration_cov is None else np.asarray(calibration_cov)
        self.config = config
        self.theta = np.zeros(5) if theta is None else np.asarray(theta, dtype=float)
        self.calibration = calibration
        self.commissioned_calibration = calibration
        self._learned_var = None
        coefficients = np.asarray(model.coefficient_matrix, dtype=float)
        if calibration is not None:
            coefficients = CalibratedCoefficients(coefficients, calibration)
        update_mask = None
        if config.vial_consider:
            update_mask = np.array([1.0, 0.0, 1.0, 1.0, 1.0])
        self.spec = ModelSpec(model.params, coefficients, DEFAULT_SCALING, 1.0, update_mask)
        self.functions = twin_functions(config.method, config.transition)
        self.limits = StateLimits.load(model.params)
        self.speed_law = load_line_speed_law()
        self.speed_exponents = prior_exponents()

    @classmethod
    def default(
        cls, calibration=None, calibration_cov=None, noise_factors=None, **config_overrides
    ) -> Twin:
        """The twin on the packaged model, optionally calibrated to a machine.

        Parameters
        ----------
        calibration : Calibration, optional
        calibration_cov : array (11, 11), optional
            Its covariance.
        noise_factors : array (5,), optional
            The machine's output noise over the tuned σ.
        **config_overrides
            :class:`TwinConfig` fields.
        """
        model = DigitalModel.default()
        return cls(
            model,
            TwinConfig.default(model, **config_overrides),
            calibration=calibration,
            calibration_cov=calibration_cov,
            noise_factors=noise_factors,
        )

    # ------------------------------------------------------------------ #
    @property
    def droplet_dynamics(self):
        """The transition variant (:mod:`ajtwin.model.droplet_dynamics`) the twin runs."""

        return load_droplet_dynamics(self.config.transition)

    def model_inputs(self, inputs, response0: float | None = None) -> np.ndarray:
        """Inputs (T, 3) as the transition reads them: with the input-response column
        (T, 4) for an ``input_following`` variant, unchanged otherwise."""
        return self.model_inputs_from(inputs, response0)[0]

    def model_inputs_from(self, inputs, response0: float | None = None, pad_to=None):
        """(inputs (T, 3 or 4) as the transition reads them, the input response r after the
        last row; None when the variant does not follow the inputs), from the response
        ``response0`` before the first row (default: the first row's equilibrium).

        ``pad_to``: compute over the rows padded to that length (a length already compiled;
        r is causal, so the padding changes nothing of the rows).
        """
        inputs = np.asarray(inputs, dtype=float)
        dynamics = self.droplet_dynamics if self.config.transition != "paper" else None
        if dynamics is None or not dynamics.follows_inputs:
            return inputs, None
        m = len(inputs)
        padded = inputs
        if pad_to is not None and pad_to > m:
            padded = np.concatenate([inputs, np.repeat(inputs[-1:], pad_to - m, axis=0)])
        augmented = augment_inputs(padded, dynamics, response0, self.spec.dt)[:m]
        return augmented, next_response(
            float(augmented[-1, -1]), inputs[-1], dynamics, self.spec.dt
        )

    def learn_speed_law(self, exponents: SpeedExponents) -> None:
        """Run with the speed law's exponents ``exponents`` (what the camera's readings at
        several speeds taught, :mod:`ajtwin.estimation.line_speed_fit`): the camera's frames
        are filed and the line drawn with them, its band with their σ."""
        self.speed_exponents = exponents
        self.speed_law = exponents.law(self.speed_law)

    @property
    def line_model(self):
        """The twin's line as a part map evaluates it: its output model, (calibrated)
        coefficients and speed law with the law's uncertainty
        (:func:`ajtwin.estimation.part_line.line_at`; what :meth:`TwinRun.line_at` and the
        live map use)."""
        return line_model(
            self.model.params,
            self.spec.coefficients,
            self.functions.output,
            self.speed_law,
            self.speed_exponents.std,
        )

    @property
    def process_cov(self) -> np.ndarray:
        """Σ_ξ: the process noise covariance (5, 5) per second."""
        return np.diag(np.asarray(self.config.process_std) ** 2)

    @property
    def measurement_std(self) -> np.ndarray:
        """Output noise σ (5,) [µm, µm, Pa, Pa, mL/s], calibrated to the machine."""
        std = np.asarray(self.config.measurement_std, dtype=float)
        if self.calibration is not None:
            # σ_Qm is relative to the nominal Q_m (noise.toml): it scales with the gain
            std = std.copy()
            std[4] *= abs(float(self.calibration.material_flow_gain))
        if self.noise_factors is not None:
            std = std * self.noise_factors
        return std

    @property
    def measurement_var(self) -> np.ndarray:
        """Output noise variances (5,): learned online when EM learns them, else σ²."""
        if self._learned_var is not None:
            return self._learned_var
        return self.measurement_std**2

    def learn_outputs(self, smoothed, inputs, measurements) -> dict:
        """Line offsets and output noise by EM over a window (pressures never), in force from
        now on (``config.learn_line_offsets`` / ``learn_output_noise``); what was learned."""

        c = self.config
        commissioned = self.commissioned_calibration or Calibration.identity()
        calibration, var = output_m_step(
            self.spec,
            smoothed,
            inputs,
            measurements,
            self.measurement_var,
            commissioned,
            functions=self.functions,
            learn_offsets=c.learn_line_offsets,
            learn_noise=c.learn_output_noise,
            tuned_var=self.measurement_std**2,
        )
        if c.learn_line_offsets:
            self.calibration = calibration
            line = jnp.asarray(self.model.coefficient_matrix)
            self.spec = self.spec._replace(coefficients=CalibratedCoefficients(line, calibration))
        if c.learn_output_noise:
            self._learned_var = var
        return {
            "linewidth_offset_um": float(calibration.linewidth_offset_um),
            "overspray_offset_um": float(calibration.overspray_offset_um),
            **{f"noise_std_{name}": float(np.sqrt(v)) for name, v in zip(OUTPUT_NAMES, var)},
        }

    @property
    def theta_prior_precision(self) -> np.ndarray:
        """Precision (5,) of θ's prior in EM (0: none; V_l's held at 0 as a consider state)."""
        std = np.asarray(self.config.theta_prior_std, dtype=float)
        precision = np.where(np.isfinite(std), 1.0 / std**2, 0.0)
        if self.config.vial_consider:
            # a consider state's smoothed path is its own prediction: θ_Vl has no data, so
            # it is held at 0 (a prior far stronger than any window's normal equations)
            precision[1] = 1e40
        return precision

    def initial_state(self, inputs, measurements, line_factors=None) -> InitialFit:
        """The initial-state fit over the first ``initial_samples`` samples.

        Parameters
        ----------
        inputs : array (T, 3)
            [mA, sccm, sccm].
        measurements : array (T, 5)
            Display units, NaN = not measured.
        line_factors : array (T, 4), optional
            A job print's (F_w, F_o, v_w, v_o) per step (:mod:`ajtwin.estimation.print_time`).
        """
        c = self.config
        return fit_initial_state(
            self.model.params,
            self.spec.coefficients,
            inputs,
            measurements,
            self.measurement_std,
            c.start_priors(),
            line_factors=line_factors,
        )

    def output_responds(self, mean, u) -> np.ndarray:
        """(5 outputs, 5 states) bool: which state each output responds to, at the state
        ``mean`` and inputs ``u`` (:func:`~ajtwin.estimation.record_checks.output_responds`)."""
        return output_responds(
            self.model.params,
            self.spec.coefficients,
            mean,
            self.limits.upper - self.limits.lower,
            u,
            self.config.measurement_std,
        )

    def calibration_covariances(self, filtered, model_inputs, line=None, carry=None):
        """The states' covariance from the calibration's uncertainty and φ_A's unknown level
        (None: neither given). ``line``: a job print's per-step line factors; ``carry``: a
        dict kept from block to block of a run (what the vial drained before it,
        :func:`calibration_state_covariance` and :func:`aerosol_level_covariance`)."""
        out = None
        if self.calibration is not None and self.calibration_cov is not None:
            out = calibration_state_covariance(
                self.spec,
                filtered,
                model_inputs,
                self.measurement_var,
                self.calibration_cov,
                self.functions,
                line_factors=line,
                carry=carry,
            )
        if self.config.aerosol_level_std > 0:
            level = aerosol_level_covariance(
                filtered.means,
                model_inputs,
                self.config.aerosol_level_std,
                self.spec.dt,
                carry=carry,
            )
            out = level if out is None else out + level
        return None if out is None else np.asarray(out)

    # ------------------------------------------------------------------ #
    def run(
        self,
        record=None,
        *,
        inputs=None,
        measurements=None,
        time_s=None,
        start=None,
        smooth: bool = False,
        progress=None,
        job=None,
        line_factors=None,
        sink=None,
    ) -> TwinRun:
        """Estimate the states over a print (and learn θ if ``config.em``): the print fed to
        the twin's core (:class:`~ajtwin.estimation.online.OnlineTwin`).

        Parameters
        ----------
        record : PrintRecord, optional
            The print; or give ``inputs`` (T, 3) and ``measurements`` (T, 5). A job print
            (format 2 with the job columns) has its camera measurements filed at their print
            times, with the horizon ``config.camera_horizon_s`` or the camera's rule
            (:mod:`ajtwin.estimation.print_time`).
        start : (mean (5,), cov (5, 5)), optional
            Start state (the previous print's end); default: the initial fit.
        smooth : bool
            Also run the RTS smoother over the whole print.
        progress : callable(int), optional
            Called with the number of rows fed so far (for a progress bar).
        job : ajtwin.job.Job, optional
            The program of a job record, as printed (:func:`~ajtwin.estimation.print_time.
            program_for_record`): speeds at print times come from it, not the record's rows.
        line_factors : array (T, 4), optional
            With ``inputs``/``measurements`` already filed: each step's (F_w, F_o, v_w, v_o).
        sink : callable(first_step, TwinRun), optional
            Takes the run a block at a time as the core commits it (a TwinRun of those
            steps: the filter's results, θ, the calibration's share, the prior floor, what
            was seen, the print's start prior), so that nothing keeps the whole print's
            results: the run returned then has the print's start, end, θ history, initial
            fit and ``seen``, ``filtered`` holds only the last ``window_s`` steps' blocks,
            ``theta_per_step`` is
            None and so is ``vial`` (:meth:`observe_vial` runs it when wanted). Not with
            ``smooth``.
        """
        if sink is not None and smooth:
            raise ValueError("a run taken in chunks (sink) cannot be smoothed: RTS needs it whole")
        inputs, measurements, time_s = self._checked_arrays(record, inputs, measurements, time_s)
        context = self._print_context(record, job)
        core = OnlineTwin(self, start, print_context=context)
        taker = _Blocks(sink, keep_steps=int(self.config.window_s))
        n = len(inputs)
        line = None if line_factors is None else np.asarray(line_factors, dtype=float)
        columns = None
        if context is not None:
            columns = (record.shutter_open, record.platen_speed, record.printed_at)
        for first in range(0, n, STREAM_READ_ROWS):
            stop = min(first + STREAM_READ_ROWS, n)
            taker.take(
                core,
                core.feed(
                    time_s[first:stop],
                    inputs[first:stop],
                    measurements[first:stop],
                    None if columns is None else tuple(c[first:stop] for c in columns),
                    line=None if line is None else line[first:stop],
                ),
            )
            if progress:
                progress(stop)
        taker.take(core, core.finish())
        self.theta = core.theta.copy()
        if sink is not None:
            light = taker.light()  # what a run in memory gives besides the sink's blocks
            return self._ended(core, taker.recent(), camera_counts=core.camera_counts, **light)
        whole = taker.whole()
        smoothed = None
        if smooth:
            consistent = ekf(
                self.spec, core.start_mean, core.start_cov, whole.model_inputs,
                whole.measurements, whole.theta_per_step, self.process_cov,
                self.measurement_var, self.config.gate_sigma, functions=self.functions,
                line_factors=whole.line,
            )  # fmt: skip
            smoothed = rts_smoother(self.spec, consistent)
        return self._ended(
            core,
            whole.filtered,
            time_s=whole.time_s,
            smoothed=smoothed,
            theta_per_step=whole.theta_per_step,
            calibration_covariances=whole.calibration_covariances,
            seen=whole.seen,
            prior_floor=whole.prior_floor if whole.prior_floor.any() else None,
            vial=self._observe_vial(
                whole.inputs, whole.measurements, core.start_mean, core.start_cov
            ),
            measurements=whole.measurements,
            inputs=whole.inputs,
            line_factors=whole.line,
            n_camera=whole.n_camera,
            camera_counts=core.camera_counts,
        )

    def _print_context(self, record, job):
        """A job record's print context (None: not a job print); a program given for a
        record without job columns is refused."""
        if record is None or not is_job_record(record):
            if job is not None:
                raise ValueError(
                    "a program was given but the record has no job columns (shutter_open, "
                    "platen_speed_mm_s, printed_at_s): it is not a job print"
                )
            return None
        return print_context(record, job, self.config.camera_horizon_s)

    def _checked_arrays(self, record, inputs, measurements, time_s):
        """Inputs (T, 3), measurements (T, 5) and times (T,) of a print, checked against the
        model (a record's inputs and output scales; shapes; at least 2 samples)."""
        if record is not None:
            inputs, measurements, time_s = record.inputs, record.outputs, record.time_s
            where = str(record.meta.get("source_file", "<record>"))
            check_model_inputs(inputs, where, time_s)
            check_output_scales(
                self.model.params,
                self.spec.coefficients,
                inputs,
                measurements,
                self.config.vial_fill_ml,
                where,
            )
        inputs = check_input(np.asarray(inputs, dtype=float))
        measurements = np.asarray(measurements, dtype=float)
        n = len(inputs)
        if measurements.shape != (n, 5):
            raise ValueError(f"measurements must be ({n}, 5); got {measurements.shape}")
        if n < 2:
            raise ValueError("a print needs at least 2 samples")
        time_s = np.arange(n, dtype=float) if time_s is None else np.asarray(time_s, dtype=float)
        return inputs, measurements, time_s

    def run_streamed(self, source, *, start=None, progress=None, sink, job=None) -> TwinRun:
        """:meth:`run` with ``sink`` over a record held on disk, read a piece at a time.

        ``source``: a :class:`~ajtwin.io.records.SpooledRecord`; ``job``: as for :meth:`run`.
        The same checks as :meth:`run` on a record (the medians a column at a time), the
        same core fed the pieces as they are read: memory does not grow with the print. The
        run returned has no per-step arrays: its start, end, θ history, initial fit, a job
        print's camera counts, ``n_steps`` and ``unseen_counts``.
        """
        where, n = source.where, len(source)
        check_print_length(n, where)
        block = spool.SPOOL_BLOCK_ROWS
        for first in range(0, n, block):  # every input checked before any work, as run's
            piece = source.piece(first, first + block)
            check_input_rows(piece.inputs, where, piece.time_s, first)
        u_med = np.array([np.median(source.column(c)) for c in INPUT_COLUMNS])
        # one column at a time: a week's column is 4.8 MB
        medians = {
            j: finite_median(source.column(OUTPUT_COLUMNS[j])) for j in SCALE_CHECKED_OUTPUTS
        }
        c = self.config
        check_output_medians(
            self.model.params, self.spec.coefficients, u_med, medians, c.vial_fill_ml, where
        )
        context = self._print_context(source, job) if is_job_record(source) else None
        if context is None and job is not None:
            self._print_context(None, job)  # refused as run refuses it
        core = OnlineTwin(self, start, print_context=context)
        taker = _Blocks(sink, keep_light=False, keep_steps=int(c.window_s))
        for first in range(0, n, STREAM_READ_ROWS):
            piece = source.piece(first, min(first + STREAM_READ_ROWS, n))
            columns = None
            if context is not None:
                columns = (piece.shutter_open, piece.platen_speed, piece.printed_at)
            inputs = check_input(piece.inputs)
            taker.take(core, core.feed(piece.time_s, inputs, piece.outputs, columns))
            if progress:
                progress(min(first + STREAM_READ_ROWS, n))
        taker.take(core, core.finish())
        self.theta = core.theta.copy()
        return self._ended(
            core,
            taker.recent(),
            n_steps=n,
            unseen_counts=core.unseen_counts.copy(),
            camera_counts=core.camera_counts,
        )

    def _ended(self, core, filtered, **fields) -> TwinRun:
        """The TwinRun of a finished core: its start, end, θ history and initial fit, with
        the run's own ``fields``."""
        fields.setdefault("time_s", None)
        fields.setdefault("smoothed", None)
        fields.setdefault("theta_per_step", None)
        fields.setdefault("line_model", self.line_model)
        if core.carry is None:
            raise ValueError("a print needs at least 2 samples")
        return TwinRun(
            filtered=filtered,
            theta_history=_theta_history_frame(core.theta_history),
            initial=core.initial,
            start_mean=core.start_mean,
            start_cov=core.start_cov,
            end_mean=np.asarray(filtered.means[-1]),
            end_cov=np.asarray(filtered.covariances[-1]),
            **fields,
        )

    def response_after(self, inputs) -> float | None:
        """The droplet size's input response r after a print of inputs (T, 3) (what the
        next print starts from); None when the variant does not follow the inputs."""
        return self.model_inputs_from(inputs)[1]

    def observe_vial(self, run):
        """The vial observer over a run's print (:class:`~ajtwin.estimation.vial.
        VialEstimate`; None when Q_m was never measured): what :meth:`run` gives as ``vial``,
        for a run taken in chunks (which leaves it out)."""
        return self._observe_vial(run.inputs, run.measurements, run.start_mean, run.start_cov)

    def _observe_vial(self, inputs, measurements, start_mean, start_cov):
        """The vial observer over the print's Q_m (None when Q_m was never measured)."""
        if not np.isfinite(measurements[:, 4]).any():
            return None
        gain = 1.0 if self.calibration is None else float(self.calibration.material_flow_gain)
        return observe_vial(
            inputs,
            measurements[:, 4],
            fill_ml=float(start_mean[1]),
            fill_std_ml=float(np.sqrt(max(start_cov[1, 1], 1e-12))),
            material_flow_gain=abs(gain),
            params=self.model.params,
        )


class _Blocks:
    """The committed blocks of a run: handed to a ``sink`` as TwinRun chunks, or kept and
    joined into the whole print."""

    #: the per-step arrays a run in memory keeps besides its sink (a few numbers a step)
    LIGHT = ("time_s", "inputs", "measurements", "seen", "line", "n_camera")

    def __init__(self, sink=None, keep_light: bool = True, keep_steps: int = 0):
        self.sink = sink
        self.blocks: list[StepBlock] = []
        self._light: list[tuple] | None = [] if keep_light else None
        self._keep_steps = int(keep_steps)  # with a sink: the last steps' blocks are kept

    def take(self, core, items) -> None:
        for block in items:
            if not isinstance(block, StepBlock):
                continue  # a provisional step: a run wants its final ones
            self.blocks.append(block)
            if self.sink is None:
                continue
            self.sink(block.first, _chunk_run(block, core))
            if self._light is not None:
                self._light.append(tuple(getattr(block, name) for name in self.LIGHT))
            while len(self.blocks) > 1 and self.blocks[1].first <= block.stop - self._keep_steps:
                self.blocks.pop(0)

    def recent(self) -> FilterResult:
        """The filter's results of the blocks kept (with a sink: the last steps')."""
        return FilterResult(
            *(np.concatenate(parts, axis=0) for parts in zip(*[b.filtered for b in self.blocks]))
        )

    def light(self) -> dict:
        """TwinRun fields of the light arrays kept (with a sink): the whole print's."""
        out = {}
        for name, parts in zip(self.LIGHT, zip(*self._light)):
            joined = None if any(p is None for p in parts) else np.concatenate(parts, axis=0)
            out["line_factors" if name == "line" else name] = joined
        return out

    def whole(self) -> StepBlock:
        """The blocks joined into one."""
        blocks = self.blocks
        if not blocks:
            raise ValueError("a print needs at least 2 samples")

        def joined(name):
            parts = [getattr(b, name) for b in blocks]
            return None if any(p is None for p in parts) else np.concatenate(parts, axis=0)

        filtered = FilterResult(
            *(np.concatenate(parts, axis=0) for parts in zip(*[b.filtered for b in blocks]))
        )
        out = StepBlock(
            first=0,
            time_s=joined("time_s"),
            inputs=joined("inputs"),
            model_inputs=joined("model_inputs"),
            measurements=joined("measurements"),
            filtered=filtered,
            theta=blocks[-1].theta,
            seen=joined("seen"),
            prior_floor=joined("prior_floor"),
            calibration_covariances=joined("calibration_covariances"),
            line=joined("line"),
            n_camera=joined("n_camera"),
        )
        out.thetas = np.concatenate([b.theta_per_step for b in blocks])
        return out


def _chunk_run(block: StepBlock, core) -> TwinRun:
    """A committed block as the TwinRun a run's ``sink`` takes."""
    return TwinRun(
        time_s=block.time_s,
        filtered=block.filtered,
        smoothed=None,
        theta_per_step=block.theta_per_step,
        theta_history=_theta_history_frame([]),
        initial=None,
        start_mean=core.start_mean,
        start_cov=core.start_cov,
        calibration_covariances=block.calibration_covariances,
        seen=block.seen,
        prior_floor=block.prior_floor if block.prior_floor.any() else None,
        measurements=block.measurements,
        inputs=block.inputs,
        line_factors=block.line,
        n_camera=block.n_camera,
    )


def _theta_history_frame(history: list) -> pd.DataFrame:
    """EM's history as a table: time, window start, iterations, convergence, log-likelihood,
    θ per state (and the learned output parameters, when learned)."""
    columns = ["time_s", "window_start_s", "iterations", "converged", "log_likelihood"] + [
        f"theta_{name}" for name in STATE_NAMES
    ]
    if history and len(history[-1]) > len(columns):
        columns += [k for k in history[-1] if k not in columns]
    return pd.DataFrame(history, columns=columns)
