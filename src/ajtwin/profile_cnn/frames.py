"""Columns across the line from alignment-camera frames, plus their CV labels.

The CNN sees exactly what the computer-vision extractor sees: each frame is
turned horizontal with the extractor's own Canny → Hough → rotation
(:class:`ajtwin.vision.extract.LineExtractor`), split into batches of ``n``
columns (paper: 50), and each batch's per-row mean is one input "column". The
200 samples are taken centred on the line (the dark-band centre the extractor
uses, to sub-pixel precision by linear interpolation) at the model's pixel
size, so a camera with another µm/px is resampled onto the model's grid.
The extractor's linewidth/overspray of the same batch is that column's CV label.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from tqdm.auto import tqdm

from ajtwin.profile_cnn.data import ColumnDataset
from ajtwin.vision import features as vision_features
from ajtwin.vision.extract import FrameResult, LineExtractor, open_source, to_gray


@dataclass
class FrameColumns:
    """Batch-mean columns of one frame.

    Attributes
    ----------
    columns : (n_batches, n_pixels) float array
        Intensities sampled across the line, centred on it.
    center_row : float
        Line centre in the rotated frame (pixel rows); nan if none was found.
    result : FrameResult
        The extractor's result (CV labels per batch in ``result.batches``).
    """

    columns: np.ndarray
    center_row: float
    result: FrameResult

    @property
    def cv_linewidth_um(self) -> np.ndarray:
        """The camera algorithm's linewidth per batch [µm]."""
        return np.array([b.linewidth_um for b in self.result.batches], dtype=float)

    @property
    def cv_overspray_um(self) -> np.ndarray:
        """The camera algorithm's overspray per batch [µm]."""
        return np.array([b.overspray_um for b in self.result.batches], dtype=float)

    @property
    def cv_ok(self) -> np.ndarray:
        """Which batches the camera algorithm measured."""
        ok = (vision_features.OK, vision_features.STD_FALLBACK)
        return np.array([b.status in ok for b in self.result.batches], dtype=bool)


def frame_columns(
    frame,
    extractor: LineExtractor,
    *,
    n_pixels: int = 200,
    model_um_per_px: float | None = None,
    index: int = 0,
    time_s: float = 0.0,
) -> FrameColumns:
    """Batch-mean columns across the line of one frame, and the extractor's labels.

    Parameters
    ----------
    frame : array
        8/16-bit gray or BGR frame.
    extractor : LineExtractor
        Carries the camera's µm/px and the batch size.
    n_pixels : int
        Column length (the network's input, 200).
    model_um_per_px : float, optional
        Pixel size of the model's grid (default: the camera's).
    index, time_s
        Frame number and time, passed to the extractor.

    Returns
    -------
    FrameColumns
        ``columns`` is empty (0 rows) when no line was found.
    """
    gray = to_gray(frame, f"frame {index}")
    result = extractor.process(gray, index=index, time_s=time_s)
    empty = np.zeros((0, n_pixels))
    if result.rotation is None:
        return FrameColumns(empty, np.nan, result)
    rotated = cv2.warpAffine(
        gray,
        result.rotation,
        (gray.shape[1], gray.shape[0]),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT_101,
    )
    mean, _, n_batches = extractor.batch_statistics(rotated)
    profile = mean.mean(axis=1)
    center = vision_features.dark_band_center(profile, float(np.median(profile)))
    if not np.isfinite(center):
        return FrameColumns(empty, np.nan, result)
    step = (model_um_per_px or extractor.um_per_px) / extractor.um_per_px  # rows per sample
    rows = center + (np.arange(n_pixels) - 0.5 * (n_pixels - 1)) * step
    if rows[0] < 0 or rows[-1] > mean.shape[0] - 1:
        raise ValueError(
            f"frame {index}: a {n_pixels}-sample column at "
            f"{model_um_per_px or extractor.um_per_px} µm/sample around row {center:.1f} "
            f"leaves the {mean.shape[0]}-row frame; the line is too close to the frame edge"
        )
    grid = np.arange(mean.shape[0])
    columns = np.stack([np.interp(rows, grid, mean[:, b]) for b in range(n_batches)])
    return FrameColumns(columns, float(center), result)


def labelled_columns_from_video(
    source,
    um_per_px: float,
    *,
    batch: int = 50,
    n_pixels: int = 200,
    fps: float | None = None,
    progress: bool = True,
):
    """Stage-2 data from real alignment-camera video: batch columns + their CV labels.

    Every batch the extractor measured (status ok / std fallback) becomes one
    labelled column; ``group`` is the frame number, so a frame never straddles
    two cross-validation folds.

    Returns
    -------
    ColumnDataset
    """

    frames = open_source(source, fps)
    extractor = LineExtractor(um_per_px, batch=batch)
    cols, lws, ovs, groups = [], [], [], []
    for index, time_s, frame in tqdm(
        frames, total=frames.count, desc="frames", unit="frame", disable=not progress
    ):
        fc = frame_columns(frame, extractor, n_pixels=n_pixels, index=index, time_s=time_s)
        if len(fc.columns) == 0:
            continue
        ok = fc.cv_ok & np.isfinite(fc.cv_linewidth_um) & np.isfinite(fc.cv_overspray_um)
        cols.append(fc.columns[ok])
        lws.append(fc.cv_linewidth_um[ok])
        ovs.append(fc.cv_overspray_um[ok])
        groups.append(np.full(int(ok.sum()), index))
    if not cols or sum(len(c) for c in cols) == 0:
        raise ValueError(f"{source}: the extractor measured no batch in any frame")
    return ColumnDataset(
        columns=np.concatenate(cols),
        um_per_px=um_per_px,
        linewidth_um=np.concatenate(lws),
        overspray_um=np.concatenate(ovs),
        group=np.concatenate(groups),
    )
