"""Q_m from alignment-camera video with a trained height-profile model.

Each frame: the extractor's line fit turns it horizontal, batches of ``n``
columns (default 50) give batch-mean columns across the line
(:func:`~ajtwin.profile_cnn.frames.frame_columns`), the CNN turns each into a
height profile, Q_m = ν ∫ h dr per batch, and the frame value is the mean over
its batches (the spread is reported too).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from ajtwin.profile_cnn.flow import material_flow_ml_s
from ajtwin.profile_cnn.frames import frame_columns
from ajtwin.profile_cnn.model import ProfileModel
from ajtwin.vision.extract import LineExtractor, open_source
from ajtwin.vision.join import join_frame_columns

QM_COLUMNS = (
    "frame",
    "time_s",
    "material_flow_mL_s",
    "material_flow_std_mL_s",
    "cross_section_um2",
    "n_columns",
    "status",
)


def infer_video(
    source,
    model: ProfileModel,
    *,
    um_per_px: float,
    platen_speed_mm_s: float,
    batch: int = 50,
    fps: float | None = None,
    progress: bool = True,
) -> pd.DataFrame:
    """Q_m per frame of a video / image folder / image.

    Parameters
    ----------
    source : path
        Video, image folder or single image (read by the vision module).
    model : ProfileModel
    um_per_px : float
        Camera pixel size, µm (columns are resampled to the model's grid when
        it differs).
    platen_speed_mm_s : float
        Platen speed ν, mm/s.
    batch : int
        Columns per batch (paper: 50).
    fps : float, optional
        Frame rate override.

    Returns
    -------
    DataFrame with columns :data:`QM_COLUMNS`; ``material_flow_mL_s`` is NaN
    for frames without a usable line (``status`` says why).
    """
    if not (np.isfinite(platen_speed_mm_s) and platen_speed_mm_s > 0):
        raise ValueError(f"platen speed must be > 0 mm/s, got {platen_speed_mm_s}")
    frames = open_source(source, fps)
    extractor = LineExtractor(um_per_px, batch=batch)
    rows = []
    for index, time_s, frame in tqdm(
        frames, total=frames.count, desc="frames", unit="frame", disable=not progress
    ):
        fc = frame_columns(
            frame,
            extractor,
            n_pixels=model.n_pixels,
            model_um_per_px=model.um_per_px,
            index=index,
            time_s=time_s,
        )
        if len(fc.columns) == 0:
            status = fc.result.status if fc.result.status != "ok" else "no_line"
            rows.append((index, time_s, np.nan, np.nan, np.nan, 0, status))
            continue
        profiles = model.predict_um(fc.columns)
        qm = material_flow_ml_s(profiles, model.um_per_px, platen_speed_mm_s)
        area = profiles.sum(axis=1) * model.um_per_px
        rows.append(
            (
                index,
                time_s,
                float(qm.mean()),
                float(qm.std(ddof=1)) if qm.size > 1 else 0.0,
                float(area.mean()),
                int(qm.size),
                "ok",
            )
        )
    return pd.DataFrame(rows, columns=list(QM_COLUMNS))


def join_material_flow(
    record: pd.DataFrame,
    qm: pd.DataFrame,
    *,
    start_offset_s: float = 0.0,
    camera_offset_um: float = 0.0,
    platen_speed_mm_s: float = 1.0,
) -> tuple[pd.DataFrame, dict]:
    """Fill a 1 Hz print record's ``material_flow_mL_s`` from per-frame Q_m.

    The same time mapping as the vision extractor's ``--join``
    (:func:`ajtwin.vision.join.frame_print_times`: start offset, camera lag
    behind the nozzle) and the same binning: record second ``t`` gets the mean
    of the frames whose print time is in ``[t, t + 1)``; seconds without a
    frame get NaN. Everything else in the record is kept.

    Returns
    -------
    joined : DataFrame
    summary : dict
        ``seconds_filled``, ``seconds_without_frames``, ``frames_used``,
        ``frames_outside_record``, ``frames_not_ok``.

    Examples
    --------
    >>> rec = pd.DataFrame({"time_s": [0.0, 1.0, 2.0]})
    >>> qm = pd.DataFrame({"time_s": [0.2, 0.7, 2.5], "material_flow_mL_s": [1.0, 3.0, 5.0],
    ...                    "status": ["ok"] * 3})
    >>> join_material_flow(rec, qm)[0]["material_flow_mL_s"].tolist()
    [2.0, nan, 5.0]
    """
    # the frame→second binning is the vision join's; finite Q_m only, as before
    finite = qm[np.isfinite(qm["material_flow_mL_s"])] if "material_flow_mL_s" in qm else qm
    try:
        joined, summary = join_frame_columns(
            record,
            finite,
            ("material_flow_mL_s",),
            start_offset_s=start_offset_s,
            camera_offset_um=camera_offset_um,
            platen_speed_mm_s=platen_speed_mm_s,
        )
    except ValueError as exc:
        raise ValueError(str(exc).replace("frame table", "Q_m table")) from None
    summary["frames_not_ok"] += int(len(qm) - len(finite))
    return joined, summary
