"""The live twin: one 1 Hz sample in → state ± σ, predicted outputs, NIS, alarms out.

:class:`TwinStream` keeps one machine's twin in step with its data, a sample at a time,
with the same math as the batch :meth:`ajtwin.estimation.Twin.run` and
:func:`ajtwin.apps.anomaly.detect_anomalies`: the EKF step is
:func:`ajtwin.estimation.filters.ekf_step` (the batch ``lax.scan``'s body plus units), the
detectors are :class:`ajtwin.apps.anomaly.AnomalyDetector` (which the batch runs over
arrays). So a record fed sample by sample gives the batch's states, θ and events.

Semantics (shared with ``Twin.run``)
------------------------------------
* Samples live on a 1 s grid k = 0, 1, …; the twin starts from the registry's carry-over
  state or, for a machine's first print, from the initial-state fit over the first
  ``initial_samples`` samples (the stream waits for them).
* Every ``every_s`` steps and at the early EM steps ``early_em_s`` (a *chunk boundary*
  pos) the filter restarts from the prediction of step pos − 1. From pos ≥ ``window_s``
  and at the early steps, and only when sample pos has arrived (the print goes on), EM
  runs over the trailing window [max(pos − window, 0), pos);
  its θ and its re-filtered end state take effect from step pos.
* EM does not stall the steps: it runs in a worker thread; samples that arrive meanwhile
  are stepped with the previous θ and published as ``provisional``, then re-stepped with
  the new θ once EM lands (the *committed* results, the ones stored and given to the
  detectors). With ``asynchronous=False`` (batch, replay, tests) EM runs inline.

Late, missing, duplicated and out-of-order samples
--------------------------------------------------
A sample's time is rounded to the grid. A jump of n > 1 s inserts n − 1 missing samples
(inputs held, outputs NaN); a sample at the last time is a duplicate and dropped; an older
one is logged and dropped. Non-finite or implausible values are logged and treated as
missing (an output → NaN; an input → the whole sample missing, inputs held).

Publish/subscribe
-----------------
Each committed (and provisional) step becomes a plain dict (:meth:`TwinStream.feed`
returns them; :class:`LiveEngine` hands them to subscribers): ``machine``, ``step``,
``time_s``, ``provisional``, ``states`` {name: value}, ``stds``, ``predicted_outputs``,
``measured_outputs``, ``inputs``, ``nis``, ``n_measured``, ``nis_p``, ``window_nis_p``,
``cusum`` {channel: max(g⁺, g⁻)}, ``status`` ("ok" / "alarm" / "warming up" …),
``cause``, ``alarms`` (detector labels fired at this step), ``events`` (raised/finalised
events as dicts with ``state`` "raised"/"final"), ``theta``.

A machine link also publishes its connection state on the same path
(:meth:`LiveEngine.publish_link`): ``{"machine", "link": {"state", "url", "since",
"attempt", "retry_in_s", "reason", "gap_s"}}`` — no ``step``; ``state`` is
``connecting``, ``connected``, ``reconnecting`` (the server is gone since ``since``,
Unix time; ``attempt`` reconnections tried), ``refused`` or ``ended``.

Examples
--------
>>> from ajtwin.simulation import simulate                      # doctest: +SKIP
>>> stream = TwinStream.new("aj300-1", asynchronous=False)       # doctest: +SKIP
>>> rec = simulate("exp1", seed=1, duration_min=2)               # doctest: +SKIP
>>> for t, u, y in zip(rec.time_s, rec.inputs, rec.outputs):    # doctest: +SKIP
...     messages = stream.feed(Sample(t, u, y))
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.apps.anomaly import AnomalyDetector, DetectorSettings
from ajtwin.estimation.em import run_em
from ajtwin.estimation.filters import EKFCarry, ekf_init, ekf_step
from ajtwin.estimation.twin import Twin, em_due, em_early_steps, predict
from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS, PLAUSIBLE_RANGES
from ajtwin.model import OUTPUT_NAMES, STATE_NAMES
from ajtwin.model.droplet_dynamics import model_input, next_response
from ajtwin.model.system import INPUT_LIMITS, INPUT_NAMES

log = logging.getLogger("ajtwin.live")

#: jitted single step; vmapped over machines by :func:`step_many`
_step = jax.jit(ekf_step, static_argnames=("functions",))


def _batched(spec, carry, u, y, theta, process_cov, measurement_cov, gate, functions):
    return jax.vmap(
        lambda c, uu, yy, th: ekf_step(
            spec, c, uu, yy, th, process_cov, measurement_cov, gate, functions
        )
    )(carry, u, y, theta)


_step_many = jax.jit(_batched, static_argnames=("functions",))


@dataclass
class Sample:
    """One 1 Hz sample: time [s], inputs (3,) [mA, sccm, sccm], outputs (5,) (NaN = missing)."""

    time_s: float
    inputs: np.ndarray
    outputs: np.ndarray


#: |time| beyond this [s] (≈ 31,700 years) is no clock reading: the sample is dropped (far
#: below 2**53 s, where float64 could no longer hold the 1 s grid)
MAX_ABS_TIME_S = 1e12
#: a gap ahead of the last step longer than this [s] is not filled with missing samples
#: (a clock jump or a stale/wrong time stamp, not an outage): the sample is dropped
MAX_GAP_S = 6 * 3600


def clean_sample(time_s, inputs, outputs, where: str = "") -> tuple[Sample | None, list[str]]:
    """Check a sample from the wire; returns (sample or None, problems as log lines).

    Non-finite or out-of-range outputs become NaN; bad or malformed inputs/outputs (not
    3 + 5 numbers) make the sample missing (all NaN); a non-finite or implausible time
    (|t| > ``MAX_ABS_TIME_S``) drops it (None).
    """
    problems = []
    prefix = f"{where}: " if where else ""
    try:
        t = float(time_s)
    except (TypeError, ValueError, OverflowError):
        t = float("nan")
    if not np.isfinite(t):
        return None, [f"{prefix}sample time {time_s!r} is not a number; sample dropped"]
    if abs(t) > MAX_ABS_TIME_S:
        return None, [f"{prefix}sample time {t:g} s is not a plausible clock; sample dropped"]
    u = np.full(3, np.nan)
    y = np.full(5, np.nan)
    try:
        u[:] = np.asarray(inputs, dtype=float).reshape(3)
        y[:] = np.asarray(outputs, dtype=float).reshape(5)
    except (TypeError, ValueError, OverflowError) as exc:
        # as the line says: a step with nothing known, not a dropped one
        missing = Sample(t, np.full(3, np.nan), np.full(5, np.nan))
        return missing, [f"{prefix}t = {t:g} s: malformed sample ({exc}); treated as missing"]
    for i, name in enumerate(INPUT_NAMES):
        low, high = INPUT_LIMITS[name]
        if not np.isfinite(u[i]) or not (low < u[i] <= high):
            problems.append(
                f"{prefix}t = {t:g} s: {INPUT_COLUMNS[i]} = {u[i]!r} outside ({low:g}, {high:g}]"
                "; sample treated as missing"
            )
    if problems:
        return Sample(t, np.full(3, np.nan), np.full(5, np.nan)), problems
    for i, column in enumerate(OUTPUT_COLUMNS):
        value = y[i]
        if np.isnan(value):
            continue
        low, high = PLAUSIBLE_RANGES.get(column, (-np.inf, np.inf))[:2]
        if not np.isfinite(value) or not (low <= value <= high):
            problems.append(
                f"{prefix}t = {t:g} s: {column} = {value!r} outside [{low:g}, {high:g}]; "
                "treated as missing"
            )
            y[i] = np.nan
    return Sample(t, u, y), problems


class _History:
    """Per-step committed results, grown as the print goes on (display units)."""

    FIELDS = (
        "time_s",
        "inputs",
        "model_inputs",  # the inputs as the transition reads them (with r: input_following)
        "measurements",
        "means",
        "covariances",
        "predicted_means",
        "predicted_covariances",
        "predicted_outputs",
        "innovation_variances",
        "log_likelihood",
        "nis",
        "n_measured",
        "reinitialised",
        "theta_per_step",
        "prior_floor",
    )

    def __init__(self):
        for name in self.FIELDS:
            setattr(self, name, [])

    def __len__(self):
        return len(self.time_s)

    def array(self, name) -> np.ndarray:
        return np.asarray(getattr(self, name), dtype=float)


class TwinStream:
    """One machine's twin, fed a sample at a time (see module docstring).

    Parameters
    ----------
    machine : str
    twin : Twin
        Model, tuning and the starting θ (``twin.theta``).
    start : (mean (5,), cov (5, 5)), optional
        Start state (the previous print's end, carried over); default: the initial fit.
    detector_settings : DetectorSettings, optional
    asynchronous : bool
        EM in a worker thread (live) or inline (batch, replay).
    executor : ThreadPoolExecutor, optional
        Shared EM workers (:class:`LiveEngine` passes one for all machines).
    long_run_history : dict, optional
        The detectors' carried long-run statistics (:func:`carried_long_run_history`).
    """

    def __init__(
        self,
        machine: str,
        twin: Twin,
        start=None,
        detector_settings: DetectorSettings | None = None,
        *,
        asynchronous: bool = True,
        executor: ThreadPoolExecutor | None = None,
        long_run_history: dict | None = None,
    ):
        self.machine = machine
        self.twin = twin
        self.config = twin.config
        if self.config.em and (self.config.every_s < 1 or self.config.window_s < 2):
            raise ValueError("EM needs every_s >= 1 and window_s >= 2")
        # the batch twin's boundaries and EM times (one rule: estimation.twin.em_due)
        self._early = em_early_steps(self.config) if self.config.em else ()
        self.asynchronous = asynchronous
        self._executor = executor
        self._own_executor = False
        self.theta = np.asarray(twin.theta, dtype=float).copy()
        self.theta_before = self.theta.copy()
        self.start = None if start is None else tuple(np.asarray(a, dtype=float) for a in start)
        self.initial = None
        self.start_mean = self.start_cov = None
        self.detector = AnomalyDetector(detector_settings, long_run_history)
        self.history = _History()
        self.theta_history: list[dict] = []
        self.carry: EKFCarry | None = None  # committed carry for the next step
        self.n_received = 0  # samples on the grid so far (committed + pending + waiting)
        self.last_time: float | None = None
        self.last_inputs: np.ndarray | None = None
        self._waiting: list[Sample] = []  # before the initial fit
        self._pending: list[Sample] = []  # arrived while EM runs
        self._em_future: Future | None = None
        self._em_pos: int | None = None
        self._em_done: int | None = None  # boundary whose EM result is in force
        self._spec_carry: EKFCarry | None = None  # speculative carry while EM runs
        self._device_constants = None
        self.dropped = {"duplicate": 0, "out_of_order": 0, "bad": 0, "far_future": 0}
        self.missing_inserted = 0
        # states the initial fit took from priors and no output has seen yet (camera-less):
        # their bands keep the prior's relative width (twin.never_seen_variance_floor)
        self._never_seen: np.ndarray | None = None
        self._responds: np.ndarray | None = None  # (5 outputs, 5 states)
        self._floor_relative = np.zeros(5)
        # the droplet size's input response r for the next committed step (a transition
        # profile that follows the inputs; the batch twin's Twin.model_inputs, one sample
        # at a time)
        self._dynamics = twin.droplet_dynamics if twin.config.transition != "paper" else None
        self._response: float | None = None

    def model_input(self, inputs, response: float | None = None):
        """(the transition's input for a committed step with ``inputs``, r after it);
        ``response`` default: the committed r."""
        r = self._response if response is None else response
        if self._dynamics is None:
            return np.asarray(inputs, dtype=float), None
        return model_input(inputs, r, self._dynamics, self.twin.spec.dt)

    @classmethod
    def new(cls, machine: str, start=None, theta=None, twin_overrides=None, **kwargs):
        """A stream with the default twin (``twin_overrides``: TwinConfig fields)."""
        twin = Twin.default(**(twin_overrides or {}))
        if theta is not None:
            twin.theta = np.asarray(theta, dtype=float)
        return cls(machine, twin, start, **kwargs)

    # ------------------------------------------------------------------ #
    @property
    def n_committed(self) -> int:
        return len(self.history)

    @property
    def em_running(self) -> bool:
        return self._em_future is not None

    def feed(self, sample: Sample) -> list[dict]:
        """Take one sample; returns the messages it produced (committed and provisional)."""
        out: list[dict] = []
        out += self.poll()
        t = float(sample.time_s)
        if self.last_time is None:
            grid = [sample]
        else:
            # clamped before rounding: a time stamp far ahead must not become a huge int
            n = int(round(min(max(t - self.last_time, -1.0), MAX_GAP_S + 2.0)))
            if n <= 0:
                if n == 0:
                    self.dropped["duplicate"] += 1
                    log.debug("%s: duplicate sample at t = %g s dropped", self.machine, t)
                else:
                    self.dropped["out_of_order"] += 1
                    log.warning(
                        "%s: sample at t = %g s is older than the last step (t = %g s); dropped",
                        self.machine,
                        t,
                        self.last_time,
                    )
                return out
            if n - 1 > MAX_GAP_S:
                self.dropped["far_future"] += 1
                log.warning(
                    "%s: sample at t = %g s is %g s ahead of the last step (t = %g s), more "
                    "than %d s; dropped (clock jump?)",
                    self.machine,
                    t,
                    t - self.last_time,
                    self.last_time,
                    MAX_GAP_S,
                )
                return out
            grid = []
            if n > 1:
                log.info(
                    "%s: %d s gap before t = %g s; treated as missing data", self.machine, n - 1, t
                )
                self.missing_inserted += n - 1
                for j in range(1, n):
                    grid.append(Sample(self.last_time + j, None, np.full(5, np.nan)))
            grid.append(Sample(self.last_time + n, sample.inputs, sample.outputs))
        for s in grid:
            out += self._accept(s)
        return out

    def take_plain(self, sample: Sample) -> Sample | None:
        """If ``sample`` is an ordinary next step (no gap, boundary, EM or start), book it
        and return it for a batched step (:class:`LiveEngine`); else None, nothing changed."""
        c = self.config
        k = self.n_committed
        if (
            self.carry is None
            or self._em_future is not None
            or self._waiting
            or self.last_time is None
            or int(round(float(sample.time_s) - self.last_time)) != 1
            or sample.inputs is None
            or not np.all(np.isfinite(sample.inputs))
            or (c.em and self._is_boundary(k) and k != self._em_done)
        ):
            return None
        sample = Sample(
            self.last_time + 1, np.asarray(sample.inputs, float), np.asarray(sample.outputs, float)
        )
        self.last_time = sample.time_s
        self.last_inputs = sample.inputs
        self.n_received += 1
        return sample

    def _accept(self, sample: Sample) -> list[dict]:
        u = None if sample.inputs is None else np.asarray(sample.inputs, dtype=float)
        y = np.asarray(sample.outputs, dtype=float)
        if u is None or not np.all(np.isfinite(u)):
            if self.last_inputs is None:
                # nothing to hold yet: the print has not started for the twin
                log.warning(
                    "%s: sample at t = %g s has no valid inputs before the first valid "
                    "sample; dropped",
                    self.machine,
                    sample.time_s,
                )
                self.dropped["bad"] += 1
                return []
            u, y = self.last_inputs.copy(), np.full(5, np.nan)
        sample = Sample(float(sample.time_s), u, y)
        self.last_time = sample.time_s
        self.last_inputs = u
        self.n_received += 1
        if self.carry is None and self.n_committed == 0 and self._em_future is None:
            self._waiting.append(sample)
            if self.start is None and len(self._waiting) < self.config.initial_samples:
                return []
            return self._start_filter()
        return self._advance(sample)

    def _start_filter(self) -> list[dict]:
        waiting, self._waiting = self._waiting, []
        if self.start is None:
            inputs = np.array([s.inputs for s in waiting])
            outputs = np.array([s.outputs for s in waiting])
            self.initial = self.twin.initial_state(inputs, outputs)
            mean, cov = self.initial.mean, self.initial.covariance
            if self.initial.states_from_prior:
                self._start_prior_floor(inputs)
        else:
            mean, cov = self.start
        self.start_mean, self.start_cov = np.asarray(mean).copy(), np.asarray(cov).copy()
        self.carry = ekf_init(self.twin.spec, mean, cov)
        out = []
        for s in waiting:
            out += self._advance(s)
        return out

    # ------------------------------------------------------------------ #
    def _advance(self, sample: Sample) -> list[dict]:
        """Step k = next grid index; handles chunk boundaries and EM."""
        if self._em_future is not None:
            self._pending.append(sample)
            return [self._speculative(sample)]
        k = self.n_committed
        c = self.config
        boundary = c.em and k > 0 and self._is_boundary(k) and k != self._em_done
        if boundary:
            if em_due(k, int(c.every_s), int(c.window_s), self._early):
                self._launch_em(k)
                self._pending.append(sample)
                if not self.asynchronous:
                    return self.poll(wait=True)
                return [self._speculative(sample)]
            self._restart_chunk(k, self.theta)
        return [self._commit(sample)]

    def _is_boundary(self, k: int) -> bool:
        """A chunk boundary: a multiple of every_s or an early EM step (the batch twin's)."""
        return k % int(self.config.every_s) == 0 or k in self._early

    def _start_prior_floor(self, inputs) -> None:
        """Which output sees which state (the batch twin's ``observed_states``, one output
        at a time) and the prior's relative σ of the states taken from priors."""
        from ajtwin.estimation.record_checks import observed_states

        twin, initial = self.twin, self.initial
        one_output_each = np.where(np.eye(5, dtype=bool), 1.0, np.nan)
        self._responds = observed_states(
            twin.model.params,
            twin.spec.coefficients,
            initial.mean,
            twin.limits.upper - twin.limits.lower,
            inputs,
            one_output_each,
            twin.config.measurement_std,
        )
        self._never_seen = np.array([n in initial.states_from_prior for n in STATE_NAMES])
        relative = np.zeros(5)
        for i in np.flatnonzero(self._never_seen):
            relative[i] = np.sqrt(initial.covariance[i, i]) / abs(initial.mean[i])
        self._floor_relative = relative

    def _prior_floor(self, mean, outputs=None) -> np.ndarray:
        """Variance floor (5,) of this step; ``outputs`` (a committed sample) update what
        has been seen."""
        if self._never_seen is None:
            return np.zeros(5)
        if outputs is not None:
            measured = np.isfinite(np.asarray(outputs, dtype=float))
            self._never_seen &= ~(measured[:, None] & self._responds).any(axis=0)
        return np.where(self._never_seen, (self._floor_relative * np.asarray(mean)) ** 2, 0.0)

    def _restart_chunk(self, pos: int, theta, last=None):
        """Filter restart at a chunk boundary: prior = prediction from step pos − 1."""
        h = self.history
        if last is None:
            last = (h.means[pos - 1], h.covariances[pos - 1])
        mean, cov = predict(
            self.twin.spec,
            last[0],
            last[1],
            h.model_inputs[pos - 1],
            theta,
            self.twin.process_cov,
            self.twin.functions,
        )
        self.carry = ekf_init(self.twin.spec, np.asarray(mean), np.asarray(cov))

    def _launch_em(self, pos: int):
        h = self.history
        c = self.config
        w0 = max(pos - int(c.window_s), 0)
        args = (
            self.twin.spec,
            np.asarray(h.predicted_means[w0]),
            np.asarray(h.predicted_covariances[w0]),
            h.array("model_inputs")[w0:pos],
            h.array("measurements")[w0:pos],
            self.theta.copy(),
            self.twin.process_cov,
            self.twin.measurement_var,
        )
        kwargs = dict(
            theta_prior_precision=self.twin.theta_prior_precision,
            max_iterations=c.em_max_iterations,
            tolerance=c.em_tolerance,
            gate=c.gate_sigma,
            functions=self.twin.functions,
        )
        self._em_pos = pos
        self._spec_carry = None
        if self.asynchronous:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="ajtwin-em")
                self._own_executor = True
            self._em_future = self._executor.submit(run_em, *args, **kwargs)
        else:
            future = Future()
            future.set_result(run_em(*args, **kwargs))
            self._em_future = future

    def poll(self, wait: bool = False) -> list[dict]:
        """Apply a finished EM (``wait``: block until it is) and replay the samples held."""
        future = self._em_future
        if future is None or (not wait and not future.done()):
            return []
        em = future.result()
        pos = self._em_pos
        h = self.history
        w0 = max(pos - int(self.config.window_s), 0)
        self.theta = np.asarray(em.theta, dtype=float)
        self.theta_history.append(
            {
                "time_s": float(h.time_s[pos - 1]),
                "window_start_s": float(h.time_s[w0]),
                "iterations": em.iterations,
                "converged": em.converged,
                "log_likelihood": em.log_likelihood,
                **{f"theta_{name}": float(v) for name, v in zip(STATE_NAMES, self.theta)},
            }
        )
        last = (np.asarray(em.filtered.means[-1]), np.asarray(em.filtered.covariances[-1]))
        self._restart_chunk(pos, self.theta, last)
        self._em_future = None
        self._em_done, self._em_pos = pos, None
        self._spec_carry = None
        pending, self._pending = self._pending, []
        out = []
        for s in pending:
            out += self._advance(s)
        return out

    def _speculative(self, sample: Sample) -> dict:
        """Step with the old θ while EM runs: published as provisional, not kept."""
        if self._spec_carry is None:
            h = self.history
            pos = self._em_pos
            mean, cov = predict(
                self.twin.spec,
                h.means[pos - 1],
                h.covariances[pos - 1],
                h.model_inputs[pos - 1],
                self.theta,
                self.twin.process_cov,
                self.twin.functions,
            )
            self._spec_carry = ekf_init(self.twin.spec, np.asarray(mean), np.asarray(cov))
        # r continued over the samples held before this one (all committed later)
        response = self._response
        if self._dynamics is not None and response is not None:
            for held in self._pending[:-1]:
                response = next_response(response, held.inputs, self._dynamics, self.twin.spec.dt)
        u, _ = self.model_input(sample.inputs, response)
        self._spec_carry, step = self._run_step(self._spec_carry, sample, u)
        return self._message(self.n_committed + len(self._pending) - 1, sample, step, None, True)

    def _constants(self):
        """Σ_ξ, σ_w², gate as device arrays, made once (a conversion per step costs more
        than the step)."""
        if self._device_constants is None:
            twin = self.twin
            self._device_constants = (
                jnp.asarray(twin.process_cov),
                jnp.asarray(twin.measurement_var),
                jnp.asarray(float(twin.config.gate_sigma)),
            )
        return self._device_constants

    def _run_step(self, carry, sample, model_input):
        carry, step = _step(
            self.twin.spec,
            carry,
            model_input,
            np.asarray(sample.outputs, dtype=float),
            self.theta,
            *self._constants(),
            functions=self.twin.functions,
        )
        return carry, jax.device_get(step)

    def _commit(self, sample: Sample, step=None, carry=None) -> dict:
        """Committed step: kept, given to the detectors, stored and published."""
        u, self._response = self.model_input(sample.inputs)
        if step is None:
            self.carry, step = self._run_step(self.carry, sample, u)
        else:
            self.carry = carry
        h = self.history
        k = len(h)
        h.time_s.append(sample.time_s)
        h.inputs.append(np.asarray(sample.inputs, dtype=float))
        h.model_inputs.append(u)
        h.measurements.append(np.asarray(sample.outputs, dtype=float))
        h.means.append(np.asarray(step.mean))
        h.covariances.append(np.asarray(step.covariance))
        h.predicted_means.append(np.asarray(step.predicted_mean))
        h.predicted_covariances.append(np.asarray(step.predicted_covariance))
        h.predicted_outputs.append(np.asarray(step.predicted_output))
        h.innovation_variances.append(np.asarray(step.innovation_variance))
        h.log_likelihood.append(float(step.log_likelihood))
        h.nis.append(float(step.nis))
        h.n_measured.append(float(step.n_measured))
        h.reinitialised.append(bool(step.reinitialised))
        h.theta_per_step.append(self.theta.copy())
        h.prior_floor.append(self._prior_floor(step.mean, sample.outputs))
        status = self.detector.update(
            sample.time_s,
            sample.outputs,
            step.predicted_output,
            step.innovation_variance,
            step.nis,
            step.n_measured,
            step.mean,
            step.predicted_mean,
            step.covariance,
            inputs=sample.inputs,
        )
        return self._message(k, sample, step, status, False)

    # ------------------------------------------------------------------ #
    def _message(self, k, sample, step, status, provisional) -> dict:
        mean = np.asarray(step.mean)
        variance = np.maximum(np.diag(np.asarray(step.covariance)), self._prior_floor(mean))
        std = np.sqrt(np.maximum(variance, 0.0))
        msg = {
            "machine": self.machine,
            "step": int(k),
            "time_s": float(sample.time_s),
            "provisional": bool(provisional),
            "states": dict(zip(STATE_NAMES, mean.tolist())),
            "stds": dict(zip(STATE_NAMES, std.tolist())),
            "predicted_outputs": dict(
                zip(OUTPUT_NAMES, np.asarray(step.predicted_output).tolist())
            ),
            "measured_outputs": dict(zip(OUTPUT_NAMES, np.asarray(sample.outputs).tolist())),
            "inputs": dict(zip(INPUT_NAMES, np.asarray(sample.inputs).tolist())),
            "nis": float(step.nis),
            "n_measured": int(step.n_measured),
            "reinitialised": bool(step.reinitialised),
            "theta": dict(zip(STATE_NAMES, self.theta.tolist())),
            "em_running": self.em_running,
        }
        events = []
        if status is not None:
            from ajtwin.apps.anomaly import CUSUM_CHANNELS

            msg["nis_p"] = status.nis_p
            msg["window_nis_p"] = status.window_nis_p
            g = np.maximum(status.cusum_pos, status.cusum_neg)
            msg["cusum"] = dict(zip(CUSUM_CHANNELS, g.tolist()))
            msg["alarms"] = list(status.alarms)
            events += [{"state": "raised", **ev.to_dict()} for ev in status.raised]
            events += [{"state": "final", **ev.to_dict()} for ev in status.finalised]
        msg["events"] = events
        msg["status"], msg["cause"] = self.status(provisional)
        return msg

    def status(self, provisional: bool = False) -> tuple[str, str]:
        """Operator status and likely cause of the latest event ("" when none)."""
        d = self.detector
        if d.start is None:
            return "warming up", ""
        if d.events:
            last = d.events[-1]
            if self.history.time_s and self.history.time_s[-1] - last.detected_s <= (
                d.settings.merge_s
            ):
                return "alarm", last.cause
        return ("ok (provisional)" if provisional else "ok"), ""

    # ------------------------------------------------------------------ #
    def finish(self) -> list[dict]:
        """End of the print: apply a running EM's result if its step arrived, finalise events.

        Samples still waiting for the initial fit (fewer than ``initial_samples``) start
        the filter with what there is.
        """
        out = self.poll(wait=True)
        if self._waiting:
            out += self._start_filter()
        events = self.detector.finish()
        if self._own_executor and self._executor is not None:
            self._executor.shutdown(wait=False)
        return out + [
            {
                "machine": self.machine,
                "finished": True,
                "events": [{"state": "final", **e.to_dict()} for e in events],
            }
        ]

    def arrays(self) -> dict[str, np.ndarray]:
        """The committed per-step results, named as the registry stores a print."""
        h = self.history
        means = h.array("means")
        covs = h.array("covariances").reshape(-1, 5, 5)
        hist = self.theta_history
        return {
            "time_s": h.array("time_s"),
            "means": means.reshape(-1, 5),
            "stds": np.sqrt(
                np.maximum(np.diagonal(covs, 0, 1, 2), h.array("prior_floor").reshape(-1, 5))
            ),
            "covariances": covs,
            "predicted_means": h.array("predicted_means").reshape(-1, 5),
            "predicted_outputs": h.array("predicted_outputs").reshape(-1, 5),
            "innovation_variances": h.array("innovation_variances").reshape(-1, 5),
            "measurements": h.array("measurements").reshape(-1, 5),
            "inputs": h.array("inputs").reshape(-1, 3),
            "nis": h.array("nis"),
            "n_measured": h.array("n_measured"),
            "reinitialised": np.asarray(h.reinitialised, dtype=bool),
            "theta_per_step": h.array("theta_per_step").reshape(-1, 5),
            "theta_history_time_s": np.array([r["time_s"] for r in hist], dtype=float),
            "theta_history": np.array(
                [[r[f"theta_{n}"] for n in STATE_NAMES] for r in hist], dtype=float
            ).reshape(-1, 5),
        }


# --------------------------------------------------------------------------- #
# Batch ingest and the registry (the same orchestration for a finished print)
# --------------------------------------------------------------------------- #


def print_summary(
    end_mean,
    end_cov,
    nis,
    reinitialised,
    n_anomalies: int,
    em_updates: int,
    started_from: str,
    status: str,
    status_reason: str,
):
    """The summary the registry keeps for a print."""
    return {
        "end_state": dict(zip(STATE_NAMES, np.asarray(end_mean, dtype=float).tolist())),
        "end_std": np.sqrt(np.diag(np.asarray(end_cov, dtype=float))).tolist(),
        "mean_nis": float(np.nanmean(np.asarray(nis, dtype=float))),
        "n_anomalies": int(n_anomalies),
        "em_updates": int(em_updates),
        "guard_reinitialisations": int(np.asarray(reinitialised).sum()),
        "started_from": started_from,
        "status": status,
        "status_reason": status_reason,
    }


def save_print(
    registry,
    machine: str,
    record,
    *,
    digest: str,
    source: str,
    arrays: dict,
    events: list,
    start,
    end,
    theta_before,
    theta_after,
    expected_last_seq,
    started_from: str,
    status: str,
    status_reason: str,
    extra_summary: dict | None = None,
    live_session: int | None = None,
    keep_live_steps: bool = False,
    long_run_history: dict | None = None,
):
    """Store a twin's run over one print in one registry transaction; (print id, summary).

    ``status``/``status_reason``: :func:`ajtwin.store.chain.judge_run` of the run;
    ``extra_summary``: more summary keys (calibration, maintenance, mismatch status);
    ``live_session``/``keep_live_steps``: the live session the print ends, closed in the
    same transaction (:meth:`ajtwin.store.registry.Registry.save_print`);
    ``long_run_history``: the detectors' long-run statistics for the machine's next print.
    """
    summary = print_summary(
        end[0],
        end[1],
        arrays["nis"],
        arrays["reinitialised"],
        len(events),
        len(arrays["theta_history_time_s"]),
        started_from,
        status,
        status_reason,
    )
    summary.update(extra_summary or {})
    meta = {k: v for k, v in record.meta.items() if k != "scenario_config"}
    print_id = registry.save_print(
        machine,
        content_hash=digest,
        source=source,
        meta=meta,
        summary=summary,
        n_samples=len(record),
        duration_s=float(record.duration_s + 1.0),
        start_mean=start[0],
        start_cov=start[1],
        end_mean=end[0],
        end_cov=end[1],
        theta_before=theta_before,
        theta_after=theta_after,
        arrays=arrays,
        anomalies=events,
        expected_last_seq=expected_last_seq,
        status=status,
        status_reason=status_reason,
        live_session=live_session,
        keep_live_steps=keep_live_steps,
        long_run_history=long_run_history,
    )
    return print_id, summary


def carried_long_run_history(registry, machine: str, chain=None) -> dict | None:
    """The detectors' long-run noise statistics the machine's next print starts with.

    From its newest commissioning when that came after its last print (the print starts
    where commissioning left the machine, :func:`ajtwin.store.calibration.machine_start`),
    else from the newest print in the chain that stored them; None for a new machine (the
    detectors then start at scale 1 and learn it from the print, as before issue 12).
    Without it a CUSUM meets a wandering gauge in the first minutes of every print with
    no scale for it (docs/anomalies.md).
    """
    from ajtwin.store.calibration import active_calibration
    from ajtwin.store.chain import chain_start

    chain = chain if chain is not None else chain_start(registry, machine)
    latest = 0 if chain.latest_seq is None else chain.latest_seq
    active = active_calibration(registry, machine)
    if active is not None and active["after_print_seq"] >= latest and active.get("long_run"):
        return active["long_run"]
    stored = registry.long_run_history(machine)
    return None if stored is None else stored[1]


def ingest_record(
    registry,
    machine: str,
    record,
    *,
    source: str = "",
    progress=None,
    twin_overrides: dict | None = None,
    detector_settings=None,
):
    """Run the machine's twin over one finished print and store the result.

    Hash the print (duplicate → stop before any work), start from the machine's chain
    (:func:`ajtwin.store.chain.chain_start`: the newest good print's end state and θ; the
    initial-state fit for its first print), run the twin (EKF + EM, :meth:`Twin.run`) and
    the detectors (:func:`~ajtwin.apps.anomaly.detect_run`, the live detectors over the
    arrays), judge the run (:func:`ajtwin.store.chain.judge_run`) and store everything in
    one transaction.

    Parameters
    ----------
    registry : Registry
    machine : str
        A registered machine name.
    record : PrintRecord
        The print (display units; NaN = not measured).
    source : str
        Where the print came from (file path), stored for the history.
    progress : callable(int), optional
        Steps done, for a progress bar.
    twin_overrides : dict, optional
        :class:`~ajtwin.estimation.twin.TwinConfig` overrides.

    Returns
    -------
    IngestResult (``duplicate=True`` and the existing print when it was ingested before).
    """
    import time

    from ajtwin.apps.anomaly import detect_run
    from ajtwin.store.chain import chain_start, judge_run
    from ajtwin.store.ingest import IngestResult
    from ajtwin.store.registry import RegistryError, record_hash

    t0 = time.perf_counter()
    digest = record_hash(record)
    existing = registry.find_print(machine, digest)
    if existing is not None:
        return IngestResult(
            machine,
            existing["id"],
            existing["seq"],
            True,
            digest,
            existing["n_samples"],
            summary=existing["summary"],
            seconds=time.perf_counter() - t0,
        )
    from ajtwin.apps.mismatch import assess_run, data_share, determined_states, relabel_events
    from ajtwin.store.calibration import machine_start

    chain = chain_start(registry, machine)
    # the machine's calibration, commissioning start and maintenance (SPEC §11)
    begin = machine_start(registry, machine, chain, twin_overrides)
    twin = Twin.default(**begin["twin_kwargs"])
    start, expected = begin["start"], chain.latest_seq
    twin.theta = begin["theta"]
    theta_before = twin.theta.copy()
    run = twin.run(record, start=start, progress=progress)
    status, status_reason = judge_run(run)
    detection = detect_run(
        run, record, detector_settings, carried_long_run_history(registry, machine, chain)
    )
    # a model that does not fit the machine is reported as such, never as a fault
    mismatch = assess_run(run, record)
    detection.events = relabel_events(detection.events, mismatch)

    f = run.filtered
    hist = run.theta_history
    arrays = {
        "time_s": run.time_s,
        "means": run.means,
        "stds": run.stds,
        "covariances": np.asarray(f.covariances),
        "predicted_means": np.asarray(f.predicted_means),
        "predicted_outputs": np.asarray(f.predicted_outputs),
        "innovation_variances": np.asarray(f.innovation_variances),
        "measurements": record.outputs,
        "inputs": record.inputs,
        "nis": np.asarray(f.nis),
        "n_measured": np.asarray(f.n_measured),
        "reinitialised": np.asarray(f.reinitialised),
        "theta_per_step": run.theta_per_step,
        "theta_history_time_s": hist["time_s"].to_numpy(float),
        "theta_history": hist[[c for c in hist.columns if c.startswith("theta_")]].to_numpy(float),
    }
    try:
        print_id, summary = save_print(
            registry,
            machine,
            record,
            digest=digest,
            source=source,
            arrays=arrays,
            events=detection.events,
            start=(run.start_mean, run.start_cov),
            end=(run.end_mean, run.end_cov),
            theta_before=theta_before,
            theta_after=twin.theta,
            expected_last_seq=expected,
            started_from=begin["started_from"],
            status=status,
            status_reason=status_reason,
            extra_summary={
                "calibration_id": begin["calibration_id"],
                "maintenance": begin["maintenance"],
                "mismatch": mismatch.to_dict(),
                # which states this print's data determined (ΔR_T: the prior's band)
                "data_share": determined_states(data_share(run.filtered)),
            },
            long_run_history=detection.long_run_history,
        )
    except RegistryError:
        # a concurrent ingest of the same print may have won the race
        existing = registry.find_print(machine, digest)
        if existing is None:
            raise
        return IngestResult(
            machine, existing["id"], existing["seq"], True, digest, existing["n_samples"]
        )
    seq = registry.get_print(print_id)["seq"]
    return IngestResult(
        machine,
        print_id,
        seq,
        False,
        digest,
        len(record),
        events=detection.events,
        summary=summary,
        seconds=time.perf_counter() - t0,
        run=run,
        detection=detection,
    )


def ingest_file(
    registry,
    machine: str,
    path,
    *,
    video=None,
    um_per_px=None,
    progress=None,
    video_progress: bool = True,
    aliases=None,
    dialect=None,
):
    """Read a print file (and optionally its video) and :func:`ingest_record` it.

    ``aliases``, ``dialect``: as :func:`ajtwin.io.records.read_record`.
    """
    from pathlib import Path

    from ajtwin.io.records import read_record
    from ajtwin.store.ingest import join_video

    path = Path(path)
    record = read_record(path, aliases=aliases, dialect=dialect)
    source = str(path)
    if video is not None:
        if um_per_px is None:
            raise ValueError("--video needs --um-per-px (the camera's pixel size on the substrate)")
        record, *_ = join_video(record, video, um_per_px, progress=video_progress)
        source += f" + {video}"
    return ingest_record(registry, machine, record, source=source, progress=progress)


# --------------------------------------------------------------------------- #
# Many machines, the registry log, subscribers
# --------------------------------------------------------------------------- #


@dataclass
class _Session:
    stream: TwinStream
    session_id: int | None
    expected_last_seq: int | None
    started_from: str
    source: str
    unsaved: list
    unsaved_events: list
    last_flush: float


class LiveEngine:
    """Live twins of many machines in one process: samples in, messages out.

    Each machine has a :class:`TwinStream`; ordinary steps of several machines that
    arrive together are run as one vmapped :func:`ekf_step` (:meth:`feed_many`). With a
    registry, every committed step, its sample and the alarms are written to the live
    log as they go (:class:`ajtwin.store.live_log.LiveLog`, a transaction every
    ``commit_every_s`` seconds), a restarted process resumes each machine's open session
    by replaying its stored samples, and :meth:`close` stores the finished print as an
    ordinary registry print (the next print starts from its end state).

    Subscribers (:meth:`subscribe`, :meth:`queue`) receive every message as a plain dict
    (see the module docstring).

    Parameters
    ----------
    registry : Registry, optional
        Where machines, live sessions and finished prints are kept (None: memory only).
    twin_overrides : dict, optional
        TwinConfig fields for every machine's twin.
    detector_settings : DetectorSettings, optional
    asynchronous : bool
        EM in worker threads (live) or inline (tests, replays).
    em_workers : int
        Threads for EM (shared by all machines).
    commit_every_s : float
        Longest time committed steps wait before they are written (0: every step).
    keep_live_steps : bool
        Keep a session's per-step rows (samples and published float64 states) after its
        print is stored (an audit log, ≈ 9 MB per print-hour until ``machine compact``).
        By default they are dropped in the transaction that stores the print, which holds
        the samples exactly and the states by the storage policy (≈ 0.4 MB per
        print-hour); they exist only while the session is open, to resume it.
    """

    def __init__(
        self,
        registry=None,
        *,
        twin_overrides: dict | None = None,
        detector_settings: DetectorSettings | None = None,
        asynchronous: bool = True,
        em_workers: int = 1,
        commit_every_s: float = 1.0,
        keep_live_steps: bool = False,
    ):
        self.registry = registry
        self.keep_live_steps = bool(keep_live_steps)
        self.log = None
        if registry is not None:
            from ajtwin.store.live_log import LiveLog

            self.log = LiveLog(registry.path)
        self.twin_overrides = dict(twin_overrides or {})
        self.detector_settings = detector_settings
        self.asynchronous = asynchronous
        self.commit_every_s = float(commit_every_s)
        self._executor = ThreadPoolExecutor(max(1, int(em_workers)), thread_name_prefix="em")
        self.sessions: dict[str, _Session] = {}
        self._subscribers: list = []

    def warm_up(self, n_machines: int = 1) -> None:
        """Compile the step functions (single and batched) before the first real sample."""
        twin = Twin.default(**self.twin_overrides)
        u = np.array([375.0, 23.0, 50.0])
        y = np.array(twin.model.outputs(np.array([3.5, 1.0, 0.0, 0.03, 1e-7]), u))
        inputs, outputs = np.tile(u, (10, 1)), np.tile(y, (10, 1))
        fit = twin.initial_state(inputs, outputs)
        stream = TwinStream(
            "warm-up",
            twin,
            (fit.mean, fit.covariance),
            self.detector_settings,
            asynchronous=False,
        )
        for k in range(3):
            stream.feed(Sample(float(k), u, y))
        stream._restart_chunk(2, stream.theta)
        if n_machines > 1:
            plain = []
            for i in range(n_machines):
                s = TwinStream(
                    f"w{i}",
                    twin,
                    (fit.mean, fit.covariance),
                    self.detector_settings,
                    asynchronous=False,
                )
                s.feed(Sample(0.0, u, y))
                plain.append((s, s.take_plain(Sample(1.0, u, y))))
            self._step_batched(plain)

    # ------------------------------------------------------------------ #
    def subscribe(self, callback) -> callable:
        """Call ``callback(message)`` for every message; returns a function that unsubscribes."""
        self._subscribers.append(callback)
        return lambda: self._subscribers.remove(callback)

    def queue(self, maxsize: int = 0, loop=None):
        """An asyncio.Queue that receives every message (thread-safe put into ``loop``)."""
        import asyncio

        loop = loop or asyncio.get_event_loop()
        q: asyncio.Queue = asyncio.Queue(maxsize)

        def put(message):
            def put_now():
                if q.full():  # a slow subscriber loses the oldest, never blocks the twin
                    q.get_nowait()
                q.put_nowait(message)

            loop.call_soon_threadsafe(put_now)

        self.subscribe(put)
        return q

    def publish_link(self, machines, link: dict) -> None:
        """Tell subscribers the state of the link that feeds ``machines`` (module docstring)."""
        self._publish([{"machine": name, "link": dict(link)} for name in machines])

    def _publish(self, messages: list[dict]) -> None:
        for message in messages:
            for callback in list(self._subscribers):
                try:
                    callback(message)
                except Exception:  # a broken subscriber must not stop the twin
                    log.exception("subscriber %r failed", callback)

    # ------------------------------------------------------------------ #
    def open(self, machine: str, source: str = "live") -> TwinStream:
        """The machine's stream: its open live session resumed, or a new one."""
        if machine in self.sessions:
            return self.sessions[machine].stream
        start, theta, expected, started_from, session_id = None, None, None, "initial fit", None
        resumed = None
        twin_kwargs = self.twin_overrides
        long_run = None
        if self.registry is not None:
            from ajtwin.store.calibration import machine_start
            from ajtwin.store.chain import chain_start

            try:
                self.registry.machine(machine)
            except Exception:
                self.registry.add_machine(machine, notes="added by ajtwin live")
                log.info("machine %r added to the registry", machine)
            resumed = self.log.open_session_of(machine)
            # the machine's calibration, commissioning start and maintenance (SPEC §11)
            chain = chain_start(self.registry, machine)
            begin = machine_start(self.registry, machine, chain, self.twin_overrides)
            twin_kwargs = begin["twin_kwargs"]
            long_run = carried_long_run_history(self.registry, machine, chain)
            if resumed is not None:
                start, theta = resumed["start"], resumed["theta_before"]
                expected, session_id = resumed["expected_last_seq"], resumed["id"]
                started_from = "initial fit" if expected is None else f"print {expected}"
            else:
                start, theta, expected = begin["start"], begin["theta"], chain.latest_seq
                started_from = begin["started_from"]
                session_id = self.log.open_session(
                    machine,
                    source=source,
                    start=start,
                    theta=np.zeros(5) if theta is None else theta,
                    expected_last_seq=expected,
                )
        stream = TwinStream.new(
            machine,
            start=start,
            theta=theta,
            twin_overrides=twin_kwargs,
            detector_settings=self.detector_settings,
            asynchronous=False,
            executor=self._executor,
            long_run_history=long_run,
        )
        if resumed is not None:
            t, u, y = self.log.samples(session_id)
            for k in range(len(t)):
                stream.feed(Sample(t[k], u[k], y[k]))
            log.info(
                "%s: resumed live session %d at step %d (t = %s s)",
                machine,
                session_id,
                stream.n_received,
                None if not len(t) else f"{t[-1]:g}",
            )
        stream.asynchronous = self.asynchronous
        self.sessions[machine] = _Session(
            stream, session_id, expected, started_from, source, [], [], time.monotonic()
        )
        return stream

    def feed(self, machine: str, sample: Sample) -> list[dict]:
        """One sample of one machine (opens the machine on first use)."""
        return self.feed_many([(machine, sample)])

    def feed_many(self, items) -> list[dict]:
        """Samples of several machines [(machine, Sample)]; ordinary steps run batched."""
        messages: list[dict] = []
        plain = []
        for machine, sample in items:
            stream = self.open(machine)
            taken = stream.take_plain(sample)
            if taken is None:
                messages += stream.feed(sample)
            else:
                plain.append((stream, taken))
        if len(plain) == 1:
            stream, sample = plain[0]
            messages.append(stream._commit(sample))
        elif plain:
            messages += self._step_batched(plain)
        messages += self.poll()
        self._record(messages)
        self._publish(messages)
        return messages

    def _step_batched(self, plain) -> list[dict]:
        twin = plain[0][0].twin
        carries = EKFCarry(*[jnp.stack(parts) for parts in zip(*[s.carry for s, _ in plain])])
        carries, steps = _step_many(
            twin.spec,
            carries,
            np.array([s.model_input(x.inputs)[0] for s, x in plain]),
            np.array([x.outputs for _, x in plain]),
            np.array([s.theta for s, _ in plain]),
            *plain[0][0]._constants(),
            functions=twin.functions,
        )
        steps = jax.device_get(steps)
        out = []
        for i, (stream, sample) in enumerate(plain):
            carry = EKFCarry(*[part[i] for part in carries])
            step = type(steps)(*[part[i] for part in steps])
            out.append(stream._commit(sample, step, carry))
        return out

    def poll(self) -> list[dict]:
        """Messages from EM results that landed (replayed held samples), all machines."""
        out = []
        for session in self.sessions.values():
            out += session.stream.poll()
        return out

    def poll_and_publish(self) -> list[dict]:
        messages = self.poll()
        self._record(messages)
        self._publish(messages)
        return messages

    # ------------------------------------------------------------------ #
    def _record(self, messages: list[dict]) -> None:
        if self.log is None:
            return
        now = time.monotonic()
        for m in messages:
            session = self.sessions.get(m.get("machine"))
            if session is None or m.get("provisional") or "step" not in m:
                continue
            u = np.array(list(m["inputs"].values()), dtype=float)
            y = np.array(list(m["measured_outputs"].values()), dtype=float)
            session.unsaved.append((m["step"], m["time_s"], u, y, m))
            session.unsaved_events += m.get("events", [])
        for session in self.sessions.values():
            if session.unsaved and now - session.last_flush >= self.commit_every_s:
                self._flush(session)

    def _flush(self, session: _Session) -> None:
        if self.log is None or session.session_id is None:
            return
        self.log.append(session.session_id, session.unsaved, session.unsaved_events)
        session.unsaved, session.unsaved_events = [], []
        session.last_flush = time.monotonic()

    def flush(self) -> None:
        """Write every committed step not yet stored."""
        for session in self.sessions.values():
            self._flush(session)

    def close(self, machine: str) -> int | None:
        """End of the machine's print: finish the twin, store the print; its registry id."""
        import pandas as pd

        from ajtwin.io.records import PrintRecord
        from ajtwin.store.registry import record_hash

        session = self.sessions.pop(machine)
        stream = session.stream
        messages = stream.finish()
        self._record_into(session, messages)
        self._flush(session)
        self._publish(messages)
        if self.registry is None or session.session_id is None:
            return None
        print_id = None
        arrays = stream.arrays()
        if len(arrays["time_s"]) >= 2:
            from types import SimpleNamespace

            from ajtwin.store.chain import judge_run

            status, reason = judge_run(
                SimpleNamespace(
                    means=arrays["means"],
                    time_s=arrays["time_s"],
                    start_mean=stream.start_mean,
                    end_mean=arrays["means"][-1],
                    end_cov=arrays["covariances"][-1],
                )
            )
            data = {"time_s": arrays["time_s"]}
            data.update({c: arrays["inputs"][:, i] for i, c in enumerate(INPUT_COLUMNS)})
            data.update({c: arrays["measurements"][:, i] for i, c in enumerate(OUTPUT_COLUMNS)})
            record = PrintRecord(
                pd.DataFrame(data),
                {
                    "machine_id": machine,
                    "source": session.source,
                    "live_session": session.session_id,
                },
            )
            print_id, _ = save_print(
                self.registry,
                machine,
                record,
                digest=record_hash(record),
                source=f"live session {session.session_id} ({session.source})",
                arrays=arrays,
                events=list(stream.detector.events),
                start=(stream.start_mean, stream.start_cov),
                end=(arrays["means"][-1], arrays["covariances"][-1]),
                theta_before=stream.theta_before,
                theta_after=stream.theta,
                expected_last_seq=session.expected_last_seq,
                started_from=session.started_from,
                status=status,
                status_reason=reason,
                live_session=session.session_id,  # closed (and thinned) with the print
                keep_live_steps=self.keep_live_steps,
                long_run_history=stream.detector.long_run_history(),
            )
        else:  # nothing stored: the session's rows are all there is of it
            self.log.close_session(session.session_id, print_id)
        return print_id

    def _record_into(self, session: _Session, messages: list[dict]) -> None:
        for m in messages:
            if "step" in m and not m.get("provisional"):
                u = np.array(list(m["inputs"].values()), dtype=float)
                y = np.array(list(m["measured_outputs"].values()), dtype=float)
                session.unsaved.append((m["step"], m["time_s"], u, y, m))
            session.unsaved_events += m.get("events", [])

    def shutdown(self) -> None:
        """Write what is committed and stop the EM workers (sessions stay open: resumable)."""
        self.flush()
        self._executor.shutdown(wait=False, cancel_futures=True)
