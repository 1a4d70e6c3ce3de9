"""Readings of every trace in every frame of a part's video, written as tables.

:func:`extract_part_video` streams the frames of a video (or an image folder) through the
program-guided extraction (:class:`ajtwin.vision.part_extract.PartExtractor`, decoding in
a background thread beside it) and writes two tables: one row per reading
(:data:`~ajtwin.vision.part_extract.READING_COLUMNS`) and, beside it as
``<out>_frames.csv``, one row per frame with the windows skipped or failed per reason
(:data:`~ajtwin.vision.part_extract.FRAME_COLUMNS`); on request the annotated frames as a
video or an image folder. A frame taken after the end of the job is refused: the video
belongs to another program, its clock is off, or the program was looped.

Examples
--------
Not run in the suite: it needs a part's video, its program and camera file (see
``tests/test_vision_part_cli.py``).

>>> done = extract_part_video("part.mp4", job, camera, "readings.csv")  # doctest: +SKIP
>>> done.n_readings, done.skipped.most_common(1)                         # doctest: +SKIP
(5120, [('stroke_end', 812)])
"""

from __future__ import annotations

import csv
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from ajtwin.config import packaged_toml
from ajtwin.vision.errors import VisionInputError
from ajtwin.vision.extract import open_source
from ajtwin.vision.part_extract import (
    FRAME_COLUMNS,
    READING_COLUMNS,
    PartExtractor,
    PartSettings,
    annotate_part,
)
from ajtwin.vision.program_match import MISPLACED_SHARE, ProgramMatch, ProgramMismatchError
from ajtwin.vision.video_features import AnnotatedOutput

__all__ = [
    "PartVideoExtraction",
    "ReadingsWriter",
    "check_video_duration",
    "check_window_count",
    "extract_part_video",
]

#: what a window measured without a reading means for the user
FAIL_HINTS = {
    "no_line": "no dark band where the program puts the trace",
    "off_program": "the line's centre is away from the program's path",
    "no_shoulder": "no shoulder peak (iii)",
    "overspray_outside": "the overspray does not end within the cross-section",
    "beyond_reach": "the overspray ends beyond --reach-um",
}


def _counts(counter: Counter) -> str:
    return ", ".join(f"{k} {v}" for k, v in counter.most_common())


@dataclass
class PartVideoExtraction:
    """What :func:`extract_part_video` wrote and found.

    Attributes
    ----------
    statuses : Counter
        Frames per status (``ok``, ``no_stroke_in_view``, ``nothing_measurable``,
        ``traces_not_found``).
    skipped, failed : Counter
        Windows in view not measured, and measured without a reading, per reason.
    widths : list of arrays
        The linewidths read, frame by frame [µm].
    n_readings : int
        Rows of the readings table.
    frames_path : Path
        The per-frame table.
    annotated : Path or None
        The annotated video or image folder, when written.
    match : ProgramMatch
        The frames compared with the program.
    """

    statuses: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)
    failed: Counter = field(default_factory=Counter)
    widths: list = field(default_factory=list)
    n_readings: int = 0
    frames_path: Path | None = None
    annotated: Path | None = None
    match: ProgramMatch = field(default_factory=ProgramMatch)

    @property
    def n_frames(self) -> int:
        """Frames read."""
        return sum(self.statuses.values())

    def summary(self) -> str:
        """Frames, windows skipped and windows measured without a reading, per reason."""
        return (
            f"  frames: {_counts(self.statuses)}\n"
            f"  windows skipped: {_counts(self.skipped) or 'none'}\n"
            f"  windows measured without a reading: {_counts(self.failed) or 'none'}"
        )

    def misplaced_warning(self) -> str | None:
        """A warning when most measured windows found no line where the program put it."""
        measured = self.n_readings + sum(self.failed.values())
        lost = self.failed.get("no_line", 0) + self.failed.get("off_program", 0)
        if lost <= MISPLACED_SHARE * measured:
            return None
        return (
            f"{lost} of {measured} measured windows found no line where the program and the "
            "camera file put it: check rotation_deg and offset_mm (ajtwin camera calibrate) "
            "and --start-offset"
        )

    def doubt_warning(self, source, program: str) -> str | None:
        """A warning when some frames show a line where the program prints nothing."""
        if self.match.verdict != "doubtful":
            return None
        return self.match.explain(source, program)

    def no_reading_reason(self, source) -> str:
        """Why no frame of ``source`` gave a reading, with what to check."""
        if sum(self.skipped.values()) + sum(self.failed.values()) == 0:
            return (
                f"no frame of {source} had a printed trace in view: check offset_mm in the "
                "camera file, --start-offset, and that the video belongs to this program"
            )
        if sum(self.failed.values()) == 0:
            return (
                f"no frame of {source} gave a reading: every trace in view was in a situation "
                f"that cannot be measured honestly ({_counts(self.skipped)})"
            )
        hints = "; ".join(
            f"{k} ({v}): {FAIL_HINTS.get(k, k)}" for k, v in self.failed.most_common()
        )
        return (
            f"no frame of {source} gave a reading: the traces are not where the program and "
            f"the camera file put them — {hints}. Check rotation_deg and offset_mm (ajtwin "
            "camera calibrate), --start-offset, and that the video belongs to this program"
        )


