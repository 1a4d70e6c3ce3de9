"""A sample of a machine: one second of inputs and outputs, checked before the twin sees it.

:func:`clean_sample` is what every source of samples (an OPC UA link, a growing CSV, a
replayed live print) passes its values through: non-finite or implausible values
become missing, a time that is no clock reading drops the sample.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS, PLAUSIBLE_RANGES
from ajtwin.model.limits import INPUT_LIMITS
from ajtwin.model.names import INPUT_NAMES


class Sample(NamedTuple):
    """One 1 Hz sample: time [s], inputs (3,) [mA, sccm, sccm], outputs (5,) (NaN = missing).

    A job print's row also carries the record's job columns (model reference §12; None for
    a print without a job): ``shutter_open`` (0/1 at t), ``platen_speed_mm_s`` (at t) and
    ``printed_at_s`` (τ of the trace the camera measured in this row).
    """

    time_s: float
    inputs: np.ndarray | None
    outputs: np.ndarray
    shutter_open: float | None = None
    platen_speed_mm_s: float | None = None
    printed_at_s: float | None = None


#: a gap ahead of the last step longer than this [s] is not filled with missing samples
#: (a clock jump or a stale/wrong time stamp, not an outage): the sample is dropped
MAX_GAP_S = 6 * 3600

#: |time| beyond this [s] (≈ 31,700 years) is no clock reading: the sample is dropped (far
#: below 2**53 s, where float64 could no longer hold the 1 s grid)
MAX_ABS_TIME_S = 1e12


def clean_sample(time_s, inputs, outputs, where: str = "") -> tuple[Sample | None, list[str]]:
    """Check a sample from the wire; returns (sample or None, problems as log lines).

    Non-finite or out-of-range outputs become NaN; bad or malformed inputs/outputs (not
    3 + 5 numbers) make the sample missing (all NaN); a non-finite or implausible time
    (|t| > ``MAX_ABS_TIME_S``) drops it (None).
    """
    problems = []
    prefix = f"{where}: " if where else ""
    try:
        t = float(time_s)
    except (TypeError, ValueError, OverflowError):
        t = float("nan")
    if not np.isfinite(t):
        return None, [f"{prefix}sample time {time_s!r} is not a number; sample dropped"]
    if abs(t) > MAX_ABS_TIME_S:
        return None, [f"{prefix}sample time {t:g} s is not a plausible clock; sample dropped"]
    u = np.full(3, np.nan)
    y = np.full(5, np.nan)
    try:
        u[:] = np.asarray(inputs, dtype=float).reshape(3)
        y[:] = np.asarray(outputs, dtype=float).reshape(5)
    except (TypeError, ValueError, OverflowError) as exc:
        # as the line says: a step with nothing known, not a dropped one
        missing = Sample(t, np.full(3, np.nan), np.full(5, np.nan))
        return missing, [f"{prefix}t = {t:g} s: malformed sample ({exc}); treated as missing"]
    for i, name in enumerate(INPUT_NAMES):
        low, high = INPUT_LIMITS[name]
        if not np.isfinite(u[i]) or not (low < u[i] <= high):
            problems.append(
                f"{prefix}t = {t:g} s: {INPUT_COLUMNS[i]} = {u[i]!r} outside ({low:g}, {high:g}]"
                "; sample treated as missing"
            )
    if problems:
        return Sample(t, np.full(3, np.nan), np.full(5, np.nan)), problems
    for i, column in enumerate(OUTPUT_COLUMNS):
        value = y[i]
        if np.isnan(value):
            continue
        low, high = PLAUSIBLE_RANGES.get(column, (-np.inf, np.inf))[:2]
        if not np.isfinite(value) or not (low <= value <= high):
            problems.append(
                f"{prefix}t = {t:g} s: {column} = {value!r} outside [{low:g}, {high:g}]; "
                "treated as missing"
            )
            y[i] = np.nan
    return Sample(t, u, y), problems
