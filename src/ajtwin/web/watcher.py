"""Notice what other processes commit to the registry and tell the open pages.

``ajtwin ingest`` writes a print in one transaction (docs/reference/registry.md). The watcher asks
the registry every ``poll_s`` seconds for its change marker (SQLite's ``PRAGMA
data_version``, PostgreSQL's newest transaction id: it changes when another connection
commits; one cheap query per tick, on a worker thread so the server never waits) and,
when it changed, for the prints and machines added since the last look; it announces each
as an event through the :class:`~ajtwin.web.publisher.LivePublisher`::

    {"type": "print", "machine": "lab1", "seq": 3, "print_id": 17, "anomalies": 1, …}
    {"type": "machines"}                      (a machine was added)

Pages then fetch what changed; nothing is reloaded.

Live prints written by twins in other processes — on the printers' own PCs, the registry
on the lab's server — reach the pages the same way: each tick the watcher reads, on a
connection of its own, the steps every open live session committed since the last look
(:func:`ajtwin.store.queries.open_live_states`) and publishes those newer than what the
publisher holds (a twin in this process publishes its own first), and ends the print of a
session that closed.
"""

from __future__ import annotations

import asyncio
import logging

from ajtwin.engine.messages import StepMessage
from ajtwin.store import queries
from ajtwin.store.registry import Registry

log = logging.getLogger(__name__)


class RegistryWatcher:
    """Poll a :class:`~ajtwin.engine.views.RegistryView` for commits (module docstring)."""

    def __init__(self, view, publisher, poll_s: float = 0.5):
        if not poll_s > 0:
            raise ValueError(f"poll interval must be > 0 s, got {poll_s}")
        self.view = view
        self.publisher = publisher
        self.poll_s = float(poll_s)
        self._marker = view.change_marker()
        self.ticks = 0
        self._live = None  # the live sessions' reader: a registry connection of its own
        self._seen: dict = {}  # session id -> last step published (queries.open_live_states)

    def check_live(self) -> int:
        """Publish the steps the open live sessions committed since the last look (module
        docstring); how many were published."""
        if self._live is None:
            self._live = Registry(self.view.path, create=False)
        messages, ended = queries.open_live_states(self._live, self._seen)
        published = 0
        for message in messages:
            latest = self.publisher.latest(message.get("machine"))
            held = latest is not None and self.publisher.is_printing(message["machine"])
            if held and float(latest["time_s"]) >= float(message.get("time_s", -1.0)):
                continue  # this process's own twin published it already
            self.publisher.publish_engine(StepMessage.from_dict(message))
            published += 1
        for machine in ended:
            self.publisher.end_print(machine)
        return published

    def close(self) -> None:
        """Close the watcher's own registry connection."""
        if self._live is not None:
            self._live.close()
            self._live = None

    def check(self) -> list[dict]:
        """One look: the events since the last look (also announced)."""
        marker = self.view.change_marker()
        events: list[dict] = []
        if marker == self._marker:
            return events
        _, last_print, last_machine = self._marker
        for entry in self.view.prints_after(last_print):
            events.append({"type": "print", **entry})
        if marker[2] != last_machine:
            events.append({"type": "machines"})
        self._marker = marker
        for event in events:
            self.publisher.announce(event)
        return events

    async def run(self) -> None:
        """Poll until cancelled (the server's lifespan cancels it on shutdown)."""
        away = False  # the registry's server did not answer the last look
        while True:
            try:
                await asyncio.to_thread(self.check)
                await asyncio.to_thread(self.check_live)
                if away:
                    log.info("registry watcher: the registry answers again")
                    away = False
            except Exception as exc:
                # the interpreter is exiting under a server thread that is still up (its
                # worker pool is gone): nothing left to watch for, and no one to tell
                if isinstance(exc, RuntimeError) and "after shutdown" in str(exc):
                    return
                if getattr(exc, "shown_as_sentence", False):  # the registry away: one line
                    if not away:
                        log.warning("registry watcher: %s; looking again every %g s", exc,
                                    self.poll_s)  # fmt: skip
                    away = True
                else:  # a locked or briefly unreadable file: try next tick
                    log.exception("registry watcher: check failed")
            self.ticks += 1
            await asyncio.sleep(self.poll_s)
