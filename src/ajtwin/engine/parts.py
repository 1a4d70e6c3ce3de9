"""A print's per-second arrays written to the registry while the twin produces them.

A print of a week is 604,800 steps; holding every step's results until the end made
``ingest`` and ``ajtwin live`` grow by 15–50 MB per print-hour. :class:`PrintWriter`
takes the steps a chunk at a time (the batch twin's filter chunks,
:meth:`ajtwin.estimation.Twin.run` with a ``sink``; a live twin's committed steps), writes
them in parts of :data:`PART_STEPS` steps to a draft of the registry
(:meth:`ajtwin.store.registry.Registry.open_draft`) and keeps only what the print's row
needs at the end: the totals of its summary, its last state, where a state first left the
physical range. :meth:`PrintWriter.save` stores the print with its parts in one
transaction; until then nothing of it is in the machine's history, and a process killed
on the way leaves a draft that the next writer removes.

The parts are encoded exactly as a whole print is (:mod:`ajtwin.store.arrays`): the
covariance key frames are those the whole print would keep, the alarms' ones included
(an alarm whose onset lies in a part already written adds its key frame from the
covariances of the last :data:`RING_STEPS` steps).
"""

from __future__ import annotations

import hashlib
import json
from collections import deque
from types import SimpleNamespace

import numpy as np

from ajtwin.engine.chain import judge_run, state_limits

#: steps per part of a print's arrays (one print-hour: ~0.4 MB of blobs)
PART_STEPS = 3600
#: the latest steps whose covariances are kept for the key frames of alarm onsets
RING_STEPS = 2 * PART_STEPS
#: a print's arrays that are not per step (the θ history): stored with the print's row
WHOLE_PRINT_ARRAYS = ("theta_history_time_s", "theta_history")


