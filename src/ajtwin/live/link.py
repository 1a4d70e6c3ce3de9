"""Machine links of the live twin: an OPC UA client and a CSV tail (``ajtwin live``).

:class:`OpcUaLink` subscribes to each machine's ``Monitoring/Process/SampleBuffer``
(the last samples as rows, so a notification that coalesces several samples loses none),
feeds new samples to a :class:`~ajtwin.engine.fleet.LiveEngine` (batched over machines),
and writes the twin's states ± σ, status and cause back to ``Monitoring/Health``; every
raised or finalised alarm is written to ``Health/Alarm``, which the server turns into a
``TwinAlarmEventType`` event. When a machine's ``PrintState`` says ``finished`` and its
last sample is in, the print is closed (stored as a registry print).

Faults: a lost connection is retried with exponential back-off (the samples the server
no longer buffers become a gap = missing data). The link's state — connecting, connected,
reconnecting since T (attempt n), refused, ended — is logged and published on the
engine's message path (:meth:`LiveEngine.publish_link`, shown by the dashboard), and
after each (re)connection written to each machine's ``Health/LinkStatus`` for HMIs;
a refused login or certificate stops the link with a clear message (retrying cannot
help); a missing node or bad values are logged and the sample treated as missing; a
``PrintState`` that is not one of its texts is logged and ignored.

New rows of a buffer are queued (:class:`RowQueue`) and fed to the engine a slice at a
time (:data:`FEED_BUDGET_S` of work, then the event loop runs): a burst of 100,000 rows
is taken over minutes while the session's keep-alives and the ``finished`` state still
get through, and a machine's print is closed only when its queue is empty. Rows whose time
goes back (the machine's clock stepped back, a buffer out of order) are dropped with one
log line per notification saying how many and which times (:func:`new_rows`); their
seconds are missing data for the twin.

:func:`follow_csv` tails a growing CSV in the record format.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
from asyncua import Client, ua

from ajtwin.engine.fleet import LiveEngine
from ajtwin.engine.messages import LinkState, StepMessage
from ajtwin.estimation.samples import Sample, clean_sample
from ajtwin.io.follow import CsvFollower
from ajtwin.live.opcua import (
    HEALTH_STATES,
    NAMESPACE_URI,
    SAMPLE_WIDTH,
    node_path,
    security_string,
)

log = logging.getLogger("ajtwin.live")

#: server answers that retrying cannot fix
REFUSALS = {
    "BadUserAccessDenied": "the server refused the user name or password",
    "BadIdentityTokenInvalid": "the server refused the user identity",
    "BadIdentityTokenRejected": "the server does not accept this kind of login "
    "(anonymous access may be off: give --username/--password)",
    "BadCertificateUntrusted": "the server does not trust our certificate",
    "BadSecurityChecksFailed": "the server refused our certificate or security settings",
    "BadCertificateInvalid": "the server found our certificate invalid",
    "BadSecurityPolicyRejected": "the server does not offer this --security policy",
    "No matching endpoints": "the server offers no endpoint with this security "
    "(an encrypted server needs --security Basic256Sha256_SignAndEncrypt)",
}


#: the texts ``PrintState`` takes (docs/reference/opcua.md)
PRINT_STATES = ("printing", "finished")

#: seconds of feeding queued samples before the link lets the event loop run again (the
#: OPC UA session's keep-alives, new notifications); a slice is at least one row per machine
FEED_BUDGET_S = 0.25
#: rows taken from each machine's queue at a time within a slice
FEED_ROWS = 32
#: a step back of the sample time by more than this [s], the samples running on from there,
#: is a new print (a machine restarted mid-print begins again at t = 0); a smaller step back
#: is a clock adjustment or a buffer out of order: those samples are dropped
NEW_PRINT_BACK_S = 60.0
#: samples in increasing order the new clock must show before it is taken as a new print
NEW_PRINT_ROWS = 3
#: a print whose first sample comes later than this [s] after its start was partly missed
MISSED_START_S = 5.0
#: rows queued at once from which the link says it is catching up (and when it has)
CATCH_UP_ROWS = 600
#: reconnection attempts made within a second of the last one before the wait grows
FAST_RETRIES = 20


class LinkRefused(RuntimeError):
    """The server refused us for good (credentials, certificate, policy)."""


@dataclass(frozen=True)
class OpcUaLogin:
    """How a client logs in to an OPC UA server.

    ``username``/``password``: an authenticated session (set-points are written only by
    one); ``security``: a policy such as ``Basic256Sha256_SignAndEncrypt`` (needs
    ``certificate`` (DER/PEM) and ``private_key`` (PEM)); ``server_certificate``: pin the
    server's certificate; ``timeout_s``: a request's longest wait.
    """

    username: str | None = None
    password: str | None = field(default=None, repr=False)
    security: str | None = None
    certificate: object = None
    private_key: object = None
    server_certificate: object = None
    timeout_s: float = 4.0


class OpcUaLink:
    """Follow machines on one OPC UA server (see module docstring).

    Parameters
    ----------
    url : str
        ``opc.tcp://host:port``.
    machines : list of str
        Machine names under ``Machines/``.
    engine : LiveEngine
    login : OpcUaLogin, optional
        How to log in (default: anonymous, no security).
    publish_ms : int
        Subscription publishing interval.
    max_backoff_s : float
        Longest wait between reconnection attempts.
    close_finished : bool
        Store a machine's print when its PrintState says finished.
    """

    def __init__(
        self,
        url: str,
        machines: list[str],
        engine: LiveEngine,
        *,
        login: OpcUaLogin | None = None,
        publish_ms: int = 100,
        max_backoff_s: float = 10.0,
        close_finished: bool = True,
    ):
        self.url = url
        self.machines = list(machines)
        self.engine = engine
        self.login = login or OpcUaLogin()
        self.publish_ms = int(publish_ms)
        self.max_backoff_s = float(max_backoff_s)
        self.close_finished = close_finished
        self.status = "starting"
        self.finished: set[str] = set()
        self.last_time: dict[str, float] = {}
        self.queues: dict[str, RowQueue] = {}  # rows received, not yet fed
        # samples taken from the queues and not fed yet, by time: [(machine, Sample), ...]
        self._unfed: deque[list] = deque()
        self.longest_slice_s = 0.0  # the longest the feeding held the event loop
        self.slices_cut = 0  # slices that gave the event loop back with rows still queued
        self.first_published: float | None = None
        self.reconnects = 0
        self.link: LinkState | None = None  # the last published link state
        self._lost_at: float | None = None  # Unix time the current outage began
        self._attempt = 0  # failed attempts in the current outage
        self.print_ids: dict[str, str] = {}  # the PrintId each machine served last
        self._new_print_queued: set[str] = set()  # a new print's rows queued behind the old
        self.new_prints = 0  # prints ended because the machine began a new one
        self.buffer_sizes: dict[str, int] = {}  # rows of each machine's SampleBuffer
        self._catching_up: dict[str, tuple] = {}  # machine → (since, rows) of a burst

    def _set_status(self, status: str, level=logging.INFO):
        if status != self.status:
            self.status = status
            log.log(level, "link %s: %s", self.url, status)

    def _announce(self, state: str, *, reason: str = "", retry_in_s=None, gap_s=None) -> None:
        """Publish the link state to the engine's subscribers (machines still followed)."""
        now = time.time()
        since = self._lost_at if state == "reconnecting" else now
        self.link = LinkState(state, self.url, since, self._attempt, retry_in_s, reason, gap_s)
        followed = [m for m in self.machines if m not in self.finished or state == "ended"]
        self.engine.publish_link(followed, self.link)

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Follow until every machine's print is finished (or ``stop`` is set)."""
        self._announce("connecting")
        while (stop is None or not stop.is_set()) and len(self.finished) < len(self.machines):
            try:
                await self._session(stop)
            except LinkRefused as exc:
                self._announce("refused", reason=str(exc))
                raise
            except (asyncio.CancelledError, KeyboardInterrupt):
                raise
            except Exception as exc:  # network faults, server restarts: retry
                refusal = _refusal(exc)
                if refusal:
                    self._set_status(f"refused: {refusal}", logging.ERROR)
                    self._announce("refused", reason=refusal)
                    raise LinkRefused(f"{self.url}: {refusal} ({type(exc).__name__})") from None
                self.engine.flush()
                reason = fault_text(exc, self.url, self.login.timeout_s)
                if self._lost_at is None:
                    self._lost_at = time.time()
                self._attempt += 1
                backoff = retry_delay_s(self._attempt, self.max_backoff_s)
                self._set_status(
                    f"disconnected ({reason}); reconnecting in {backoff:g} s", logging.WARNING
                )
                self._announce("reconnecting", reason=reason, retry_in_s=backoff)
                self.reconnects += 1
                try:
                    await asyncio.wait_for(
                        stop.wait() if stop else asyncio.sleep(backoff), timeout=backoff
                    )
                except TimeoutError:
                    pass
        self.engine.flush()
        self._announce("ended")

    async def _client(self):

        client = Client(self.url, timeout=self.login.timeout_s)
        client.session_timeout = 30000
        if self.login.username:
            client.set_user(self.login.username)
            client.set_password(self.login.password or "")
        if self.login.security:
            await client.set_security_string(
                security_string(
                    self.login.security,
                    self.login.certificate,
                    self.login.private_key,
                    self.login.server_certificate,
                )
            )
            client.application_uri = "urn:ajtwin:live-client"
        elif self.login.certificate:
            raise LinkRefused("--certificate given without --security")
        return client

    async def _session(self, stop):

        client = await self._client()
        async with client:
            idx = await client.get_namespace_index(NAMESPACE_URI)
            nodes = {}
            for name in self.machines:
                if name in self.finished:
                    continue
                try:
                    nodes[name] = await self._nodes(client, idx, name)
                except ua.UaStatusCodeError as exc:
                    log.error(
                        "machine %r: node missing on %s (%s); not followed", name, self.url, exc
                    )
            if not nodes:
                raise LinkRefused(f"{self.url}: none of the machines {self.machines} is served")
            for name in nodes:
                self.engine.open(name, source=self.url)  # resumes an open live session
                await self._check_print_id(name, nodes[name])
            queue: asyncio.Queue = asyncio.Queue()
            by_node = {n["buffer"].nodeid: name for name, n in nodes.items()}
            by_node.update({n["state"].nodeid: name for name, n in nodes.items()})
            id_nodes = {n["print_id"].nodeid: name for name, n in nodes.items() if n["print_id"]}
            by_node.update(id_nodes)

            class Handler:
                def datachange_notification(self, node, value, data):
                    queue.put_nowait((by_node.get(node.nodeid), node.nodeid, value))

                def status_change_notification(self, status):
                    queue.put_nowait((None, "status", status))

            sub = await client.create_subscription(self.publish_ms, Handler())
            await sub.subscribe_data_change([n["buffer"] for n in nodes.values()])
            await sub.subscribe_data_change([n["state"] for n in nodes.values()])
            if id_nodes:
                await sub.subscribe_data_change(
                    [n["print_id"] for n in nodes.values() if n["print_id"]]
                )
            self._set_status(f"connected, following {', '.join(nodes)}")
            await self._connected(client, nodes)
            states = {name: "printing" for name in nodes}
            buffered: set[str] = set()  # machines whose buffer came on this connection
            last_check = time.monotonic()
            while stop is None or not stop.is_set():
                if self._unfed or any(self.queues.values()):  # to feed: only look at the queue
                    await asyncio.sleep(0)
                    item = None
                else:
                    try:
                        item = await asyncio.wait_for(queue.get(), timeout=0.5)
                    except TimeoutError:
                        item = None
                batch = [item] if item else []
                while not queue.empty():
                    batch.append(queue.get_nowait())
                buffers = {}
                for name, nodeid, value in batch:
                    if nodeid == "status":
                        raise ConnectionError(subscription_status_text(value))
                    if name is None or name not in nodes:
                        continue
                    if nodeid == nodes[name]["state"].nodeid:
                        state = print_state(name, value, states.get(name, "printing"))
                        if states.get(name) == "finished" and state == "printing":
                            # its print ended and the next began before we closed it
                            self._begin_new_print(name, "its PrintState went from finished back "
                                                  "to printing")  # fmt: skip
                        states[name] = state
                    elif nodeid in id_nodes:
                        self._print_id_seen(name, value)
                    else:
                        buffers[name] = value
                buffered.update(buffers)
                for name, value in buffers.items():
                    self._enqueue(name, value)
                messages = self._feed_slice()
                messages += self.engine.poll_and_publish()
                await self._publish(client, nodes, messages)
                for name in list(nodes):
                    # finished, its final buffer read (not only the state) and all of it fed
                    if (
                        states.get(name) == "finished"
                        and name in buffered
                        and name not in buffers
                        and not self.queues.get(name)
                        and not self._has_unfed(name)
                    ):
                        if self.close_finished and name in self.engine.sessions:
                            final = self.engine.close(name)
                            log.info("%s: print finished, stored as registry print %s", name, final)
                        self.finished.add(name)
                        nodes.pop(name)
                if not nodes:
                    return
                if time.monotonic() - last_check > 2.0:
                    await client.check_connection()
                    last_check = time.monotonic()

    async def _connected(self, client, nodes) -> None:
        """The link is up: publish it, and write each machine's ``Health/LinkStatus``."""

        gap_s = None if self._lost_at is None else time.time() - self._lost_at
        attempts = self._attempt
        self._lost_at, self._attempt = None, 0
        self._announce("connected", gap_s=gap_s)
        stamp = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        text = f"connected {stamp}"
        if gap_s is not None:
            text += f", back after a {gap_s:.0f} s gap ({attempts} failed attempt(s))"
        for name, n in nodes.items():
            if n.get("link_status") is None:
                continue
            try:
                await n["link_status"].write_value(ua.Variant(text, ua.VariantType.String))
            except ua.UaStatusCodeError as exc:  # read-only or gone: the twin goes on
                log.warning("%s: could not write Health/LinkStatus (%s)", name, exc)

    async def _nodes(self, client, idx, name) -> dict:

        def node(*parts):
            return client.get_node(ua.NodeId(node_path(name, *parts), idx))

        out = {
            "buffer": node("Monitoring", "Process", "SampleBuffer"),
            "state": node("Monitoring", "Process", "PrintState"),
            "alarm": node("Monitoring", "Health", "Alarm"),
            "health": {},
        }
        for key in ("Status", "Cause", "NIS", "TwinTime", "Theta"):
            out["health"][key] = node("Monitoring", "Health", key)
        for key in HEALTH_STATES:
            out["health"][key] = node("Monitoring", "Health", key)
            out["health"][key + "Std"] = node("Monitoring", "Health", key + "Std")
        for n in (out["buffer"], out["state"], out["alarm"]):
            await n.read_browse_name()  # raises BadNodeIdUnknown when missing
        out["link_status"] = node("Monitoring", "Health", "LinkStatus")
        try:
            await out["link_status"].read_browse_name()
        except ua.UaStatusCodeError:  # a server without it (optional)
            out["link_status"] = None
        out["print_id"] = node("Monitoring", "Process", "PrintId")
        try:
            await out["print_id"].read_browse_name()
        except ua.UaStatusCodeError:  # optional too: the clock and PrintState still tell
            out["print_id"] = None
        return out

    async def _check_print_id(self, name: str, nodes: dict) -> None:
        """At a (re)connection: the machine's ``PrintId`` now (a new print if it changed
        while we were away), before any of its samples of this connection are taken."""
        if nodes.get("print_id") is None:
            return
        try:
            value = await nodes["print_id"].read_value()
        except ua.UaStatusCodeError as exc:
            log.warning(
                "%s: could not read PrintId (%s); a new print is told by its clock", name, exc
            )
            return
        self._print_id_seen(name, value)

    def _print_id_seen(self, name: str, value) -> None:
        """A ``PrintId`` value: remembered; a change from the one seen before begins a new
        print."""
        value = None if value is None else str(value)
        before = self.print_ids.get(name)
        if value is None or value == before:
            return
        self.print_ids[name] = value
        if before is not None:
            self._begin_new_print(name, f"its PrintId changed from {before!r} to {value!r}")

    def _begin_new_print(self, name: str, why: str, clock_from: float | None = None) -> None:
        """Rows queued from now on belong to a new print: the queue gets a boundary, where
        the print so far is stored and a new one opened (:meth:`_feed_slice`)."""
        queue = self.queues.setdefault(name, RowQueue())
        queue.mark_new_print()
        queue.tail = None
        self.last_time[name] = -np.inf if clock_from is None else clock_from
        self._new_print_queued.add(name)
        log.warning(
            "%s: the machine began a new print (%s): the print followed so far is stored and "
            "a new one opened",
            name,
            why,
        )

    def _enqueue(self, name: str, value) -> None:
        """Queue the new rows of a machine's buffer (:func:`new_rows`); log what is refused."""
        queue = self.queues.setdefault(name, RowQueue())
        rows, problems = buffer_rows(name, value)
        if rows is None:
            for p in problems:
                log.warning(p)
            return
        self.buffer_sizes[name] = len(rows)
        newest = self._newest(name)
        # a machine that serves a PrintId says itself when a print is new: its clock going
        # back under the same id is a server continuing the print (those rows are dropped)
        start = None if name in self.print_ids else new_print_start(rows, newest)
        if start is not None:  # the clock began again: the rows before are the old print's
            self._take_rows(name, queue, rows[:start], newest)
            self._begin_new_print(
                name,
                f"its clock went back from t = {newest:g} s to t = {rows[start, 0]:g} s and runs "
                "on from there",
            )
            rows, newest = rows[start:], -np.inf
        self._take_rows(name, queue, rows, newest)

    def _newest(self, name: str) -> float:
        """The time [s] of the machine's newest sample taken in the print being queued."""
        newest = self.last_time.get(name, -np.inf)
        session = self.engine.sessions.get(name)
        if name in self._new_print_queued or session is None:
            return newest
        if session.stream.last_time is not None:
            newest = max(newest, session.stream.last_time)  # resumed: skip what is stored
        return newest

    def _take_rows(self, name: str, queue: RowQueue, rows, newest: float) -> None:
        """Queue the rows later than ``newest`` (:func:`new_rows`); log those that went back."""
        taken, queue.tail, dropped, after, problems = new_rows(name, rows, queue.tail, newest)
        for p in problems:
            log.warning(p)
        if len(dropped):
            log.warning(
                "%s: %d sample(s) whose time went backwards dropped (t = %s s, after t = %g s):"
                " the machine's clock stepped back or its buffer is out of order; their seconds"
                " are missing data",
                name,
                len(dropped),
                _times_text(dropped),
                after,
            )
        if len(taken):
            queue.append(taken)
            self.last_time[name] = float(taken[-1, 0])
            if len(queue) >= CATCH_UP_ROWS and name not in self._catching_up:
                self._catching_up[name] = (time.monotonic(), len(queue))
                log.warning(
                    "%s: %d samples arrived at once (%.1f min of print): the twin takes them "
                    "in slices and lags the machine until it has caught up",
                    name,
                    len(queue),
                    len(queue) / 60.0,
                )

    def _feed_slice(self) -> list:
        """Feed queued rows to the engine for about :data:`FEED_BUDGET_S` (at least one
        round), machines merged in time order so that their ordinary steps run batched."""
        messages = []
        start = time.monotonic()
        while self._unfed or any(self.queues.values()):
            if not self._unfed:
                by_time: dict[float, list] = {}
                for name, queue in self.queues.items():
                    if queue.at_new_print():  # the old print's rows are all fed
                        queue.pass_new_print()
                        messages += self._store_and_reopen(name)
                    rows = queue.take(FEED_ROWS)
                    if not len(rows):
                        continue
                    samples, _, problems = buffer_samples(name, rows, -np.inf)
                    for p in problems:
                        log.warning(p)
                    for sample in samples:
                        by_time.setdefault(sample.time_s, []).append((name, sample))
                self._unfed.extend(by_time[t] for t in sorted(by_time))
            # the budget is checked after each time step (a step may replay held samples)
            while self._unfed and time.monotonic() - start < FEED_BUDGET_S:
                items = self._unfed.popleft()
                self._say_missed_start(items)
                messages += self.engine.feed_many(items)
            if time.monotonic() - start >= FEED_BUDGET_S:
                self.slices_cut += bool(self._unfed or any(self.queues.values()))
                break
        self.longest_slice_s = max(self.longest_slice_s, time.monotonic() - start)
        for name, (since, rows) in list(self._catching_up.items()):
            if not self.queues.get(name) and not self._has_unfed(name):
                log.warning(
                    "%s: caught up: the %d samples that arrived at once took %.0f s",
                    name,
                    rows,
                    time.monotonic() - since,
                )
                del self._catching_up[name]
        return messages

    def _has_unfed(self, name: str) -> bool:
        """Whether rows of ``name`` taken from its queue still wait to be fed."""
        return any(m == name for items in self._unfed for m, _ in items)

    def _store_and_reopen(self, name: str) -> list:
        """A machine's new print: the print so far stored, a new live session opened."""
        if not self.queues[name].has_new_print():
            self._new_print_queued.discard(name)
        stream = self.engine.stream(name)
        if stream is None or not stream.n_received:  # nothing of the old print: no print
            return []
        final = self.engine.close(name)
        self.new_prints += 1
        log.warning("%s: the print followed so far is stored as registry print %s", name, final)
        self.engine.open(name, source=self.url)
        return []

    def _say_missed_start(self, items) -> None:
        """The first sample of a machine's print: if it comes well after the print's start,
        say how much of the print the twin missed and why (log and link state)."""
        for name, sample in items:
            stream = self.engine.stream(name)
            if stream is None or stream.n_received or sample.time_s <= MISSED_START_S:
                continue
            text = missed_start_text(sample.time_s, self.buffer_sizes.get(name))
            log.warning("%s: %s", name, text)
            link = replace(self.link or LinkState("connected", self.url), missed_s=sample.time_s)
            self.engine.publish_link([name], link)

    async def _publish(self, client, nodes, messages):

        latest = {}
        for m in messages:
            if isinstance(m, StepMessage):
                latest[m.machine] = m
        for name, m in latest.items():
            if name not in nodes:
                continue
            h = nodes[name]["health"]
            targets, values = [], []
            for key, (state, *_) in HEALTH_STATES.items():
                targets += [h[key], h[key + "Std"]]
                values += [m.states[state], m.stds[state]]
            targets += [h["NIS"], h["TwinTime"]]
            values += [m.nis, m.time_s]
            variants = [ua.Variant(float(v), ua.VariantType.Double) for v in values]
            targets += [h["Status"], h["Cause"], h["Theta"]]
            variants += [
                ua.Variant(m.status, ua.VariantType.String),
                ua.Variant(m.cause, ua.VariantType.String),
                ua.Variant(list(m.theta.values()), ua.VariantType.Double),
            ]
            await client.write_values(targets, [ua.DataValue(v) for v in variants])
            if self.first_published is None:
                self.first_published = time.monotonic()
        for m in messages:
            for event in getattr(m, "events", ()):
                if m.machine not in nodes:
                    continue
                await nodes[m.machine]["alarm"].write_value(
                    ua.Variant(json.dumps(event, default=str), ua.VariantType.String)
                )
                log.warning(
                    "%s: ALARM %s at t = %g s (onset %g s): %s",
                    m.machine,
                    event["state"],
                    event["detected_s"],
                    event["onset_s"],
                    event["description"],
                )
                await asyncio.sleep(0.15)  # one server-side notification per alarm


