"""Writes that wait while the database server cannot be reached (a restart, a lost network).

A live twin must not stop, nor lose a sample, because the lab's PostgreSQL server is
restarting or the network to it is down. Its writes that may wait (the live log's steps,
a running print's array parts) go through an :class:`Outbox`: written at once while the
server answers; when a write fails with :class:`~ajtwin.store.database.ConnectionLost`
it is kept, in order, with every later one, and a thread of the outbox writes them when
the server answers again (every ``retry_every_s``), saying so in the log::

    WARNING ajtwin.store: postgresql://twin@server/ajtwin: the database server cannot be
            reached (...); writes are kept in memory and retried every 2 s
    INFO    ajtwin.store: postgresql://twin@server/ajtwin: reached again after 121 s;
            58 kept writes stored

Each write must be idempotent (a write whose COMMIT reached the server but whose answer
was lost is made again): the registry's are (``ON CONFLICT DO NOTHING`` on their keys).
What is kept lives in the process: a process killed while the server is away loses it,
as a process killed on SQLite loses the steps it had not committed
(docs/howto/lab-with-several-printers.md).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from ajtwin.store.database import ConnectionLost

log = logging.getLogger("ajtwin.store")


class Outbox:
    """Ordered writes to one database that wait out its absence (module docstring).

    Parameters
    ----------
    where : str
        The database as messages name it.
    retry_every_s : float
        Seconds between attempts while the server is away.
    """

    def __init__(self, where: str, retry_every_s: float = 2.0):
        self.where = str(where)
        self.retry_every_s = float(retry_every_s)
        self._items: deque = deque()
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._lost_at: float | None = None
        self._done = threading.Condition(self._lock)
        self.kept_total = 0  # writes that had to wait, over the outbox's life

    def __len__(self) -> int:
        return len(self._items)

    def submit(self, write) -> bool:
        """Run ``write()`` now, or keep it (after the kept ones) if the server is away or
        writes are already waiting; whether it was written now."""
        with self._lock:
            if not self._items:
                try:
                    write()
                    return True
                except ConnectionLost as exc:
                    self._lost(exc)
            self._items.append(write)
            self.kept_total += 1
            self._start()
            return False

    def drain(self, timeout_s: float | None = None) -> None:
        """Wait until every kept write is stored (at most ``timeout_s``; None: as long as it
        takes); :class:`ConnectionLost` if the server is still away then."""
        deadline = None if timeout_s is None else time.monotonic() + float(timeout_s)
        with self._lock:
            while self._items:
                if not self._thread_alive():
                    self._start()
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise ConnectionLost(
                        f"{self.where}: the database server is still away after "
                        f"{timeout_s:g} s; {len(self._items)} writes are kept in memory"
                    )
                self._done.wait(timeout=self.retry_every_s if left is None else min(left, 1.0))

    def _lost(self, exc) -> None:
        if self._lost_at is None:
            self._lost_at = time.monotonic()
            log.warning(
                "%s; writes are kept in memory and retried every %g s", exc, self.retry_every_s
            )

    def _thread_alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _start(self) -> None:
        if not self._thread_alive():
            self._thread = threading.Thread(target=self._run, name="ajtwin-outbox", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        # the lock is not held while a write is tried (a connection attempt may take the
        # server's connect timeout): the twin keeps adding writes meanwhile, never waits
        while True:
            time.sleep(self.retry_every_s)
            n = 0
            while True:
                with self._lock:
                    if not self._items:
                        break
                    write = self._items[0]
                try:
                    write()
                except ConnectionLost:
                    break
                except Exception:  # not the server's absence: said, and the rest go on
                    log.exception("%s: a kept write failed and is dropped", self.where)
                with self._lock:
                    self._items.popleft()
                    n += 1
            with self._lock:
                if self._items:
                    continue
                away = 0.0 if self._lost_at is None else time.monotonic() - self._lost_at
                log.info(
                    "%s: reached again after %.0f s; %d kept writes stored", self.where, away, n
                )
                self._lost_at = None
                self._thread = None
                self._done.notify_all()
                return
