"""The live twins of many machines in one process: samples in, messages out.

:class:`LiveEngine` keeps one :class:`~ajtwin.engine.stream.TwinStream` per machine,
steps the machines whose samples arrive together as one vmapped EKF step, writes the
live log as it goes, resumes open sessions after a restart and stores a finished print
as an ordinary registry print.

Publish/subscribe
-----------------
Every committed (and provisional) step is a :class:`~ajtwin.engine.messages.StepMessage`
(:meth:`TwinStream.feed` returns them; :class:`LiveEngine` hands them to subscribers), the
end of a print a :class:`~ajtwin.engine.messages.FinishedMessage`; a machine link's
connection state comes on the same path as a :class:`~ajtwin.engine.messages.LinkMessage`
(:meth:`LiveEngine.publish_link`). ``to_dict()`` gives each as JSON
(docs/reference/live-messages.md).
"""

from __future__ import annotations

import asyncio
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from ajtwin.apps.detection.settings import DetectorSettings
from ajtwin.engine.chain import chain_start
from ajtwin.engine.ingest import TwinOutcome, save_print
from ajtwin.engine.messages import FinishedMessage, LinkMessage, LinkState, StepMessage
from ajtwin.engine.parts import WHOLE_PRINT_ARRAYS, PrintWriter
from ajtwin.engine.start import carried_long_run_history, machine_start
from ajtwin.engine.stream import TwinStream, step_streams_together, warm_up_streams
from ajtwin.estimation.samples import Sample
from ajtwin.store.live_log import LiveLog

log = logging.getLogger("ajtwin.live")


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
    writer: PrintWriter | None = None  # the print's arrays, written as the steps commit
    written: int = 0  # committed steps given to the writer


