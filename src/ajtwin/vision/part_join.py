"""Readings of a part's traces into the print record (record format version 2).

A job print's record has one row per second, ``t_k = time_s``. The camera columns of row k
(``linewidth_um``, ``overspray_um``) are what the frames taken during ``[t_k, t_k + 1)``
measured, and ``printed_at_s`` is when the measured trace was printed (τ ≤ t_k + 1; a
trailing camera sees what was printed earlier). Those frames may show several traces, or
one trace printed over several seconds; a row must stand for one line, so it takes one
group of readings: those of one stroke printed within one second ``⌊τ⌋`` — the group with
the most readings (the most precise), the latest-printed on a tie. The row then holds the
group's mean linewidth and overspray and its mean print time. Rows whose frames gave no
reading are NaN in all three columns (no measurement). Every other column is kept.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

CAMERA_COLUMNS = ("linewidth_um", "overspray_um", "printed_at_s")


def join_part_readings(
    record: pd.DataFrame, readings: pd.DataFrame, frame_to_record_s: float = 0.0
) -> tuple[pd.DataFrame, dict]:
    """Fill a record's camera columns from program-guided readings.

    Parameters
    ----------
    record : DataFrame
        The print record's table (``time_s`` at 1 Hz).
    readings : DataFrame
        ``ajtwin extract --job`` readings: ``time_s`` (job time of the frame), ``stroke``,
        ``print_time_s``, ``linewidth_um``, ``overspray_um``.
    frame_to_record_s : float
        Record time minus job time (0 when the record's clock is the job's).

    Returns
    -------
    joined : DataFrame
        A copy of ``record`` with ``linewidth_um``, ``overspray_um`` and ``printed_at_s``
        replaced.
    summary : dict
        ``seconds_filled``, ``readings_used``, ``readings_outside_record``,
        ``readings_in_other_groups`` (readings of the same seconds not in the chosen group).

    Examples
    --------
    >>> rec = pd.DataFrame({"time_s": [0.0, 1.0, 2.0]})
    >>> rd = pd.DataFrame({"time_s": [1.2, 1.5, 1.7], "stroke": [3, 3, 4],
    ...                    "print_time_s": [0.2, 0.4, 1.1], "linewidth_um": [40.0, 42.0, 50.0],
    ...                    "overspray_um": [20.0, 22.0, 30.0]})
    >>> out, _ = join_part_readings(rec, rd)
    >>> out["linewidth_um"].tolist()[1], round(out["printed_at_s"].tolist()[1], 3)
    (41.0, 0.3)
    """
    for column in ("time_s", "stroke", "print_time_s", "linewidth_um", "overspray_um"):
        if column not in readings.columns:
            raise ValueError(f"readings table has no column {column!r}")
    if "time_s" not in record.columns:
        raise ValueError("print record has no column 'time_s'")
    record_time = record["time_s"].to_numpy(float)
    frame_time = readings["time_s"].to_numpy(float) + frame_to_record_s
    print_time = readings["print_time_s"].to_numpy(float) + frame_to_record_s
    row = np.searchsorted(record_time, frame_time, side="right") - 1
    inside = (row >= 0) & (row < record_time.size)
    offset = frame_time - record_time[np.clip(row, 0, max(record_time.size - 1, 0))]
    inside &= (offset >= 0) & (offset < 1.0)
    table = pd.DataFrame(
        {
            "row": row[inside],
            "stroke": readings["stroke"].to_numpy()[inside],
            "second": np.floor(print_time[inside]),
            "print_time_s": print_time[inside],
            "linewidth_um": readings["linewidth_um"].to_numpy(float)[inside],
            "overspray_um": readings["overspray_um"].to_numpy(float)[inside],
        }
    )
    joined = record.copy()
    for column in CAMERA_COLUMNS:
        joined[column] = np.nan
    used = 0
    if not table.empty:
        groups = (
            table.groupby(["row", "stroke", "second"])
            .agg(
                n=("linewidth_um", "size"),
                linewidth_um=("linewidth_um", "mean"),
                overspray_um=("overspray_um", "mean"),
                printed_at_s=("print_time_s", "mean"),
            )
            .reset_index()
            .sort_values(["row", "n", "printed_at_s"], ascending=[True, False, False])
        )
        best = groups.drop_duplicates("row", keep="first")
        rows = best["row"].to_numpy(int)
        for column in CAMERA_COLUMNS:
            values = joined[column].to_numpy(float).copy()
            values[rows] = best[column].to_numpy(float)
            joined[column] = values
        used = int(best["n"].sum())
    summary = {
        "seconds_filled": int(np.isfinite(joined["linewidth_um"]).sum()),
        "readings_used": used,
        "readings_outside_record": int((~inside).sum()),
        "readings_in_other_groups": int(inside.sum()) - used,
    }
    return joined, summary