class PrintWriter:
    """The arrays of one print, written to ``registry`` in parts as they are produced.

    Parameters
    ----------
    registry : Registry
    machine : str
    label : str
        What the print is, for a draft left behind ("ingest of p.parquet", "live session 3").
    part_steps : int
        Steps per part.
    """

    def __init__(self, registry, machine: str, label: str, *, part_steps: int = PART_STEPS):
        self.registry = registry
        self.machine = machine
        self.draft = registry.open_draft(machine, label)
        self.part_steps = int(part_steps)
        self._chunks: list[dict] = []  # steps added and not yet written
        self._pending = 0
        self.n_steps = 0  # steps added so far
        self._first_pending = 0
        self._origin_s: float | None = None
        self._after_s: float | None = None  # time of the last step written
        self._alarm_times: list[float] = []
        self._ring: deque = deque()  # (first step, times, covariances) of the latest chunks
        self._ring_steps = 0  # steps in the ring
        self._extra: dict[int, np.ndarray] = {}  # key frames of alarms in written parts
        self._nis_sum, self._nis_count, self._reinitialised = 0.0, 0, 0
        self.last_time: float | None = None
        self.last_mean = self.last_cov = None
        self._violation = None  # (times, means) of the first chunk with a state out of range
        self.bytes_written = 0
        self._hash = hashlib.sha256()  # of the samples (time, inputs, outputs), row by row

    # ------------------------------------------------------------------ taking steps
    def add(self, arrays: dict) -> None:
        """Steps following those added before, named as
        :meth:`~ajtwin.store.registry.Registry.print_arrays` returns them (``time_s``,
        ``means``, ``covariances`` (n, 5, 5), ``nis``, ...; the θ history is not per step:
        :meth:`save` takes it)."""
        arrays = {k: np.asarray(v) for k, v in arrays.items() if k not in WHOLE_PRINT_ARRAYS}
        t = np.asarray(arrays["time_s"], dtype=float)
        n = len(t)
        if not n:
            return
        if self._origin_s is None:
            self._origin_s = float(t[0])
        covs = np.asarray(arrays["covariances"], dtype=float)
        self._ring.append((self.n_steps, t, covs))
        self._ring_steps += n
        # a live print adds a step at a time: the count is kept, not summed over the ring
        while self._ring_steps - len(self._ring[0][1]) >= RING_STEPS:
            self._ring_steps -= len(self._ring.popleft()[1])
        nis = np.asarray(arrays["nis"], dtype=float)
        self._nis_sum += float(np.nansum(nis))
        self._nis_count += int(np.isfinite(nis).sum())
        self._reinitialised += int(np.asarray(arrays["reinitialised"]).sum())
        means = np.asarray(arrays["means"], dtype=float)
        if self._violation is None and state_limits().first_violation_index(means) is not None:
            self._violation = (t, means)
        self.last_time, self.last_mean, self.last_cov = float(t[-1]), means[-1], covs[-1]
        rows = np.column_stack([t, arrays["inputs"], arrays["measurements"]]).astype(np.float64)
        self._hash.update(np.ascontiguousarray(rows).tobytes())
        self._chunks.append(arrays)
        self._pending += n
        self.n_steps += n
        if self._pending >= self.part_steps:
            self._write(last=False)

    def note_alarm(self, *times) -> None:
        """An alarm's detection and onset times [s]: their covariances become key frames."""
        for when in times:
            when = float(when)
            if not np.isfinite(when):
                continue
            self._alarm_times.append(when)
            if self._after_s is not None and when <= self._after_s:
                self._keyframe_from_ring(when)

    def _keyframe_from_ring(self, when: float) -> None:
        for first, t, covs in self._ring:
            k = int(np.searchsorted(t, when))
            if k < len(t) and (first + k) < self._first_pending:
                self._extra[first + k] = covs[k]
                return

    def _write(self, last: bool) -> None:
        arrays = {k: np.concatenate([c[k] for c in self._chunks]) for k in self._chunks[0]}
        part = {
            "first_step": self._first_pending,
            "origin_s": self._origin_s,
            "after_s": self._after_s,
            "last": last,
        }
        self.bytes_written += self.registry.append_draft(
            self.draft, arrays, part, self._alarm_times
        )
        self._after_s = float(arrays["time_s"][-1])
        self._first_pending += len(arrays["time_s"])
        self._chunks, self._pending = [], 0

    # ------------------------------------------------------------------ the end
    def close(self) -> None:
        """Write the steps not yet written (the print's last part, with its last step's key
        frame) and the key frames of alarms whose onset lay in an earlier part."""
        if self._chunks:
            self._write(last=True)
        elif self.last_cov is not None:
            self._extra[self.n_steps - 1] = self.last_cov
        if self._extra:
            steps = np.array(sorted(self._extra), dtype=np.int64)
            extra = {
                "covariance_steps": steps,
                "covariance_keyframes": np.array([self._extra[k] for k in steps]),
            }
            self.bytes_written += self.registry.append_draft(
                self.draft, extra, {"first_step": 0, "origin_s": 0.0, "after_s": None, "last": True}
            )
            self._extra = {}

    def content_hash(self, meta: dict) -> str:
        """SHA-256 of the samples added (time, inputs, outputs, row by row) and ``meta``: the
        identity of a print that exists only as it was streamed (a live print)."""
        h = self._hash.copy()
        h.update(json.dumps(meta, sort_keys=True, default=str).encode())
        return h.hexdigest()

    @property
    def totals(self) -> dict:
        """What the print's summary says of all its steps: mean NIS, guard re-initialisations."""
        mean = self._nis_sum / self._nis_count if self._nis_count else float("nan")
        return {"mean_nis": mean, "reinitialised": self._reinitialised}

    def judgement(self, start_mean) -> tuple[str, str]:
        """(status, reason) of the print as :func:`ajtwin.engine.chain.judge_run` gives it for
        the whole run (the first state out of range is looked for in the chunk that has it)."""
        times, means = self._violation or (np.array([self.last_time]), self.last_mean[None])
        run = SimpleNamespace(
            means=means,
            time_s=times,
            start_mean=start_mean,
            end_mean=self.last_mean,
            end_cov=self.last_cov,
        )
        return judge_run(run)

    def discard(self) -> None:
        """Remove the draft (the print was refused or failed: nothing of it stays)."""
        self.registry.discard_draft(self.draft)
