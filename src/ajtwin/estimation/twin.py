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
>>> run = Twin.default().run(simulate("exp1", seed=1))          # doctest: +SKIP
>>> run.to_frame()[["time_s", "droplet_diameter_um"]].tail(1)   # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np
import pandas as pd

from ajtwin._jax import jax, jnp
from ajtwin.estimation.calibration_uncertainty import (
    aerosol_level_covariance,
    calibration_state_covariance,
)
from ajtwin.estimation.em import run_em
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
from ajtwin.estimation.initial import InitialFit, fit_initial_state
from ajtwin.estimation.part_line import LineEstimate, line_at, line_model
from ajtwin.estimation.print_time import (
    FiledPrint,
    file_record,
    is_job_record,
    print_context,
)
from ajtwin.estimation.record_checks import (
    SCALE_CHECKED_OUTPUTS,
    check_input_rows,
    check_model_inputs,
    check_output_medians,
    check_output_scales,
    check_print_length,
    finite_median,
    observed_states,
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
from ajtwin.model.system import check_input


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
        phi = float(model.steady_aerosol_fraction(u, 1.0))
        q_m = float(model.outputs(np.array([3.5, 1.0, 0.0, 0.0, phi]), u)[4])
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
        frame = pd.DataFrame({"time_s": self.time_s})
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
        return frame


def never_seen_variance_floor(initial, seen, means) -> np.ndarray | None:
    """Variance floor (T, 5) of the states the initial fit took from their priors
    (``initial.states_from_prior``: a machine without a camera), up to the first second
    an output sees them (``seen``):

        floor_k,i = (σ₀,ᵢ / |x̂₀,ᵢ| · |x̂_k,i|)²   while state i has not been seen by step k,

    i.e. such a state keeps the prior's *relative* width. Without it the reported band
    is the model's: φ_A relaxes to the generation model's steady state within seconds,
    which contracts its variance to the process noise's (≈ 2.6 % against the prior's
    50 %), and on the virtual printer the truth's generation wander then lies outside
    ±2σ a third of the time. The offset of a real atomizer's generation from the model
    is what no pressure can see (docs/validation.md, "A machine without a camera").
    Returns None when every state was fitted from data.
    """
    if initial is None or not initial.states_from_prior or seen is None:
        return None
    means = np.asarray(means, dtype=float)
    floor = np.zeros_like(means)
    not_yet = ~np.logical_or.accumulate(np.asarray(seen, dtype=bool), axis=0)
    for name in initial.states_from_prior:
        i = STATE_NAMES.index(name)
        relative = np.sqrt(initial.covariance[i, i]) / abs(initial.mean[i])
        floor[:, i] = np.where(not_yet[:, i], (relative * means[:, i]) ** 2, 0.0)
    return floor


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


def predict(spec, mean, cov, u, theta, process_cov, functions: ModelFunctions = None):
    """One EKF prediction x̂_{k+1|k}, P_{k+1|k} in display units."""
    step = (functions or model_functions("euler")).step
    s = spec.scaling.state

    def f_scaled(z):
        return step(z * s, u, theta, spec.params, spec.dt) / s

    z = mean / s
    jac = jax.jacfwd(f_scaled)(z)
    p = jac @ (cov / jnp.outer(s, s)) @ jac.T
    return f_scaled(z) * s, p * jnp.outer(s, s) + process_cov


predict = jax.jit(predict, static_argnames=("functions",))


def em_early_steps(config: TwinConfig) -> tuple:
    """The early EM steps of ``config`` (:attr:`TwinConfig.early_em_s`), sorted; those at or
    beyond ``window_s`` are dropped (the full-window schedule runs from there)."""
    early = tuple(sorted({int(t) for t in config.early_em_s}))
    if any(t < 2 for t in early):
        raise ValueError(f"early_em_s {config.early_em_s}: an EM window needs >= 2 steps")
    return tuple(t for t in early if t < int(config.window_s))


def next_em_boundary(pos: int, every: int, early: tuple) -> int:
    """The chunk boundary after step ``pos``: the next multiple of ``every`` or early step."""
    following = (pos // every + 1) * every
    return min([t for t in early if t > pos] + [following])


def em_due(pos: int, every: int, window: int, early: tuple) -> bool:
    """EM runs at chunk boundary ``pos``: every ``every`` steps once a window is full, and at
    the early steps (over the print so far). One rule for the batch twin and the live engine."""
    return (pos >= window and pos % every == 0) or pos in early


def em_schedule(n: int, every: int, window: int, early: tuple):
    """The run's chunks over ``n`` steps: (first step, end, whether EM updates θ at the end),
    boundaries at multiples of ``every`` and the ``early`` steps (:meth:`Twin.run`'s
    chunking; an update needs a full ``window`` or an early step, and a step after it)."""
    pos = 0
    while pos < n:
        end = min(next_em_boundary(pos, every, early), n)
        yield pos, end, em_due(end, every, window, early) and end < n
        pos = end


def first_em_update_time(config: TwinConfig, time_s) -> float | None:
    """When :meth:`Twin.run` will make its first EM update over a print of times ``time_s``
    (the time of the last step before that boundary; None: EM off or never due), known
    before the run from the run's own schedule (:func:`em_schedule`)."""
    n = len(time_s)
    if not config.em or n == 0:
        return None
    every, window = int(config.every_s), int(config.window_s)
    if every < 1 or window < 2:
        return None  # the run refuses such a config itself
    for _, end, update in em_schedule(n, every, window, em_early_steps(config)):
        if update:
            return float(time_s[end - 1])
    return None


# NumPy, not jnp: a jnp concatenate/slice of each new length is one more compiled function
def _concat(results: list[FilterResult]) -> FilterResult:
    return FilterResult(*[np.concatenate(parts, axis=0) for parts in zip(*results)])


def _slice(result: FilterResult, stop: int) -> FilterResult:
    return FilterResult(*[np.asarray(part)[:stop] for part in result])


def _keep_from(pieces: list, starts: list, step: int) -> None:
    """Drop the filter chunks that end before ``step`` (an EM window starts there at the
    earliest); the chunk that holds it stays."""
    while len(starts) > 1 and starts[1] <= step:
        pieces.pop(0)
        starts.pop(0)


def _pad(array: np.ndarray, length: int, fill) -> np.ndarray:
    if len(array) == length:
        return array
    pad = np.repeat(
        array[-1:] if fill is None else np.full_like(array[-1:], fill), length - len(array), axis=0
    )
    return np.concatenate([array, pad], axis=0)


#: Steps a run over a record held on disk reads at a time (:class:`SpooledSteps`).
STREAM_READ_ROWS = 4096


@dataclass
class StepRows:
    """Rows [first, first + m) of a print as the filter, EM and a run's chunks read them."""

    time_s: np.ndarray  # (m,)
    inputs: np.ndarray  # (m, 3) u_k
    measurements: np.ndarray  # (m, 5) what the filter uses (a job print's: filed)
    model_inputs: np.ndarray  # (m, 3 or 4) as the transition reads them
    line: np.ndarray | None  # (m, 4) a job print's line factors
    seen: np.ndarray  # (m, 5) bool (record_checks.observed_states)
    n_camera: np.ndarray | None  # (m, 2) a job print's camera frames per step


class HeldSteps:
    """A print's steps held whole in memory: :class:`StepRows` are slices of its arrays."""

    def __init__(self, time_s, inputs, measurements, model_inputs, line, seen, n_camera=None):
        self.arrays = (time_s, inputs, measurements, model_inputs, line, seen, n_camera)
        self.n = len(time_s)

    def rows(self, first: int, stop: int) -> StepRows:
        """Steps [first, stop)."""
        return StepRows(*(None if a is None else a[first:stop] for a in self.arrays))

    def time(self, k: int) -> float:
        """The time [s] of step ``k``."""
        return float(self.arrays[0][k])


class SpooledSteps:
    """A print's steps read from a record held on disk (:class:`~ajtwin.io.records.
    SpooledRecord`) as the run reaches them; only the last ``keep`` steps before the
    furthest asked for stay (what EM's trailing window reads again).

    The model inputs' input response is carried from piece to piece
    (:func:`~ajtwin.model.droplet_dynamics.next_response`); what each step's outputs see
    comes from the print's median inputs (``u_med``, :func:`observed_states`) once the start
    state is known (``start_mean``). A job print's rows go through one delay line
    (``bins``: :class:`~ajtwin.estimation.print_time.PrintTimeBins`, as
    :func:`~ajtwin.estimation.print_time.file_record` feeds it) and its steps are the filed
    ones: one per row, final ``horizon_s`` rows later.
    """

    def __init__(self, twin, source, u_med, keep: int, bins=None, read_rows: int | None = None):
        self.twin, self.source, self.u_med, self.bins = twin, source, u_med, bins
        self.start_mean = None  # set once the start is known: what the steps see needs it
        self.n, self.keep = len(source), int(keep)
        self.read_rows = int(read_rows or STREAM_READ_ROWS)
        self._follows = twin.config.transition != "paper" and twin.droplet_dynamics.follows_inputs
        self.first = 0  # the step the held rows start at
        self.held: StepRows | None = None
        self._response = None  # the input response at the next step to read
        self._rows_read = 0
        self._filed: list = []  # a job print's steps filed but not yet held

    def _read(self, first: int, stop: int) -> StepRows:
        """Steps [first, stop) (``first``: the first not held yet)."""
        twin = self.twin
        if self.bins is None:
            piece = self.source.piece(first, stop)
            time_s, inputs, measurements = piece.time_s, piece.inputs, piece.outputs
            line = n_camera = None
        else:
            time_s, inputs, measurements, line, n_camera = self._file(stop - first)
        inputs = check_input(inputs)  # its rows named in the run's check before any work
        model_inputs = twin.model_inputs(inputs, self._response)
        if self._follows:
            self._response = next_response(
                float(model_inputs[-1, -1]), inputs[-1], twin.droplet_dynamics, twin.spec.dt
            )
        measurements = np.asarray(measurements, dtype=float)
        return self._seen(
            StepRows(time_s, inputs, measurements, model_inputs, line, None, n_camera)
        )

    def _seen(self, rows: StepRows | None) -> StepRows | None:
        """``rows`` with what their outputs see, once the start state is known (rows read
        before it, for the initial fit, get it when first asked for after)."""
        if rows is not None and rows.seen is None and self.start_mean is not None:
            rows.seen = self.twin.observed_states(
                self.start_mean, rows.inputs, rows.measurements, self.u_med
            )
        return rows

    def _file(self, count: int):
        """The next ``count`` filed steps of a job print: rows fed to the delay line until
        it has given them (all that are left at the print's end)."""
        while len(self._filed) < count and self._rows_read < self.n:
            stop = min(self._rows_read + self.read_rows, self.n)
            piece = self.source.piece(self._rows_read, stop)
            for row in zip(piece.time_s, piece.inputs, piece.outputs, piece.shutter_open,
                           piece.platen_speed, piece.printed_at):  # fmt: skip
                self._filed += self.bins.add(*row)
            self._rows_read = stop
            if stop == self.n:
                self._filed += self.bins.finish()
        steps, self._filed = self._filed[:count], self._filed[count:]
        return (
            np.array([s.time_s for s in steps], dtype=float),
            np.array([s.inputs for s in steps]).reshape(-1, 3),
            np.array([s.outputs for s in steps]).reshape(-1, 5),
            np.array([s.line for s in steps]).reshape(-1, 4),
            np.array([s.n_camera for s in steps]).reshape(-1, 2),
        )

    def rows(self, first: int, stop: int) -> StepRows:
        """Steps [first, stop): ``first`` no earlier than ``keep`` steps before the furthest
        step asked for so far."""
        held_to = self.first + (0 if self.held is None else len(self.held.time_s))
        self._seen(self.held)
        if stop > held_to:
            new = self._read(held_to, min(max(stop, held_to + self.read_rows), self.n))
            self.held = new if self.held is None else _join_rows(self.held, new)
        if first < self.first:
            raise ValueError(f"step {first} was let go (held from {self.first})")
        out = StepRows(
            *(None if a is None else a[first - self.first : stop - self.first]
              for a in _fields(self.held))
        )  # fmt: skip
        drop = max(stop - self.keep - self.first, 0)
        if drop:
            self.held = StepRows(*(None if a is None else a[drop:].copy()
                                   for a in _fields(self.held)))  # fmt: skip
            self.first += drop
        return out

    def time(self, k: int) -> float:
        """The time [s] of step ``k``."""
        return self.source.time_at(k)


def _fields(rows: StepRows) -> tuple:
    return tuple(getattr(rows, f.name) for f in fields(StepRows))


def _join_rows(a: StepRows, b: StepRows) -> StepRows:
    return StepRows(
        *(None if x is None else np.concatenate([x, y]) for x, y in zip(_fields(a), _fields(b)))
    )


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
        coefficients = jnp.asarray(model.coefficient_matrix)
        if calibration is not None:
            coefficients = CalibratedCoefficients(coefficients, calibration)
        update_mask = None
        if config.vial_consider:
            update_mask = jnp.asarray([1.0, 0.0, 1.0, 1.0, 1.0])
        self.spec = ModelSpec(model.params, coefficients, DEFAULT_SCALING, 1.0, update_mask)
        self.functions = twin_functions(config.method, config.transition)
        self.limits = StateLimits.load(model.params)
        self.speed_law = load_line_speed_law()

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
        if self.config.transition == "paper":
            return np.asarray(inputs, dtype=float)

        return augment_inputs(inputs, self.droplet_dynamics, response0, self.spec.dt)

    @property
    def line_model(self):
        """The twin's line as a part map evaluates it: its output model, (calibrated)
        coefficients and speed law with the law's uncertainty
        (:func:`ajtwin.estimation.part_line.line_at`; what :meth:`TwinRun.line_at` and the
        live map use)."""
        return line_model(
            self.model.params, self.spec.coefficients, self.functions.output, self.speed_law
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

    def _output_em(self, smoothed, inputs, measurements) -> dict:
        """Line offsets and output noise by EM over a window (pressures never)."""

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
            n_samples=c.initial_samples,
            vial_fill_ml=c.vial_fill_ml,
            vial_fill_std_ml=c.vial_fill_std_ml,
            tube_prior_std_um=c.tube_prior_std_um,
            nozzle_prior_std_um=c.nozzle_prior_std_um,
            droplet_prior_um=c.droplet_prior_um,
            droplet_prior_std_um=c.droplet_prior_std_um,
            aerosol_prior_relative_std=c.aerosol_prior_relative_std,
            line_factors=line_factors,
        )

    def _predict(self, mean, cov, u, theta):
        m, p = predict(self.spec, mean, cov, u, theta, self.process_cov, self.functions)
        return np.asarray(m), np.asarray(p)

    def _filter(self, mean, cov, inputs, measurements, thetas, line=None):
        return ekf(
            self.spec,
            mean,
            cov,
            inputs,
            measurements,
            thetas,
            self.process_cov,
            self.measurement_var,
            self.config.gate_sigma,
            functions=self.functions,
            line_factors=line,
        )

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
        """Estimate the states over a print (and learn θ if ``config.em``).

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
            Called with the number of steps done (for a progress bar).
        job : ajtwin.job.Job, optional
            The program of a job record, as printed (:func:`~ajtwin.estimation.print_time.
            program_for_record`): speeds at print times come from it, not the record's rows.
        line_factors : array (T, 4), optional
            With ``inputs``/``measurements`` already filed: each step's (F_w, F_o, v_w, v_o).
        sink : callable(first_step, TwinRun), optional
            Takes the run a chunk at a time as the filter finishes it (a TwinRun of those
            steps: the filter's results, θ, the calibration's share, the prior floor, what
            was seen, the print's start prior), so that nothing keeps the whole print's
            results: the run returned then has the print's start, end, θ history, initial
            fit, vial observer and ``seen``, ``filtered`` holds only the last chunks,
            ``theta_per_step`` is None (each chunk had its own) and so is ``vial``
            (:meth:`observe_vial` runs it when wanted). Not with ``smooth``.
        """
        if sink is not None and smooth:
            raise ValueError("a run taken in chunks (sink) cannot be smoothed: RTS needs it whole")
        inputs, measurements, time_s = self._checked_arrays(record, inputs, measurements, time_s)
        filed = self._filed(record, job)
        if filed is not None:
            measurements, line_factors = filed.measurements, filed.line_factors
        line = None if line_factors is None else np.asarray(line_factors, dtype=float)
        n = len(inputs)
        initial = None
        if start is None:
            initial = self.initial_state(inputs, measurements, line)
            mean, cov = initial.mean, initial.covariance
        else:
            mean, cov = (np.asarray(a, dtype=float) for a in start)
        start_mean, start_cov = mean.copy(), cov.copy()
        seen = self.observed_states(start_mean, inputs, measurements)
        # the transition variant's extra input column (input response), if it has one
        model_inputs = self.model_inputs(inputs)
        steps = HeldSteps(
            time_s, inputs, measurements, model_inputs, line, seen,
            None if filed is None else filed.n_camera,
        )  # fmt: skip
        emit = None
        if sink is not None:
            emit, _ = self._chunk_emitter(sink, steps, initial, (start_mean, start_cov))
        if not self.config.em:
            thetas = np.tile(self.theta, (n, 1))
            filtered = self._filter(mean, cov, model_inputs, measurements, self.theta, line)
            theta, history = self.theta.copy(), []
            if emit is not None:
                emit(0, filtered, thetas)
            if progress:
                progress(n)
        else:
            filtered, theta, thetas, history = self._filter_with_em(
                mean, cov, steps, progress, emit
            )
        smoothed = None
        if smooth:
            consistent = self._filter(
                start_mean, start_cov, model_inputs, measurements, thetas, line
            )
            smoothed = rts_smoother(self.spec, consistent)
        self.theta = theta
        return _ended_run(
            filtered,
            history,
            initial,
            (start_mean, start_cov),
            time_s=time_s,
            smoothed=smoothed,
            theta_per_step=thetas,
            calibration_covariances=None
            if sink
            else self._calibration_covariances(filtered, model_inputs, line),
            seen=seen,
            prior_floor=None if sink else never_seen_variance_floor(initial, seen, filtered.means),
            # a run taken in chunks leaves it to the caller (observe_vial): it holds (T, 4, 4)
            vial=None if sink else self._observe_vial(inputs, measurements, start_mean, start_cov),
            measurements=measurements,
            inputs=inputs,
            line_factors=line,
            n_camera=None if filed is None else filed.n_camera,
            camera_counts={} if filed is None else dict(filed.counts),
            line_model=self.line_model,
        )

    def _filed(self, record, job) -> FiledPrint | None:
        """A job record's rows filed at their print times (None: not a job print)."""
        if record is None or not is_job_record(record):
            if job is not None:
                raise ValueError(
                    "a program was given but the record has no job columns (shutter_open, "
                    "platen_speed_mm_s, printed_at_s): it is not a job print"
                )
            return None
        context = print_context(record, job, self.config.camera_horizon_s)
        return file_record(record, context, self.speed_law)

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

    def _filter_with_em(self, mean, cov, steps, progress, emit=None, learn: bool = True):
        """The filter in chunks between EM boundaries; EM over the trailing window at each
        boundary, its θ and re-filtered end state taking effect from there (the module's
        chunking). ``steps``: the print's steps (:class:`HeldSteps` or :class:`SpooledSteps`).
        ``emit(first_step, chunk, θ per step)`` takes each chunk as it is done, and only the
        chunks EM still needs are kept. ``learn=False``: the same chunks, θ held (a run
        without EM taken in chunks). Returns (filter result, θ at the end, θ per step (T, 5)
        or None with ``emit``, EM history)."""
        c = self.config
        n = steps.n
        every, window = int(c.every_s), int(c.window_s)
        if every < 1 or window < 2:
            raise ValueError("EM needs every_s >= 1 and window_s >= 2")
        early = em_early_steps(c)
        theta = self.theta.copy()
        # θ per step of the whole print; with ``emit`` each chunk's goes with it instead
        thetas = None if emit is not None else np.zeros((n, 5))
        pieces, starts, history = [], [], []
        for pos, end, update in em_schedule(n, every, window, early):
            rows = steps.rows(pos, end)
            seg = self._filter(
                mean,
                cov,
                _pad(rows.model_inputs, every, None),
                _pad(rows.measurements, every, np.nan),
                theta,
                None if rows.line is None else _pad(rows.line, every, None),
            )
            seg = _slice(seg, end - pos)
            pieces.append(seg)
            starts.append(pos)
            if thetas is not None:
                thetas[pos:end] = theta
            if emit is not None:
                emit(pos, seg, np.tile(theta, (end - pos, 1)))
                _keep_from(pieces, starts, end - window)
            last_mean = np.asarray(seg.means[-1])
            last_cov = np.asarray(seg.covariances[-1])
            if update and learn:
                w0 = max(end - window, 0)
                em, learned = self._em_over_window(pieces, starts, w0, steps.rows(w0, end), theta)
                theta = em.theta
                last_mean = np.asarray(em.filtered.means)[-1]
                last_cov = np.asarray(em.filtered.covariances)[-1]
                history.append(
                    {
                        "time_s": steps.time(end - 1),
                        "window_start_s": steps.time(w0),
                        "iterations": em.iterations,
                        "converged": em.converged,
                        "log_likelihood": em.log_likelihood,
                        **{f"theta_{name}": float(v) for name, v in zip(STATE_NAMES, theta)},
                        **learned,
                    }
                )
            if end < n:
                mean, cov = self._predict(last_mean, last_cov, rows.model_inputs[-1], theta)
            if progress:
                progress(end)
        return _concat(pieces), theta, thetas, history

    def _em_over_window(self, pieces, starts, w0, window: StepRows, theta):
        """EM over the steps ``window`` (from step w0) from the filter's prediction of step
        w0 (in the chunk that holds it); with ``learn_line_offsets``/``learn_output_noise``
        also the output EM. Returns (EM result, the learned output parameters as a dict)."""
        c = self.config
        piece = int(np.searchsorted(starts, w0, side="right")) - 1
        offset = w0 - starts[piece]
        em = run_em(
            self.spec,
            pieces[piece].predicted_means[offset],
            pieces[piece].predicted_covariances[offset],
            window.model_inputs,
            window.measurements,
            theta,
            self.process_cov,
            self.measurement_var,
            theta_prior_precision=self.theta_prior_precision,
            max_iterations=c.em_max_iterations,
            tolerance=c.em_tolerance,
            gate=c.gate_sigma,
            functions=self.functions,
            line_factors=window.line,
        )
        learned = {}
        if c.learn_line_offsets or c.learn_output_noise:
            if window.line is not None:
                raise ValueError(
                    "learning line offsets or output noise online is not available on a job "
                    "print (the line's speed factors are not in that M-step)"
                )
            learned = self._output_em(em.smoothed, window.model_inputs, window.measurements)
        return em, learned

    def _calibration_covariances(self, filtered, model_inputs, line=None, carry=None):
        """The states' covariance from the calibration's uncertainty and φ_A's unknown level
        (None: neither given). ``line``: a job print's per-step line factors; ``carry``: a
        chunk of a run (what the vial drained before it, :func:`calibration_state_covariance`
        and :func:`aerosol_level_covariance`)."""
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
        return out

    def _chunk_emitter(self, sink, steps, initial, start):
        """``(emit, tally)``: ``emit(first_step, filtered chunk, θ per step)`` for the runs'
        ``sink``: each chunk as a TwinRun of its steps, with what :meth:`run` adds to a whole
        print (the calibration's share, with the vial's drain carried over; the prior floor,
        with what was seen before the chunk; the inputs, the measurements the filter used
        and a job print's line factors and camera frames; the print's start (mean, cov)).
        ``tally["unseen"]``: per state, the seconds emitted so far that no output saw it."""
        carry: dict = {}
        tally = {"unseen": np.zeros(len(STATE_NAMES), np.int64)}
        seen_before = np.zeros(len(STATE_NAMES), dtype=bool)

        def emit(first: int, chunk, thetas) -> None:
            nonlocal seen_before
            stop = first + len(chunk.means)
            rows = steps.rows(first, stop)
            seen_chunk = np.asarray(rows.seen) | seen_before
            seen_before = seen_before | seen_chunk.any(axis=0)
            tally["unseen"] += (~np.asarray(rows.seen)).sum(axis=0)
            sink(
                first,
                TwinRun(
                    time_s=rows.time_s,
                    filtered=chunk,
                    smoothed=None,
                    theta_per_step=np.asarray(thetas),
                    theta_history=_theta_history_frame([]),
                    initial=None,
                    start_mean=start[0],
                    start_cov=start[1],
                    calibration_covariances=self._calibration_covariances(
                        chunk, rows.model_inputs, rows.line, carry
                    ),
                    seen=rows.seen,
                    prior_floor=never_seen_variance_floor(initial, seen_chunk, chunk.means),
                    measurements=rows.measurements,
                    inputs=rows.inputs,
                    line_factors=rows.line,
                    n_camera=rows.n_camera,
                ),
            )

        return emit, tally

    def observed_states(self, mean, inputs, measurements, u_med=None) -> np.ndarray:
        """(T, 5) bool: which states an output measured at each step responds to
        (:func:`~ajtwin.estimation.record_checks.observed_states` with the twin's model)."""
        return observed_states(
            self.model.params,
            self.spec.coefficients,
            mean,
            self.limits.upper - self.limits.lower,
            inputs,
            measurements,
            self.config.measurement_std,
            u_med,
        )

    def run_streamed(self, source, *, start=None, progress=None, sink, job=None) -> TwinRun:
        """:meth:`run` with ``sink`` over a record held on disk, read a piece at a time.

        ``source``: a :class:`~ajtwin.io.records.SpooledRecord`; ``job``: as for :meth:`run`
        (a job print's rows are filed at their print times through one delay line as they
        are read). The same checks as :meth:`run` on a record (the medians a column at a
        time), the same chunks, filter and EM (:meth:`_filter_with_em` over
        :class:`SpooledSteps`): memory does not grow with the print. The run returned has
        no per-step arrays: its start, end, θ history, initial fit, a job print's camera
        counts, ``n_steps`` and ``unseen_counts``.
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
        context = None
        if is_job_record(source):
            context = print_context(source, job, c.camera_horizon_s)
        elif job is not None:
            self._filed(source, job)  # refused as run refuses it
        bins = None if context is None else context.bins(self.speed_law)
        steps = SpooledSteps(self, source, u_med, keep=int(c.window_s), bins=bins)
        initial = None
        if start is None:
            head = steps.rows(0, min(n, int(c.initial_samples)))
            initial = self.initial_state(head.inputs, head.measurements, head.line)
            mean, cov = initial.mean, initial.covariance
        else:
            mean, cov = (np.asarray(a, dtype=float) for a in start)
        start_mean, start_cov = mean.copy(), cov.copy()
        steps.start_mean = start_mean
        emit, tally = self._chunk_emitter(sink, steps, initial, (start_mean, start_cov))
        filtered, self.theta, _, history = self._filter_with_em(
            mean, cov, steps, progress, emit, learn=c.em
        )
        # no per-step arrays: each chunk went to the sink with its own
        kept = {"time_s": None, "smoothed": None, "theta_per_step": None, "n_steps": n}
        kept.update(line_model=self.line_model, unseen_counts=tally["unseen"])
        if bins is not None:
            kept["camera_counts"] = {**bins.counts, "horizon_s": context.horizon_s}
        return _ended_run(filtered, history, initial, (start_mean, start_cov), **kept)

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


def _ended_run(filtered, history: list, initial, start: tuple, **fields) -> TwinRun:
    """A run's TwinRun: the filter's result, EM's history, the initial fit, the start
    (mean, cov) and the end state (the filter's last), with the run's own ``fields``."""
    return TwinRun(
        filtered=filtered,
        theta_history=_theta_history_frame(history),
        initial=initial,
        start_mean=start[0],
        start_cov=start[1],
        end_mean=np.asarray(filtered.means[-1]),
        end_cov=np.asarray(filtered.covariances[-1]),
        **fields,
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
