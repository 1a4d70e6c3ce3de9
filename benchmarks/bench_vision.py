"""The camera algorithm's speed: :meth:`LineExtractor.process` on rendered frames
(1280 x 1024 and 1920 x 1080), as in a video (8 distinct frames cycled, line tracking on),
and end to end on an mp4 of the same frames: ``open_source`` and every frame extracted, with
decoding in a second thread (``FrameSource.prefetched``, what ``ajtwin extract`` runs) and in
one thread. Its accuracy against the truth is a study: ``python -m ajtwin.studies.vision_accuracy``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

FRAMES = 60
SHAPES = {"1280x1024": (1024, 1280), "1920x1080": (1080, 1920)}
LINE = (43.0, 29.0, 15.0)  # nominal linewidth µm, overspray µm, cross-section µm²


def _frames(shape, count=8, tilt=4.0, seed=0):
    from ajtwin.vision.profile import line_profile
    from ajtwin.vision.render import RenderSettings, Substrate, render_frame

    r = np.arange(-160.0, 160.0, 0.05)
    settings = RenderSettings.from_defaults(tilt_deg=tilt)
    rng = np.random.default_rng(seed)
    substrate = Substrate(shape, settings, rng)
    h = line_profile(r, *LINE)
    return [
        render_frame(r, h, shape, settings, rng=rng, substrate=substrate, travel_um=40.0 * k)
        for k in range(count)
    ]


def _end_to_end_fps(path, prefetched: bool) -> float:
    """Frames/s of decode → features over the whole video."""
    from ajtwin.vision.extract import LineExtractor, open_source

    source = open_source(path)
    extractor = LineExtractor(0.75)
    start = time.perf_counter()
    reader = source.prefetched() if prefetched else iter(source)
    count = 0
    try:
        for index, time_s, gray in reader:
            extractor.process(gray, index, time_s)
            count += 1
    finally:
        getattr(reader, "close", lambda: None)()
    return count / (time.perf_counter() - start)


class LineExtraction:
    """One frame through the extractor, and a whole mp4 end to end."""

    params = list(SHAPES)
    param_names = ["frame"]
    timeout = 600

    def setup_cache(self):
        """An mp4 of :data:`FRAMES` frames of each size (asv's folder for the class)."""
        import cv2  # writing the video

        for name, shape in SHAPES.items():
            frames = _frames(shape)
            fourcc = cv2.VideoWriter_fourcc(*"mp4v")
            writer = cv2.VideoWriter(f"{name}.mp4", fourcc, 30, (shape[1], shape[0]), False)
            for k in range(FRAMES):
                writer.write(frames[k % len(frames)])
            writer.release()
        return os.getcwd()

    def setup(self, folder, frame):
        from ajtwin.vision.extract import LineExtractor

        self.video = Path(folder) / f"{frame}.mp4"
        self.frames = _frames(SHAPES[frame])
        self.extractor = LineExtractor(0.75)
        for image in self.frames:  # the first Hough runs without tracking
            self.extractor.process(image)
        self.k = 0

    def time_extract_one_frame(self, folder, frame):
        self.extractor.process(self.frames[self.k % len(self.frames)])
        self.k += 1

    def track_end_to_end_fps(self, folder, frame):
        """Decoding in its own thread beside the features (``ajtwin extract``)."""
        return _end_to_end_fps(self.video, prefetched=True)

    def track_end_to_end_one_thread_fps(self, folder, frame):
        return _end_to_end_fps(self.video, prefetched=False)

    track_end_to_end_fps.unit = track_end_to_end_one_thread_fps.unit = "frames/s"