class RowQueue:
    """A machine's buffer rows received and not yet fed (oldest first), with the boundaries
    where a new print begins, and the last row of its latest buffer (where the next
    buffer's new rows begin)."""

    def __init__(self):
        self._parts: list[np.ndarray | None] = []  # None: a new print begins here
        self._head = 0  # rows of the first part already taken
        self.tail: np.ndarray | None = None

    def __len__(self) -> int:
        return sum(len(p) for p in self._parts if p is not None) - self._head

    def __bool__(self) -> bool:
        """Rows or a new print's boundary still to take."""
        return bool(self._parts)

    def append(self, rows: np.ndarray) -> None:
        """Queue rows (n, SAMPLE_WIDTH)."""
        self._parts.append(np.asarray(rows, dtype=float))

    def mark_new_print(self) -> None:
        """The rows queued after this belong to a new print."""
        self._parts.append(None)

    def at_new_print(self) -> bool:
        """Whether every row before the next new print's boundary has been taken."""
        return bool(self._parts) and self._parts[0] is None

    def has_new_print(self) -> bool:
        """Whether a new print's boundary is queued."""
        return any(p is None for p in self._parts)

    def pass_new_print(self) -> None:
        """Step over the boundary at the head (:meth:`at_new_print`)."""
        if self.at_new_print():
            self._parts.pop(0)

    def take(self, n: int) -> np.ndarray:
        """Up to ``n`` oldest rows, removed from the queue; never past a new print's
        boundary."""
        out = []
        while self._parts and self._parts[0] is not None and n > 0:
            part = self._parts[0]
            chunk = part[self._head : self._head + n]
            out.append(chunk)
            n -= len(chunk)
            self._head += len(chunk)
            if self._head >= len(part):
                self._parts.pop(0)
                self._head = 0
        return np.concatenate(out) if out else np.empty((0, SAMPLE_WIDTH))


