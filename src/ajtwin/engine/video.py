"""Video join: a print record's linewidth and overspray from its alignment-camera video.

:func:`join_video` runs the camera algorithm (:mod:`ajtwin.vision.extract`) over every
frame, places the frames on the print's time line (:mod:`ajtwin.vision.join`) and fills
the record's ``linewidth_um``/``overspray_um``; an ingest with ``--video`` and the demo
call it.

On a part (a job print, record format version 2) the readings of the program-guided
extraction (``ajtwin extract --job``, :mod:`ajtwin.vision.part_video`) fill the record
instead (:func:`join_part_readings`, :func:`join_part_video`). A job print's record has one
row per second, ``t_k = time_s``. The camera columns of row k (``linewidth_um``,
``overspray_um``) are what the frames taken during ``(t_k − 1, t_k]`` measured (the
record's camera measurement at t_k sees only what is printed by then), and
``printed_at_s`` is when the measured trace was printed (τ ≤ t_k; a trailing camera sees
what was printed earlier). Those frames may show several traces, or one trace printed
over several seconds; a row must stand for one line, so it takes one group of readings:
those of one stroke printed within one second ``⌊τ⌋`` — the group with the most readings
(the most precise), the latest-printed on a tie. The row then holds the group's mean
linewidth and overspray and its mean print time. Rows whose frames gave no reading are NaN
in all three columns (no measurement). Every other column is kept.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from ajtwin.io.records import PrintRecord
from ajtwin.vision import join as vision_join

#: the columns a part's readings fill in a record
PART_JOIN_COLUMNS = ("linewidth_um", "overspray_um", "printed_at_s")


def join_video(
    record, video, um_per_px: float, *, progress: bool = True, fps=None, annotate_times=()
):
    """Fill the record's linewidth/overspray from an alignment-camera video (ajtwin.vision).

    Parameters
    ----------
    record : PrintRecord
    video : path of the video (or image folder)
    um_per_px : float, camera pixel size on the substrate [µm]
    annotate_times : sequence of float, optional
        Video times [s] of frames to return annotated (paper's Fig. annotated_acam).

    Returns
    -------
    record : PrintRecord with linewidth_um/overspray_um from the video (NaN where no frame)
    summary : dict, the join counts
    features : DataFrame, one row per frame (``ajtwin extract`` columns)
    annotated : dict {frame time [s]: BGR image}
    """
    # OpenCV is loaded only for a print that comes with a video
    from ajtwin.vision.extract import LineExtractor, annotate, open_source

    frames = open_source(video, fps=fps)
    extractor = LineExtractor(um_per_px)
    wanted = sorted(float(t) for t in annotate_times)
    annotated = {}
    rows = []
    for index, time_s, gray in tqdm(
        frames, total=frames.count, unit="frame", desc="extract video", disable=not progress
    ):
        result = extractor.process(gray, index=index, time_s=time_s)
        rows.append(result.row())
        if wanted and time_s >= wanted[0]:
            annotated[float(time_s)] = annotate(gray, result)
            wanted.pop(0)
    features = pd.DataFrame(rows)
    if (
        features.empty
        or not features["status"].isin(("ok", "ok_std_fallback", "few_batches")).any()
    ):
        counts = features["status"].value_counts().to_dict() if len(features) else {}
        raise ValueError(f"{video}: no frame gave a linewidth (statuses: {counts})")
    good = features["status"].isin(("ok", "ok_std_fallback", "few_batches"))
    vision_join.check_linewidth_scale(features.loc[good, "linewidth_um"], um_per_px, video)
    joined, summary = vision_join.join_features(
        record.data,
        features,
        platen_speed_mm_s=float(record.meta.get("platen_speed_mm_s", 1.0)),
    )
    meta = dict(record.meta)
    meta["vision"] = {"video": str(video), **summary}
    return PrintRecord(joined, meta), summary, features, annotated


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
    >>> out["linewidth_um"].tolist()[2], round(out["printed_at_s"].tolist()[2], 3)
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
    # row k takes the frames of (t_{k-1}, t_k]: a frame never sees a trace printed later
    row = np.searchsorted(record_time, frame_time, side="left")
    inside = (row >= 0) & (row < record_time.size)
    offset = record_time[np.clip(row, 0, max(record_time.size - 1, 0))] - frame_time
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
    for column in PART_JOIN_COLUMNS:
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
        for column in PART_JOIN_COLUMNS:
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


def join_part_video(
    record: PrintRecord,
    readings: pd.DataFrame,
    camera,
    *,
    source,
    program,
    camera_file,
) -> tuple[PrintRecord, dict]:
    """A job print's record with its camera columns from a part's readings.

    Parameters
    ----------
    record : PrintRecord
        The print (its clock is the job's).
    readings : DataFrame
        ``ajtwin extract --job`` readings (:func:`join_part_readings`).
    camera : ajtwin.vision.camera.Camera
        The camera the video was taken with: the record's ``camera`` metadata gets its
        offset (the mode is kept when the record states one, else ``at_nozzle`` for a zero
        offset and ``trailing`` otherwise).
    source, program, camera_file
        The video, the program and the camera file, for ``meta["vision"]``.

    Returns
    -------
    record : PrintRecord
        ``linewidth_um``, ``overspray_um`` and ``printed_at_s`` from the readings.
    summary : dict
        The join counts (:func:`join_part_readings`).
    """
    joined, summary = join_part_readings(record.data, readings)
    meta = dict(record.meta)
    previous = meta.get("camera") if isinstance(meta.get("camera"), dict) else {}
    offset = [float(v) for v in camera.offset_mm]
    meta["camera"] = {
        "mode": previous.get("mode") or ("at_nozzle" if offset == [0.0, 0.0] else "trailing"),
        "offset_mm": offset,
    }
    meta["vision"] = {
        "source": str(source),
        "program": Path(program).name,
        "camera_file": str(camera_file),
        "um_per_px": camera.um_per_px,
        "rotation_deg": camera.rotation_deg,
        **summary,
    }
    return PrintRecord(joined, meta), summary
