"""A growing record file, read as it grows, with the record reader's rules.

``ajtwin live --follow FILE`` runs the twin beside a machine that appends its log to a
file. :class:`CsvFollower` reads what was appended since the last call — complete lines
only, in bounded pieces — and gives 1 s samples for the live twin. It follows the same
rules as :func:`ajtwin.io.records.read_record`: a byte-order mark and CRLF line ends, the
dialect (detected from the first lines, or given), column names with units (converted),
aliases, the time formats of :mod:`ajtwin.io.timebase`, samples averaged per second, and
columns judged by their resolution (:mod:`ajtwin.io.quality`: the first
``follow_window_s`` rows are held back to judge them before the twin sees any; an output
judged unusable is missing from then on). Where the batch reader refuses a whole file, a
live log goes on: a line that is cut, shifted or holds a cell that is not a number is
reported and skipped (the twin treats its second as missing), as is a row whose time does
not increase.

Examples
--------
>>> follower = CsvFollower("print.csv")
>>> samples, log_lines = follower.poll()
>>> time_s, inputs, outputs = samples[0]
>>> time_s, inputs                                # [s]; I_A [mA], Q_c, Q_s [sccm]
(0.0, array([375.,  23.,  50.]))
>>> outputs                                       # L_w, L_o [µm], P_c, P_s [Pa], Q_m [mL/s]
array([4.3200e+01, 2.9100e+01, 5.6613e+03, 5.6412e+03, 1.5000e-08])
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.io.columns import convert_values
from ajtwin.io.dialect import CsvDialect, dialect_from_name, parse_numbers, sniff_dialect
from ajtwin.io.quality import ColumnQuality, judge, settings
from ajtwin.io.schema import INPUT_COLUMNS, OUTPUT_COLUMNS, TIME_COLUMN, RecordError
from ajtwin.io.table import BLANKS, TableBuilder, time_cells
from ajtwin.io.timebase import SecondBinner, TimeError, time_base

#: Bytes read per piece (a file followed from its start is read in pieces, never whole).
READ_BYTES = 1 << 22
_BOM = b"\xef\xbb\xbf"

Sample = tuple[float, np.ndarray, np.ndarray]


class CsvFollower:
    """Read a growing delimited-text record incrementally (see the module doc).

    Parameters
    ----------
    path : path
        The file (it may not exist yet).
    aliases : path, optional
        The user's alias file.
    dialect : str or CsvDialect, optional
        The file's dialect (default: detected from its first lines).
    """

    def __init__(self, path, *, aliases=None, dialect: str | CsvDialect | None = None):
        self.path = Path(path)
        self.aliases = aliases
        self.dialect = dialect_from_name(dialect)
        self.position = 0
        self.line_number = 0
        self.header: list[str] | None = None
        self.header_line = 0
        self.builder: TableBuilder | None = None  # the column plan and required columns
        self.pending: list[tuple[int, list[str]]] = []  # rows held back (line, cells)
        self.timebase = None
        self.binner = SecondBinner(len(INPUT_COLUMNS) + len(OUTPUT_COLUMNS))
        self.quality = {c: ColumnQuality() for c in (*INPUT_COLUMNS, *OUTPUT_COLUMNS)}
        self.unusable: dict[str, str] = {}
        self.last_t: float | None = None
        self.window = int(settings()["outputs"].get("follow_window_s", 30))
        self.started = False

    # ------------------------------------------------------------------ #
    def poll(self) -> tuple[list[Sample], list[str]]:
        """Read what was appended; returns (1 s samples ready for the twin, log lines).

        Raises
        ------
        RecordError
            A header that lacks a required column (or names one twice), a time column
            that is no time, or an input printed too coarsely.
        """
        log: list[str] = []
        lines = self._new_lines()
        for number, text in lines:
            if self.header is None:
                if not text.strip() or text.startswith("#"):
                    continue
                self.header, self.header_line = [text], number
                continue
            if not text.strip():
                continue
            self.pending.append((number, text))
        if self.header is not None and self.builder is None and self.pending:
            self._start(log)
        if self.builder is None:
            return [], log
        if not self.started and len(self.pending) < self.window:
            return [], log
        return self._process(log, final=False), log

    def flush(self) -> tuple[list[Sample], list[str]]:
        """Everything held back, including the second still open (the log has ended)."""
        log: list[str] = []
        if self.header is not None and self.builder is None and self.pending:
            self._start(log)
        if self.builder is None:
            return [], log
        return self._process(log, final=True), log

    # ------------------------------------------------------------------ #
    def _new_lines(self) -> list[tuple[int, str]]:
        if not self.path.exists():
            return []
        out = []
        with self.path.open("rb") as fh:
            while True:
                fh.seek(self.position)
                data = fh.read(READ_BYTES)
                if not data:
                    break
                if self.position == 0 and data.startswith(_BOM):
                    data = data[len(_BOM) :]
                    self.position += len(_BOM)
                end = data.rfind(b"\n")
                if end < 0:
                    break  # a partly written line: read it next time
                self.position += end + 1
                for raw in data[: end + 1].split(b"\n")[:-1]:
                    self.line_number += 1
                    out.append((self.line_number, raw.rstrip(b"\r").decode("utf-8", "replace")))
                if len(data) < READ_BYTES:
                    break
        return out

    def _start(self, log: list[str]) -> None:
        """Header and first data lines: the dialect and the column plan."""
        header = self.header[0]
        if self.dialect is None:
            self.dialect = sniff_dialect([header] + [text for _, text in self.pending])
            if not self.dialect.is_default or self.dialect.assumed:
                log.append(
                    f"{self.path}: read as {self.dialect.describe()} (detected"
                    + ("; " + "; ".join(self.dialect.assumed) if self.dialect.assumed else "")
                    + "); --csv-dialect sets it"
                )
        names = next(csv.reader([header], delimiter=self.dialect.delimiter), [])
        names = [n if n != "" else f"Unnamed: {i}" for i, n in enumerate(names)]
        where = f"{self.path}: line {self.header_line}"
        self.builder = TableBuilder(names, where, aliases=self.aliases, dialect=self.dialect)
        log.extend(self.builder.notes)
        self.names = names

    def _process(self, log: list[str], final: bool) -> list[Sample]:
        rows, self.pending = self.pending, []
        builder = self.builder
        width = len(self.names)
        good_lines, cells = [], []
        for number, text in rows:
            fields = next(csv.reader([text], delimiter=self.dialect.delimiter), [])
            if len(fields) != width:
                log.append(
                    f"{self.path}: line {number} has {len(fields)} fields but the header (line "
                    f"{self.header_line}) has {width}; treated as missing"
                )
                continue
            good_lines.append(number)
            cells.append(fields)
        samples: list[Sample] = []
        if cells:
            frame = pd.DataFrame(cells, columns=builder.plan.by_name().keys(), dtype="string")
            samples = self._rows(frame, np.asarray(good_lines), log)
        if final:
            samples += self._samples(self.binner.finish())
        return samples

    def _rows(self, frame: pd.DataFrame, lines: np.ndarray, log: list[str]) -> list[Sample]:
        builder = self.builder
        columns = builder.columns
        time = time_cells(frame[TIME_COLUMN], self.dialect)
        if not pd.api.types.is_numeric_dtype(time) and self.dialect.is_default:
            as_numbers = pd.to_numeric(time.str.strip(), errors="coerce")
            if as_numbers.notna().all():
                time = as_numbers
        try:
            if self.timebase is None:
                unit = columns[TIME_COLUMN].unit
                self.timebase = time_base(time, str(self.path), None if unit == "s" else unit)
                if self.timebase.note:
                    log.append(f"{self.path}: {self.timebase.note}")
            t = self.timebase.seconds(time, str(self.path))
        except TimeError as exc:
            raise RecordError(str(exc)) from None
        names = (*INPUT_COLUMNS, *OUTPUT_COLUMNS)
        values = np.full((len(frame), len(names)), np.nan)
        ok = np.isfinite(t)
        for j, name in enumerate(names):
            if name not in frame.columns:
                continue  # an absent camera or material flow: missing
            text = frame[name].str.strip()
            blank = text.isna() | text.str.lower().isin(BLANKS)
            numbers = parse_numbers(text.where(~blank), self.dialect)
            bad = (numbers.isna() & ~blank).to_numpy(dtype=bool)
            for position in np.flatnonzero(bad & ok):
                log.append(
                    f"{self.path}: line {lines[position]}: not numbers ({name} = "
                    f"{frame[name].iloc[position]!r}); treated as missing"
                )
            ok &= ~bad
            values[:, j] = convert_values(numbers.to_numpy(dtype=float, na_value=np.nan),
                                          columns[name])  # fmt: skip
        for position in np.flatnonzero(~np.isfinite(t)):
            log.append(
                f"{self.path}: line {lines[position]}: time "
                f"{frame[TIME_COLUMN].iloc[position]!r} is not a time; treated as missing"
            )
        keep = []
        for position in np.flatnonzero(ok):
            if self.last_t is not None and t[position] <= self.last_t:
                log.append(
                    f"{self.path}: line {lines[position]}: time {t[position]:g} s does not "
                    f"increase (previous {self.last_t:g} s); dropped"
                )
                continue
            self.last_t = float(t[position])
            keep.append(position)
        keep = np.asarray(keep, dtype=int)
        t, values = t[keep], values[keep]
        for j, name in enumerate(names):
            self.quality[name].add(values[:, j])
        verdict = judge({n: q for n, q in self.quality.items() if n in frame.columns},
                        str(self.path))  # fmt: skip
        if verdict.refused:
            raise RecordError("\n".join(verdict.refused))
        for name, reason in verdict.missing.items():
            if name not in self.unusable:
                self.unusable[name] = reason
                log.append(f"{self.path}: column {name!r} treated as missing: {reason}")
        for name in self.unusable:
            values[:, names.index(name)] = np.nan
        self.started = True
        return self._samples(self.binner.push(t, values))

    def _samples(self, bins) -> list[Sample]:
        n_in = len(INPUT_COLUMNS)
        return [
            (float(k), bins.means[i, :n_in].copy(), bins.means[i, n_in:].copy())
            for i, k in enumerate(bins.seconds)
        ]