def _rounds(items) -> list[list]:
    """``items`` [(machine, Sample)] cut, in order, into runs in which each machine comes at
    most once (a machine seen again starts the next run)."""
    rounds: list[list] = [[]]
    names: set = set()
    for machine, sample in items:
        if machine in names:
            rounds.append([])
            names = set()
        rounds[-1].append((machine, sample))
        names.add(machine)
    return [r for r in rounds if r]


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
            self.log = LiveLog(registry.path)
        self.twin_overrides = dict(twin_overrides or {})
        self.detector_settings = detector_settings
        self.asynchronous = asynchronous
        self.commit_every_s = float(commit_every_s)
        self._executor = ThreadPoolExecutor(max(1, int(em_workers)), thread_name_prefix="em")
        self.sessions: dict[str, _Session] = {}
        self._subscribers: list = []
        #: machine → the job its print runs (:func:`ajtwin.engine.print_job.job_entry`),
        #: stored with the print when it ends
        self.jobs: dict[str, dict] = {}

    def warm_up(self, n_machines: int = 1) -> None:
        """Compile the step functions (single and batched) before the first real sample."""
        warm_up_streams(self.twin_overrides, self.detector_settings, n_machines)

    # ------------------------------------------------------------------ #
    def subscribe(self, callback) -> callable:
        """Call ``callback(message)`` for every message; returns a function that unsubscribes."""
        self._subscribers.append(callback)
        return lambda: self._subscribers.remove(callback)

    def queue(self, maxsize: int = 0, loop=None):
        """An asyncio.Queue that receives every message (thread-safe put into ``loop``)."""
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

    def publish_link(self, machines, link: LinkState) -> None:
        """Tell subscribers the state of the link that feeds ``machines`` (module docstring)."""
        self._publish([LinkMessage(name, link) for name in machines])

    def _publish(self, messages: list[dict]) -> None:
        for message in messages:
            for callback in list(self._subscribers):
                try:
                    callback(message)
                except Exception:  # a broken subscriber must not stop the twin
                    log.exception("subscriber %r failed", callback)

    # ------------------------------------------------------------------ #
    def open(self, machine: str, source: str = "live", print_context=None) -> TwinStream:
        """The machine's stream: its open live session resumed, or a new one.

        ``print_context`` (:class:`~ajtwin.estimation.print_time.PrintContext`): the machine
        prints a job; its samples carry the job columns and the camera's measurements are
        filed at their print times (:class:`TwinStream`). Such a stream steps on its own,
        not in the batched step of the other machines. Resuming a job session after a
        restart replays its stored samples, which hold the filed steps without their speed
        factors: refused (start a new session).
        """
        if machine in self.sessions:
            return self.sessions[machine].stream
        start, theta, expected, started_from, session_id = None, None, None, "initial fit", None
        resumed = None
        twin_kwargs = self.twin_overrides
        long_run = None
        if self.registry is not None:
            try:
                self.registry.machine(machine)
            except Exception:
                self.registry.add_machine(machine, notes="added by ajtwin live")
                log.info("machine %r added to the registry", machine)
            resumed = self.log.open_session_of(machine)
            if resumed is not None and print_context is not None:
                raise ValueError(
                    f"{machine}: live session {resumed['id']} is open; a job print cannot "
                    "resume it (its stored samples are filed steps without their speed "
                    "factors): close it first"
                )
            # the machine's calibration, commissioning start and maintenance (model reference §11)
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
            print_context=print_context,
        )
        session = _Session(
            stream, session_id, expected, started_from, source, [], [], time.monotonic()
        )
        if session_id is not None:
            label = f"live session {session_id}"
            self.registry.discard_drafts(machine, label)  # a replay writes its parts again
            session.writer = PrintWriter(self.registry, machine, label)
        if resumed is not None:
            self._replay(session, machine)
        stream.asynchronous = self.asynchronous
        self.sessions[machine] = session
        return stream

    def stream(self, machine: str) -> TwinStream | None:
        """The machine's stream while its print is open (None otherwise)."""
        entry = self.sessions.get(machine)
        return None if entry is None else entry.stream

    def _replay(self, session: _Session, machine: str) -> None:
        """A resumed session: its stored samples through the twin again, a batch at a time,
        the print's parts written as they go."""
        stream, t_last = session.stream, None
        for t, u, y in self.log.iter_samples(session.session_id):
            for k in range(len(t)):
                stream.feed(Sample(t[k], u[k], y[k]))
            self._write_parts(session)
            t_last = t[-1] if len(t) else t_last
        log.info(
            "%s: resumed live session %d at step %d (t = %s s)",
            machine,
            session.session_id,
            stream.n_received,
            None if t_last is None else f"{t_last:g}",
        )

    def _write_parts(self, session: _Session) -> None:
        """Give the writer the steps committed since the last call (it writes whole parts)."""
        if session.writer is None:
            return
        stream = session.stream
        done = stream.n_committed
        if done > session.written:
            arrays = stream.arrays(since=session.written)
            session.writer.add(arrays)
            session.written = done

    def feed(self, machine: str, sample: Sample) -> list[dict]:
        """One sample of one machine (opens the machine on first use)."""
        return self.feed_many([(machine, sample)])

    def feed_many(self, items) -> list[dict]:
        """Samples of several machines [(machine, Sample)]; ordinary steps run batched.

        A machine's samples are taken in order, one per batched round: a machine's next
        step starts from the carry its previous step left (several of its samples in one
        batch would all start from the same one), and a batch is never larger than the
        fleet (each new batch size is one more compiled step kept for the process's life).
        """
        messages: list[dict] = []
        for batch in _rounds(items):
            plain = []
            for machine, sample in batch:
                stream = self.open(machine)
                taken = stream.take_plain(sample)
                if taken is None:
                    messages += stream.feed(sample)
                else:
                    plain.append((stream, taken))
            messages += step_streams_together(plain)
        messages += self.poll()
        self._record(messages)
        self._publish(messages)
        return messages

    def poll(self) -> list[dict]:
        """Messages from EM results that landed (replayed held samples), all machines."""
        out = []
        for session in self.sessions.values():
            out += session.stream.poll()
        return out

    def poll_and_publish(self) -> list[dict]:
        """Messages of EM results that landed, recorded in the live log and published."""
        messages = self.poll()
        self._record(messages)
        self._publish(messages)
        return messages

    # ------------------------------------------------------------------ #
    def _record(self, messages: list) -> None:
        if self.log is None:
            return
        now = time.monotonic()
        for m in messages:
            session = self.sessions.get(m.machine)
            if session is None or not isinstance(m, StepMessage) or m.provisional:
                continue
            session.unsaved.append((m.step, m.time_s, m.input_values, m.output_values, m.to_dict()))
            session.unsaved_events += list(m.events)
            if session.writer is not None:
                for event in m.events:
                    session.writer.note_alarm(event["detected_s"], event["onset_s"])
        for session in self.sessions.values():
            if session.unsaved and now - session.last_flush >= self.commit_every_s:
                self._flush(session)

    def _flush(self, session: _Session) -> None:
        if self.log is None or session.session_id is None:
            return
        self.log.append(session.session_id, session.unsaved, session.unsaved_events)
        session.unsaved, session.unsaved_events = [], []
        session.last_flush = time.monotonic()
        self._write_parts(session)

    def flush(self) -> None:
        """Write every committed step not yet stored."""
        for session in self.sessions.values():
            self._flush(session)

    def close(self, machine: str) -> int | None:
        """End of the machine's print: finish the twin, store the print; its registry id."""
        session = self.sessions.pop(machine)
        stream = session.stream
        messages = stream.finish()
        self._record_into(session, messages)
        self._flush(session)
        self._publish(messages)
        if self.registry is None or session.session_id is None:
            return None
        self._write_parts(session)
        writer = session.writer
        if writer.n_steps < 2:  # nothing stored: the session's rows are all there is of it
            writer.discard()
            self.log.close_session(session.session_id, None)
            return None
        meta = {"machine_id": machine, "source": session.source, "live_session": session.session_id}
        for event in stream.detector.events:  # the alarms' covariances are key frames
            writer.note_alarm(event.detected_s, event.onset_s)
        status, reason = writer.judgement(stream.start_mean)
        theta_history = {
            k: v
            for k, v in stream.arrays(since=stream.n_committed).items()
            if k in WHOLE_PRINT_ARRAYS
        }
        outcome = TwinOutcome(
            arrays=theta_history,
            events=list(stream.detector.events),
            start=(stream.start_mean, stream.start_cov),
            end=(writer.last_mean, writer.last_cov),
            theta_before=stream.theta_before,
            theta_after=stream.theta,
            started_from=session.started_from,
            status=status,
            status_reason=reason,
            long_run_history=stream.detector.long_run_history(),
        )
        print_id, _ = save_print(
            self.registry,
            machine,
            SimpleNamespace(meta=meta),
            outcome,
            digest=writer.content_hash(meta),
            source=f"live session {session.session_id} ({session.source})",
            expected_last_seq=session.expected_last_seq,
            live_session=session.session_id,  # closed (and thinned) with the print
            keep_live_steps=self.keep_live_steps,
            writer=writer,
            n_samples=writer.n_steps,
            job=self.jobs.get(machine),
        )
        return print_id

    def _record_into(self, session: _Session, messages: list) -> None:
        for m in messages:
            if isinstance(m, StepMessage) and not m.provisional:
                session.unsaved.append(
                    (m.step, m.time_s, m.input_values, m.output_values, m.to_dict())
                )
            if isinstance(m, StepMessage | FinishedMessage):
                session.unsaved_events += list(m.events)

    def shutdown(self) -> None:
        """Write what is committed and stop the EM workers (sessions stay open: resumable)."""
        self.flush()
        self._executor.shutdown(wait=False, cancel_futures=True)
