"""The twin's core: one machine's estimator fed a print a sample or a block at a time.

:class:`OnlineTwin` is the one implementation of running the twin over a print. The batch
:meth:`ajtwin.estimation.Twin.run` feeds it the whole print (or a record read from disk a
piece at a time), the live engine feeds it a sample at a time, the MPC plans from its
state; what comes out is the same steps, θ and EM history whichever way it was fed.

What it does, in order
----------------------
* **Rows in.** A row is one second of the machine's log: time, inputs u (3,), outputs y (5,
  NaN = not measured) and, on a job print, the job columns (shutter, platen speed, the
  print time τ of the camera's measurement). :meth:`OnlineTwin.feed` takes a block of
  rows on the 1 s grid; :meth:`OnlineTwin.feed_sample` takes one sample from the wire and
  puts it on the grid (a jump of n > 1 s inserts n − 1 missing rows: inputs held, outputs
  NaN; a duplicate is dropped, an older sample is logged and dropped; non-finite inputs
  make the row missing).
* **Final steps.** Without a job every row is a final step as it comes. On a job print the
  rows pass the delay line of :class:`~ajtwin.estimation.print_time.PrintTimeBins`: a camera
  measurement is filed at the step of its print time, and a step is final H rows after its
  own (H the camera horizon).
* **The start.** The carried-over state, or the initial fit over the first
  ``initial_samples`` final steps (the core waits for them).
* **Chunks and EM.** The filter (:func:`~ajtwin.estimation.filters.ekf_continue`) runs in
  chunks between boundaries k (multiples of ``every_s`` and the early EM steps
  ``early_em_s``): at a boundary it restarts from the prediction of step k − 1, and where
  EM is due (:func:`em_due`: k ≥ ``window_s`` or an early step) EM runs over the trailing
  window [max(k − window, 0), k) first; its θ and its re-filtered end state take effect
  from step k. Each block of steps committed between boundaries is a :class:`StepBlock`.
* **EM in the background** (an ``executor``, the live engine): steps that arrive while EM
  runs are filtered with the previous θ and given out as :class:`Provisional`, then
  committed with the new θ once EM lands (:attr:`OnlineTwin.REPLAY_STEPS` per
  :meth:`~OnlineTwin.poll`). Without an executor EM runs inline.
* **The state now on a job print.** :meth:`OnlineTwin.provisional_now` re-runs the filter
  from the last committed step over the steps not final yet, with what has been filed so
  far (docs/explanation/out-of-sequence-camera.md).

Math of a step: :mod:`ajtwin.estimation.filters`; of EM: :mod:`ajtwin.estimation.em`.

Examples
--------
>>> import numpy as np
>>> from ajtwin.estimation import Twin
>>> from ajtwin.estimation.online import OnlineTwin
>>> twin = Twin.default(em=False)
>>> u = np.array([375.0, 23.0, 50.0])
>>> y = np.asarray(twin.model.outputs(np.array([3.5, 1.0, 0.0, 0.0, 4.6e-7]), u))
>>> core = OnlineTwin(twin)
>>> blocks = core.feed(np.arange(12.0), np.tile(u, (12, 1)), np.tile(y, (12, 1)))
>>> core.n_committed, round(float(core.last_mean[0]), 1)
(12, 3.5)
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from concurrent.futures import Future
from typing import NamedTuple

import numpy as np

from ajtwin._aot import exported_jit
from ajtwin._jax import jax, jnp
from ajtwin.estimation.em import EMSettings, prefetch_em, run_em
from ajtwin.estimation.filters import (
    EKFCarry,
    FilterResult,
    ekf_continue,
    ekf_init,
    ekf_step,
)
from ajtwin.estimation.print_time import PrintContext
from ajtwin.estimation.samples import MAX_GAP_S, Sample
from ajtwin.model import STATE_NAMES

#: what happens to samples from the wire (gaps, duplicates, old samples) is the live log's
log = logging.getLogger("ajtwin.live")


# ---------------------------------------------------------------------- the EM schedule
def em_early_steps(config) -> tuple:
    """The early EM steps of ``config`` (``TwinConfig.early_em_s``), sorted; those at or
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
    the early steps (over the print so far)."""
    return (pos >= window and pos % every == 0) or pos in early


def first_em_update_time(config, time_s, window_from_s: float | None = None) -> float | None:
    """When the twin makes its first EM update over a print of times ``time_s`` (the time of
    the last step before that boundary; None: EM off or never due), known before the run:
    the first boundary where EM is due that has a step after it. ``window_from_s``: the
    first update whose window (the last ``window_s`` steps, or the print so far at an early
    step) begins at or after that time, i.e. whose θ no earlier step has shaped."""
    n = len(time_s)
    if not config.em or n == 0:
        return None
    every, window = int(config.every_s), int(config.window_s)
    if every < 1 or window < 2:
        return None  # the twin refuses such a config itself
    early = em_early_steps(config)
    pos = 0
    while pos < n:
        pos = next_em_boundary(pos, every, early)
        if pos < n and em_due(pos, every, window, early):
            start = max(pos - window, 0)
            if window_from_s is None or float(time_s[start]) >= window_from_s:
                return float(time_s[pos - 1])
    return None


# ---------------------------------------------------------------------- what comes out
@dataclasses.dataclass
class StepBlock:
    """Committed steps [first, first + m) of a print, display units.

    Attributes
    ----------
    first : int
        The first step's number (0 = the print's first step).
    time_s : array (m,)
    inputs : array (m, 3)
        u_k [mA, sccm, sccm].
    model_inputs : array (m, 3 or 4)
        The inputs as the transition reads them (with the input response r_k for a variant
        that follows the inputs).
    measurements : array (m, 5)
        What the filter used: the record's outputs, or on a job print the camera's filed at
        their print times.
    filtered : FilterResult
        The filter's results of these steps (NumPy arrays).
    theta : array (5,)
        θ in force over the block [1/s].
    seen : array (m, 5) of bool
        Some measured output at that second responds to the state.
    prior_floor : array (m, 5)
        The variance floor of states no data has constrained yet (zeros when every state was
        fitted from data).
    calibration_covariances : array (m, 5, 5) or None
        What the calibration's own uncertainty and φ_A's unknown level add (None: neither).
    line : array (m, 4) or None
        A job print's (F_w, F_o, v_w, v_o) per step.
    n_camera : array (m, 2) or None
        A job print's camera frames filed per step for L_w, L_o.
    """

    first: int
    time_s: np.ndarray
    inputs: np.ndarray
    model_inputs: np.ndarray
    measurements: np.ndarray
    filtered: FilterResult
    theta: np.ndarray
    seen: np.ndarray
    prior_floor: np.ndarray
    calibration_covariances: np.ndarray | None = None
    line: np.ndarray | None = None
    n_camera: np.ndarray | None = None
    #: θ per step (m, 5) where it is not one θ over the block (blocks joined into a print)
    thetas: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def stop(self) -> int:
        """The step after the block's last."""
        return self.first + len(self.time_s)

    @property
    def theta_per_step(self) -> np.ndarray:
        """θ in force at each step (m, 5)."""
        if self.thetas is not None:
            return self.thetas
        return np.tile(self.theta, (len(self), 1))

    def total_covariances(self) -> np.ndarray:
        """The covariances (m, 5, 5) the twin reports: the filter's, the calibration's share
        added, the never-seen states' floor on the diagonal."""
        covariances = np.asarray(self.filtered.covariances)
        if self.calibration_covariances is not None:
            covariances = covariances + self.calibration_covariances
        if self.prior_floor.any():
            covariances = covariances.copy()
            diagonal = np.einsum("tii->ti", covariances)
            np.maximum(diagonal, self.prior_floor, out=diagonal)
        return covariances

    @property
    def stds(self) -> np.ndarray:
        """State σ (m, 5) as the twin reports them (:meth:`total_covariances`)."""
        variances = np.diagonal(self.total_covariances(), 0, 1, 2)
        return np.sqrt(np.maximum(variances, 0.0))


