"""A record's 1 Hz table held on disk while it is read and used (what keeps memory flat).

A week-long log at 1 Hz is 600,000 rows. Held in memory its table grows the reader by
~0.4 MB per print-hour and, with the arrays a twin derives from it, ``ingest`` by
~1.2 MB per print-hour. :class:`RowSpool` keeps the rows in an anonymous temporary file
(unlinked as it is made, so nothing is left behind even when the process is killed)
and gives them back by row range or column; :class:`SpooledTable` is a record's table in
such a file, with the text columns (an operator's note) beside it in memory, and gives
any slice of rows as the DataFrame the whole table would have given.

Examples
--------
>>> import numpy as np
>>> spool = RowSpool(2, "<example>")
>>> spool.append(np.array([[0.0, 1.0], [1.0, 2.0], [2.0, 4.0]]))
>>> spool.read(1, 3)[:, 1]
array([2., 4.])
>>> spool.column(1)
array([1., 2., 4.])
>>> spool.close()
"""

from __future__ import annotations

import tempfile

import numpy as np
import pandas as pd

from ajtwin.io.schema import RecordError

#: Rows read from the spool at a time when a whole column or the whole table is wanted
#: (8 bytes × columns × this: ~2 MB for a record's ~20 columns).
SPOOL_BLOCK_ROWS = 16_384


class RowSpool:
    """Rows of float64 values appended to an anonymous temporary file.

    Parameters
    ----------
    width : int
        Values per row.
    where : str
        The record, for messages.
    directory : str, optional
        Where the file goes (default: the system's temporary folder, ``TMPDIR``).
    """

    def __init__(self, width: int, where: str, directory: str | None = None):
        self.width, self.where = int(width), where
        self.directory = directory or tempfile.gettempdir()
        self.rows = 0
        try:
            self.file = tempfile.TemporaryFile(prefix="ajtwin-record-", dir=directory)
        except OSError as exc:
            raise RecordError(self._no_room(exc)) from None

    def _no_room(self, exc: OSError) -> str:
        return (
            f"{self.where}: cannot hold the record's table on disk while it is read "
            f"({exc.strerror or exc}, in the temporary folder {self.directory!r}): free space "
            "there or point TMPDIR at a folder with room"
        )

    def append(self, block: np.ndarray) -> None:
        """Add rows (m, width) at the end."""
        block = np.ascontiguousarray(block, dtype=np.float64)
        if block.ndim != 2 or block.shape[1] != self.width:
            raise ValueError(f"rows must be (m, {self.width}); got {block.shape}")
        try:
            self.file.seek(self.rows * self.width * 8)
            self.file.write(block.tobytes())
        except OSError as exc:
            raise RecordError(self._no_room(exc)) from None
        self.rows += len(block)

    def read(self, start: int, stop: int) -> np.ndarray:
        """Rows [start, stop) as a (stop − start, width) C-ordered array."""
        start, stop = max(int(start), 0), min(int(stop), self.rows)
        out = np.empty((max(stop - start, 0), self.width))
        if len(out):
            self.file.seek(start * self.width * 8)
            got = self.file.readinto(memoryview(out).cast("B"))
            if got != out.nbytes:
                raise RecordError(f"{self.where}: the record's spool file ended early")
        return out

    def blocks(self, rows: int | None = None):
        """(first row, rows) over the whole spool, ``rows`` (:data:`SPOOL_BLOCK_ROWS`) at a
        time."""
        rows = rows or SPOOL_BLOCK_ROWS
        for start in range(0, self.rows, rows):
            yield start, self.read(start, start + rows)

    def column(self, j: int, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Column ``j`` over rows [start, stop) (read a block of rows at a time)."""
        stop = self.rows if stop is None else min(int(stop), self.rows)
        out = np.empty(max(stop - start, 0))
        for first in range(start, stop, SPOOL_BLOCK_ROWS):
            last = min(first + SPOOL_BLOCK_ROWS, stop)
            out[first - start : last - start] = self.read(first, last)[:, j]
        return out

    def close(self) -> None:
        """Let the file go (the system frees its space)."""
        self.file.close()


class SpooledTable:
    """A record's table: numeric columns in a :class:`RowSpool`, text columns in memory.

    Parameters
    ----------
    spool : RowSpool
        The numeric columns, in the table's order (``names``).
    names : list of str
        The numeric columns' names, as many as the spool's width.
    texts : dict, optional
        Text column name → (its position in the table, object array (n,)).
    """

    def __init__(self, spool: RowSpool, names: list[str], texts: dict | None = None):
        if len(names) != spool.width:
            raise ValueError(f"{len(names)} names for a spool {spool.width} wide")
        self.spool, self.names = spool, list(names)
        self.texts = dict(texts or {})

    def __len__(self) -> int:
        return self.spool.rows

    @property
    def columns(self) -> list[str]:
        """The table's column names, in order."""
        names = list(self.names)
        for name, (position, _) in self.texts.items():
            names.insert(position, name)
        return names

    def column(self, name: str) -> np.ndarray:
        """One numeric column over the whole table (n,)."""
        return self.spool.column(self.names.index(name))

    def frame(self, start: int = 0, stop: int | None = None) -> pd.DataFrame:
        """Rows [start, stop) as a DataFrame (one column-major block; index from 0)."""
        stop = len(self) if stop is None else min(int(stop), len(self))
        start = min(max(int(start), 0), stop)
        block = np.empty((stop - start, len(self.names)), order="F")
        for first in range(start, stop, SPOOL_BLOCK_ROWS):
            last = min(first + SPOOL_BLOCK_ROWS, stop)
            block[first - start : last - start] = self.spool.read(first, last)
        frame = pd.DataFrame(block, columns=self.names, copy=False)
        for name, (position, values) in self.texts.items():
            frame.insert(position, name, values[start:stop])
        return frame

    def close(self) -> None:
        """Let the spool's file go."""
        self.spool.close()
