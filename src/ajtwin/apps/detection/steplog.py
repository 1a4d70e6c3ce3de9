"""Per-step values addressed by the step number, of which only the latest are kept.

The detectors and the streaming twin look back over a bounded span (an event's evidence, an
EM window) but used to keep every step of the print: a week-long print held 604,800 of
each. A :class:`StepLog` is appended to like a list and indexed by absolute step number
(``log[k]``, ``log[a:b]``, ``log[-1]``, ``len(log)`` = steps appended so far), and keeps
the last ``keep`` steps; asking for an older one is an IndexError that says so.

>>> log = StepLog(keep=3)
>>> for k in range(10):
...     log.append(k * 10)
>>> len(log), log[9], log[7:9], log.first
(10, 90, [70, 80], 7)
"""

from __future__ import annotations

import numpy as np


class StepLog:
    """A list of per-step values that keeps the last ``keep`` (None: all) of them.

    Parameters
    ----------
    keep : int or None
        Steps kept at least (storage is trimmed in blocks of an eighth of ``keep``, so up
        to an eighth more: the log is full, and stops growing, after 1.125 ``keep`` steps).
    """

    def __init__(self, keep: int | None = None):
        self.keep = None if keep is None else max(int(keep), 1)
        # a trim moves the kept items: once every block, not at each step
        self._block = None if keep is None else max(self.keep // 8, 1)
        self._items: list = []
        self._offset = 0  # step number of self._items[0]

    @property
    def first(self) -> int:
        """The oldest step still kept."""
        return self._offset

    def append(self, value) -> None:
        """Add the next step's value."""
        self._items.append(value)
        if self.keep is not None and len(self._items) >= self.keep + self._block:
            drop = len(self._items) - self.keep
            del self._items[:drop]
            self._offset += drop

    def __len__(self) -> int:
        return self._offset + len(self._items)

    def __bool__(self) -> bool:
        return len(self) > 0

    def _index(self, k: int) -> int:
        k = int(k)
        if k < 0:
            k += len(self)
        if not self._offset <= k < len(self):
            raise IndexError(f"step {k} is not kept (steps {self._offset}–{len(self) - 1} are)")
        return k - self._offset

    def __getitem__(self, key):
        if isinstance(key, slice):
            start, stop, step = key.indices(len(self))
            if start < self._offset and start < stop:
                raise IndexError(f"step {start} is not kept (steps from {self._offset} are)")
            return self._items[start - self._offset : stop - self._offset : step]
        return self._items[self._index(key)]

    def __iter__(self):
        if self._offset:
            raise IndexError(f"steps before {self._offset} are no longer kept")
        return iter(self._items)

    def kept(self) -> list:
        """The values of the steps still kept (from :attr:`first` on)."""
        return list(self._items)

    def search(self, value) -> int:
        """The first kept step whose value is ≥ ``value`` (values increasing, e.g. times);
        ``len(self)`` if none."""
        return self._offset + int(np.searchsorted(np.asarray(self._items, dtype=float), value))
