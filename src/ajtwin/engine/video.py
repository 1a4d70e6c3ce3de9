"""Video join: a print record's linewidth and overspray from its alignment-camera video.

:func:`join_video` runs the camera algorithm (:mod:`ajtwin.vision.extract`) over every
frame, places the frames on the print's time line (:mod:`ajtwin.vision.join`) and fills
the record's ``linewidth_um``/``overspray_um``; an ingest with ``--video`` and the demo
call it.
"""

from __future__ import annotations

import pandas as pd
from tqdm import tqdm

from ajtwin.io.records import PrintRecord
from ajtwin.vision import join as vision_join


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