def new_print_start(rows, newest: float, back_s: float = NEW_PRINT_BACK_S,
                    min_rows: int = NEW_PRINT_ROWS) -> int | None:  # fmt: skip
    """Where a new print begins in a buffer, or None.

    The buffer's newest row lies more than ``back_s`` seconds before the newest sample
    taken (``newest``) and ends a run of at least ``min_rows`` rows in increasing time: the
    machine's clock began again (a restart begins at t = 0) and runs on. Returns the index
    of the run's first row. Rows going back one after another (a clock stepping back, a
    buffer out of order) are no run and give None.

    Examples
    --------
    >>> rows = lambda times: np.array([[t] + [0.0] * 8 for t in times])
    >>> new_print_start(rows([747, 748, 749, 0, 1, 2, 3]), 749.0)
    3
    >>> new_print_start(rows([100, 97, 94, 91]), 100.0) is None   # going back, no run
    True
    >>> new_print_start(rows([700, 701, 702]), 749.0) is None      # a reconnection's overlap
    True
    """
    rows = np.asarray(rows, dtype=float)
    times = rows[:, 0] if rows.ndim == 2 and len(rows) else np.empty(0)
    index = np.flatnonzero(np.isfinite(times))
    if not len(index) or not times[index[-1]] < newest - back_s:
        return None
    k = len(index) - 1
    while k > 0 and times[index[k - 1]] < times[index[k]]:
        k -= 1
    return int(index[k]) if len(index) - k >= min_rows else None


