"""A virtual print replayed as a live feed, sample by sample, to a publisher
(:class:`ajtwin.web.publisher.LivePublisher`: ``ajtwin dashboard --virtual-print``).

The source of the dashboard's live tests and benchmark: the virtual printer simulates a
print
(:func:`ajtwin.simulation.simulate`), the twin runs over it (:class:`ajtwin.estimation.Twin`,
EKF + EM, the same code ``ajtwin ingest`` runs) and the anomaly detectors over the twin's
innovations (:func:`ajtwin.apps.detection.batch.detect_run`); the result is then replayed at
``rate_hz`` samples per second of wall time: sample k carries x̂_k ± σ, the truth, the
one-step prediction, the measurement, the detectors' statistics at k, and the alarms
whose detection time is k. No physics is done here.

Parameters (:class:`VirtualPrintFeed`)
--------------------------------------
publisher : LivePublisher or any object with ``open_print``, ``publish``, ``end_print``,
    ``announce`` and ``n_subscribers``
machine : str, the name the samples carry
scenario : str, a virtual-printer scenario (``nozzle_clog``, ``exp1``, …)
seed : int
minutes : float, print length [min]
onset_min : float, optional, fault onset [min] (scenarios with a fault)
rate_hz : float, samples published per wall-clock second (1 = real time)
wait_for_viewer_s : float, hold the replay until a page subscribes (at most this long)
job : str or Path, optional, a machine program: the virtual printer prints it (looped to
    the print's length, the default trailing camera) and the part map fills in as the print
    goes (:class:`ajtwin.apps.quality.live_map.LivePartMap`; the publisher then also needs
    ``open_part`` and ``publish_part``)
tolerance : Tolerance, optional, the part's linewidth tolerance (with ``job``)

Example
-------
>>> from ajtwin.web.publisher import LivePublisher             # doctest: +SKIP
>>> feed = VirtualPrintFeed(LivePublisher(), "vm1", "nozzle_clog", minutes=8,
...                         onset_min=3, rate_hz=50)          # doctest: +SKIP
>>> feed.start(); feed.join(timeout=120)                       # doctest: +SKIP
"""

from __future__ import annotations

import threading
import time

import numpy as np

from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.settings import cusum_thresholds
from ajtwin.apps.detection.settling import StartupWatch
from ajtwin.apps.quality.live_map import LivePartMap
from ajtwin.estimation import Twin
from ajtwin.simulation import load_scenario, run_job_print, simulate


def _merge_chunk(into: dict, chunk: dict) -> None:
    """Append a part chunk to one published at the same row (portions, points, alarms;
    the newest outline wins)."""
    for key in ("portions", "points"):
        if key in chunk:
            held = into.setdefault(key, {})
            for name, values in chunk[key].items():
                held.setdefault(name, []).extend(values)
    if "alarms" in chunk:
        into.setdefault("alarms", []).extend(chunk["alarms"])
    if "outline" in chunk:
        into["outline"] = chunk["outline"]