class ReadingsWriter:
    """Readings to CSV in blocks of frames (pandas' writer: ~10x faster than row by row).

    At most ``FRAMES_PER_BLOCK`` frames' readings wait in memory; an error or a stop
    (Ctrl-C) writes what waits before leaving (the caller's ``finally``).

    Parameters
    ----------
    handle : text file
        Open for writing; the header is written at once.
    columns : sequence of str
        The table's columns (keys of every readings dict added).
    """

    FRAMES_PER_BLOCK = 32
    #: written to 1 µs, 1 nm (positions in mm), 1e-4 µm and 0.01 (SNR): far below what
    #: the figures can resolve, and short lines that pandas writes fast
    DECIMALS = {
        "time_s": 6,
        "print_time_s": 6,
        "s_mm": 6,
        "x_mm": 6,
        "y_mm": 6,
        "linewidth_um": 4,
        "overspray_um": 4,
        "linewidth_se_um": 4,
        "offset_um": 4,
        "snr": 2,
    }

    def __init__(self, handle, columns):
        self.handle, self.columns = handle, list(columns)
        self.pending: list[dict] = []
        handle.write(",".join(self.columns) + "\n")

    def add(self, readings: dict) -> None:
        """Queue one frame's readings (column -> array); a full block is written."""
        self.pending.append(readings)
        if len(self.pending) >= self.FRAMES_PER_BLOCK:
            self.flush()

    def flush(self) -> None:
        """Write the queued readings."""
        if not self.pending:
            return
        block = {c: np.concatenate([r[c] for r in self.pending]) for c in self.columns}
        self.pending = []
        for column, decimals in self.DECIMALS.items():
            block[column] = np.round(block[column], decimals)
        pd.DataFrame(block, columns=self.columns).to_csv(
            self.handle, header=False, index=False, lineterminator="\n"
        )
        self.handle.flush()


def check_video_duration(frames, start_offset_s: float, job, source, program_name: str) -> None:
    """Refuse a video that lasts beyond the job (the wrong program, clock or a looped job).

    Parameters
    ----------
    frames : FrameSource
        The opened video (:func:`ajtwin.vision.extract.open_source`); a source that does not
        state its frame count is let through (its frames are checked one by one).
    start_offset_s : float
        Job time of the first frame [s].
    job : ajtwin.job.Job
    source, program_name
        The video and the program, for the message.

    Raises
    ------
    VisionInputError
    """
    if not frames.count:
        return
    last = start_offset_s + (frames.count - 1) / frames.fps
    if last > job.duration_s + 1.0 / frames.fps:
        raise VisionInputError(
            f"{source}: {frames.count} frames at {frames.fps:g} frames/s from job time "
            f"{start_offset_s:g} s last until {last:.3f} s, but {program_name} ends at "
            f"{job.duration_s:.3f} s: the video does not belong to this program, --start-offset "
            "is wrong, or the program was looped (--repeat-to)"
        )


def check_window_count(
    job, camera, settings: PartSettings, source, program_name: str, limit: int | None = None
) -> None:
    """Refuse, before building them, more measurement windows than ``limit`` (default
    ``max_windows`` of ``vision/part.toml [bounds]``): the strokes the video can see, cut
    into windows of ``batch`` pixels.

    Raises
    ------
    VisionInputError
    """
    window_mm = settings.batch * camera.um_per_px * 1e-3
    lengths = job.strokes["length_mm"].to_numpy(dtype=float)
    count = int(np.floor(lengths / window_mm + 1e-9).sum())
    if limit is None:
        limit = int(packaged_toml("vision/part.toml")["bounds"]["max_windows"])
    if count > limit:
        raise VisionInputError(
            f"{source}: up to its last frame {program_name} prints {lengths.sum():.0f} mm of "
            f"strokes, {count:,} measurement windows of {1e3 * window_mm:.1f} µm, more than the "
            f"{limit:,} extract holds (vision/part.toml max_windows): extract the video in "
            "shorter stretches, each with its own --start-offset"
        )


def _format(value):
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.6g}" if abs(value) < 1e5 else f"{float(value):.10g}"
    if isinstance(value, np.integer):
        return int(value)
    return value


def _formatted(row: dict) -> dict:
    return {k: _format(v) for k, v in row.items()}