def retry_delay_s(attempt: int, max_backoff_s: float) -> float:
    """The wait [s] before reconnection attempt ``attempt + 1`` of an outage: 0.5 s, then
    1 s for :data:`FAST_RETRIES` attempts (a server restarting is back within seconds, and
    every second away is a second of print the twin may not get back), then doubling up
    to ``max_backoff_s``.

    >>> [retry_delay_s(a, 10.0) for a in (1, 2, 20, 21, 22, 25)]
    [0.5, 1.0, 1.0, 2.0, 4.0, 10.0]
    """
    if attempt <= 1:
        delay = 0.5
    elif attempt <= FAST_RETRIES:
        delay = 1.0
    else:
        delay = 2.0 ** (attempt - FAST_RETRIES)
    return min(delay, max_backoff_s)


def missed_start_text(first_s: float, buffer_rows: int | None) -> str:
    """The sentence for a print the twin joined late (its first sample at ``first_s``).

    >>> missed_start_text(210.0, 300)[:62]
    'joined this print 3.5 min after its start (first sample t = 21'
    """
    held = f"{buffer_rows} samples" if buffer_rows else "its last samples"
    return (
        f"joined this print {first_s / 60:.1f} min after its start (first sample t = "
        f"{first_s:g} s): the first {first_s / 60:.1f} min were printed before the twin "
        f"connected and are no longer in the machine's buffer ({held}); the twin starts "
        "from there. Start the twin before the print (`printer serve --wait-for-client` "
        "holds a virtual print until it connects)"
    )


