"""The streaming twin: one 1 Hz sample in → state ± σ, predicted outputs, NIS, alarms out.

:class:`TwinStream` keeps one machine's twin in step with its data, a sample at a time,
with the same math as the batch :meth:`ajtwin.estimation.Twin.run` and
:func:`ajtwin.apps.detection.batch.detect_anomalies`: the EKF step is
:func:`ajtwin.estimation.filters.ekf_step` (the batch ``lax.scan``'s body plus units), the
detectors are :class:`ajtwin.apps.detection.streaming.AnomalyDetector` (which the batch runs over
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

A job print: measurements at their print time
----------------------------------------------
Opened with a :class:`~ajtwin.estimation.print_time.PrintContext`, the stream puts every
row (its ``shutter_open``, ``platen_speed_mm_s``, ``printed_at_s``) through the batch
twin's delay line (:class:`~ajtwin.estimation.print_time.PrintTimeBins`): a camera
measurement is filed at the step of its print time, and a step is *final* H rows after
its own (H the horizon). Only final steps go on as above — committed, stored, given to
the detectors and to EM — so they are the batch twin's steps, and the detectors see a
step H s after it was printed (the alarm delay grows by H). The state *now* is published
as a provisional message: the filter rolled back to the last committed step and re-run
over the steps not yet final with what has been filed so far
(docs/explanation/out-of-sequence-camera.md).

Each committed (and provisional) step becomes a plain dict, a *message*
(:mod:`ajtwin.engine.fleet` lists its keys).

Examples
--------
>>> from ajtwin.simulation import simulate                      # doctest: +SKIP
>>> stream = TwinStream.new("aj300-1", asynchronous=False)       # doctest: +SKIP
>>> rec = simulate("exp1", seed=1, duration_min=2)               # doctest: +SKIP
>>> for t, u, y in zip(rec.time_s, rec.inputs, rec.outputs):    # doctest: +SKIP
...     messages = stream.feed(Sample(t, u, y))
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.apps.detection.settings import CUSUM_CHANNELS, DetectorSettings
from ajtwin.apps.detection.steplog import StepLog
from ajtwin.apps.detection.streaming import AnomalyDetector
from ajtwin.engine.samples import MAX_GAP_S, Sample
from ajtwin.estimation.em import run_em
from ajtwin.estimation.filters import EKFCarry, EKFStepOutput, ekf, ekf_init, ekf_step
from ajtwin.estimation.print_time import PrintContext
from ajtwin.estimation.record_checks import observed_states
from ajtwin.estimation.twin import Twin, em_due, em_early_steps, predict
from ajtwin.model import OUTPUT_NAMES, STATE_NAMES
from ajtwin.model.droplet_dynamics import model_input, next_response
from ajtwin.model.names import INPUT_NAMES

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

#: the batch filter for the provisional re-run of a job print's steps not final yet, as a
#: plain jit: one call a row, where the disk-cached wrapper's per-call bookkeeping would
#: cost more than the steps themselves
_rerun = jax.jit(ekf.__wrapped__, static_argnames=("functions",))


def _on_host(step):
    """A step's results as NumPy arrays that own their data. ``jax.device_get`` on the CPU
    gives views of the device buffers, and a kept view keeps its buffer (~1.7 kB each, ten
    times the numbers): the committed steps a stream keeps held ~17 kB a step this way."""
    return type(step)(*(np.array(part) for part in jax.device_get(step)))


#: committed steps a stream keeps beyond its EM window and period: the part of the print a
#: live engine has not yet written to the registry (:data:`ajtwin.engine.parts.PART_STEPS`)
UNWRITTEN_STEPS = 3600


class _History:
    """Per-step committed results of the last ``keep`` steps (display units), addressed by
    step number (:class:`~ajtwin.apps.detection.steplog.StepLog`)."""

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
        "line_factors",  # a job step's (F_w, F_o, v_w, v_o); None without a job
    )

    def __init__(self, keep: int | None = None):
        for name in self.FIELDS:
            setattr(self, name, StepLog(keep))

    def __len__(self):
        return len(self.time_s)

    def array(self, name, start: int | None = None, stop: int | None = None) -> np.ndarray:
        """Steps [start, stop) of a field as an array (default: every step kept)."""
        log = getattr(self, name)
        start = log.first if start is None else start
        return np.asarray(log[start:stop], dtype=float)


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
    print_context : PrintContext, optional
        A job print: its horizon, camera and program (module docstring); None: rows are
        final as they come.
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
        print_context: PrintContext | None = None,
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
        # the EM window (and the restart step before it) and what a live engine still writes
        keep = int(self.config.window_s) + int(self.config.every_s) + UNWRITTEN_STEPS
        self.history = _History(keep)
        self.theta_history: list[dict] = []
        self.carry: EKFCarry | None = None  # committed carry for the next step
        self.n_received = 0  # samples on the grid so far (committed + pending + waiting)
        self.last_time: float | None = None
        self.last_inputs: np.ndarray | None = None
        self._waiting: list[Sample] = []  # before the initial fit
        self._pending: list[Sample] = []  # arrived while EM runs
        # held samples after EM's result, committed REPLAY_STEPS per poll (then the new ones)
        self._replay: deque[Sample] = deque()
        self._replaying = False
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
        # variant that follows the inputs; the batch twin's Twin.model_inputs, one sample
        # at a time)
        self._dynamics = twin.droplet_dynamics if twin.config.transition != "paper" else None
        self._response: float | None = None
        # a job print: the delay line in front of the committed steps, and the provisional
        # re-run over the steps not yet final (predicted mean and covariance before each)
        self.print_context = print_context
        self._bins = None if print_context is None else print_context.bins(twin.speed_law)
        self._tail_priors: dict[int, tuple] = {}
        self._tail_key = None
        # the transition's input and r after it of each step not final yet (kept: a step's
        # inputs never change), and the end of that run of steps
        self._tail_inputs: dict[int, tuple] = {}
        self._tail_inputs_end = 0
        self._restarts = 0  # chunk restarts so far: a kept provisional re-run is stale after one
        self._tail_start: EKFCarry | None = None  # provisional start before the filter's own
        #: a job print's state now: (time [s], mean (5,), covariance (5, 5)) of the newest
        #: provisional message, display units (None: none yet); what a controller plans from
        self.provisional: tuple | None = None

    def model_input(self, inputs, response: float | None = None):
        """(the transition's input for a committed step with ``inputs``, r after it);
        ``response`` default: the committed r."""
        r = self._response if response is None else response
        if self._dynamics is None:
            return np.asarray(inputs, dtype=float), None
        return model_input(inputs, r, self._dynamics, self.twin.spec.dt)

    @property
    def camera_counts(self) -> dict:
        """A job print's filing so far: frames filed, dropped by reason, the horizon ({})."""
        if self._bins is None:
            return {}
        return {**self._bins.counts, "horizon_s": self._bins.horizon_s}

    @property
    def n_pending(self) -> int:
        """Rows received whose step is not final yet (0 without a job)."""
        return 0 if self._bins is None else self._bins.n_pending

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
        """Steps committed so far (stepped with the θ in force, stored, given to the detectors)."""
        return len(self.history)

    @property
    def em_running(self) -> bool:
        """Whether an EM update runs in a worker thread now."""
        return self._em_future is not None

    def feed(self, sample: Sample, provisional: bool = True) -> list[dict]:
        """Take one sample; returns the messages it produced (committed and provisional).

        ``provisional=False``: a job print's provisional re-run is left for a later
        :meth:`refresh_provisional` (a controller that plans once per period needs the
        state at the period's end only; the re-run then starts at the oldest step changed
        since the last one, so the result is the same as re-running after every sample).
        """
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
            grid.append(dataclasses.replace(sample, time_s=self.last_time + n))
        for s in grid:
            out += self._accept(s)
        if provisional and self._bins is not None and grid:
            out += self._provisional_now()
        return out

    def refresh_provisional(self) -> list[dict]:
        """A job print's provisional message of the newest row now (:attr:`provisional`
        updated); [] when the print has no job or no row yet."""
        if self._bins is None or self.last_time is None:
            return []
        return self._provisional_now()

    def take_plain(self, sample: Sample) -> Sample | None:
        """If ``sample`` is an ordinary next step (no gap, boundary, EM or start), book it
        and return it for a batched step (:class:`LiveEngine`); else None, nothing changed."""
        c = self.config
        k = self.n_committed
        if (
            self.carry is None
            or self._bins is not None
            or self._em_future is not None
            or self._replay
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
        sample = dataclasses.replace(sample, time_s=float(sample.time_s), inputs=u, outputs=y)
        self.last_time = sample.time_s
        self.last_inputs = u
        self.n_received += 1
        if self._bins is None:
            return self._accept_final(sample)
        out = []
        for step in self._bins.add(
            sample.time_s,
            u,
            y,
            np.nan if sample.shutter_open is None else sample.shutter_open,
            np.nan if sample.platen_speed_mm_s is None else sample.platen_speed_mm_s,
            np.nan if sample.printed_at_s is None else sample.printed_at_s,
        ):
            out += self._accept_final(
                Sample(step.time_s, step.inputs, step.outputs, line=step.line)
            )
        return out

    def _accept_final(self, sample: Sample) -> list[dict]:
        """A final step (every row without a job): the initial fit, then the filter."""
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
            line = None if self._bins is None else np.array([s.line for s in waiting])
            self.initial = self.twin.initial_state(inputs, outputs, line)
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
        if self._replay and not self._replaying:
            self._replay.append(sample)  # after the held samples still to be committed
            return []
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

    # ------------------------------------------------------------------ #
    #: steps per call of the provisional re-run (one compiled shape of the batch filter)
    TAIL_BLOCK = 64

    def _provisional_now(self) -> list[dict]:
        """A job print's state now: the filter re-run from the last committed step over the
        steps not final yet, with what has been filed into them so far (module docstring).

        The re-run starts at the oldest step that changed since the last one (a measurement
        filed there, or a new row); the predictions before the steps after it are kept from
        the last re-run while θ and the committed head are those it ran from. Published as a
        provisional message of the newest row: not stored, not given to the detectors.
        """
        bins = self._bins
        changed = bins.take_changed()
        if bins.n_pending == 0:
            return []
        first, last = bins.first_open, bins.n_rows - 1
        head = self._spec_carry if self._em_future is not None else self.carry
        if head is None and self.n_committed == 0 and not self._pending and not self._replay:
            head = self._provisional_start(changed)
        if head is None:
            return []
        key = (self.theta.tobytes(), len(self.theta_history), self._restarts)
        if key != self._tail_key:
            self._tail_priors, self._tail_key = {}, key
        start = first if changed is None else max(first, changed)
        if start not in self._tail_priors or start == first:
            s = self.twin.spec.scaling.state
            start = first
            self._tail_priors[first] = (
                np.asarray(head.predicted_mean) * s,
                np.asarray(head.predicted_cov) * np.outer(s, s),
            )
        for j in [j for j in self._tail_priors if j < first]:
            del self._tail_priors[j]
        pending = bins.pending()[start - first :]
        inputs = self._tail_model_inputs(pending, start - first)
        result = None
        for b in range(0, len(pending), self.TAIL_BLOCK):
            block = pending[b : b + self.TAIL_BLOCK]
            result = self._tail_block(start + b, block, inputs[b : b + len(block)])
        # the newest step's row of the last block (FilterResult's fields are a step's, stacked)
        step = EKFStepOutput(*(np.asarray(field)[len(block) - 1] for field in result))
        newest = pending[-1]
        sample = Sample(newest.time_s, newest.inputs, newest.outputs, line=newest.line)
        self.provisional = (
            float(newest.time_s),
            np.asarray(step.mean),
            np.asarray(step.covariance),
        )
        return [self._message(last, sample, step, None, True)]

    def _provisional_start(self, changed: int | None) -> EKFCarry | None:
        """Before the filter starts (its first steps are not final yet: an inspection pass
        comes after the print), the start it would have now: the carried-over state, or the
        initial fit over the first steps as filed so far (kept until they change)."""
        if self.start is not None:
            return ekf_init(self.twin.spec, *self.start)
        n = int(self.config.initial_samples)
        if self._tail_start is None or (changed is not None and changed < n):
            steps = self._bins.pending()[:n]
            inputs = np.array([s.inputs for s in steps])
            outputs = np.array([s.outputs for s in steps])
            line = np.array([s.line for s in steps])
            try:
                fit = self.twin.initial_state(inputs, outputs, line)
            except ValueError:  # nothing to start from yet (no line output, no priors)
                return None
            self._tail_start = ekf_init(self.twin.spec, fit.mean, fit.covariance)
            self._tail_key = None
        return self._tail_start

    def _tail_block(self, j0: int, block: list, model_inputs: np.ndarray):
        """The batch filter over steps j0 … of ``block`` from the kept prediction of step j0,
        padded to one compiled length; keeps the predictions of the steps after them."""
        n, size = len(block), self.TAIL_BLOCK + 1
        prior_mean, prior_cov = self._tail_priors[j0]
        u = np.repeat(model_inputs[-1:], size, axis=0)
        u[:n] = model_inputs
        y = np.full((size, 5), np.nan)
        y[:n] = [step.outputs for step in block]
        line = np.ones((size, 4))
        line[:n] = [step.line for step in block]
        twin = self.twin
        result = _rerun(
            twin.spec,
            prior_mean,
            prior_cov,
            u,
            y,
            self.theta,
            twin.process_cov,
            twin.measurement_var,
            twin.config.gate_sigma,
            functions=twin.functions,
            line_factors=line,
        )
        means, covs = np.asarray(result.predicted_means), np.asarray(result.predicted_covariances)
        for i in range(1, n + 1):
            self._tail_priors[j0 + i] = (means[i], covs[i])
        return result

    def _tail_model_inputs(self, pending: list, skipped: int) -> np.ndarray:
        """The transition's inputs of the steps not final yet (the input response r carried
        on from the committed steps and those held while EM runs).

        A step's inputs never change once filed and the committed r follows the same
        sequence, so each step's (input, r after it) is computed once and kept until the
        step is final: a re-run costs the new steps only, not every step since the last
        final one (an inspection pass: the whole print).
        """
        if self._dynamics is None:
            return np.array([step.inputs for step in pending], dtype=float)
        first = self._bins.first_open
        steps = self._bins.pending()
        kept = self._tail_inputs
        if self._tail_inputs_end <= first:  # nothing kept that is not final yet
            kept.clear()
            end, response = first, self._response
            for held in [*self._pending, *self._replay]:  # in order, before the pending bins
                _, response = self.model_input(held.inputs, response)
        else:
            for j in [j for j in kept if j < first]:
                del kept[j]
            end = self._tail_inputs_end
            response = kept[end - 1][1]
        for j in range(end, first + len(steps)):
            kept[j] = self.model_input(steps[j - first].inputs, response)
            response = kept[j][1]
        self._tail_inputs_end = first + len(steps)
        return np.array([kept[j][0] for j in range(first + skipped, first + len(steps))])

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
        self._restarts += 1

    def _launch_em(self, pos: int):
        h = self.history
        c = self.config
        w0 = max(pos - int(c.window_s), 0)
        args = (
            self.twin.spec,
            np.asarray(h.predicted_means[w0]),
            np.asarray(h.predicted_covariances[w0]),
            h.array("model_inputs", w0, pos),
            h.array("measurements", w0, pos),
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
            line_factors=None if self._bins is None else h.array("line_factors", w0, pos),
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

    #: held samples committed per :meth:`poll` once EM's result is in (a burst of rows that
    #: arrived while EM ran is replayed in slices, so a live link's event loop keeps running)
    REPLAY_STEPS = 50

    def poll(self, wait: bool = False) -> list[dict]:
        """Apply a finished EM (``wait``: block until it is) and replay the samples held:
        :attr:`REPLAY_STEPS` of them per call, all with ``wait``. Samples that arrive while
        some are still to be replayed wait behind them."""
        future = self._em_future
        if future is not None and (wait or future.done()):
            self._apply_em(future.result())
        return self._drain(None if wait else self.REPLAY_STEPS)

    def _drain(self, limit: int | None) -> list[dict]:
        """Commit up to ``limit`` (None: all) held samples, oldest first."""
        out, n = [], 0
        was, self._replaying = self._replaying, True
        try:
            while self._replay and (limit is None or n < limit):
                out += self._advance(self._replay.popleft())
                n += 1
        finally:
            self._replaying = was
        return out

    def _apply_em(self, em) -> None:
        """EM's result in force from its boundary; the samples it held go first in line."""
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
        # held while EM ran: older than any still to be replayed
        self._replay.extendleft(reversed(self._pending))
        self._pending = []

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
            line=None if sample.line is None else np.asarray(sample.line, dtype=float),
        )
        return carry, _on_host(step)

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
        h.line_factors.append(sample.line)
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
        while self._em_future is not None or self._replay:  # an EM the replay started
            out += self.poll(wait=True)
        if self._bins is not None:  # the end of the print: every step left is final
            for step in self._bins.finish():
                final = Sample(step.time_s, step.inputs, step.outputs, line=step.line)
                out += self._accept_final(final)
        while self._em_future is not None:
            out += self.poll(wait=True)
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

    def arrays(self, since: int | None = None) -> dict[str, np.ndarray]:
        """The committed per-step results from step ``since`` on (default: the oldest step
        kept), named as the registry stores a print (a job print's with ``line_factors``, the
        (F_w, F_o, v_w, v_o) of each filed step). A stream keeps its last steps only (a long
        live print is written in parts as it goes, :class:`~ajtwin.engine.parts.
        PrintWriter`); a short print's are all kept."""
        h = self.history
        since = h.time_s.first if since is None else since

        def steps(name, *shape):
            return h.array(name, since).reshape(-1, *shape)

        means = steps("means", 5)
        covs = steps("covariances", 5, 5)
        hist = self.theta_history
        return {
            "time_s": h.array("time_s", since),
            "means": means,
            "stds": np.sqrt(np.maximum(np.diagonal(covs, 0, 1, 2), steps("prior_floor", 5))),
            "covariances": covs,
            "predicted_means": steps("predicted_means", 5),
            "predicted_outputs": steps("predicted_outputs", 5),
            "innovation_variances": steps("innovation_variances", 5),
            "measurements": steps("measurements", 5),
            "inputs": steps("inputs", 3),
            "nis": h.array("nis", since),
            "n_measured": h.array("n_measured", since),
            "reinitialised": np.asarray(h.reinitialised[since:], dtype=bool),
            "theta_per_step": steps("theta_per_step", 5),
            "theta_history_time_s": np.array([r["time_s"] for r in hist], dtype=float),
            "theta_history": np.array(
                [[r[f"theta_{n}"] for n in STATE_NAMES] for r in hist], dtype=float
            ).reshape(-1, 5),
            # a job print's filed steps carry their speed-law factors: the run can be re-made
            **(
                {}
                if self._bins is None
                else {"line_factors": h.array("line_factors", since).reshape(-1, 4)}
            ),
        }


def step_together(plain: list[tuple[TwinStream, Sample]]) -> list[dict]:
    """Ordinary steps of several streams that share the twin's functions, run as one
    vmapped EKF step (one stream: the single step); their committed messages.

    Parameters
    ----------
    plain : list of (TwinStream, Sample)
        Each stream with the sample :meth:`TwinStream.take_plain` accepted.
    """
    if len(plain) == 1:
        stream, sample = plain[0]
        return [stream._commit(sample)]
    if not plain:
        return []
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
    steps = _on_host(steps)
    out = []
    for i, (stream, sample) in enumerate(plain):
        carry = EKFCarry(*[part[i] for part in carries])
        step = type(steps)(*[np.array(part[i]) for part in steps])
        out.append(stream._commit(sample, step, carry))
    return out


def warm_up_streams(twin_overrides: dict, detector_settings, n_machines: int = 1) -> None:
    """Compile the step functions (single, chunk restart and, for several machines,
    batched) before the first real sample arrives.

    Parameters
    ----------
    twin_overrides : dict
        TwinConfig fields of the machines' twins.
    detector_settings : DetectorSettings or None
    n_machines : int
        Machines the process will follow (> 1 also compiles the batched step).
    """
    twin = Twin.default(**twin_overrides)
    u = np.array([375.0, 23.0, 50.0])
    y = np.array(twin.model.outputs(np.array([3.5, 1.0, 0.0, 0.03, 1e-7]), u))
    inputs, outputs = np.tile(u, (10, 1)), np.tile(y, (10, 1))
    fit = twin.initial_state(inputs, outputs)
    start = (fit.mean, fit.covariance)
    stream = TwinStream("warm-up", twin, start, detector_settings, asynchronous=False)
    for k in range(3):
        stream.feed(Sample(float(k), u, y))
    stream._restart_chunk(2, stream.theta)
    if n_machines > 1:
        plain = []
        for i in range(n_machines):
            s = TwinStream(f"w{i}", twin, start, detector_settings, asynchronous=False)
            s.feed(Sample(0.0, u, y))
            plain.append((s, s.take_plain(Sample(1.0, u, y))))
        step_together(plain)