class VirtualPrintFeed:
    """Replays a virtual print through the twin as live samples (module docstring)."""

    def __init__(
        self,
        publisher,
        machine: str,
        scenario: str = "nozzle_clog",
        *,
        seed: int = 1,
        minutes: float = 8.0,
        onset_min: float | None = 3.0,
        rate_hz: float = 10.0,
        wait_for_viewer_s: float = 0.0,
        job=None,
        tolerance=None,
    ):
        if not rate_hz > 0:
            raise ValueError(f"rate must be > 0 samples/s, got {rate_hz}")
        self.publisher = publisher
        self.machine = machine
        self.scenario = scenario
        self.seed = int(seed)
        self.minutes = float(minutes)
        self.onset_min = onset_min
        self.rate_hz = float(rate_hz)
        self.wait_for_viewer_s = float(wait_for_viewer_s)
        self.job = job
        self.tolerance = tolerance
        self.part_header: dict | None = None
        self.part_chunks: dict[int, dict] = {}
        self.samples: list[dict] | None = None
        self.error: str | None = None
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ compute
    def prepare(self) -> list[dict]:
        """Simulate, run the twin and the detectors; returns the samples to publish."""
        overrides = None
        if self.onset_min is not None and load_scenario(self.scenario).fault_kind != "none":
            overrides = {"fault": {"onset_min": float(self.onset_min)}}
        twin = Twin.default()
        if self.job is None:
            record = simulate(
                self.scenario, seed=self.seed, duration_min=self.minutes, overrides=overrides
            )
            printed_job = None
        else:
            job_print = run_job_print(
                self.job, self.scenario, self.seed, duration_min=self.minutes, overrides=overrides
            )
            record, printed_job = job_print.record, job_print.plan.job
        # as the print ran: the camera's frames filed at their print times
        run = twin.run(record, job=printed_job)
        det = detect_run(run, record)
        f = run.filtered
        means, stds = run.means, run.stds
        predicted = np.asarray(f.predicted_outputs)
        nis = np.asarray(f.nis)
        g = np.maximum(det.cusum_pos, det.cusum_neg)
        log_p = -np.log10(np.maximum(det.window_nis_p, 1e-300))
        thresholds = [float(h) for h in cusum_thresholds(det.settings)]
        nis_threshold = float(-np.log10(det.settings.nis_alpha))
        truth = record.true_states if record.has_truth else None
        # ready to print as the live twin says it (one verdict per atomizer run)
        ready = StartupWatch().update(run.time_s, record.inputs, f.means, predicted)
        by_step: dict[int, list] = {}
        for ev in det.events:
            k = int(np.searchsorted(run.time_s, ev.detected_s))
            by_step.setdefault(k, []).append(
                {
                    "detected_s": ev.detected_s,
                    "onset_s": ev.onset_s,
                    "cause": ev.cause,
                    "description": ev.description,
                    "detectors": ", ".join(ev.detectors),
                }
            )
        samples = []
        for k, t in enumerate(run.time_s):
            sample = {
                "machine": self.machine,
                "time_s": float(t),
                "states": means[k],
                "state_stds": stds[k],
                "predicted": predicted[k],
                "measured": record.outputs[k],
                "inputs": record.inputs[k],
                "nis": float(nis[k]),
                "theta": run.theta_per_step[k],
                "detectors": {
                    "cusum": g[k],
                    "cusum_thresholds": thresholds,
                    "window_nis_log10p": float(log_p[k]),
                    "window_nis_threshold": nis_threshold,
                },
                "alarms": by_step.get(k, []),
                "settling": {key: ready[k][key] for key in ("ready", "ready_at_s", "text")},
                "source": f"virtual printer: {self.scenario} seed {self.seed}",
            }
            if truth is not None:
                sample["truth"] = truth[k]
            samples.append(sample)
        self.fault_onset_s = record.meta.get("fault_onset_s")
        self.events = det.events
        if printed_job is not None:
            self._prepare_part(printed_job, twin.line_model, run, record, by_step)
        return samples

    def _prepare_part(self, job, line_model, run, record, alarms_by_step: dict) -> None:
        """The part map's chunks, step by step, from the filtered states, each published
        when a live twin would have it: once the step is final, H rows after it (the
        camera's horizon, :mod:`ajtwin.estimation.print_time`; 0 without a job)."""
        part = LivePartMap(job, line_model, self.tolerance)
        self.part_header = part.header()
        covariances = run.total_covariances()
        last = len(run.time_s) - 1
        horizon = float(run.camera_counts.get("horizon_s", 0.0))
        for k, t in enumerate(run.time_s):
            chunk = part.step(float(t), run.means[k], covariances[k], record.inputs[k])
            if alarms_by_step.get(k):
                chunk = dict(chunk or {})
                chunk["alarms"] = part.alarms(alarms_by_step[k])
            if chunk:
                final_at = last if not np.isfinite(horizon) else min(k + int(horizon), last)
                held = self.part_chunks.setdefault(final_at, {})
                _merge_chunk(held, chunk)

    # ------------------------------------------------------------------ replay
    def _run(self):
        try:
            if self.samples is None:
                self.samples = self.prepare()
            # optionally hold the print until a page listens (bounded), so nothing is missed
            deadline = time.monotonic() + self.wait_for_viewer_s
            while self.publisher.n_subscribers == 0 and time.monotonic() < deadline:
                if self._stop.wait(0.05):
                    break
            period = 1.0 / self.rate_hz
            t0 = time.monotonic()
            if self.part_header is not None:
                self.publisher.open_part(self.machine, self.part_header)
            for k, sample in enumerate(self.samples):
                if self._stop.is_set():
                    break
                delay = t0 + k * period - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                self.publisher.publish(sample)
                if k in self.part_chunks:
                    self.publisher.publish_part(self.machine, self.part_chunks[k])
            self.publisher.end_print(self.machine)
        except Exception as exc:  # shown on the page and the server log, not swallowed
            self.error = f"{type(exc).__name__}: {exc}"
            self.publisher.announce(
                {"type": "feed_error", "machine": self.machine, "message": self.error}
            )
            raise
        finally:
            self.done.set()

    def start(self) -> VirtualPrintFeed:
        """Prepare and replay in a background thread; returns the feed."""
        self.publisher.open_print(self.machine)
        self._thread = threading.Thread(target=self._run, name="virtual-print-feed", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Ask the replay to stop after its current sample."""
        self._stop.set()

    def join(self, timeout: float | None = None) -> bool:
        """Wait (at most ``timeout`` seconds) for the replay to end; whether it did."""
        return self.done.wait(timeout)
