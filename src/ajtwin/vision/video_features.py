"""Linewidth and overspray of every frame of a video, written as a table (``ajtwin extract``).

:func:`extract_video` streams the frames of a video, an image folder or one image
through the camera algorithm (:class:`ajtwin.vision.extract.LineExtractor`, decoding in a
background thread beside it), writes one CSV row per frame (and optionally one per
batch of columns) and, on request, the annotated frames as a video or an image folder.

Examples
--------
>>> done = extract_video("print.mp4", 0.75, "features.csv")   # 6 frames, 0.75 µm/px
>>> done.statuses.most_common(1)
[('ok', 6)]
"""

from __future__ import annotations

import contextlib
import csv
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ajtwin.vision.extract import LineExtractor, VisionInputError, annotate, open_source

#: columns of the per-frame table
FRAME_COLUMNS = [
    "frame",
    "time_s",
    "linewidth_um",
    "overspray_um",
    "linewidth_std_um",
    "overspray_std_um",
    "n_batches",
    "status",
]
#: columns of the per-batch table
BATCH_COLUMNS = [
    "frame",
    "time_s",
    "batch",
    "col_start",
    "col_end",
    "linewidth_um",
    "overspray_um",
    "status",
]
#: what a frame status means for the user, when no frame gave a linewidth
STATUS_HINTS = {
    "dark_frame": "frames are (nearly) black — lens cap, lighting or exposure?",
    "blank_frame": "frames are featureless — nothing in focus?",
    "no_line": "no straight line found (Canny/Hough); lines must lie within 45° of horizontal",
    "steep_line": (
        "the line is steeper than 45° from the image's horizontal, beyond what the paper's "
        "algorithm reads: rotate the video, or give --job and --camera (lines at any angle)"
    ),
    "line_fills_frame": (
        "the line leaves no substrate background in the frame — the line is wider than the "
        "frame can show; check --um-per-px and the field of view"
    ),
    "no_shoulder": "no shoulder peak (iii) in the brightness profile",
    "overspray_outside_frame": "the overspray does not end inside the analysed band",
}
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv")


@dataclass
class VideoExtraction:
    """What :func:`extract_video` wrote and found.

    Attributes
    ----------
    statuses : Counter
        Frames per status (``ok``, ``few_batches``, or why a frame gave no value).
    widths : list of float
        The linewidths measured [µm] (frames with a value).
    batch_path : Path or None
        The per-batch table, when written.
    annotated : Path or None
        The annotated video or image folder, when written.
    """

    statuses: Counter = field(default_factory=Counter)
    widths: list = field(default_factory=list)
    batch_path: Path | None = None
    annotated: Path | None = None

    @property
    def n_frames(self) -> int:
        """Frames read."""
        return sum(self.statuses.values())

    @property
    def n_measured(self) -> int:
        """Frames that gave a linewidth."""
        return sum(self.statuses[s] for s in ("ok", "few_batches"))

    def failure_reasons(self) -> str:
        """Why no frame gave a linewidth, status by status, with a hint each."""
        return "; ".join(
            f"{k} ({v} frames): {STATUS_HINTS.get(k, k)}" for k, v in self.statuses.most_common()
        )


class AnnotatedOutput:
    """Annotated frames to a video (``.mp4``/``.avi``/``.mkv``) or into an image folder.

    Parameters
    ----------
    path : Path
        The video file or the folder.
    fps : float
        Frame rate of the video [1/s].
    """

    def __init__(self, path: Path, fps: float):
        self.path = Path(path)
        self.fps = fps
        self.writer = None

    def write(self, index: int, canvas: np.ndarray) -> None:
        """Add frame ``index`` (a BGR image)."""
        if self.path.suffix.lower() in VIDEO_SUFFIXES:
            if self.writer is None:
                self.writer = _open_writer(self.path, self.fps, canvas.shape)
            self.writer.write(canvas)
        else:
            self.path.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(self.path / f"frame_{index:06d}.png"), canvas)

    def close(self) -> None:
        """Finish the video file (an image folder needs nothing)."""
        if self.writer is not None:
            self.writer.release()


def _open_writer(path: Path, fps: float, shape):
    fourcc = "mp4v" if path.suffix.lower() == ".mp4" else "FFV1"
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(
        str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (shape[1], shape[0]), True
    )
    if not writer.isOpened():
        raise VisionInputError(f"{path}: OpenCV cannot write this video here")
    return writer


def _frame_row(result) -> dict:
    return {k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in result.row().items()}


def _batch_rows(index: int, time_s: float, result) -> list:
    return [
        [index, f"{time_s:.4f}", number, b.col_start, b.col_end,
         f"{b.linewidth_um:.4f}", f"{b.overspray_um:.4f}", b.status]
        for number, b in enumerate(result.batches)
    ]  # fmt: skip


def extract_video(
    source,
    um_per_px: float,
    out,
    *,
    batch: int = 50,
    per_batch: bool = False,
    annotate_to=None,
    fps: float | None = None,
    progress: bool = True,
) -> VideoExtraction:
    """Run the camera algorithm over every frame of ``source`` and write the tables.

    Parameters
    ----------
    source : path
        A video (mp4/avi/...), a folder of images or one PNG/TIFF.
    um_per_px : float
        Pixel size on the substrate [µm].
    out : path
        The per-frame CSV (:data:`FRAME_COLUMNS`).
    batch : int
        Columns per batch (the paper's n).
    per_batch : bool
        Also write every batch's values to ``<out>_batches.csv``.
    annotate_to : path, optional
        Annotated video (``.mp4``/``.avi``/``.mkv``) or image folder: Hough fit (green),
        linewidth (red), overspray (blue).
    fps : float, optional
        Frame rate (videos: overrides the file's; image folders: default 1).
    progress : bool
        A progress bar.

    Raises
    ------
    VisionInputError
        A source that cannot be read, or a writer that cannot be opened.
    """
    source, out = Path(source), Path(out)
    frames = open_source(source, fps)
    extractor = LineExtractor(um_per_px, batch=batch)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = VideoExtraction()
    done.batch_path = out.with_name(out.stem + "_batches.csv") if per_batch else None
    annotated = None if annotate_to is None else AnnotatedOutput(annotate_to, frames.fps)
    try:
        with contextlib.ExitStack() as stack:
            # decoding runs in a background thread, beside the feature extraction below
            decoded = stack.enter_context(frames.prefetched())
            table = csv.DictWriter(stack.enter_context(out.open("w", newline="")), FRAME_COLUMNS)
            table.writeheader()
            batch_table = None
            if done.batch_path is not None:
                batch_table = csv.writer(stack.enter_context(done.batch_path.open("w", newline="")))
                batch_table.writerow(BATCH_COLUMNS)
            bar = tqdm(decoded, total=frames.count, unit="frame",
                       desc=f"extract {source.name}", disable=not progress)  # fmt: skip
            for index, time_s, gray in bar:
                result = extractor.process(gray, index=index, time_s=time_s)
                table.writerow(_frame_row(result))
                done.statuses[result.status] += 1
                if np.isfinite(result.linewidth_um):
                    done.widths.append(result.linewidth_um)
                if batch_table is not None:
                    batch_table.writerows(_batch_rows(index, time_s, result))
                if annotated is not None:
                    annotated.write(index, annotate(gray, result))
    finally:
        if annotated is not None:
            annotated.close()
    done.annotated = None if annotated is None else annotated.path
    return done
