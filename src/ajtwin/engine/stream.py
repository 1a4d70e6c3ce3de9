"""One machine's live twin: a sample in → the twin's core → the detectors → messages out.

:class:`TwinStream` wires what a live print needs and computes nothing itself: each sample
goes to the twin's core (:class:`ajtwin.estimation.online.OnlineTwin`: the grid, a job
print's delay line, the filter, EM; the batch :meth:`ajtwin.estimation.Twin.run` drives the
same core), each committed step through the detectors
(:class:`ajtwin.apps.detection.streaming.AnomalyDetector`), and each committed or
provisional step becomes a message (:mod:`ajtwin.engine.messages`). The committed steps not
yet written are kept for the print's writer (:meth:`TwinStream.arrays`).

Examples
--------
>>> from ajtwin.simulation import simulate
>>> rec = simulate("exp1", seed=1, duration_min=0.5)
>>> stream = TwinStream.new("aj300-1", twin_overrides={"em": False}, asynchronous=False)
>>> messages = [m for t, u, y in zip(rec.time_s, rec.inputs, rec.outputs)
...             for m in stream.feed(Sample(t, u, y))]
>>> stream.n_committed, messages[-1].status
(30, 'warming up')
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ajtwin.apps.detection.settings import DetectorSettings
from ajtwin.apps.detection.settling import StartupWatch
from ajtwin.apps.detection.streaming import AnomalyDetector
from ajtwin.engine.messages import (
    StepMessage,
    finished_message,
    provisional_message,
    step_message,
)
from ajtwin.estimation.online import OnlineTwin, Provisional, Sample, StepBlock, step_together
from ajtwin.estimation.print_time import PrintContext
from ajtwin.estimation.twin import Twin
from ajtwin.model import STATE_NAMES

__all__ = ["Sample", "TwinStream", "step_streams_together", "warm_up_streams"]

#: committed steps a stream keeps beyond its EM window and period: the part of the print a
#: live engine has not yet written to the registry (:data:`ajtwin.engine.parts.PART_STEPS`)
UNWRITTEN_STEPS = 3600


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
        Shared EM workers (:class:`~ajtwin.engine.fleet.LiveEngine` passes one for all
        machines).
    long_run_history : dict, optional
        The detectors' carried long-run statistics.
    print_context : PrintContext, optional
        A job print: its horizon, camera and program; None: rows are final as they come.
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
        self.detector = AnomalyDetector(detector_settings, long_run_history)
        # "ready to print": one per print, a new detector when the atomizer starts again
        self.startup = StartupWatch()
        self._executor = executor
        self._own_executor = False
        self.core = OnlineTwin(twin, start, print_context=print_context, name=machine)
        self.asynchronous = asynchronous
        keep = int(twin.config.window_s) + int(twin.config.every_s) + UNWRITTEN_STEPS
        self._blocks: deque[StepBlock] = deque()  # committed, the last ``keep`` steps
        self._keep = keep

    @classmethod
    def new(cls, machine: str, start=None, theta=None, twin_overrides=None, **kwargs):
        """A stream with the default twin (``twin_overrides``: TwinConfig fields)."""
        twin = Twin.default(**(twin_overrides or {}))
        if theta is not None:
            twin.theta = np.asarray(theta, dtype=float)
        return cls(machine, twin, start, **kwargs)

    # ------------------------------------------------------------------ #
    @property
    def asynchronous(self) -> bool:
        """EM in a worker thread (True) or inline."""
        return self.core.executor is not None

    @asynchronous.setter
    def asynchronous(self, value: bool) -> None:
        """EM in a worker thread (True: one of its own unless an executor was given)."""
        if value and self._executor is None:
            self._executor = ThreadPoolExecutor(1, thread_name_prefix="ajtwin-em")
            self._own_executor = True
        self.core.executor = self._executor if value else None

    @property
    def config(self):
        """The twin's tuning (:class:`~ajtwin.estimation.twin.TwinConfig`)."""
        return self.twin.config

    @property
    def carry(self):
        """The filter's carry (None before the start)."""
        return self.core.carry

    @property
    def theta(self) -> np.ndarray:
        """θ in force [1/s]."""
        return self.core.theta

    @property
    def theta_before(self) -> np.ndarray:
        """θ at the print's start."""
        return self.core.theta_before

    @property
    def start_mean(self):
        """The print's start mean (5,) (None before the start)."""
        return self.core.start_mean

    @property
    def start_cov(self):
        """The print's start covariance (5, 5) (None before the start)."""
        return self.core.start_cov

    @property
    def n_committed(self) -> int:
        """Steps committed so far (stepped with the θ in force, stored, given to the detectors)."""
        return self.core.n_committed

    @property
    def n_received(self) -> int:
        """Samples on the grid so far (committed, held and not final yet)."""
        return self.core.n_received

    @property
    def last_time(self):
        """The time of the newest sample on the grid [s] (None before the first)."""
        return self.core.last_time

    @property
    def dropped(self) -> dict:
        """Samples dropped by reason (duplicate, out of order, bad, far future)."""
        return self.core.dropped

    @property
    def missing_inserted(self) -> int:
        """Missing seconds inserted for gaps."""
        return self.core.missing_inserted

    @property
    def provisional(self):
        """A job print's state now: (time [s], mean, covariance) (None: none yet)."""
        return self.core.provisional

    @property
    def camera_counts(self) -> dict:
        """A job print's filing so far: frames filed, dropped by reason, the horizon."""
        return self.core.camera_counts

    @property
    def n_pending(self) -> int:
        """Rows received whose step is not final yet (0 without a job)."""
        return self.core.n_pending

    @property
    def em_running(self) -> bool:
        """Whether an EM update runs in the background now."""
        return self.core.em_running

    # ------------------------------------------------------------------ #
    def feed(self, sample: Sample, provisional: bool = True) -> list[StepMessage]:
        """Take one sample; returns the messages it produced (committed and provisional).

        ``provisional=False``: a job print's provisional re-run is left for a later
        :meth:`refresh_provisional` (a controller that plans once per period needs the
        state at the period's end only).
        """
        out = self._messages(self.core.feed_sample(sample))
        if provisional and self.core.print_context is not None and self.core.last_time is not None:
            out += self._messages(self.core.provisional_now())
        return out

    def refresh_provisional(self) -> list[StepMessage]:
        """A job print's provisional message of the newest row now; [] when none."""
        return self._messages(self.core.provisional_now())

    def poll(self, wait: bool = False) -> list[StepMessage]:
        """Messages of an EM result that landed (the held samples committed)."""
        return self._messages(self.core.poll(wait))

    def take_plain(self, sample: Sample) -> Sample | None:
        """If ``sample`` is an ordinary next step, book it and return it for a batched step
        (:func:`step_streams_together`); else None, nothing changed."""
        if not self.core.take_plain(sample):
            return None
        return Sample(self.core.last_time, np.asarray(sample.inputs, float),
                      np.asarray(sample.outputs, float))  # fmt: skip

    def finish(self) -> list:
        """End of the print: every step committed, the detectors' events finalised."""
        out = self._messages(self.core.finish())
        events = self.detector.finish()
        if self._own_executor and self._executor is not None:
            self._executor.shutdown(wait=False)
        return out + [finished_message(self.machine, events)]

    def status(self, provisional: bool = False, at_s: float | None = None) -> tuple[str, str]:
        """Operator status and likely cause of the latest event ("" when none), at the
        committed step of time ``at_s`` (default the newest)."""
        d = self.detector
        if d.start is None:
            return "warming up", ""
        last_time = self.core.last_time_committed if at_s is None else at_s
        if d.events and last_time is not None:
            last = d.events[-1]
            if last_time - last.detected_s <= d.settings.merge_s:
                return "alarm", last.cause
        return ("ok (provisional)" if provisional else "ok"), ""

    # ------------------------------------------------------------------ #
    def _messages(self, items) -> list[StepMessage]:
        out = []
        for item in items:
            if isinstance(item, Provisional):
                status = self.status(True)
                out.append(provisional_message(self.machine, item.block, status, self.em_running,
                                               self.startup.status()))  # fmt: skip
            else:
                out += self._committed(item)
        return out

    def _committed(self, block: StepBlock) -> list[StepMessage]:
        """A committed block: kept for the writer, each step through the detectors and out
        as a message with the status after it."""
        self._blocks.append(block)
        while len(self._blocks) > 1 and self._blocks[1].first <= self.n_committed - self._keep:
            self._blocks.popleft()
        out = []
        f = block.filtered
        ready = self.startup.update(block.time_s, block.inputs, f.means, f.predicted_outputs)

        def each(i, detector_step):
            status = self.status(at_s=float(block.time_s[i]))
            out.append(step_message(self.machine, block, i, detector_step, status,
                                    self.em_running, ready[i]))  # fmt: skip

        self.detector.update_block(block, each)
        return out

    def arrays(self, since: int | None = None) -> dict[str, np.ndarray]:
        """The committed per-step results from step ``since`` on (default: the oldest step
        kept), named as the registry stores a print (a job print's with ``line_factors``). A
        stream keeps its last steps only (a long live print is written in parts as it goes,
        :class:`~ajtwin.engine.parts.PrintWriter`); a short print's are all kept."""
        blocks = list(self._blocks)
        since = (blocks[0].first if blocks else 0) if since is None else int(since)
        kept = [b for b in blocks if b.stop > since]
        hist = self.core.theta_history

        def joined(get, *shape):
            parts = [np.asarray(get(b))[max(since - b.first, 0) :] for b in kept]
            return np.concatenate(parts, axis=0) if parts else np.zeros((0, *shape))

        out = {
            "time_s": joined(lambda b: b.time_s),
            "means": joined(lambda b: b.filtered.means, 5),
            "stds": joined(lambda b: b.stds, 5),
            "covariances": joined(lambda b: b.filtered.covariances, 5, 5),
            "predicted_means": joined(lambda b: b.filtered.predicted_means, 5),
            "predicted_outputs": joined(lambda b: b.filtered.predicted_outputs, 5),
            "innovation_variances": joined(lambda b: b.filtered.innovation_variances, 5),
            "measurements": joined(lambda b: b.measurements, 5),
            "inputs": joined(lambda b: b.inputs, 3),
            "nis": joined(lambda b: b.filtered.nis),
            "n_measured": joined(lambda b: b.filtered.n_measured),
            "reinitialised": joined(lambda b: b.filtered.reinitialised).astype(bool),
            "theta_per_step": joined(lambda b: b.theta_per_step, 5),
            "theta_history_time_s": np.array([r["time_s"] for r in hist], dtype=float),
            "theta_history": np.array(
                [[r[f"theta_{n}"] for n in STATE_NAMES] for r in hist], dtype=float
            ).reshape(-1, 5),
        }
        if self.core.print_context is not None:
            # a job print's filed steps carry their speed-law factors: the run can be re-made
            out["line_factors"] = joined(lambda b: b.line, 4)
        return out

    def model_inputs(self) -> np.ndarray:
        """The transition's inputs (m, 3 or 4) of the committed steps kept."""
        return np.concatenate([b.model_inputs for b in self._blocks], axis=0)


def step_streams_together(plain: list[tuple[TwinStream, Sample]]) -> list[StepMessage]:
    """Ordinary steps of several machines' streams as one vmapped step
    (:func:`ajtwin.estimation.online.step_together`); their committed messages."""
    blocks = step_together([(stream.core, sample) for stream, sample in plain])
    out = []
    for (stream, _), block in zip(plain, blocks):
        out += stream._committed(block)
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
    fit = twin.initial_state(np.tile(u, (10, 1)), np.tile(y, (10, 1)))
    start = (fit.mean, fit.covariance)
    stream = TwinStream("warm-up", twin, start, detector_settings, asynchronous=False)
    for k in range(3):
        stream.feed(Sample(float(k), u, y))
    stream.core._restart_chunk(2, stream.theta)
    if n_machines > 1:
        plain = []
        for i in range(n_machines):
            s = TwinStream(f"w{i}", twin, start, detector_settings, asynchronous=False)
            s.feed(Sample(0.0, u, y))
            plain.append((s, s.take_plain(Sample(1.0, u, y))))
        step_streams_together(plain)