def buffer_rows(name: str, value) -> tuple[np.ndarray | None, list[str]]:
    """A ``SampleBuffer`` value as rows (n, SAMPLE_WIDTH), or (None, the log line) when it
    is not a table of numbers of that width (None, text, bytes, a ragged list)."""
    try:
        return np.asarray(value, dtype=float).reshape(-1, SAMPLE_WIDTH), []
    except (TypeError, ValueError, OverflowError):
        return None, [f"{name}: SampleBuffer has the wrong shape or type; ignored"]


def _last_index_of(rows: np.ndarray, row: np.ndarray) -> int | None:
    same = (rows == row) | (np.isnan(rows) & np.isnan(row))
    found = np.flatnonzero(same.all(axis=1))
    return int(found[-1]) if found.size else None


def new_rows(name: str, rows, previous_tail, newest: float):
    """The rows of a buffer that are new samples, in order.

    A buffer holds the machine's last samples, oldest first. Its new rows are those after
    the previous buffer's last row (``previous_tail``), when that row is still in it. A new
    row must be later than every sample taken (``newest`` [s]) and than the new rows
    before it; one that is not went back in time and is dropped (the machine's clock
    stepped back; where to put it on the 1 s grid is unknown). Without the previous last
    row (the first buffer, a reconnection, more new rows than the buffer holds) the rows up
    to the first later one are taken as the overlap with what was read before.
    All-NaN rows (a buffer's unfilled slots) are skipped; a row without a finite time is
    reported.

    Returns
    -------
    taken : (k, SAMPLE_WIDTH) the new samples' rows, times increasing
    tail : the buffer's last row (for the next buffer)
    dropped : (j,) times [s] of the rows that went back in time
    after : the time [s] the first of them should have followed (NaN: none dropped)
    problems : log lines for rows without a time

    Examples
    --------
    >>> row = lambda t: [t, 375, 23, 50, 70, 8, 5800, 5780, 1e-8]
    >>> taken, tail, dropped, after, _ = new_rows(
    ...     "m", np.array([row(4), row(5), row(2), row(6)]), np.array(row(4)), 4.0)
    >>> taken[:, 0].tolist(), dropped.tolist(), after
    ([5.0, 6.0], [2.0], 5.0)
    """
    rows = np.asarray(rows, dtype=float)
    filled = ~np.isnan(rows).all(axis=1)
    tail = rows[filled][-1].copy() if filled.any() else previous_tail
    start = None if previous_tail is None else _last_index_of(rows, previous_tail)
    known = start is not None  # the rows after the previous tail are all new
    later = float(newest)
    after = np.nan
    keep, dropped, problems = [], [], []
    for i in range(0 if start is None else start + 1, len(rows)):
        if not filled[i]:
            continue
        t = rows[i, 0]
        if not np.isfinite(t):
            problems.append(f"{name}: SampleBuffer row with time {t!r}; dropped")
        elif t > later:
            keep.append(i)
            later, known = float(t), True
        elif known:
            after = later if not dropped else after
            dropped.append(float(t))
    taken = rows[keep] if keep else np.empty((0, SAMPLE_WIDTH))
    return taken, tail, np.asarray(dropped, dtype=float), after, problems


