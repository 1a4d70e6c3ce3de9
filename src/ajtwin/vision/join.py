"""Map video frame times onto print time and fill a print record's linewidth/overspray.

Frame ``k`` of a video at ``fps`` frames/s is taken ``k / fps`` seconds after the video
starts.  The print record's clock (``time_s``, 1 Hz) may have started earlier or later
(``start_offset_s`` = print time of video frame 0), and the camera looks at the line a
distance ``camera_offset_um`` behind the nozzle, so the line it sees was printed
``camera_offset_um / platen speed`` earlier:

    print_time = frame_time + start_offset_s - camera_offset_um / (1000 * platen_speed_mm_s)

Each record second ``t`` gets the mean of the successfully measured frames with
``print_time`` in ``[t, t + 1)`` — the record's row ``t`` stands for the second that starts
at ``t``, as in the renderer, which shows row ``t``'s line until ``t + 1``.  Seconds without
such frames get NaN (no measurement).  Everything else in the record is kept.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ajtwin.io.records import PLAUSIBLE_RANGES
from ajtwin.units import mm_per_s_to_um_per_s
from ajtwin.vision.errors import VisionInputError

GOOD_STATUS = ("ok", "ok_std_fallback", "few_batches")


def frame_print_times(
    frame_time_s,
    *,
    start_offset_s: float = 0.0,
    camera_offset_um: float = 0.0,
    platen_speed_mm_s: float = 1.0,
) -> np.ndarray:
    """Print time (s) of the line seen in each frame (see module docstring).

    Examples
    --------
    >>> frame_print_times([0.0, 0.5], start_offset_s=10.0, camera_offset_um=500.0)
    array([ 9.5, 10. ])
    """
    if not (np.isfinite(platen_speed_mm_s) and platen_speed_mm_s > 0):
        raise ValueError(f"platen speed must be > 0 mm/s, got {platen_speed_mm_s}")
    lag_s = camera_offset_um / mm_per_s_to_um_per_s(platen_speed_mm_s)
    return np.asarray(frame_time_s, dtype=float) + start_offset_s - lag_s


def join_frame_columns(
    record: pd.DataFrame,
    frames: pd.DataFrame,
    columns: tuple[str, ...],
    *,
    start_offset_s: float = 0.0,
    camera_offset_um: float = 0.0,
    platen_speed_mm_s: float = 1.0,
) -> tuple[pd.DataFrame, dict]:
    """Bin per-frame values onto a 1 Hz record: the one join every video reader uses.

    Record second ``t`` gets, for each of ``columns``, the mean of the frames with a good
    ``status`` whose print time (:func:`frame_print_times`) is in ``[t, t + 1)``; seconds
    without such a frame get NaN. Everything else in the record is kept.

    Returns
    -------
    joined : DataFrame
        A copy of ``record`` with ``columns`` replaced.
    summary : dict
        ``seconds_filled`` (of the first column), ``seconds_without_frames``, ``frames_used``,
        ``frames_outside_record``, ``frames_not_ok``.
    """
    for column in ("time_s", *columns, "status"):
        if column not in frames.columns:
            raise ValueError(f"frame table has no column {column!r}")
    if "time_s" not in record.columns:
        raise ValueError("print record has no column 'time_s'")
    good = frames[frames["status"].isin(GOOD_STATUS)]
    print_time = frame_print_times(
        good["time_s"].to_numpy(dtype=float),
        start_offset_s=start_offset_s,
        camera_offset_um=camera_offset_um,
        platen_speed_mm_s=platen_speed_mm_s,
    )
    record_time = record["time_s"].to_numpy(dtype=float)
    # the record second each frame falls in (half-open bins [t, t + 1))
    index = np.searchsorted(record_time, print_time, side="right") - 1
    inside = (index >= 0) & (index < record_time.size)
    offset = print_time - record_time[np.clip(index, 0, max(record_time.size - 1, 0))]
    inside &= (offset >= 0) & (offset < 1.0)
    joined = record.copy()
    for column in columns:
        values = good[column].to_numpy(dtype=float)
        ok = inside & np.isfinite(values)
        sums = np.bincount(index[ok], weights=values[ok], minlength=record_time.size)
        counts = np.bincount(index[ok], minlength=record_time.size)
        with np.errstate(invalid="ignore", divide="ignore"):
            joined[column] = np.where(counts > 0, sums / counts, np.nan)
    filled = int(np.isfinite(joined[columns[0]]).sum())
    summary = {
        "seconds_filled": filled,
        "seconds_without_frames": int(record_time.size - filled),
        "frames_used": int(inside.sum()),
        "frames_outside_record": int((~inside).sum()),
        "frames_not_ok": int(len(frames) - len(good)),
    }
    return joined, summary


def join_features(
    record: pd.DataFrame,
    features: pd.DataFrame,
    *,
    start_offset_s: float = 0.0,
    camera_offset_um: float = 0.0,
    platen_speed_mm_s: float = 1.0,
) -> tuple[pd.DataFrame, dict]:
    """Fill ``linewidth_um`` and ``overspray_um`` of a 1 Hz record from frame features.

    Parameters
    ----------
    record : DataFrame
        Print record table with ``time_s`` (1 Hz).
    features : DataFrame
        ``ajtwin extract`` output: ``time_s``, ``linewidth_um``, ``overspray_um``, ``status``.
    start_offset_s, camera_offset_um, platen_speed_mm_s
        See :func:`frame_print_times`.

    Returns
    -------
    joined : DataFrame
        A copy of ``record`` with the two columns replaced (NaN where no frame fell).
    summary : dict
        Counts: seconds filled, seconds without frames, frames used, frames outside the
        record's time span.
    """
    try:
        return join_frame_columns(
            record,
            features,
            ("linewidth_um", "overspray_um"),
            start_offset_s=start_offset_s,
            camera_offset_um=camera_offset_um,
            platen_speed_mm_s=platen_speed_mm_s,
        )
    except ValueError as exc:
        raise ValueError(str(exc).replace("frame table", "features table")) from None


def check_linewidth_scale(widths_um, um_per_px: float, source) -> float:
    """Refuse extracted linewidths whose median no real line has: a wrong ``--um-per-px``.

    The one plausibility check of every video reader (``ajtwin extract`` and ``ajtwin
    ingest --video``): the median of the finite linewidths must lie in the print-record
    reader's plausible linewidth range (``PLAUSIBLE_RANGES["linewidth_um"]``), so a pixel
    size off by orders of magnitude never reaches a record or the registry.

    Returns
    -------
    float
        The median linewidth [µm].

    Raises
    ------
    VisionInputError
        No finite linewidth, or a median outside the range (naming the source and pixel size).
    """

    low, high = PLAUSIBLE_RANGES["linewidth_um"][:2]
    widths = np.asarray(widths_um, dtype=float)
    widths = widths[np.isfinite(widths)]
    if widths.size == 0:
        raise VisionInputError(f"{source}: no frame gave a finite linewidth")
    median = float(np.median(widths))
    if not low <= median <= high:
        raise VisionInputError(
            f"{source}: median linewidth {median:.3g} µm with --um-per-px {um_per_px:g} is "
            f"implausible (expected {low:g}–{high:g} µm): check the pixel size"
        )
    return median