class Provisional(NamedTuple):
    """A step given out before it is final (not stored, not given to the detectors): a step
    filtered with the previous θ while EM runs, or a job print's state now. ``block``: a
    one-step :class:`StepBlock` of it (its ``first`` the step's number)."""

    block: StepBlock


class _Rows(NamedTuple):
    """Final steps not committed yet (arrays of m rows)."""

    time_s: np.ndarray  # (m,)
    inputs: np.ndarray  # (m, 3)
    measurements: np.ndarray  # (m, 5)
    line: np.ndarray | None  # (m, 4)
    n_camera: np.ndarray | None  # (m, 2)

    def __len__(self):
        return len(self.time_s)

    def cut(self, n: int) -> tuple[_Rows, _Rows]:
        head = _Rows(*(None if a is None else a[:n] for a in self))
        tail = _Rows(*(None if a is None else a[n:] for a in self))
        return head, tail


def _join(parts: list[_Rows]) -> _Rows:
    if len(parts) == 1:
        return parts[0]
    return _Rows(
        *(None if parts[0][i] is None else np.concatenate([p[i] for p in parts]) for i in range(5))
    )


# ---------------------------------------------------------------------- the step functions
def _on_host(tree):
    """A result as NumPy arrays that own their data (a kept view of a device buffer keeps
    the whole buffer alive)."""
    return jax.tree_util.tree_map(lambda a: np.array(a), jax.device_get(tree))


#: one step (the live engine's ordinary sample): a plain jit, whose per-call cost is a
#: fraction of the disk-cached wrapper's
_step_one = jax.jit(ekf_step, static_argnames=("functions",))


def _batched(spec, carry, u, y, theta, process_cov, measurement_cov, gate, functions):
    return jax.vmap(
        lambda c, uu, yy, th: ekf_step(
            spec, c, uu, yy, th, process_cov, measurement_cov, gate, functions
        )
    )(carry, u, y, theta)


#: one step of several machines at once (:func:`step_together`)
_step_many = jax.jit(_batched, static_argnames=("functions",))

#: a block of a job print's steps not final yet (the provisional re-run), as a plain jit
_continue_plain = jax.jit(ekf_continue.__wrapped__, static_argnames=("functions",))


def predict(spec, mean, cov, u, theta, process_cov, functions):
    """One EKF prediction x̂_{k+1|k}, P_{k+1|k} in display units (a chunk's restart)."""
    s = spec.scaling.state

    def f_scaled(z):
        return functions.step(z * s, u, theta, spec.params, spec.dt) / s

    z = mean / s
    jac = jax.jacfwd(f_scaled)(z)
    p = jac @ (cov / jnp.outer(s, s)) @ jac.T
    return f_scaled(z) * s, p * jnp.outer(s, s) + process_cov


predict = exported_jit(
    predict, static_argnames=("functions",), constant_fields=(("spec", "params"),)
)