def _times_text(times) -> str:
    """``"97, 94 … 13"``: the first two and the last of a list of times."""
    shown = [f"{t:g}" for t in times[:2]]
    if len(times) > 3:
        shown.append("…")
    if len(times) > 2:
        shown.append(f"{times[-1]:g}")
    return ", ".join(shown)


def print_state(name: str, value, current: str) -> str:
    """A ``PrintState`` value: one of :data:`PRINT_STATES`, or logged and ignored (the
    machine keeps ``current``): a number (3.14), an empty or unknown text."""
    text = value.strip().lower() if isinstance(value, str) else None
    if text in PRINT_STATES:
        return text
    log.warning(
        "%s: PrintState = %r is not a print state (%s); ignored, the print stays %s",
        name,
        value,
        " or ".join(PRINT_STATES),
        current,
    )
    return current


#: subscription statuses a server sends as it ends a session, in words (asyncua's client
#: also ends its subscriptions with BadShutdown when it finds the connection lost)
STATUS_WORDS = {
    "BadShutdown": "the server stopped, is restarting or no longer answers",
    "BadServerHalted": "the server has stopped",
    "BadTimeout": "the server timed the subscription out (the twin was too busy to answer "
    "in time, or the network dropped)",
    "BadSessionClosed": "the server closed the session",
    "BadSessionIdInvalid": "the server no longer knows this session (it restarted)",
    "BadNoSubscription": "the server no longer holds the subscription",
    "BadCommunicationError": "the network between the twin and the server failed",
    "BadConnectionClosed": "the server closed the connection",
}


