"""What `make test` says while it runs: the long test files first, and what is still running.

Two pieces, wired into pytest by ``tests/conftest.py``:

* :func:`longest_files_first` — with ``--dist loadfile`` each test file goes whole to the next
  free worker, in collection order. A long file that starts last keeps one worker busy, alone,
  at the end (the silent last minutes of a run). Files are put in the order of their last
  measured duration (the pytest cache, ``ajtwin/file_seconds``; in a fresh clone, the long
  files of one measured run kept in ``tests/file_seconds.json``), longest first; the other
  files keep their order, after those known to take over :data:`LONG_FILE_S`.
* :class:`Heartbeat` — every ``AJTWIN_TEST_HEARTBEAT`` seconds (``make test`` sets 30) a line
  naming the tests that have run that long or longer, so a wait on a long test is never silent.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

#: the cache key of the per-file durations [s] of the last run
CACHE_KEY = "ajtwin/file_seconds"
#: a file measured at least this long [s] is started before the files never measured
LONG_FILE_S = 20.0
#: the long files' durations [s] of one measured `make test` run, for a clone without a cache
KNOWN = Path(__file__).with_name("file_seconds.json")


def known_file_seconds() -> dict[str, float]:
    """The durations kept in :data:`KNOWN` ({} without the file)."""
    try:
        return {str(k): float(v) for k, v in json.loads(KNOWN.read_text("utf-8")).items()}
    except (OSError, ValueError):
        return {}


def file_of(nodeid: str) -> str:
    """The test file of a node id.

    >>> file_of("tests/test_web_browser.py::test_fleet_page[chromium]")
    'tests/test_web_browser.py'
    """
    return nodeid.split("::", 1)[0]


def longest_files_first(nodeids: list[str], seconds: dict[str, float]) -> list[int]:
    """The order (indices into ``nodeids``) that runs whole files longest first.

    Tests keep their order within a file. Files measured ≥ :data:`LONG_FILE_S` come first,
    longest first; then every other file in collection order.

    >>> ids = ["a.py::t1", "b.py::t1", "a.py::t2", "c.py::t1"]
    >>> longest_files_first(ids, {"c.py": 300.0, "a.py": 1.0})
    [3, 0, 2, 1]
    """
    files: dict[str, list[int]] = {}
    for i, nodeid in enumerate(nodeids):
        files.setdefault(file_of(nodeid), []).append(i)
    position = {name: k for k, name in enumerate(files)}

    def key(name: str):
        took = float(seconds.get(name, 0.0))
        return (0, -took, 0) if took >= LONG_FILE_S else (1, 0.0, position[name])

    return [i for name in sorted(files, key=key) for i in files[name]]


class Heartbeat:
    """Says, every ``every_s`` seconds, which tests have been running that long or longer.

    ``write`` takes one line of text. :meth:`started` and :meth:`finished` are called from
    pytest's hooks (with xdist, in the controlling process as workers report).

    >>> lines = []
    >>> beat = Heartbeat(30.0, lines.append, clock=iter([0.0, 90.0, 95.0]).__next__)
    >>> beat.started("tests/test_web_browser.py::test_live")
    >>> beat.started("tests/test_model.py::test_quick")      # started at 90 s: not yet long
    >>> beat.say()
    >>> lines
    ['… 0 tests done; running for 30 s or more: tests/test_web_browser.py::test_live 1 min 35 s']
    """

    def __init__(self, every_s: float, write, clock=time.monotonic):
        self.every_s = float(every_s)
        self.write = write
        self.clock = clock
        self.running: dict[str, float] = {}
        self.done = 0
        self.total: int | None = None  # tests to run, once known
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def started(self, nodeid: str) -> None:
        with self._lock:
            self.running[nodeid] = self.clock()

    def finished(self, nodeid: str) -> None:
        with self._lock:
            if self.running.pop(nodeid, None) is not None:
                self.done += 1

    def say(self) -> None:
        """Write one line naming the tests running for ``every_s`` or longer, longest running
        first (at most 3 named); nothing while the tests come and go faster (the dots say it).
        """
        now = self.clock()
        with self._lock:
            running = sorted(self.running.items(), key=lambda kv: kv[1])
        running = [(nodeid, t0) for nodeid, t0 in running if now - t0 >= self.every_s]
        if not running:
            return
        named = ", ".join(f"{nodeid} {_took(now - t0)}" for nodeid, t0 in running[:3])
        more = f" and {len(running) - 3} more" if len(running) > 3 else ""
        # the line breaks pytest's row of dots before its percentage: say how far it is
        done = f"{self.done} of {self.total}" if self.total else f"{self.done}"
        self.write(f"… {done} tests done; running for {_took(self.every_s)} or more: {named}{more}")

    def start(self) -> None:
        def loop():
            while not self._stop.wait(self.every_s):
                self.say()

        self._thread = threading.Thread(target=loop, name="test-heartbeat", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)


def _took(seconds: float) -> str:
    """``"45 s"``, ``"1 min 35 s"``.

    >>> _took(45.2), _took(95.0)
    ('45 s', '1 min 35 s')
    """
    seconds = int(round(seconds))
    return f"{seconds} s" if seconds < 60 else f"{seconds // 60} min {seconds % 60} s"
