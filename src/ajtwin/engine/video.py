"""What the registry decides about a print's start: carry-over between prints.

The orchestration of an ingest (hash, start state, twin, detectors, store) lives in the
engine, :func:`ajtwin.live.engine.ingest_record`, shared with the live twin;
``ingest_record``/``ingest_file`` here are compatibility wrappers. :func:`join_video`
fills a record's linewidth/overspray from the alignment-camera video.

Which print the next one starts from, how the fast states' variance is widened between
prints and when a print is kept out of the chain (a state outside the physical range):
:mod:`ajtwin.store.chain`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ajtwin.store.chain import BETWEEN_PRINT_STD, carry_over
from ajtwin.store.registry import Registry

__all__ = ["BETWEEN_PRINT_STD", "carry_over", "ingest_record", "ingest_file", "join_video"]


@dataclass
class IngestResult:
    machine: str
    print_id: int
    seq: int
    duplicate: bool
    content_hash: str
    n_samples: int
    events: list = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    seconds: float = 0.0
    run: object = None  # TwinRun (None for a duplicate)
    detection: object = None  # DetectionResult (None for a duplicate)


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
    import pandas as pd
    from tqdm import tqdm

    from ajtwin.io.records import PrintRecord
    from ajtwin.vision.extract import LineExtractor, annotate, open_source
    from ajtwin.vision.join import check_linewidth_scale, join_features

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
    check_linewidth_scale(features.loc[good, "linewidth_um"], um_per_px, video)
    joined, summary = join_features(
        record.data,
        features,
        platen_speed_mm_s=float(record.meta.get("platen_speed_mm_s", 1.0)),
    )
    meta = dict(record.meta)
    meta["vision"] = {"video": str(video), **summary}
    return PrintRecord(joined, meta), summary, features, annotated


def ingest_record(registry: Registry, machine: str, record, **kwargs):
    """Compatibility: the orchestration moved to :func:`ajtwin.live.engine.ingest_record`."""
    from ajtwin.live.engine import ingest_record as _ingest_record

    return _ingest_record(registry, machine, record, **kwargs)


def ingest_file(registry: Registry, machine: str, path, **kwargs):
    """Compatibility: moved to :func:`ajtwin.live.engine.ingest_file`."""
    from ajtwin.live.engine import ingest_file as _ingest_file

    return _ingest_file(registry, machine, path, **kwargs)