def status_code_text(code) -> str:
    """An OPC UA status code in words: its name and, for the codes a link meets when a
    server goes away, what it means.

    >>> status_code_text(2148270080)
    'BadShutdown: the server stopped, is restarting or no longer answers'
    """
    value = getattr(code, "value", code)
    try:
        name, doc = ua.status_codes.get_name_and_doc(int(value))
    except (TypeError, ValueError, KeyError):
        return f"status code {value!r}"
    return f"{name}: {STATUS_WORDS.get(name, doc.rstrip('.') or 'no description')}"


def subscription_status_text(notification) -> str:
    """A subscription's ``StatusChangeNotification`` in words (a raw
    ``StatusCode(value=2148270080)`` said nothing)."""
    code = getattr(notification, "Status", notification)
    return f"the subscription ended: {status_code_text(code)}"


def fault_text(exc: BaseException, url: str, timeout_s: float) -> str:
    """A connection fault in words (the log line and the dashboard's link state): an empty
    TimeoutError said only "TimeoutError: "."""
    if isinstance(exc, TimeoutError):
        return (
            f"no answer from {url} within {timeout_s:g} s (TimeoutError): the server accepts "
            "the connection but does not answer OPC UA, or it is hung"
        )
    if isinstance(exc, ConnectionRefusedError):
        return f"nothing listens at {url} (connection refused): is the server running?"
    if isinstance(exc, ua.UaStatusCodeError):
        return status_code_text(exc.code)
    text = str(exc) or getattr(exc, "strerror", None) or ""
    if text.startswith("the subscription ended"):
        return text
    return f"{type(exc).__name__}: {text}" if text else f"{type(exc).__name__} (no details)"


