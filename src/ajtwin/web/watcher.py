"""Notice what other processes commit to the registry and tell the open pages.

``ajtwin ingest`` writes a print in one transaction (docs/reference/registry.md). The watcher asks
SQLite every ``poll_s`` seconds for ``PRAGMA data_version`` (it changes when another
connection commits; one cheap query per tick, on a worker thread so the server never
waits) and, when it changed, for the prints and machines added since the last look; it
announces each as an event through the :class:`~ajtwin.web.publisher.LivePublisher`::

    {"type": "print", "machine": "lab1", "seq": 3, "print_id": 17, "anomalies": 1, …}
    {"type": "machines"}                      (a machine was added)

Pages then fetch what changed; nothing is reloaded.
"""

from __future__ import annotations

import asyncio
import logging

log = logging.getLogger(__name__)


class RegistryWatcher:
    """Poll a :class:`~ajtwin.web.data.RegistryView` for commits (module docstring)."""

    def __init__(self, view, publisher, poll_s: float = 0.5):
        if not poll_s > 0:
            raise ValueError(f"poll interval must be > 0 s, got {poll_s}")
        self.view = view
        self.publisher = publisher
        self.poll_s = float(poll_s)
        self._marker = view.change_marker()
        self.ticks = 0

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
        while True:
            try:
                await asyncio.to_thread(self.check)
            except RuntimeError as exc:
                # the interpreter is exiting under a server thread that is still up (its
                # worker pool is gone): nothing left to watch for, and no one to tell
                if "after shutdown" in str(exc):
                    return
                log.exception("registry watcher: check failed")
            except Exception:  # a locked or briefly unreadable file: try next tick
                log.exception("registry watcher: check failed")
            self.ticks += 1
            await asyncio.sleep(self.poll_s)