# ---------------------------------------------------------------------- the core
class OnlineTwin:
    """One machine's twin over one print, fed rows as they come (module docstring).

    Parameters
    ----------
    twin : Twin
        Model, tuning, calibration and the starting θ (``twin.theta``, updated as EM learns).
    start : (mean (5,), cov (5, 5)), optional
        Start state (the previous print's end, carried over); default: the initial fit.
    print_context : PrintContext, optional
        A job print: its horizon, camera and program; None: rows are final as they come.
    executor : concurrent.futures.Executor, optional
        Where EM runs (a worker thread: the live engine); None: inline.
    keep_steps : int
        Committed steps kept for :meth:`recent` beyond what EM needs.
    name : str
        The machine, for log lines.
    """

    #: held steps committed per :meth:`poll` once EM's result is in (a burst of rows that
    #: arrived while EM ran is committed in slices, so a live link's event loop keeps running)
    REPLAY_STEPS = 50
    #: steps per call of a job print's provisional re-run (one compiled shape)
    TAIL_BLOCK = 64

    def __init__(
        self,
        twin,
        start=None,
        *,
        print_context: PrintContext | None = None,
        executor=None,
        keep_steps: int = 0,
        name: str = "twin",
    ):
        c = twin.config
        self.name = name
        if c.em and (int(c.every_s) < 1 or int(c.window_s) < 2):
            raise ValueError("EM needs every_s >= 1 and window_s >= 2")
        self.twin = twin
        self.config = c
        self.executor = executor
        self._every, self._window = int(c.every_s), int(c.window_s)
        self._early = em_early_steps(c) if c.em else ()
        self.theta = np.asarray(twin.theta, dtype=float).copy()
        self.theta_before = self.theta.copy()
        self.theta_history: list[dict] = []
        self.start = None if start is None else tuple(np.asarray(a, dtype=float) for a in start)
        self.initial = None
        self.start_mean = self.start_cov = None
        self.print_context = print_context
        self._bins = None if print_context is None else print_context.bins(twin.speed_law)
        self._dynamics = twin.droplet_dynamics if c.transition != "paper" else None
        if self._dynamics is not None and not self._dynamics.follows_inputs:
            self._dynamics = None
        # the grid of samples (feed_sample)
        self.last_time: float | None = None
        self.last_inputs: np.ndarray | None = None
        self.n_received = 0
        self.dropped = {"duplicate": 0, "out_of_order": 0, "bad": 0, "far_future": 0}
        self.missing_inserted = 0
        # final steps
        self._waiting: list[_Rows] = []  # before the start
        self._held: deque[_Rows] = deque()  # final, not committed (EM running or replaying)
        self.n_committed = 0
        self.carry: EKFCarry | None = None
        self._response: float | None = None  # r before the next committed step
        self._window_blocks: deque[StepBlock] = deque()
        self._keep = self._window + self._every + 1 + int(keep_steps)
        # EM
        self._em_future: Future | None = None
        self._em_pos: int | None = None
        self._em_done: int | None = None  # boundary whose EM result is in force
        self._spec: tuple | None = None  # (carry, r) of the speculative steps while EM runs
        self._spec_steps = 0
        # what the data has seen, the never-seen states' floor, the calibration's share
        self._responds: np.ndarray | None = None  # (5 outputs, 5 states)
        self._never_seen = np.zeros(5, dtype=bool)
        self._floor_relative = np.zeros(5)
        self._calibration_carry: dict = {}
        self._device_constants = None
        self.unseen_counts = np.zeros(5, dtype=np.int64)
        # a job print's provisional re-run
        self._tail_priors: dict[int, tuple] = {}
        self._tail_key = None
        self._tail_inputs: dict[int, tuple] = {}
        self._tail_inputs_end = 0
        self._restarts = 0
        self._tail_start: EKFCarry | None = None
        #: a job print's state now: (time [s], mean (5,), covariance (5, 5)) of the newest
        #: provisional step, display units (None: none yet); what a controller plans from
        self.provisional: tuple | None = None

    # ------------------------------------------------------------------ state
    @property
    def em_running(self) -> bool:
        """Whether an EM update runs in the background now."""
        return self._em_future is not None

    @property
    def started(self) -> bool:
        """Whether the filter has its start (the initial fit is done or a start was given)."""
        return self.carry is not None

    @property
    def n_pending(self) -> int:
        """Rows received whose step is not final yet (0 without a job)."""
        return 0 if self._bins is None else self._bins.n_pending

    @property
    def camera_counts(self) -> dict:
        """A job print's filing so far: frames filed, dropped by reason, the horizon ({})."""
        if self._bins is None:
            return {}
        return {**self._bins.counts, "horizon_s": self._bins.horizon_s}

    @property
    def last_block(self) -> StepBlock | None:
        """The newest committed block (None before the first)."""
        return self._window_blocks[-1] if self._window_blocks else None

    @property
    def last_mean(self) -> np.ndarray | None:
        """The newest committed step's mean (5,)."""
        block = self.last_block
        return None if block is None else np.asarray(block.filtered.means[-1])

    @property
    def last_cov(self) -> np.ndarray | None:
        """The newest committed step's covariance (5, 5) (the filter's)."""
        block = self.last_block
        return None if block is None else np.asarray(block.filtered.covariances[-1])

    @property
    def last_time_committed(self) -> float | None:
        """The newest committed step's time [s]."""
        block = self.last_block
        return None if block is None else float(block.time_s[-1])

    def recent(self, name: str, n: int) -> np.ndarray:
        """The last ``n`` committed steps' ``name`` (a :class:`~ajtwin.estimation.filters.
        FilterResult` field, or ``time_s``, ``inputs``, ``model_inputs``, ``measurements``),
        oldest first; fewer while fewer are kept."""
        return self._window_array(name, max(self.n_committed - int(n), 0), self.n_committed)

    def response_after(self) -> float | None:
        """The droplet size's input response r after the last committed step (None: the
        transition does not follow the inputs, or nothing was committed)."""
        return self._response

    # ------------------------------------------------------------------ rows in
    def feed(self, time_s, inputs, outputs, job_columns=None, line=None) -> list:
        """Rows of the print on the 1 s grid, following those fed before; the committed
        :class:`StepBlock` and :class:`Provisional` steps they produced, in order.

        Parameters
        ----------
        time_s : array (m,)
        inputs : array (m, 3)
            Finite (a missing row holds the last inputs: :meth:`feed_sample`).
        outputs : array (m, 5)
            NaN where not measured.
        job_columns : (shutter_open, platen_speed_mm_s, printed_at_s), optional
            A job print's columns, arrays (m,) (NaN: unknown).
        line : array (m, 4), optional
            Rows already filed (a stored job print run again): each step's (F_w, F_o, v_w,
            v_o); the rows are final as they come.
        """
        time_s = np.asarray(time_s, dtype=float).reshape(-1)
        inputs = np.asarray(inputs, dtype=float).reshape(-1, 3)
        outputs = np.asarray(outputs, dtype=float).reshape(-1, 5)
        if not len(time_s):
            return []
        self.n_received += len(time_s)
        self.last_time, self.last_inputs = float(time_s[-1]), inputs[-1].copy()
        if self._bins is None or line is not None:
            line = None if line is None else np.asarray(line, dtype=float).reshape(-1, 4)
            return self._accept(_Rows(time_s, inputs, outputs, line, None))
        m = len(time_s)
        shutter, speed, printed = (np.full(m, np.nan),) * 3 if job_columns is None else job_columns
        steps = []
        for row in zip(time_s, inputs, outputs, shutter, speed, printed):
            steps += self._bins.add(*row)
        return self._accept(_filed_rows(steps))

    def feed_sample(self, sample: Sample) -> list:
        """One sample from the wire, put on the grid (module docstring); what it produced."""
        t = float(sample.time_s)
        if self.last_time is not None:
            # clamped before rounding: a time stamp far ahead must not become a huge int
            n = int(round(min(max(t - self.last_time, -1.0), MAX_GAP_S + 2.0)))
            if n <= 0:
                if n == 0:
                    self.dropped["duplicate"] += 1
                    log.debug("%s: duplicate sample at t = %g s dropped", self.name, t)
                else:
                    self.dropped["out_of_order"] += 1
                    log.warning(
                        "%s: sample at t = %g s is older than the last step (t = %g s); dropped",
                        self.name,
                        t,
                        self.last_time,
                    )
                return []
            if n - 1 > MAX_GAP_S:
                self.dropped["far_future"] += 1
                log.warning(
                    "%s: sample at t = %g s is %g s ahead of the last step (t = %g s), more "
                    "than %d s; dropped (clock jump?)",
                    self.name,
                    t,
                    t - self.last_time,
                    self.last_time,
                    MAX_GAP_S,
                )
                return []
            gap = n - 1
            if gap:
                log.info("%s: %d s gap before t = %g s; treated as missing data", self.name, gap, t)
                self.missing_inserted += gap
            sample = sample._replace(time_s=self.last_time + n)
        else:
            gap = 0
        out = self.poll()
        if gap:
            # the missing seconds in one block: inputs held, nothing measured
            times = self.last_time + np.arange(1.0, gap + 1.0)
            columns = None if self._bins is None else (np.full(gap, np.nan),) * 3
            out += self.feed(
                times, np.tile(self.last_inputs, (gap, 1)), np.full((gap, 5), np.nan), columns
            )
        u = None if sample.inputs is None else np.asarray(sample.inputs, dtype=float)
        y = np.asarray(sample.outputs, dtype=float)
        if u is None or not np.all(np.isfinite(u)):
            if self.last_inputs is None:
                log.warning(
                    "%s: sample at t = %g s has no valid inputs before the first valid "
                    "sample; dropped",
                    self.name,
                    sample.time_s,
                )
                self.dropped["bad"] += 1
                return out
            u, y = self.last_inputs.copy(), np.full(5, np.nan)
        columns = None
        if self._bins is not None:
            columns = tuple(
                np.array([np.nan if v is None else float(v)])
                for v in (sample.shutter_open, sample.platen_speed_mm_s, sample.printed_at_s)
            )
        out += self.feed(np.array([float(sample.time_s)]), u[None], y[None], columns)
        return out

    def finish(self) -> list:
        """The end of the print: every step left is final and committed (a running EM's
        result applied first); samples still waiting for the initial fit start the filter
        with what there is."""
        out = self.poll(wait=True)
        while self._em_future is not None or self._held:
            out += self.poll(wait=True)
        if self._bins is not None:
            out += self._accept(_filed_rows(self._bins.finish()))
            while self._em_future is not None or self._held:
                out += self.poll(wait=True)
        if self._waiting and self.carry is None:
            out += self._start_filter()
            while self._em_future is not None or self._held:
                out += self.poll(wait=True)
        return out

    def poll(self, wait: bool = False) -> list:
        """Apply a finished EM (``wait``: block until it is) and commit the steps held:
        :attr:`REPLAY_STEPS` of them per call, all with ``wait`` or without an executor."""
        future = self._em_future
        if future is not None and (wait or future.done()):
            self._apply_em(future.result())
        if self._em_future is not None:
            return []
        limit = None if (wait or self.executor is None) else self.REPLAY_STEPS
        return self._process(limit)

    # ------------------------------------------------------------------ final steps
    def _accept(self, rows: _Rows) -> list:
        if not len(rows):
            return []
        if self.carry is None:
            self._waiting.append(rows)
            n = sum(len(r) for r in self._waiting)
            if self.start is None and n < int(self.config.initial_samples):
                return []
            return self._start_filter()
        backlog = bool(self._held)
        self._held.append(rows)
        if self._em_future is not None:
            return self._speculative(rows)
        if backlog and self.executor is not None:
            return []  # behind the held steps still to be committed (poll)
        return self._process(None if self.executor is None else max(len(rows), 1))

    def _start_filter(self) -> list:
        waiting = _join(self._waiting)
        self._waiting = []
        if self.config.em:
            self._prefetch_em(waiting)
        if self.start is None:
            self.initial = self.twin.initial_state(
                waiting.inputs, waiting.measurements, waiting.line
            )
            mean, cov = self.initial.mean, self.initial.covariance
        else:
            mean, cov = self.start
        self.start_mean = np.asarray(mean, dtype=float).copy()
        self.start_cov = np.asarray(cov, dtype=float).copy()
        self._start_seen(waiting.inputs[0])
        self.carry = ekf_init(self.twin.spec, self.start_mean, self.start_cov)
        self._held.append(waiting)
        return self._process(None)

    def _start_seen(self, u0) -> None:
        """Which output sees which state (at the start state and the first step's inputs)
        and the prior's relative σ of the states the initial fit took from priors."""
        twin = self.twin
        self._responds = twin.output_responds(self.start_mean, u0)
        if self.initial is not None and self.initial.states_from_prior:
            self._never_seen = np.array(
                [n in self.initial.states_from_prior for n in STATE_NAMES], dtype=bool
            )
            for i in np.flatnonzero(self._never_seen):
                self._floor_relative[i] = np.sqrt(self.initial.covariance[i, i]) / abs(
                    self.initial.mean[i]
                )

    def _process(self, limit: int | None) -> list:
        """Commit held steps in order, chunk by chunk, running EM at its boundaries; stops
        when none are left, EM runs in the background, or ``limit`` steps were committed."""
        out, done = [], 0
        while self._held and (limit is None or done < limit):
            if self._em_future is not None:
                if not self._em_future.done() and self.executor is not None:
                    break
                self._apply_em(self._em_future.result())
            k = self.n_committed
            if self.config.em and k > 0 and self._is_boundary(k) and k != self._em_done:
                if em_due(k, self._every, self._window, self._early):
                    self._launch_em(k)
                    if self.executor is not None:
                        # the steps held from here on are given out provisionally
                        self._spec_steps = 0
                        for rows in list(self._held):
                            out += self._speculative(rows)
                        break
                    continue
                self._restart_chunk(k, self.theta)
            room = self._next_boundary(k) - k
            if limit is not None:
                room = min(room, limit - done)
            rows = self._held.popleft()
            if len(rows) > room:
                rows, rest = rows.cut(room)
                self._held.appendleft(rest)
            out.append(self._commit(rows))
            done += len(rows)
        return out

    def _is_boundary(self, k: int) -> bool:
        """A chunk boundary: a multiple of every_s or an early EM step."""
        return k % self._every == 0 or k in self._early

    def _next_boundary(self, k: int) -> int:
        """Where the block from step k must end: the next chunk boundary (EM on), else the
        next multiple of every_s (only so that a block has a compiled length)."""
        if self.config.em:
            return next_em_boundary(k, self._every, self._early)
        return (k // self._every + 1) * self._every

    # ------------------------------------------------------------------ the filter
    def _constants(self):
        """Σ_ξ, σ_w², gate as device arrays (made once: a conversion per step costs more
        than the step; made again when output EM changes σ_w)."""
        twin = self.twin
        var = np.asarray(twin.measurement_var, dtype=float)
        if self._device_constants is None or not np.array_equal(self._device_constants[0], var):
            self._device_constants = (
                var,
                # placed on the device without a compiled op (jnp.asarray compiles one)
                jax.device_put(
                    (
                        np.asarray(twin.process_cov, dtype=float),
                        var,
                        np.asarray(float(twin.config.gate_sigma)),
                    )
                ),
            )
        return self._device_constants[1]

    def _model_inputs(self, inputs, response):
        """(the transition's inputs of the rows, r after the last)."""
        inputs = np.asarray(inputs, dtype=float)
        if self._dynamics is None:
            return inputs, None
        return self.twin.model_inputs_from(inputs, response)

    def _filter(self, carry, model_inputs, rows: _Rows, theta):
        """The filter over the rows from ``carry``: (carry after them, FilterResult on the
        host). One row: the single step; more: one compiled block of every_s rows."""
        twin = self.twin
        process_cov, measurement_var, gate = self._constants()
        m = len(rows)
        if m == 1:
            line = None if rows.line is None else rows.line[0]
            carry, step = _step_one(
                twin.spec, carry, model_inputs[0], rows.measurements[0], theta,
                process_cov, measurement_var, gate, functions=twin.functions, line=line,
            )  # fmt: skip
            # each kept array owns its numbers (a view would keep its device buffer alive)
            return carry, FilterResult(*(np.array(np.asarray(part)[None]) for part in step))
        size = max(self._every, m)
        carry, result = ekf_continue(
            twin.spec,
            carry,
            _pad(model_inputs, size, None),
            _pad(rows.measurements, size, np.nan),
            theta,
            process_cov,
            measurement_var,
            gate,
            functions=twin.functions,
            line_factors=None if rows.line is None else _pad(rows.line, size, None),
            n_steps=m,
        )
        result = FilterResult(*(np.array(np.asarray(part)[:m]) for part in result))
        # the carry on the host: the next call's arguments are alike, one compiled program
        return EKFCarry(*(np.asarray(part) for part in carry)), result

    def _commit(self, rows: _Rows, result=None, carry=None) -> StepBlock:
        """Filter the rows (or take a result computed for them) and keep them."""
        model_inputs, response = self._model_inputs(rows.inputs, self._response)
        if result is None:
            carry, result = self._filter(self.carry, model_inputs, rows, self.theta)
        self.carry, self._response = carry, response
        block = self._block(self.n_committed, rows, model_inputs, result, self.theta)
        self.n_committed += len(rows)
        self._keep_block(block)
        return block

    def _block(self, first, rows: _Rows, model_inputs, result, theta, provisional=False):
        """A StepBlock of filtered rows: what the data saw, the prior floor, the
        calibration's share (carried over the blocks; not for provisional steps)."""
        measured = np.isfinite(rows.measurements)
        seen = (measured[:, :, None] & self._responds[None]).any(axis=1)
        floor = np.zeros((len(rows), 5))
        if self._never_seen.any():
            not_yet = ~np.logical_or.accumulate(seen, axis=0) & self._never_seen
            floor = np.where(not_yet, (self._floor_relative * result.means) ** 2, 0.0)
            if not provisional:
                self._never_seen &= not_yet[-1]
        calibration = None
        if not provisional:
            self.unseen_counts += (~seen).sum(axis=0)
            calibration = self.twin.calibration_covariances(
                result, model_inputs, rows.line, self._calibration_carry
            )
        return StepBlock(
            first=first,
            time_s=np.asarray(rows.time_s, dtype=float),
            inputs=np.asarray(rows.inputs, dtype=float),
            model_inputs=model_inputs,
            measurements=np.asarray(rows.measurements, dtype=float),
            filtered=result,
            theta=np.asarray(theta, dtype=float).copy(),
            seen=seen,
            prior_floor=floor,
            calibration_covariances=calibration,
            line=rows.line,
            n_camera=rows.n_camera,
        )

    def _keep_block(self, block: StepBlock) -> None:
        """Keep what EM, a restart and :meth:`recent` need: the last ``keep`` steps."""
        self._window_blocks.append(block)
        while (
            len(self._window_blocks) > 1
            and self._window_blocks[1].first <= self.n_committed - self._keep
        ):
            self._window_blocks.popleft()

    def _window_array(self, name: str, start: int, stop: int) -> np.ndarray:
        """Steps [start, stop) of a kept field (a StepBlock attribute or a FilterResult
        field), concatenated over the blocks that hold them."""
        parts = []
        for block in self._window_blocks:
            if block.stop <= start or block.first >= stop:
                continue
            a = max(start - block.first, 0)
            b = min(stop, block.stop) - block.first
            source = getattr(block, name, None)
            if source is None or name in FilterResult._fields:
                source = getattr(block.filtered, name)
            parts.append(np.asarray(source)[a:b])
        if not parts:
            return np.zeros((0,))
        return np.concatenate(parts, axis=0)

    def _restart_chunk(self, pos: int, theta, last=None) -> None:
        """Filter restart at a chunk boundary: prior = prediction from step pos − 1."""
        if last is None:
            last = (
                self._window_array("means", pos - 1, pos)[0],
                self._window_array("covariances", pos - 1, pos)[0],
            )
        u = self._window_array("model_inputs", pos - 1, pos)[0]
        twin = self.twin
        mean, cov = predict(twin.spec, last[0], last[1], u, theta, twin.process_cov, twin.functions)
        self.carry = ekf_init(twin.spec, np.asarray(mean), np.asarray(cov))
        self._restarts += 1

    # ------------------------------------------------------------------ EM
    def _launch_em(self, pos: int) -> None:
        twin = self.twin
        w0 = max(pos - self._window, 0)
        line = None if self._bins is None else self._window_array("line", w0, pos)
        args = (
            twin.spec,
            self._window_array("predicted_means", w0, w0 + 1)[0],
            self._window_array("predicted_covariances", w0, w0 + 1)[0],
            self._window_array("model_inputs", w0, pos),
            self._window_array("measurements", w0, pos),
            self.theta.copy(),
            twin.process_cov,
            twin.measurement_var,
        )
        kwargs = self._em_options(line)
        self._em_pos = pos
        self._spec = None
        if self.executor is not None:
            self._em_future = self.executor.submit(run_em, *args, **kwargs)
        else:
            future = Future()
            future.set_result(run_em(*args, **kwargs))
            self._em_future = future

    def _em_options(self, line) -> dict:
        """:func:`run_em`'s keywords: the twin's EM settings; every window at the full
        window's length (early windows padded: one compiled EM program)."""
        twin, c = self.twin, self.config
        return dict(
            settings=EMSettings(
                twin.theta_prior_precision, c.em_max_iterations, c.em_tolerance, c.gate_sigma
            ),
            functions=twin.functions,
            line_factors=line,
            padded_steps=self._window,
        )

    def _prefetch_em(self, rows: _Rows) -> None:
        """Start loading EM's kept program in the background (:func:`prefetch_em`), with
        arguments shaped as a window of these rows' kind, so that the load overlaps the
        start's fit and the filtering before the first EM window."""
        model_inputs, _ = self._model_inputs(rows.inputs[:1], self._response)
        n, twin = self._window, self.twin
        line = None if rows.line is None else np.repeat(rows.line[:1], n, axis=0)
        n_states = len(self.theta)
        prefetch_em(
            twin.spec,
            np.zeros(n_states),
            np.eye(n_states),
            np.repeat(model_inputs, n, axis=0),
            np.full((n, rows.measurements.shape[1]), np.nan),
            self.theta,
            twin.process_cov,
            twin.measurement_var,
            **self._em_options(line),
        )

    def _apply_em(self, em) -> None:
        """EM's result in force from its boundary (the output EM too, when it learns)."""
        pos = self._em_pos
        w0 = max(pos - self._window, 0)
        learned = {}
        if self.config.learn_line_offsets or self.config.learn_output_noise:
            if self._bins is not None:
                raise ValueError(
                    "learning line offsets or output noise online is not available on a job "
                    "print (the line's speed factors are not in that M-step)"
                )
            learned = self.twin.learn_outputs(
                em.smoothed,
                self._window_array("model_inputs", w0, pos),
                self._window_array("measurements", w0, pos),
            )
        self.theta = np.asarray(em.theta, dtype=float)
        self.twin.theta = self.theta.copy()
        self.theta_history.append(
            {
                "time_s": float(self._window_array("time_s", pos - 1, pos)[0]),
                "window_start_s": float(self._window_array("time_s", w0, w0 + 1)[0]),
                "iterations": em.iterations,
                "converged": em.converged,
                "log_likelihood": em.log_likelihood,
                **{f"theta_{name}": float(v) for name, v in zip(STATE_NAMES, self.theta)},
                **learned,
            }
        )
        last = (np.asarray(em.filtered.means)[-1], np.asarray(em.filtered.covariances)[-1])
        self._restart_chunk(pos, self.theta, last)
        self._em_future = None
        self._em_done, self._em_pos = pos, None
        self._spec = None

    def _speculative(self, rows: _Rows) -> list:
        """Steps with the old θ while EM runs: given out as provisional, not kept."""
        if self._spec is None:
            pos = self._em_pos
            twin = self.twin
            mean, cov = predict(
                twin.spec,
                self._window_array("means", pos - 1, pos)[0],
                self._window_array("covariances", pos - 1, pos)[0],
                self._window_array("model_inputs", pos - 1, pos)[0],
                self.theta,
                twin.process_cov,
                twin.functions,
            )
            # r continued over the steps held before these (all committed later)
            response = self._response
            for held in self._held:
                if held is rows:
                    break
                _, response = self._model_inputs(held.inputs, response)
            self._spec = (ekf_init(twin.spec, np.asarray(mean), np.asarray(cov)), response)
            self._spec_steps = sum(len(h) for h in self._held) - len(rows)
        carry, response = self._spec
        out = []
        for i in range(len(rows)):
            row = _Rows(*(None if a is None else a[i : i + 1] for a in rows))
            u, response = self._model_inputs(row.inputs, response)
            carry, result = self._filter(carry, u, row, self.theta)
            block = self._block(
                self.n_committed + self._spec_steps, row, u, result, self.theta, True
            )
            out.append(_provisional(block))
            self._spec_steps += 1
        self._spec = (carry, response)
        return out

    # ------------------------------------------------------------------ several machines
    def take_plain(self, sample: Sample) -> bool:
        """Whether ``sample`` is an ordinary next step (on the grid, finite inputs, no job,
        boundary, EM, backlog or start pending) that :func:`step_together` may run with
        other machines' steps; if so it is counted as received."""
        c = self.config
        k = self.n_committed
        if (
            self.carry is None
            or self._bins is not None
            or self._em_future is not None
            or self._held
            or self._waiting
            or self.last_time is None
            or int(round(float(sample.time_s) - self.last_time)) != 1
            or sample.inputs is None
            or not np.all(np.isfinite(sample.inputs))
            or (c.em and self._is_boundary(k) and k != self._em_done)
            or (not c.em and k % self._every == 0)
        ):
            return False
        self.last_time += 1.0
        self.last_inputs = np.asarray(sample.inputs, dtype=float)
        self.n_received += 1
        return True

    # ------------------------------------------------------------------ a job print now
    def provisional_now(self) -> list:
        """A job print's state now: the filter re-run from the last committed step over the
        steps not final yet, with what has been filed into them so far; one
        :class:`Provisional` of the newest row ([] without a job or before any row).

        The re-run starts at the oldest step that changed since the last one (a measurement
        filed there, or a new row); the predictions before the steps after it are kept from
        the last re-run while θ and the committed head are those it ran from.
        """
        bins = self._bins
        if bins is None or self.last_time is None:
            return []
        changed = bins.take_changed()
        if bins.n_pending == 0:
            return []
        first = bins.first_open
        head = self._spec[0] if self._em_future is not None and self._spec else self.carry
        if head is None and self.n_committed == 0 and not self._held:
            head = self._provisional_start(changed)
        if head is None:
            return []
        key = (self.theta.tobytes(), len(self.theta_history), self._restarts)
        if key != self._tail_key:
            self._tail_priors, self._tail_key = {}, key
        start = first if changed is None else max(first, changed)
        s = self.twin.spec.scaling.state
        if start not in self._tail_priors or start == first:
            start = first
            self._tail_priors[first] = (
                np.asarray(head.predicted_mean) * s,
                np.asarray(head.predicted_cov) * np.outer(s, s),
            )
        for j in [j for j in self._tail_priors if j < first]:
            del self._tail_priors[j]
        pending = bins.pending()[start - first :]
        rows = _filed_rows(pending)
        inputs = self._tail_model_inputs(pending, start - first)
        for b in range(0, len(pending), self.TAIL_BLOCK):
            part = _Rows(*(None if a is None else a[b : b + self.TAIL_BLOCK] for a in rows))
            result = self._tail_block(start + b, part, inputs[b : b + len(part)], head)
        n = len(part)
        step = type(result)(*(np.asarray(f)[n - 1 : n] for f in result))
        block = self._block(bins.n_rows - 1, _last_row(part), inputs[-1:], step, self.theta, True)
        self.provisional = (
            float(block.time_s[-1]),
            np.asarray(step.means[-1]),
            np.asarray(step.covariances[-1]),
        )
        return [_provisional(block)]

    def _provisional_start(self, changed: int | None) -> EKFCarry | None:
        """Before the filter starts (its first steps are not final yet: an inspection pass
        comes after the print), the start it would have now: the carried-over state, or the
        initial fit over the first steps as filed so far (kept until they change)."""
        if self.start is not None:
            if self._responds is None:
                self.start_mean = np.asarray(self.start[0], dtype=float)
                pending = self._bins.pending()
                self._responds = self.twin.output_responds(self.start_mean, pending[0].inputs)
            return ekf_init(self.twin.spec, *self.start)
        n = int(self.config.initial_samples)
        if self._tail_start is None or (changed is not None and changed < n):
            rows = _filed_rows(self._bins.pending()[:n])
            try:
                fit = self.twin.initial_state(rows.inputs, rows.measurements, rows.line)
            except ValueError:  # nothing to start from yet (no line output, no priors)
                return None
            self._tail_start = ekf_init(self.twin.spec, fit.mean, fit.covariance)
            self._responds = self.twin.output_responds(fit.mean, rows.inputs[0])
            self._tail_key = None
        return self._tail_start

    def _tail_block(self, j0: int, part: _Rows, model_inputs, head: EKFCarry):
        """The filter over steps j0 … of ``part`` from the kept prediction of step j0, padded
        to one compiled length; keeps the predictions of the steps after them."""
        n, size = len(part), self.TAIL_BLOCK + 1
        prior_mean, prior_cov = self._tail_priors[j0]
        s = self.twin.spec.scaling.state
        carry = EKFCarry(
            jnp.asarray(prior_mean / s),
            jnp.asarray(prior_cov / np.outer(s, s)),
            head.reset_mean,
            head.reset_cov,
        )
        twin = self.twin
        process_cov, measurement_var, gate = self._constants()
        _, result = _continue_plain(
            twin.spec,
            carry,
            _pad(model_inputs, size, None),
            _pad(part.measurements, size, np.nan),
            self.theta,
            process_cov,
            measurement_var,
            gate,
            functions=twin.functions,
            line_factors=_pad(part.line, size, None),
            n_steps=n,
        )
        result = FilterResult(*(np.asarray(f) for f in _on_host(result)))
        for i in range(1, n + 1):
            self._tail_priors[j0 + i] = (result.predicted_means[i], result.predicted_covariances[i])
        return FilterResult(*(f[:n] for f in result))

    def _tail_model_inputs(self, pending: list, skipped: int) -> np.ndarray:
        """The transition's inputs of the steps not final yet (r carried on from the
        committed steps and those held), each computed once while it stays provisional."""
        if self._dynamics is None:
            return np.array([step.inputs for step in pending], dtype=float).reshape(-1, 3)
        first = self._bins.first_open
        steps = self._bins.pending()
        kept = self._tail_inputs
        if self._tail_inputs_end <= first:  # nothing kept that is not final yet
            kept.clear()
            end, response = first, self._response
            for held in self._held:  # in order, before the pending bins
                _, response = self._model_inputs(held.inputs, response)
        else:
            for j in [j for j in kept if j < first]:
                del kept[j]
            end = self._tail_inputs_end
            response = kept[end - 1][1]
        for j in range(end, first + len(steps)):
            u, r = self._model_inputs(np.asarray(steps[j - first].inputs)[None], response)
            kept[j] = (u[0], r)
            response = r
        self._tail_inputs_end = first + len(steps)
        return np.array([kept[j][0] for j in range(first + skipped, first + len(steps))])


def _last_row(rows: _Rows) -> _Rows:
    return _Rows(*(None if a is None else a[-1:] for a in rows))


def _provisional(block: StepBlock) -> Provisional:
    """A provisional one-step block."""
    assert len(block) == 1, "a provisional step is one step"
    return Provisional(block)


def _filed_rows(steps: list) -> _Rows:
    """A job print's filed steps (:class:`~ajtwin.estimation.print_time.FiledStep`) as rows."""
    return _Rows(
        np.array([s.time_s for s in steps], dtype=float),
        np.array([s.inputs for s in steps], dtype=float).reshape(-1, 3),
        np.array([s.outputs for s in steps], dtype=float).reshape(-1, 5),
        np.array([s.line for s in steps], dtype=float).reshape(-1, 4),
        np.array([s.n_camera for s in steps], dtype=float).reshape(-1, 2),
    )


def _pad(array, length: int, fill):
    """``array`` (m, …) to ``length`` rows: its last row repeated (``fill`` None) or ``fill``."""
    array = np.asarray(array, dtype=float)
    if len(array) == length:
        return array
    pad = np.repeat(
        array[-1:] if fill is None else np.full_like(array[-1:], fill), length - len(array), axis=0
    )
    return np.concatenate([array, pad], axis=0)


def step_together(plain: list[tuple[OnlineTwin, Sample]]) -> list[StepBlock]:
    """Ordinary steps of several machines' twins that share the twin's functions, run as
    one vmapped EKF step (one twin: its own step); each twin's committed one-step block.

    Parameters
    ----------
    plain : list of (OnlineTwin, Sample)
        Each twin with the sample :meth:`OnlineTwin.take_plain` accepted.
    """
    if not plain:
        return []
    if len(plain) == 1:
        core, sample = plain[0]
        return [core._commit(_sample_rows(sample))]
    twin = plain[0][0].twin
    rows = [_sample_rows(s) for _, s in plain]
    model_inputs = [
        core._model_inputs(r.inputs, core._response)[0] for (core, _), r in zip(plain, rows)
    ]
    carries = EKFCarry(*[jnp.stack(parts) for parts in zip(*[c.carry for c, _ in plain])])
    carries, steps = _step_many(
        twin.spec,
        carries,
        np.array([u[0] for u in model_inputs]),
        np.array([r.measurements[0] for r in rows]),
        np.array([c.theta for c, _ in plain]),
        *plain[0][0]._constants(),
        functions=twin.functions,
    )
    steps = jax.device_get(steps)
    out = []
    for i, ((core, _), r) in enumerate(zip(plain, rows)):
        carry = EKFCarry(*[part[i] for part in carries])
        result = FilterResult(*(np.array(np.asarray(part)[i : i + 1]) for part in steps))
        out.append(core._commit(r, result, carry))
    return out


def _sample_rows(sample: Sample) -> _Rows:
    return _Rows(
        np.array([float(sample.time_s)]),
        np.asarray(sample.inputs, dtype=float).reshape(1, 3),
        np.asarray(sample.outputs, dtype=float).reshape(1, 5),
        None,
        None,
    )
