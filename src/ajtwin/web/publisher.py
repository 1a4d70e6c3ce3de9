"""In-process publish/subscribe between a live twin and the dashboard's open pages.

A live engine (``ajtwin live … --dashboard``) or the virtual-print feed
(:mod:`ajtwin.engine.replay`) calls :meth:`LivePublisher.publish` once per sample, from any
thread; every open page's websocket holds a :class:`Subscription` (an asyncio queue) and
receives the sample as JSON within one event-loop turn. The registry watcher announces
committed prints through the same object, so a page has one stream to listen to.

Sample (a dict; keys beyond ``machine`` and ``time_s`` are optional, extra keys pass
through unchanged)::

    machine      str                       machine name (registry name when registered)
    time_s       float                     seconds since the print started
    states       [5] d_a µm, V_l mL, ΔR_T µm, ΔR_N µm, φ_A –   (filtered x̂_k)
    state_stds   [5] σ of the same
    truth        [5] true states (virtual printer only)
    predicted    [5] one-step predicted outputs L_w µm, L_o µm, P_c Pa, P_s Pa, Q_m mL/s
    measured     [5] measured outputs (None = not measured)
    inputs       [3] I_A mA, Q_c sccm, Q_s sccm
    nis          float   normalised innovation squared of this step
    theta        [5] θ in force [1/s]
    detectors    {"cusum": [6] g per channel (L_w, L_o, P_c, P_s, Q_m, P_c+P_s),
                  "cusum_thresholds": [6], "window_nis_log10p": float,
                  "window_nis_threshold": float}
    alarms       [{"detected_s", "onset_s", "cause", "description", "detectors"}]
                 alarms the twin raised at this sample
    settling     {"ready", "ready_at_s", "text"}: ready to print (the start-up has settled)

A machine link's state (``ajtwin live``: connected, reconnecting since T, …; see
:meth:`ajtwin.engine.fleet.LiveEngine.publish_link`) is kept per machine and pushed as
``{"type": "link", "machine", "link": {…, "text"}}``; ``text`` (:func:`link_text`) is
what the pages show.

A live print of a job also has a part map (:mod:`ajtwin.apps.quality.live_map`): its outline
first (:meth:`LivePublisher.open_part`, event ``{"type": "part_outline", "machine", "part"}``),
then a chunk per step that finished portions (:meth:`LivePublisher.publish_part`, event
``{"type": "part", "machine", "chunk"}``); the publisher keeps them so a page opened
mid-print gets the map so far (:meth:`LivePublisher.part_snapshot`).

The publisher stamps ``published_at`` (Unix time, s) on each event so a page (same
machine clock) can measure how long delivery took.

Example
-------
>>> pub = LivePublisher(history=3)
>>> for k in range(5):
...     pub.publish({"machine": "vm1", "time_s": float(k)})
>>> [s["time_s"] for s in pub.snapshot("vm1")]
[2.0, 3.0, 4.0]
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time
from collections import deque

from ajtwin.apps.detection.settings import CUSUM_CHANNELS, DetectorSettings
from ajtwin.engine.messages import FinishedMessage, LinkMessage, Message, StepMessage
from ajtwin.engine.views import detector_thresholds
from ajtwin.model.names import INPUT_NAMES, OUTPUT_NAMES, STATE_NAMES


def link_text(link: dict | None) -> str:
    """The operator's sentence for a link state (see :meth:`LivePublisher.publish_link`).

    >>> link_text({"state": "reconnecting", "attempt": 3, "since": 0.0, "retry_in_s": 4})
    'link lost since 00:00:00 UTC — reconnecting (attempt 3, next in 4 s)'
    >>> link_text({"state": "connected", "gap_s": 12.4})
    'link up (back after a 12 s gap: missing data)'
    >>> link_text({"state": "connected", "missed_s": 210.0})
    'link up — joined the print 3.5 min after its start: the first 3.5 min were not seen'
    """
    if not link:
        return ""
    state = link.get("state")
    if state == "reconnecting":
        since = _number(link.get("since"))
        when = (
            ""
            if since is None or not 0 <= since < 1e11  # a Unix time gmtime can show
            else " since " + time.strftime("%H:%M:%S UTC", time.gmtime(since))
        )
        retry = _number(link.get("retry_in_s"))
        nxt = "" if retry is None else f", next in {retry:g} s"
        why = f" ({link['reason']})" if link.get("reason") else ""
        return f"link lost{when}{why} — reconnecting (attempt {link.get('attempt', 0)}{nxt})"
    if state == "connected":
        gap, missed = _number(link.get("gap_s")), _number(link.get("missed_s"))
        text = "link up" if gap is None else f"link up (back after a {gap:.0f} s gap: missing data)"
        if missed is not None:
            text += (
                f" — joined the print {missed / 60:.1f} min after its start: the first "
                f"{missed / 60:.1f} min were not seen"
            )
        return text
    if state == "connecting":
        return "link: connecting…"
    if state == "refused":
        return f"link refused: {link.get('reason') or 'by the server'}"
    if state == "ended":
        return "link closed (prints finished)"
    return f"link {state}"


def _number(value) -> float | None:
    """A finite real number, or None (a link state's times come from another process)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        value = float(value)
    except OverflowError:  # an int beyond float
        return None
    return value if math.isfinite(value) else None


def sample_from_engine(message: StepMessage) -> dict | None:
    """A live-engine step (:class:`~ajtwin.engine.messages.StepMessage`) as a dashboard
    sample (module docstring). Provisional steps give None: the committed step for the
    same time follows and is the one drawn.
    """
    if message.provisional:
        return None

    def ordered(values: dict, names):
        return [values.get(n) for n in names]

    sample = {
        "machine": message.machine,
        "time_s": message.time_s,
        "states": ordered(message.states, STATE_NAMES),
        "state_stds": ordered(message.stds, STATE_NAMES),
        "predicted": ordered(message.predicted_outputs, OUTPUT_NAMES),
        "measured": ordered(message.measured_outputs, OUTPUT_NAMES),
        "inputs": ordered(message.inputs, INPUT_NAMES),
        "theta": ordered(message.theta, STATE_NAMES),
        "nis": message.nis,
        "engine_status": message.status,
    }
    if message.settling is not None:
        sample["settling"] = {k: message.settling.get(k) for k in ("ready", "ready_at_s", "text")}
    if message.cusum is not None:
        settings = DetectorSettings()
        p = _number(message.window_nis_p)
        sample["detectors"] = {
            "cusum": [message.cusum.get(c) for c in CUSUM_CHANNELS],
            "cusum_thresholds": detector_thresholds(settings),
            "window_nis_log10p": None if p is None else -math.log10(max(p, 1e-300)),
            "window_nis_threshold": -math.log10(settings.nis_alpha),
        }
    sample["alarms"] = [
        {
            "detected_s": ev.get("detected_s"),
            "onset_s": ev.get("onset_s"),
            "cause": ev.get("cause"),
            "description": ev.get("description"),
            "detectors": _detector_names(ev.get("detectors")),
        }
        for ev in message.raised()
    ]
    return sample


def _as_list(value) -> list:
    return list(value) if isinstance(value, list | tuple) else []


def _detector_names(value) -> str:
    if isinstance(value, str):
        return value
    return ", ".join(str(v) for v in _as_list(value))


class Subscription:
    """One listener (a page's websocket): an asyncio queue fed thread-safely.

    A slow page loses its oldest events rather than holding up the publisher or
    growing without bound (``maxsize`` events are kept).
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, maxsize: int = 2000):
        self.loop = loop
        self.queue: asyncio.Queue = asyncio.Queue(maxsize=maxsize)
        self.dropped = 0

    def _put(self, event: dict) -> None:  # runs in the subscriber's loop
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped += 1
        self.queue.put_nowait(event)

    async def get(self) -> dict:
        """The next event (waits)."""
        return await self.queue.get()


#: deepest nesting of an event (a sample is 3 levels deep); deeper ones are refused
MAX_EVENT_DEPTH = 32


def _clean(value, depth: int = 0):
    """Any value as plain JSON data, so every event a page receives is strict JSON:
    NaN/inf → None, NumPy values → numbers/lists, tuples and sets → lists, keys → text,
    bytes and other objects → their text. Nesting beyond :data:`MAX_EVENT_DEPTH` is a
    ``ValueError`` (a publisher's bug, said at ``publish``, never a dead page stream)."""
    if depth > MAX_EVENT_DEPTH:
        raise ValueError(f"a live event nested deeper than {MAX_EVENT_DEPTH} levels")
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k if isinstance(k, str) else str(k): _clean(v, depth + 1) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [_clean(v, depth + 1) for v in value]
    if hasattr(value, "tolist") and hasattr(value, "dtype"):  # NumPy arrays and scalars
        plain = value.tolist()
        return None if plain is value else _clean(plain, depth + 1)
    if isinstance(value, bytes | bytearray):
        return bytes(value).decode("utf-8", "replace")
    return str(value)


def event_text(event: dict) -> str:
    """An event as the text a page receives: strict JSON (no NaN, every key text)."""
    return json.dumps(_clean(event), allow_nan=False)


class LivePublisher:
    """Fan-out of live samples and registry events to the dashboard's pages.

    Parameters
    ----------
    history : int
        Samples kept per machine, so a page opened mid-print shows the print so far.
    printing_timeout_s : float
        A machine counts as printing while its last sample is younger than this.
    """

    def __init__(self, history: int = 7200, printing_timeout_s: float = 30.0):
        self.history = int(history)
        self.printing_timeout_s = float(printing_timeout_s)
        self._lock = threading.Lock()
        self._subscribers: set[Subscription] = set()
        self._samples: dict[str, deque] = {}
        self._alarms: dict[str, list] = {}
        self._last_seen: dict[str, float] = {}
        self._ended: set[str] = set()
        self._links: dict[str, dict] = {}
        self._parts: dict[str, dict] = {}

    # ------------------------------------------------------------------ publishing
    def publish(self, sample: dict) -> None:
        """Deliver one sample (see module docstring) to every page; thread-safe."""
        if not isinstance(sample, dict):
            raise ValueError(f"a live sample is a dict, got {type(sample).__name__}")
        if "machine" not in sample or "time_s" not in sample:
            raise ValueError("a live sample needs at least 'machine' and 'time_s'")
        event = _clean(dict(sample))
        event["type"] = "sample"
        event["published_at"] = time.time()
        name = str(event["machine"])
        with self._lock:
            buffer = self._samples.setdefault(name, deque(maxlen=self.history))
            if name in self._ended:  # a new print on this machine
                buffer.clear()
                self._alarms[name] = []
                self._ended.discard(name)
            buffer.append(event)
            if isinstance(event.get("alarms"), list) and event["alarms"]:
                self._alarms.setdefault(name, []).extend(
                    a for a in event["alarms"] if isinstance(a, dict)
                )
            self._last_seen[name] = time.monotonic()
        self._broadcast(event)

    def open_print(self, machine: str) -> None:
        """Announce a live print of ``machine`` before its first sample (pages may open it)."""
        with self._lock:
            self._samples.setdefault(machine, deque(maxlen=self.history))
        self._broadcast({"type": "print_start", "machine": machine, "published_at": time.time()})

    def publish_link(self, machine: str, link: dict) -> None:
        """The state of the link feeding ``machine`` (``state``, ``since``, ``attempt``, …;
        see :meth:`ajtwin.engine.fleet.LiveEngine.publish_link`); kept and pushed to pages."""
        if not isinstance(link, dict):
            raise ValueError(f"a link state is a dict, got {type(link).__name__}")
        link = _clean({**link, "text": link_text(link)})
        with self._lock:
            self._samples.setdefault(machine, deque(maxlen=self.history))
            self._links[machine] = link
        self._broadcast(
            {"type": "link", "machine": machine, "link": link, "published_at": time.time()}
        )

    def open_part(self, machine: str, part: dict) -> None:
        """The part map of the machine's live print starts: its outline and tolerance
        (:meth:`ajtwin.apps.quality.live_map.LivePartMap.header`); the previous map is dropped."""
        if not isinstance(part, dict):
            raise ValueError(f"a part map is a dict, got {type(part).__name__}")
        part = _clean({**part, "portions": None, "points": None, "alarms": []})
        with self._lock:
            self._parts[machine] = part
        self._broadcast(
            {"type": "part_outline", "machine": machine, "part": part, "published_at": time.time()}
        )

    def publish_part(self, machine: str, chunk: dict) -> None:
        """Portions of the live part map that just finished (and alarms placed on the part,
        or a new outline when the job was looped further); kept and pushed to pages."""
        if not isinstance(chunk, dict):
            raise ValueError(f"a part chunk is a dict, got {type(chunk).__name__}")
        chunk = _clean(chunk)
        with self._lock:
            part = self._parts.setdefault(machine, {"portions": None, "points": None, "alarms": []})
            if isinstance(chunk.get("outline"), dict):
                part.update({k: v for k, v in chunk["outline"].items()})
            for key in ("portions", "points"):
                if isinstance(chunk.get(key), dict):
                    if part.get(key) is None:
                        part[key] = {k: list(v) for k, v in chunk[key].items()}
                    else:
                        for k, v in chunk[key].items():
                            part[key].setdefault(k, []).extend(v)
            if isinstance(chunk.get("alarms"), list):
                part.setdefault("alarms", []).extend(chunk["alarms"])
        self._broadcast(
            {"type": "part", "machine": machine, "chunk": chunk, "published_at": time.time()}
        )

    def part_snapshot(self, machine: str) -> dict | None:
        """The live part map of the machine so far (None: its live print has no job)."""
        with self._lock:
            part = self._parts.get(machine)
            if part is None:
                return None
            return {
                k: ({kk: list(vv) for kk, vv in v.items()} if isinstance(v, dict) else v)
                for k, v in part.items()
            }

    def link(self, machine: str) -> dict | None:
        """The last link state of ``machine`` (None: no live link reported)."""
        with self._lock:
            return self._links.get(machine)

    def publish_engine(self, message: Message) -> None:
        """Publish a message of the live engine (:func:`sample_from_engine`); thread-safe."""
        if isinstance(message, LinkMessage):
            self.publish_link(message.machine, message.link.to_dict())
            return
        if isinstance(message, FinishedMessage):
            return  # the end of a print: the link's "ended" and the page's own timeout say it
        if not isinstance(message, StepMessage):
            raise ValueError(
                "a live-engine message is a StepMessage, LinkMessage or FinishedMessage "
                f"(ajtwin.engine.messages), got {type(message).__name__}"
            )
        sample = sample_from_engine(message)
        if sample is not None:
            self.publish(sample)

    def end_print(self, machine: str) -> None:
        """The live print of ``machine`` ended (its buffer is kept until the next one)."""
        with self._lock:
            self._ended.add(machine)
            self._last_seen.pop(machine, None)
        self._broadcast({"type": "print_end", "machine": machine, "published_at": time.time()})

    def announce(self, event: dict) -> None:
        """Broadcast a non-sample event (e.g. ``{"type": "print", "machine": …}``)."""
        if not isinstance(event, dict):
            raise ValueError(f"an announced event is a dict, got {type(event).__name__}")
        if not isinstance(event.get("type"), str):
            raise ValueError("an announced event needs a 'type' (text) the pages dispatch on")
        event = _clean(dict(event))
        # always the publisher's clock, as for samples: a caller's value (None, text, a
        # stale stamp) would break the pages' delivery-time measure (found by test_fuzz_ws)
        event["published_at"] = time.time()
        self._broadcast(event)

    def _broadcast(self, event: dict) -> None:
        with self._lock:
            subscribers = list(self._subscribers)
        for sub in subscribers:
            try:
                sub.loop.call_soon_threadsafe(sub._put, event)
            except RuntimeError:  # that page's loop is closed
                self.unsubscribe(sub)

    # ------------------------------------------------------------------ listening
    def subscribe(self, loop: asyncio.AbstractEventLoop | None = None) -> Subscription:
        """A new subscription whose queue receives every event from now on."""
        sub = Subscription(loop or asyncio.get_running_loop())
        with self._lock:
            self._subscribers.add(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        """Stop sending events to ``sub``."""
        with self._lock:
            self._subscribers.discard(sub)

    @property
    def n_subscribers(self) -> int:
        """Open subscriptions (pages listening)."""
        with self._lock:
            return len(self._subscribers)

    # ------------------------------------------------------------------ state
    def snapshot(self, machine: str) -> list[dict]:
        """The samples of the machine's current (or last) live print."""
        with self._lock:
            return list(self._samples.get(machine, ()))

    def alarms(self, machine: str) -> list[dict]:
        """The alarms of the machine's live print so far."""
        with self._lock:
            return list(self._alarms.get(machine, ()))

    def machines(self) -> list[str]:
        """Machines that published a sample, by name."""
        with self._lock:
            return sorted(self._samples)

    def is_printing(self, machine: str) -> bool:
        """Whether the machine published within ``printing_timeout_s``."""
        with self._lock:
            seen = self._last_seen.get(machine)
        return seen is not None and time.monotonic() - seen < self.printing_timeout_s

    def latest(self, machine: str) -> dict | None:
        """The machine's newest sample (None: none yet)."""
        with self._lock:
            buffer = self._samples.get(machine)
            return buffer[-1] if buffer else None