def buffer_samples(name: str, value, last: float) -> tuple[list[Sample], float, list[str]]:
    """A ``SampleBuffer`` value as it came off the wire → the new samples in it.

    Parameters
    ----------
    name : machine (for the log lines)
    value : anything
        The subscription value: rows of ``SAMPLE_WIDTH`` numbers (time [s], I_A [mA],
        Q_c [sccm], Q_s [sccm], the five outputs), flattened or not. Anything else (None,
        text, bytes, a ragged list) is refused whole with a log line.
    last : float
        Time [s] of the newest sample already taken; rows at or before it are the
        buffer's overlap with the previous notification and are skipped silently, as are
        all-NaN rows (the slots of a buffer not yet filled).

    Returns
    -------
    samples : cleaned samples (:func:`~ajtwin.estimation.samples.clean_sample`), in buffer order
    last : the newest time taken (unchanged if none)
    problems : log lines for everything refused, treated as missing or dropped
    """
    try:
        rows = np.asarray(value, dtype=float).reshape(-1, SAMPLE_WIDTH)
    except (TypeError, ValueError, OverflowError):
        return [], last, [f"{name}: SampleBuffer has the wrong shape or type; ignored"]
    samples, problems = [], []
    for row in rows:
        if np.isnan(row).all():
            continue  # an unfilled slot: the server pads its buffer with all-NaN rows
        if not np.isfinite(row[0]):
            problems.append(f"{name}: SampleBuffer row with time {row[0]!r}; dropped")
            continue
        if row[0] <= last:
            continue
        sample, found = clean_sample(row[0], row[1:4], row[4:], where=name)
        problems += found
        if sample is None:
            continue
        samples.append(sample)
        last = sample.time_s
    return samples, last, problems


def _refusal(exc) -> str | None:
    name = type(exc).__name__
    text = f"{name} {exc}"
    for code, message in REFUSALS.items():
        if code in text:
            return message
    return None


async def follow_csv(
    path,
    machine: str,
    engine: LiveEngine,
    *,
    poll_s: float = 0.5,
    idle_timeout_s: float | None = None,
    stop: asyncio.Event | None = None,
    aliases=None,
    dialect=None,
) -> int | None:
    """Tail a growing record file; feed each 1 s sample to the engine.

    The file is read by :class:`ajtwin.io.follow.CsvFollower`, with the record reader's
    rules (BOM, dialect, names with units, time formats, per-second averaging); lines it
    cannot read are logged and their seconds are missing for the twin.

    Returns the registry print id when the print was closed after ``idle_timeout_s``
    seconds without a new line (None: stopped, the session stays open and resumable).
    """

    follower = CsvFollower(path, aliases=aliases, dialect=dialect)
    last_new = time.monotonic()
    engine.open(machine, source=str(path))

    def feed(samples, problems) -> bool:
        for line in problems:
            log.warning(line)
        for t, u, y in samples:
            sample, issues = clean_sample(t, u, y, where=f"{path}: t = {t:g} s")
            for issue in issues:
                log.warning(issue)
            if sample is not None:
                engine.feed(machine, sample)
        return bool(samples)

    while stop is None or not stop.is_set():
        new = feed(*follower.poll())
        engine.poll_and_publish()
        if new:
            last_new = time.monotonic()
        elif idle_timeout_s is not None and time.monotonic() - last_new > idle_timeout_s:
            feed(*follower.flush())  # the second still open, and rows held back
            return engine.close(machine)
        try:
            await asyncio.wait_for(stop.wait() if stop else asyncio.sleep(poll_s), poll_s)
        except TimeoutError:
            pass
    engine.flush()
    return None


__all__ = ["LinkRefused", "OpcUaLink", "RowQueue", "Sample", "follow_csv", "new_rows"]
