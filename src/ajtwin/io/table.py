"""A log's table, chunk by chunk, into a record's 1 Hz table (the core of the readers).

:class:`TableBuilder` takes the column names of a file, then its rows in chunks (as
pandas reads them, in the file's dialect), and gives the record's table. Per chunk it

1. names the columns (:mod:`ajtwin.io.columns`: aliases, units in the name) and converts
   values to the record's units (:func:`ajtwin.units.convert`);
2. turns cells into numbers in the file's dialect (:mod:`ajtwin.io.dialect`); a cell of a
   record column that is not a number is an error naming row, line and column; other
   columns are kept — as numbers, or as text (an operator's note);
3. turns the time column into seconds (:mod:`ajtwin.io.timebase`) and checks it increases,
   jumps no more than :data:`~ajtwin.io.schema.MAX_GAP_S` and spans no more than
   :data:`~ajtwin.io.schema.MAX_RECORD_SECONDS`;
4. checks plausible ranges (a unit slip) and gathers each column's resolution
   (:mod:`ajtwin.io.quality`);
5. averages the rows into 1 s steps (:class:`~ajtwin.io.timebase.SecondBinner`), keeping
   only the second still open, so memory follows the print's length, not the file's.

:meth:`TableBuilder.finish` then treats outputs printed too coarsely as missing (inputs:
refused), applies the live twin's rule to seconds without inputs
(:func:`~ajtwin.io.timebase.hold_missing_inputs`) and returns the table and the notes to
report (warnings of the reader).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ajtwin.io.columns import ColumnError, convert_values, resolve_columns
from ajtwin.io.dialect import CsvDialect, parse_numbers
from ajtwin.io.quality import ColumnQuality, judge, settings
from ajtwin.io.schema import (
    CAMERA_COLUMNS,
    INPUT_COLUMNS,
    JOB_COLUMNS,
    LINE_TRUTH_COLUMNS,
    MAX_GAP_S,
    MAX_RECORD_SECONDS,
    OUTPUT_COLUMNS,
    PLAUSIBLE_RANGES,
    RECORD_COLUMNS,
    REQUIRED_COLUMNS,
    SAMPLES_COLUMN,
    SCALE_FLOORS,
    TIME_COLUMN,
    TRUTH_COLUMNS,
    UNITS,
    RecordError,
)
from ajtwin.io.spool import RowSpool, SpooledTable
from ajtwin.io.timebase import SecondBinner, TimeError, hold_missing_inputs, time_base

#: Cells read as "no value" (after pandas' own NA spellings such as #N/A).
BLANKS = ("", "nan", "na", "n/a", "none", "null")
#: A median step [s] at or above this means milliseconds in a seconds column.
MILLISECONDS_STEP_S = 100.0
#: A median step [s] below this (over 1000 rows per second) is no time in seconds.
FASTEST_STEP_S = 1e-3


class TableBuilder:
    """Build a record's table from a file's chunks (see the module doc).

    Parameters
    ----------
    names : list of str
        The file's column names, in order.
    where : str
        The file, for messages.
    aliases : path, optional
        The user's alias file.
    dialect : CsvDialect, optional
        How cells write numbers (None: plain, as pandas reads them).
    line_offset : int
        File line of data row 1, minus 1 (0: no lines, e.g. Parquet).
    """

    def __init__(
        self,
        names,
        where: str,
        *,
        aliases=None,
        dialect: CsvDialect | None = None,
        line_offset: int = 0,
    ):
        self.where = where
        self.dialect = dialect or CsvDialect()
        self.line_offset = line_offset
        self.notes: list[str] = []
        try:
            self.plan = resolve_columns(list(names), where, aliases)
        except ColumnError as exc:
            raise RecordError(str(exc)) from None
        renamed = self.plan.describe_renames()
        if renamed:
            self.notes.append(f"{where}: renamed columns by alias: {renamed}")
        present = {c.name for c in self.plan.columns if c.known}
        has_camera = any(c in present for c in CAMERA_COLUMNS)
        required = [c for c in REQUIRED_COLUMNS if has_camera or c not in CAMERA_COLUMNS]
        missing = [c for c in required if c not in present]
        if missing:
            hint = self.plan.missing_hint(missing)
            raise RecordError(
                f"{where}: missing required column(s) {', '.join(map(repr, missing))}; "
                f"found {', '.join(repr(str(c.source)) for c in self.plan.columns)}. If your "
                "log names them differently, add the names to an alias file (see "
                "docs/reference/record-format.md)." + (f"\n{hint}" if hint else "")
            )
        self.added: list[str] = []
        if not has_camera:
            self.notes.append(
                f"{where}: no {' or '.join(map(repr, CAMERA_COLUMNS))} column (no camera); added "
                "as all-NaN — the twin starts droplet size and aerosol fraction from priors"
            )
            self.added += list(CAMERA_COLUMNS)
        if "material_flow_mL_s" not in present:
            self.notes.append(
                f"{where}: no 'material_flow_mL_s' column; added as all-NaN (no measurement)"
            )
            self.added.append("material_flow_mL_s")
        truth = [c for c in TRUTH_COLUMNS if c in present]
        if truth and len(truth) != len(TRUTH_COLUMNS):
            lacking = [c for c in TRUTH_COLUMNS if c not in present]
            self.notes.append(f"{where}: partial truth; lacking {', '.join(lacking)}")
        order = [
            c
            for c in (*RECORD_COLUMNS, *JOB_COLUMNS, *TRUTH_COLUMNS, *LINE_TRUTH_COLUMNS)
            if c in present or c in self.added
        ]
        self.known = [c for c in order if c != TIME_COLUMN]
        self.columns = {c.name: c for c in self.plan.columns}
        self.extras = [c.name for c in self.plan.columns if not c.known]
        self.extra_text: dict[str, bool] = {}
        self.quality = {c: ColumnQuality() for c in self.known if c in present}
        self.timebase = None
        self.binner: SecondBinner | None = None
        self.rows = 0
        self.last_t: float | None = None
        self.first_t: float | None = None
        self.step_range = [np.inf, -np.inf]
        # the emitted steps: values and sample counts on disk, texts of other columns here
        self.spool: RowSpool | None = None
        self.text_pieces: list[np.ndarray] = []
        self.first_step: int | None = None
        self.next_step: int | None = None

    # ------------------------------------------------------------------ #
    def _label(self, row: int) -> str:
        label = f"row {row + 1}"
        if self.line_offset:
            label += f" (line {row + 1 + self.line_offset})"
        return label

    def _numbers(self, series: pd.Series, name: str, first_row: int, strict: bool = True):
        """A column's cells as float (NaN: no value). ``strict``: a cell that is not a
        number is an error naming it; else such cells are NaN and ``(values, True)`` says
        the column holds text."""
        if pd.api.types.is_bool_dtype(series) or pd.api.types.is_complex_dtype(series):
            if not strict:
                return np.full(len(series), np.nan), True
            # True/False or a+bj is no measurement, though NumPy would turn it into a number
            raise RecordError(
                f"{self.where}: column {name!r} has type {series.dtype}; expected real numbers"
            )
        if pd.api.types.is_numeric_dtype(series):
            values = series.to_numpy(dtype=float, na_value=np.nan)
            return values if strict else (values, False)
        text = _as_text(series, self.where, name)
        blank = text.isna() | text.str.lower().isin(BLANKS)
        numbers = parse_numbers(text.where(~blank), self.dialect)
        bad = (numbers.isna() & ~blank).to_numpy(dtype=bool)
        values = numbers.to_numpy(dtype=float, na_value=np.nan)
        if not strict:
            return values, bool(bad.any())
        if bad.any():
            position = int(np.flatnonzero(bad)[0])
            dialect = (
                ""
                if self.dialect.is_default
                else f" in this file's dialect ({self.dialect.describe()}; --csv-dialect sets it)"
            )
            raise RecordError(
                f"{self.where}: {self._label(first_row + position)}, column {name!r}: "
                f"value {series.iloc[position]!r} is not a number{dialect}"
            )
        return values

    def _times(self, chunk: pd.DataFrame, first_row: int) -> np.ndarray:
        column = time_cells(chunk[TIME_COLUMN], self.dialect)
        unit = self.columns[TIME_COLUMN].unit
        try:
            if self.timebase is None:
                self.timebase = time_base(column, self.where, None if unit == "s" else unit)
                if self.timebase.note:
                    self.notes.append(f"{self.where}: {self.timebase.note}")
            t = self.timebase.seconds(column, self.where, first_row)
        except TimeError as exc:
            raise RecordError(str(exc)) from None
        except (TypeError, ValueError, OverflowError) as exc:  # lists, bytes, … in the column
            raise RecordError(
                f"{self.where}: column 'time_s' holds values that are not text or numbers "
                f"({type(exc).__name__}: {str(exc)[:80]})"
            ) from None
        bad = ~np.isfinite(t)
        if bad.any():
            position = int(np.flatnonzero(bad)[0])
            raw = column.iloc[position]
            label = self._label(first_row + position)
            if pd.api.types.is_scalar(raw) and (pd.isna(raw) or str(raw).strip().lower() in BLANKS):
                raise RecordError(
                    f"{self.where}: {label}, column 'time_s': time stamp {raw} is missing; "
                    "every row needs a time"
                )
            if isinstance(raw, int | float | np.number):
                raise RecordError(
                    f"{self.where}: {label}, column 'time_s': time stamp {raw!r} is not finite"
                )
            raise RecordError(
                f"{self.where}: {label}, column 'time_s': value {raw!r} is not a number "
                "(nor a time stamp like the first rows')"
            )
        return t

    def _check_times(self, t: np.ndarray, first_row: int) -> None:
        previous = self.last_t
        joined = t if previous is None else np.concatenate([[previous], t])
        steps = np.diff(joined)
        shift = 0 if previous is None else 1  # steps[i] ends at chunk row i + 1 - shift
        bad = steps <= 0
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            row = first_row + i + 1 - shift
            raise RecordError(
                f"{self.where}: {self._label(row)}, column 'time_s': time {joined[i + 1]:g} s "
                f"does not increase (previous row {joined[i]:g} s); time must be strictly "
                "increasing"
            )
        if previous is None and len(steps) >= 3:
            median = float(np.median(steps))
            if median >= MILLISECONDS_STEP_S:
                raise RecordError(
                    f"{self.where}: column 'time_s': median step {median:g} between rows; the "
                    "time looks like milliseconds (expected seconds, one row per ~1 s; name "
                    "the column 'time_ms' or 'Time [ms]' if it is)"
                )
            if median < FASTEST_STEP_S:
                raise RecordError(
                    f"{self.where}: column 'time_s': median step {median:.3g} between rows is "
                    "more than 1000 rows per second; the time is in another unit (days? "
                    "hours?). ajtwin reads seconds (or a unit in the column name: "
                    "'Time [min]'), ISO date-times, Excel serial days and Unix epoch "
                    "seconds or milliseconds"
                )
        jumps = steps > MAX_GAP_S
        if jumps.any():
            i = int(np.flatnonzero(jumps)[0])
            row = first_row + i + 1 - shift
            median = float(np.median(steps)) if len(steps) else float("nan")
            raise RecordError(
                f"{self.where}: {self._label(row)}, column 'time_s': time stamp "
                f"{joined[i + 1]:.6g} s jumps {steps[i]:.6g} s after the previous row "
                f"({joined[i]:.6g} s; median step {median:.3g} s): a gap of more than "
                f"{MAX_GAP_S / 3600:g} h is refused (the live twin drops such a sample too); "
                "is that row in another clock or unit?"
            )
        if self.first_t is None:
            self.first_t = float(t[0])
        beyond = t - self.first_t > MAX_RECORD_SECONDS
        if beyond.any():
            i = int(np.flatnonzero(beyond)[0])
            raise RecordError(
                f"{self.where}: {self._label(first_row + i)}, column 'time_s': the print "
                f"reaches {t[i] - self.first_t:.0f} s ({(t[i] - self.first_t) / 86400:.1f} "
                f"days) here, more than a record may span ({MAX_RECORD_SECONDS} s = "
                f"{MAX_RECORD_SECONDS / 86400:g} days; docs/reference/record-format.md, Limits); "
                "split the log into prints"
            )
        if len(steps):
            self.step_range = [
                min(self.step_range[0], float(steps.min())),
                max(self.step_range[1], float(steps.max())),
            ]
        self.last_t = float(t[-1])

    def _check_ranges(self, name: str, values: np.ndarray, first_row: int) -> None:
        if name not in PLAUSIBLE_RANGES:
            return
        low, high, small_hint, large_hint = PLAUSIBLE_RANGES[name]
        if np.isinf(values).any():
            position = int(np.flatnonzero(np.isinf(values))[0])
            raise RecordError(
                f"{self.where}: {self._label(first_row + position)}, column {name!r}: "
                f"value {values[position]!r} is infinite (use NaN for a missing measurement)"
            )
        finite = np.isfinite(values)
        for mask, hint, side in (
            (finite & (values < low), small_hint, "below"),
            (finite & (values > high), large_hint, "above"),
        ):
            if mask.any():
                position = int(np.flatnonzero(mask)[0])
                guess = f"; the values look like {hint}" if hint else ""
                raise RecordError(
                    f"{self.where}: {self._label(first_row + position)}, column {name!r}: "
                    f"value {values[position]:g} is {side} the plausible range "
                    f"[{low:g}, {high:g}] {UNITS[name]}{guess}"
                )

    # ------------------------------------------------------------------ #
    def push(self, chunk: pd.DataFrame, first_row: int) -> None:
        """Take the next rows of the file (``first_row``: the 0-based data row of the first)."""
        if not len(chunk):
            return
        chunk = chunk.set_axis([c.name for c in self.plan.columns], axis=1)
        chunk = chunk.reset_index(drop=True)
        t = self._times(chunk, first_row)
        numeric = np.full((len(chunk), len(self.known)), np.nan)
        for j, name in enumerate(self.known):
            if name in self.added:
                continue
            values = self._numbers(chunk[name], name, first_row)
            values = convert_values(values, self.columns[name])
            self._check_ranges(name, values, first_row)
            self.quality[name].add(values)
            numeric[:, j] = values
        # other columns are kept: as numbers (averaged per second) unless some cell is text
        extra_numbers, extra_texts = [], []
        for name in self.extras:
            values, has_text = self._numbers(chunk[name], name, first_row, strict=False)
            self.extra_text[name] = self.extra_text.get(name, False) or has_text
            extra_numbers.append(convert_values(values, self.columns[name]))
            extra_texts.append(_text_cells(chunk[name]))
        self._check_times(t, first_row)
        if self.binner is None:
            self.binner = SecondBinner(len(self.known) + len(self.extras), len(self.extras))
        matrix = np.column_stack([numeric, *extra_numbers]) if extra_numbers else numeric
        texts = np.column_stack(extra_texts) if extra_texts else None
        self.rows += len(chunk)
        self._emit(self.binner.push(t, matrix, texts))

    def _emit(self, bins) -> None:
        if not len(bins):
            return
        if self.next_step is None:
            self.first_step = self.next_step = int(bins.seconds[0])
            self.spool = RowSpool(len(self.known) + len(self.extras) + 1, self.where)
        span = int(bins.seconds[-1]) - self.next_step + 1
        position = bins.seconds - self.next_step
        # one row per second: the columns' means, then the number of samples averaged
        rows = np.full((span, bins.means.shape[1] + 1), np.nan)
        rows[position, :-1] = bins.means
        rows[:, -1] = 0.0
        rows[position, -1] = bins.counts
        self.spool.append(rows)
        if self.extras:
            texts = np.full((span, bins.texts.shape[1]), "", dtype=object)
            texts[position] = bins.texts
            self.text_pieces.append(texts)
        self.next_step += span

    # ------------------------------------------------------------------ #
    def finish(self) -> SpooledTable:
        """The record's table, held on disk (see the module doc); the notes to report are
        in ``notes``."""
        if self.binner is not None:
            self._emit(self.binner.finish())
        if self.spool is None or not self.spool.rows:
            raise RecordError(f"{self.where}: the record has no rows")
        try:
            return self._finished()
        except BaseException:
            self.spool.close()
            raise

    def _finished(self) -> SpooledTable:
        raw = self.spool
        n = raw.rows
        texts = {c for c in self.extras if self.extra_text[c]}
        counts_column = raw.width - 1
        counts = raw.column(counts_column)
        resampled = n != self.rows or bool((counts != 1).any())
        empty = int((counts == 0).sum())
        del counts
        self._scale_floors(raw)
        verdict = judge(self.quality, self.where)
        for name in settings()["outputs"]["refuse_when_unusable"]:
            if name in verdict.missing:
                verdict.refused.append(
                    f"{self.where}: column {name!r} is unusable: {verdict.missing[name]} (a "
                    "record without its pressures is refused: they alone see the nozzle)"
                )
        if verdict.refused:
            raise RecordError("\n".join(verdict.refused))
        for name, reason in verdict.missing.items():
            self.notes.append(
                f"{self.where}: column {name!r} treated as missing (no measurement): {reason}"
            )
        if resampled:
            low, high = self.step_range
            steps = f"steps {low:g}–{high:g} s" if np.isfinite(low) else "one row"
            self.notes.append(
                f"{self.where}: time stamps not one per second ({steps}); resampled "
                f"{self.rows} samples to {n} seconds by averaging each second (the mean of the "
                f"samples within ±0.5 s; {self.binner.merged} samples shared a second, {empty} "
                f"second(s) had none and are missing); column {SAMPLES_COLUMN!r} counts them"
            )
        table = self._final_table(raw, set(verdict.missing), texts, resampled)
        raw.close()
        return table

    def _final_table(self, raw, missing: set, texts: set, resampled: bool) -> SpooledTable:
        """The table from the raw spool, a block at a time: the time column, the columns
        the verdict found unusable as NaN, the live twin's rule for seconds without
        complete inputs (:func:`~ajtwin.io.timebase.hold_missing_inputs`, carried over the
        blocks), the sample counts when the log was resampled."""
        layout = [*self.known, *self.extras]
        numbers = [TIME_COLUMN, *self.known] + [c for c in self.extras if c not in texts]
        wanted = [layout.index(c) for c in numbers[1:]]
        cleared = [layout.index(c) for c in missing]
        u_at = [layout.index(c) for c in INPUT_COLUMNS]
        y_at = [layout.index(c) for c in OUTPUT_COLUMNS]
        names = numbers + ([SAMPLES_COLUMN] if resampled else [])
        out = RowSpool(len(names), self.where)
        hold = _InputHold(len(INPUT_COLUMNS))
        for start, rows in raw.blocks():
            rows[:, cleared] = np.nan
            kept, u, y = hold.push(rows[:, u_at], rows[:, y_at])
            if not len(kept):
                continue
            rows = rows[kept]
            rows[:, u_at], rows[:, y_at] = u, y
            block = [self.first_step + start + kept[:, None], rows[:, wanted]]
            if resampled:
                block.append(rows[:, -1:])
            out.append(np.concatenate(block, axis=1))
        if hold.first >= raw.rows:
            out.close()
            raise RecordError(
                f"{self.where}: no second has all three inputs "
                f"({', '.join(INPUT_COLUMNS)}); the model needs them every second"
            )
        if hold.any_missing:
            self._note_held(hold)
        text_columns = {}
        for name in (c for c in self.extras if c in texts):  # an operator's note, in its place
            j = self.extras.index(name)
            values = np.concatenate([p[:, j] for p in self.text_pieces])[hold.first :]
            text_columns[name] = (1 + len(self.known) + j, values)
        self.text_pieces = []
        return SpooledTable(out, names, text_columns)

    def _note_held(self, hold) -> None:
        counts = dict(zip(INPUT_COLUMNS, hold.missing_counts.tolist(), strict=True))
        per_column = ", ".join(f"{c}: {k}" for c, k in counts.items() if k)
        if hold.held:
            start_s = self.first_step + hold.first + hold.longest_start
            text = (
                f"{self.where}: {hold.held} second(s) without complete inputs ({per_column}; "
                f"the longest run {hold.longest} s from t = {start_s:g} s): inputs held at "
                "their last value and the outputs missing there, as the live twin does"
            )
        else:
            text = f"{self.where}: inputs missing ({per_column})"
        if hold.first:
            text += f"; the first {hold.first} second(s), before any complete inputs, dropped"
        self.notes.append(text)

    def _scale_floors(self, raw) -> None:
        layout = [*self.known, *self.extras]
        for name, (floor, hint) in SCALE_FLOORS.items():
            if name not in layout or name in self.added:
                continue
            values = raw.column(layout.index(name))
            finite = np.isfinite(values)
            if not (finite & (values > 0)).any():
                continue  # no overspray at all, or none measured: not a unit
            high = float(np.percentile(values[finite], 95))
            if high < floor:
                position = int(np.flatnonzero(finite & (values > 0))[0])
                raise RecordError(
                    f"{self.where}: {self._label(position)}, column {name!r}: 95 % of its "
                    f"values are at most {high:g} {UNITS[name]}, below {floor:g} (the largest "
                    f"{np.max(values[finite]):g}); the values look like {hint}"
                )


class _InputHold:
    """:func:`~ajtwin.io.timebase.hold_missing_inputs` over a table a block at a time: the
    last complete inputs carried from block to block, and what the note says (seconds
    held, per column missing, the longest run without inputs after the first complete
    second and where it starts)."""

    def __init__(self, n_inputs: int):
        self.carry: np.ndarray | None = None  # (1, n_inputs) the last complete inputs
        self.first = 0  # seconds before the first with complete inputs (dropped)
        self.held = 0
        self.missing_counts = np.zeros(n_inputs, np.int64)
        self.any_missing = False
        self.longest, self.longest_start = 0, 0
        self._run, self._run_start, self._kept = 0, 0, 0  # the run still open at the end

    def push(self, u: np.ndarray, y: np.ndarray):
        """(rows kept, their inputs held, their outputs) of the next block."""
        missing = ~np.isfinite(u)
        self.missing_counts += missing.sum(axis=0)
        self.any_missing = self.any_missing or bool(missing.any())
        if self.carry is None:
            held_u, held_y, first, held = hold_missing_inputs(u, y)
            self.first += first
            kept = np.arange(first, len(u))
        else:
            joined_u = np.concatenate([self.carry, u])
            joined_y = np.concatenate([np.full((1, y.shape[1]), np.nan), y])
            held_u, held_y, _, held = hold_missing_inputs(joined_u, joined_y)
            held_u, held_y = held_u[1:], held_y[1:]
            kept = np.arange(len(u))
        self.held += held
        if len(kept):
            self.carry = held_u[-1:].copy()
            self._track_runs(missing[kept].any(axis=1))
        return kept, held_u, held_y

    def _track_runs(self, rows: np.ndarray) -> None:
        """The longest run of seconds without complete inputs (the first of the longest),
        a run carried on from the block before when it reaches this one's first row."""
        edges = np.flatnonzero(np.diff(np.r_[False, rows, False].astype(np.int8)))
        carried = self._run
        self._run = 0
        for begin, end in zip(edges[0::2], edges[1::2], strict=True):
            length, start = int(end - begin), self._kept + int(begin)
            if begin == 0 and carried:
                length, start = carried + length, self._run_start
            if length > self.longest:
                self.longest, self.longest_start = length, start
            if end == len(rows):
                self._run, self._run_start = length, start
        self._kept += len(rows)


