"""Time in a log → seconds on the twin's 1 s grid; gaps and the inputs held through them.

Time columns
------------
:func:`time_base` looks at the first rows of a log's time column and fixes how every row
becomes seconds (:meth:`TimeBase.seconds`):

* seconds (the record format), or another unit the column name gives (``Time [ms]``,
  ``time_min``);
* wall-clock text: ISO 8601 (``2026-11-21T14:00:01``, with or without a zone, the same on
  every row), ``21.11.2026 14:00:01`` (day first, as European spreadsheets write it) or a
  time of day ``14:00:01`` (a log past midnight goes on counting); seconds since the
  first row. ``03/04/2026``-style dates are refused: day and month cannot be told apart;
* numbers that are plainly not seconds since the start of a print: Excel serial days
  (25569–73051 = 1970–2100, one row every ~1e-5 days), Unix epoch seconds (1e8–4.2e9)
  and epoch milliseconds (1e11–4.2e12); seconds since the first row.

Each conversion is reported (a warning by the reader).

The 1 s grid
------------
:class:`SecondBinner` averages samples into 1 s steps: step k holds the samples with
k − ½ ≤ t < k + ½ and gets the mean of each column over the samples where that column has
a value, and the number of samples. A log on the grid already (one sample at each whole
second) passes unchanged; a 10 Hz log gives the mean of its ten samples; a second without
any sample is missing. It works chunk by chunk (a file read in pieces, a growing file),
keeping only the samples of the second still open.

Gaps
----
:func:`hold_missing_inputs` is the live twin's rule (:mod:`ajtwin.estimation.samples`, "Late,
missing, duplicated and out-of-order samples") for a second without complete inputs: the
inputs are held at their last value and the outputs are missing, so the twin predicts
through the gap; seconds before the first complete inputs are dropped (nothing to hold).
A finished print read from a file gets the same rule, so ``estimate``/``ingest`` and the
live twin treat a gap alike.

Examples
--------
>>> binner = SecondBinner(n_values=1)
>>> bins = binner.push(np.array([0.0, 0.1, 0.9, 1.2]), np.array([[1.0], [3.0], [4.0], [6.0]]))
>>> bins.seconds.tolist(), bins.means[:, 0].tolist(), bins.counts.tolist()
([0], [2.0], [2])
>>> last = binner.finish()
>>> last.seconds.tolist(), last.means[:, 0].tolist(), last.counts.tolist()
([1], [5.0], [2])
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ajtwin import units

#: Excel serial days of 1970-01-01 and 2100-01-01 (the 1900 date system).
EXCEL_DAYS_RANGE = (25569.0, 73051.0)
EXCEL_EPOCH = pd.Timestamp("1899-12-30")
#: Unix epoch seconds of 1973-03-03 … 2103-02-03, and the same in milliseconds.
EPOCH_S_RANGE = (1e8, 4.2e9)
EPOCH_MS_RANGE = (1e11, 4.2e12)
#: A logging step [s] inside which these numbers are taken for such clocks (10 ms … 1 h).
CLOCK_STEP_RANGE_S = (0.01, 3600.0)
#: Wall-clock text formats tried after ISO 8601 (pandas/strftime syntax).
TEXT_FORMATS = (
    ("%d.%m.%Y %H:%M:%S.%f", "day-first date"),
    ("%d.%m.%Y %H:%M:%S", "day-first date"),
    ("%d.%m.%Y %H:%M", "day-first date"),
    ("%H:%M:%S.%f", "time of day"),
    ("%H:%M:%S", "time of day"),
)
_AMBIGUOUS_FORMATS = ("%d/%m/%Y %H:%M:%S", "%m/%d/%Y %H:%M:%S", "%d/%m/%Y %H:%M", "%m/%d/%Y %H:%M")


class TimeError(ValueError):
    """A time column that cannot be turned into seconds; the message says why."""


@dataclass
class TimeBase:
    """How a log's time column becomes seconds (fixed from its first rows).

    ``kind``: ``"seconds"``, ``"iso"``, ``"text"`` (a strftime ``text_format``),
    ``"time of day"``, ``"excel days"``, ``"epoch s"`` or ``"epoch ms"``. ``scale``: seconds
    per unit of the column; ``origin``: the value (or time stamp) that becomes 0 (None: the
    log's own seconds are kept).
    """

    kind: str
    scale: float = 1.0
    origin: object = None
    text_format: str | None = None
    utc: bool = False
    note: str | None = None
    _day_offset: float = 0.0
    _last_of_day: float | None = None

    def seconds(self, column: pd.Series, where: str, first_row: int = 0) -> np.ndarray:
        """The rows' times in seconds (float64); NaN for a cell that is not a time.

        ``first_row`` — the row number of the column's first cell in the file (for
        messages); chunks must come in order (a time of day counts days across chunks).

        Raises
        ------
        TimeError
            A row with a time zone where the first rows have none, or the reverse.
        """
        if pd.api.types.is_datetime64_any_dtype(column):
            return (column - self.origin).dt.total_seconds().to_numpy(dtype=float, na_value=np.nan)
        if self.kind in ("seconds", "excel days", "epoch s", "epoch ms"):
            values = _numbers(column)
            if self.origin is not None:
                values = values - self.origin
            return values * self.scale
        text = column.astype("string").str.strip()
        if self.kind == "iso":
            zoned = _zoned(text).to_numpy(dtype=bool)
            odd = ~zoned if self.utc else zoned
            if odd.any():
                position = int(np.flatnonzero(odd)[0])
                state, first = ("no", "have one") if self.utc else ("a", "have none")
                raise TimeError(
                    f"{where}: row {first_row + position + 1}, column 'time_s': {state} time "
                    f"zone where the first rows {first}; give every time stamp the same zone "
                    "(or none)"
                )
            stamps = pd.to_datetime(text, errors="coerce", format="ISO8601", utc=self.utc)
        else:
            stamps = pd.to_datetime(text, errors="coerce", format=self.text_format)
        if self.kind == "time of day":
            of_day = (
                stamps.dt.hour * 3600.0
                + stamps.dt.minute * 60.0
                + stamps.dt.second
                + stamps.dt.microsecond * 1e-6
            ).to_numpy(dtype=float, na_value=np.nan)
            out = np.empty_like(of_day)
            for i, value in enumerate(of_day):  # past midnight a time of day starts again at 0
                if np.isfinite(value):
                    if self._last_of_day is not None and value < self._last_of_day - 43200.0:
                        self._day_offset += 86400.0
                    self._last_of_day = value
                out[i] = value + self._day_offset
            return out - float(self.origin)
        seconds = (stamps - self.origin).dt.total_seconds()
        return seconds.to_numpy(dtype=float, na_value=np.nan)


def _numbers(column: pd.Series) -> np.ndarray:
    if pd.api.types.is_numeric_dtype(column):
        return column.to_numpy(dtype=float, na_value=np.nan)
    return pd.to_numeric(column, errors="coerce").to_numpy(dtype=float, na_value=np.nan)


def _zoned(text: pd.Series) -> pd.Series:
    return text.str.contains(r"(?:Z|[+-]\d\d:?\d\d)$", regex=True).fillna(False)


def _median_step(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    if len(finite) < 2:
        return math.nan
    return float(np.median(np.diff(finite)))


def time_base(column: pd.Series, where: str, unit: str | None = None) -> TimeBase:
    """How this time column becomes seconds, from its first rows (see the module doc).

    Parameters
    ----------
    column : Series
        The first rows of the time column as read (numbers, text or datetimes).
    unit : str, optional
        The unit the column's name gives (``"ms"`` for ``Time [ms]``), a time unit of
        :mod:`ajtwin.units`; None: seconds, or whatever the values show.

    Raises
    ------
    TimeError
        Inconsistent time zones, or day/month-ambiguous dates.
    """
    if pd.api.types.is_datetime64_any_dtype(column):
        origin = column.iloc[0]
        base = TimeBase("datetime", origin=origin)
        base.note = f"'time_s' holds wall-clock time stamps; converted to seconds since {origin}"
        return base
    scale = 1.0 if unit is None else float(units.convert(1.0, unit, "s"))
    if not pd.api.types.is_numeric_dtype(column):
        text = column.astype("string").str.strip()
        if not pd.to_numeric(text, errors="coerce").notna().all():
            base = _text_base(text, where)
            if base is not None:
                return base
    return _numeric_base(_numbers(column) * scale, scale, unit)


def _numeric_base(values: np.ndarray, scale: float, unit: str | None) -> TimeBase:
    finite = values[np.isfinite(values)]
    if len(finite) == 0:
        return TimeBase("seconds", scale)
    first = float(finite[0])
    raw_first = first / scale
    step = _median_step(values)
    low, high = CLOCK_STEP_RANGE_S
    if unit is None and EXCEL_DAYS_RANGE[0] <= first <= EXCEL_DAYS_RANGE[1]:
        if np.isfinite(step) and low <= step * 86400.0 <= high:
            stamp = EXCEL_EPOCH + pd.to_timedelta(first, unit="D")
            base = TimeBase("excel days", 86400.0, origin=first)
            base.note = (
                f"the time column holds Excel serial days ({first:.10g} = "
                f"{stamp.round('s')}); converted to seconds since the first row"
            )
            return base
    if EPOCH_S_RANGE[0] <= first <= EPOCH_S_RANGE[1] and np.isfinite(step) and low <= step <= high:
        stamp = pd.Timestamp(first, unit="s", tz="UTC").round("s")
        base = TimeBase("epoch s", scale, origin=raw_first)
        base.note = (
            f"the time column holds Unix epoch seconds ({first:.10g} = {stamp}); converted "
            "to seconds since the first row"
        )
        return base
    if (
        unit is None
        and EPOCH_MS_RANGE[0] <= first <= EPOCH_MS_RANGE[1]
        and np.isfinite(step)
        and low <= step / 1000.0 <= high
    ):
        stamp = pd.Timestamp(first / 1000.0, unit="s", tz="UTC").round("s")
        base = TimeBase("epoch ms", 1e-3, origin=first)
        base.note = (
            f"the time column holds Unix epoch milliseconds ({first:.13g} = {stamp}); "
            "converted to seconds since the first row"
        )
        return base
    base = TimeBase("seconds", scale)
    if unit not in (None, "s"):
        base.note = f"the time column is in {unit}; converted to seconds"
    return base


def _parses(sample: pd.Series, **kwargs) -> pd.Series:
    try:
        return pd.to_datetime(sample, errors="coerce", **kwargs)
    except (ValueError, TypeError, OverflowError):
        return pd.Series(pd.NaT, index=sample.index)


def _text_base(text: pd.Series, where: str) -> TimeBase | None:
    """A base for wall-clock text, when the first time stamp is in a format ajtwin reads
    (later cells that are not are then named by the reader); None: not a time format."""
    sample = text.dropna()
    sample = sample[sample != ""]
    if sample.empty:
        return None
    first_text = sample.iloc[0]
    zoned = _zoned(sample)
    if zoned.any() and not zoned.all():
        with_zone = int(np.flatnonzero(zoned.to_numpy())[0])
        without = int(np.flatnonzero(~zoned.to_numpy())[0])
        raise TimeError(
            f"{where}: column 'time_s': row {with_zone + 1} has a time zone and row "
            f"{without + 1} has none; give every time stamp the same zone (or none)"
        )
    utc = bool(zoned.all())
    stamps = _parses(sample, format="ISO8601", utc=utc)
    if pd.notna(stamps.iloc[0]) and not sample.iloc[0].replace(".", "", 1).isdigit():
        origin = stamps.iloc[0]
        base = TimeBase("iso", origin=origin, utc=utc)
        base.note = f"'time_s' holds wall-clock time stamps; converted to seconds since {origin}"
        return base
    for text_format, kind in TEXT_FORMATS:
        parsed = _parses(sample, format=text_format)
        if pd.isna(parsed.iloc[0]):
            continue
        first = parsed.iloc[0]
        if kind == "time of day":
            origin = first.hour * 3600.0 + first.minute * 60.0 + first.second
            base = TimeBase("time of day", origin=origin + first.microsecond * 1e-6,
                            text_format=text_format)  # fmt: skip
            base.note = (
                f"'time_s' holds times of day (first {first_text}); converted to seconds "
                "since the first row (past midnight the count goes on)"
            )
        else:
            base = TimeBase("text", origin=first, text_format=text_format)
            base.note = (
                f"'time_s' holds day-first date-times (first {first_text} = {first}); "
                "converted to seconds since the first row"
            )
        return base
    if any(pd.notna(_parses(sample.iloc[:1], format=f).iloc[0]) for f in _AMBIGUOUS_FORMATS):
        raise TimeError(
            f"{where}: column 'time_s': dates like {first_text!r} can be day/month or "
            "month/day; write ISO dates (2026-11-21 14:00:00) or seconds since the start"
        )
    return None


# --------------------------------------------------------------------------- #
# The 1 s grid
# --------------------------------------------------------------------------- #
@dataclass
class Bins:
    """Completed 1 s steps: ``seconds`` (b,) int, ``means`` (b, m), ``counts`` (b,) int —
    samples in each step — and ``texts`` (b, p) object (the distinct texts, joined)."""

    seconds: np.ndarray
    means: np.ndarray
    counts: np.ndarray
    texts: np.ndarray

    def __len__(self) -> int:
        return len(self.seconds)


class SecondBinner:
    """Average samples into 1 s steps as they come (see the module doc).

    Parameters
    ----------
    n_values : int
        Numeric columns per sample (averaged, NaN = no value).
    n_texts : int
        Text columns per sample (a step gets its samples' distinct non-empty texts,
        joined by " | ").
    """

    def __init__(self, n_values: int, n_texts: int = 0):
        self.n_values, self.n_texts = n_values, n_texts
        self._t = np.empty(0)
        self._v = np.empty((0, n_values))
        self._x = np.empty((0, n_texts), dtype=object)
        self.samples_in = 0
        self.merged = 0  # samples that shared a step with another

    @staticmethod
    def step_of(t) -> np.ndarray:
        """The 1 s step each time belongs to: k with k − ½ ≤ t < k + ½."""
        return np.floor(np.asarray(t, dtype=float) + 0.5).astype(np.int64)

    def push(self, t, values, texts=None, final: bool = False) -> Bins:
        """Add samples (times strictly increasing, after those pushed before); returns the
        steps now complete (all of them with ``final``)."""
        t = np.asarray(t, dtype=float)
        values = np.asarray(values, dtype=float).reshape(len(t), self.n_values)
        texts = (
            np.full((len(t), self.n_texts), "", dtype=object)
            if texts is None
            else np.asarray(texts, dtype=object).reshape(len(t), self.n_texts)
        )
        self.samples_in += len(t)
        if len(self._t):
            t = np.concatenate([self._t, t])
            values = np.concatenate([self._v, values])
            texts = np.concatenate([self._x, texts])
        steps = self.step_of(t)
        if final or not len(t):
            done = len(t)
        else:
            done = int(np.searchsorted(steps, steps[-1], side="left"))
        self._t, self._v, self._x = t[done:], values[done:], texts[done:]
        return self._bin(steps[:done], values[:done], texts[:done])

    def finish(self) -> Bins:
        """The step still open (the last one)."""
        return self.push(np.empty(0), np.empty((0, self.n_values)), None, final=True)

    def _bin(self, steps, values, texts) -> Bins:
        if not len(steps):
            return Bins(
                np.empty(0, np.int64),
                np.empty((0, self.n_values)),
                np.empty(0, np.int64),
                np.empty((0, self.n_texts), dtype=object),
            )
        starts = np.r_[0, np.flatnonzero(np.diff(steps)) + 1]
        counts = np.diff(np.r_[starts, len(steps)])
        if len(starts) == len(steps):  # one sample per step: unchanged
            return Bins(steps.copy(), values.copy(), counts, texts.copy())
        self.merged += int((counts[counts > 1]).sum())
        finite = np.isfinite(values)
        sums = np.add.reduceat(np.where(finite, values, 0.0), starts, axis=0)
        n = np.add.reduceat(finite.astype(np.int64), starts, axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            means = np.where(n > 0, sums / np.maximum(n, 1), np.nan)
        joined = texts[starts].copy()
        for b in np.flatnonzero(counts > 1):
            block = texts[starts[b] : starts[b] + counts[b]]
            for j in range(self.n_texts):
                seen = []
                for value in block[:, j]:
                    if isinstance(value, str) and value.strip() and value not in seen:
                        seen.append(value)
                joined[b, j] = " | ".join(seen) if seen else block[0, j]
        return Bins(steps[starts], means, counts, joined)


def hold_missing_inputs(inputs: np.ndarray, outputs: np.ndarray):
    """The live twin's rule for seconds without complete inputs (see the module doc).

    Parameters
    ----------
    inputs : (T, 3) float
    outputs : (T, 5) float

    Returns
    -------
    inputs, outputs, first, held
        The arrays from the first second with complete inputs on (inputs held, outputs
        NaN where inputs were missing), the index of that first second (T when there is
        none) and the number of seconds whose inputs were held.
    """
    inputs = np.asarray(inputs, dtype=float)
    outputs = np.asarray(outputs, dtype=float)
    missing = ~np.isfinite(inputs).all(axis=1)
    n = len(inputs)
    if not missing.any():
        return inputs, outputs, 0, 0
    complete = np.flatnonzero(~missing)
    if not len(complete):
        return inputs[:0], outputs[:0], n, 0
    first = int(complete[0])
    last_complete = np.maximum.accumulate(np.where(missing, 0, np.arange(n)))
    held_inputs = inputs[last_complete]
    held_outputs = np.where(missing[:, None], np.nan, outputs)
    held = int(missing[first:].sum())
    return held_inputs[first:], held_outputs[first:], first, held