def extract_part_video(
    source,
    job,
    camera,
    out,
    *,
    settings: PartSettings | None = None,
    fiducials=(),
    start_offset_s: float = 0.0,
    fps: float | None = None,
    annotate_to=None,
    progress: bool = True,
    program_name: str | None = None,
) -> PartVideoExtraction:
    """Measure every trace the program puts in every frame of ``source``; write the tables.

    Parameters
    ----------
    source : path
        A video (mp4/avi/...) or a folder of images.
    job : ajtwin.job.Job
        The program as the print ran it (speeds, looping).
    camera : ajtwin.vision.camera.Camera
        The camera's geometry over the part.
    out : path
        The readings CSV; the frames CSV is written beside it as ``<out>_frames.csv``.
    settings : PartSettings, optional
        Default ``vision/part.toml``.
    fiducials : sequence of (x, y) or (x, y, r) [mm]
        Marks whose surroundings are not measured.
    start_offset_s : float
        Job time of the first frame [s].
    fps : float, optional
        Frame rate (videos: overrides the file's; image folders: default 1).
    annotate_to : path, optional
        Annotated video (``.mp4``/``.avi``/``.mkv``) or image folder.
    progress : bool
        A progress bar.
    program_name : str, optional
        The program, for the messages (default: the job's file name).

    Raises
    ------
    ProgramMismatchError
        The frames do not show what the program prints
        (:class:`~ajtwin.vision.program_match.ProgramMatch`): lines where it prints nothing
        in enough frames. No table is written; the annotated frames, asked for, are kept
        (they show the lines off the program).
    VisionInputError
        A source that cannot be read, a video that lasts beyond the job, a writer that
        cannot be opened. The tables keep what was measured before the error.
    """
    source, out = Path(source), Path(out)
    program_name = program_name or Path(job.path).name
    settings = settings or PartSettings.from_defaults()
    frames = open_source(source, fps)
    check_video_duration(frames, start_offset_s, job, source, program_name)
    limit = job.duration_s + 1.0 / frames.fps
    if frames.count and hasattr(job, "until"):
        # nothing printed after the last frame can be seen: a 24-h loop under a short video
        # holds only what the video can show
        job = job.until(start_offset_s + frames.count / frames.fps)
    check_window_count(job, camera, settings, source, program_name)
    extractor = PartExtractor(job, camera, settings, fiducials=fiducials)
    done = PartVideoExtraction(frames_path=out.with_name(out.stem + "_frames.csv"))
    out.parent.mkdir(parents=True, exist_ok=True)
    # the tables are written beside their names and put in place at the end: a video that
    # does not match the program leaves nothing (an error or a stop keeps what was measured)
    partial = {path: path.with_name(path.name + ".partial") for path in (out, done.frames_path)}
    annotated = None if annotate_to is None else AnnotatedOutput(annotate_to, frames.fps)
    refused = False
    try:
        with (
            frames.prefetched() as decoded,
            partial[out].open("w", newline="") as fh,
            partial[done.frames_path].open("w", newline="") as ffh,
        ):
            table = ReadingsWriter(fh, READING_COLUMNS)
            frame_table = csv.DictWriter(ffh, fieldnames=FRAME_COLUMNS)
            frame_table.writeheader()
            bar = tqdm(decoded, total=frames.count, unit="frame",
                       desc=f"extract {source.name}", disable=not progress)  # fmt: skip
            try:
                for index, video_time, gray in bar:
                    t = start_offset_s + video_time
                    if t > limit:
                        raise VisionInputError(
                            f"{source}: frame {index} is at job time {t:.3f} s, after the end "
                            f"of {program_name} ({job.duration_s:.3f} s): the video does not "
                            "belong to this program, --start-offset is wrong, or the program "
                            "was looped (--repeat-to)"
                        )
                    result = extractor.process(gray, index=index, time_s=t)
                    _tally(done, result)
                    frame_table.writerow(_formatted(result.row()))
                    if result.n_readings:
                        table.add(result.readings)
                    if annotated is not None:
                        annotated.write(index, annotate_part(gray, result, extractor))
            finally:  # what waits is written, also when a frame is refused
                table.flush()
        if done.n_readings and done.match.verdict == "mismatch":
            refused = True
            kept = "" if annotated is None else f" (the annotated frames: {annotated.path})"
            raise ProgramMismatchError(
                f"{done.match.explain(source, program_name)} No table was written{kept}."
            )
    finally:
        if annotated is not None:
            annotated.close()
        for path, written in partial.items():
            if refused:
                written.unlink(missing_ok=True)
            elif written.exists():
                written.replace(path)
    done.annotated = None if annotated is None else annotated.path
    return done


def _tally(done: PartVideoExtraction, result) -> None:
    """Add one frame's outcome to what the video gave."""
    done.statuses[result.status] += 1
    done.skipped.update(result.skipped)
    done.failed.update(result.failed)
    if result.n_readings:
        done.n_readings += result.n_readings
        done.widths.append(result.readings["linewidth_um"])
    done.match.add_frame(result)