def time_cells(column: pd.Series, dialect: CsvDialect) -> pd.Series:
    """A time column as numbers when every cell is a number in ``dialect`` (``1.234,5``
    in a decimal-comma file), else as it is (date-times, or a bad cell to name)."""
    if dialect.is_default or pd.api.types.is_numeric_dtype(column):
        return column
    if pd.api.types.is_datetime64_any_dtype(column):
        return column
    try:
        text = column.astype("string").str.strip()
    except (TypeError, ValueError):
        return column
    blank = text.isna() | text.str.lower().isin(BLANKS)
    numbers = parse_numbers(text.where(~blank), dialect)
    if (numbers.notna() | blank).all():
        return numbers
    return column


def _as_text(series: pd.Series, where: str, column) -> pd.Series:
    """A column as stripped text; bytes that are not UTF-8 (a binary column) are refused."""
    try:
        return series.astype("string").str.strip()
    except (TypeError, ValueError, UnicodeDecodeError) as exc:
        raise RecordError(
            f"{where}: column {column!r} holds values that are not text or numbers "
            f"({type(exc).__name__}: {str(exc)[:80]})"
        ) from None


def _text_cells(series: pd.Series) -> np.ndarray:
    """A text column's cells as Python strings ('' for no value)."""
    if pd.api.types.is_bool_dtype(series):
        return series.map(lambda v: "" if pd.isna(v) else str(v)).to_numpy(dtype=object)
    try:
        text = series.astype("string")
    except (TypeError, ValueError, UnicodeDecodeError):
        text = series.map(lambda v: v.decode("utf-8", "replace") if isinstance(v, bytes)
                          else str(v))  # fmt: skip
    return text.fillna("").to_numpy(dtype=object)
