"""The camera on a part: program-guided extraction (``ajtwin extract --job``).

* Part: a meander of 12 legs, 2 mm long and 0.25 mm apart, joined by U-turns of 125 µm
  radius, printed at 2 mm/s; the camera trails 0.3 mm behind the nozzle along X, so each
  1920 x 1080 frame (0.75 µm/px) shows about six legs: ~100 windows in view, ~60 readings.
* Video: 90 frames at 30 frames/s rendered (:mod:`ajtwin.vision.part_render`) and written as
  mp4 (mp4v).
* ``extract``: :meth:`PartExtractor.process` on a decoded frame, one thread.
  ``end_to_end``: reading the program and the camera file, then
  :func:`ajtwin.vision.part_video.extract_part_video` on the mp4, what the command runs
  (decoding in a second thread, extraction, both CSVs). Aim: at least 100 frames/s end to
  end on 2 cores.
* ``windows``: building the extractor (windows along every stroke and what spoils each)
  for public programs: the one-time cost before the first frame.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "prg" / "prg2svg"
FRAMES = 90
FPS = 30.0
START_S = 3.0


def meander(legs=12, leg_mm=2.0, pitch_mm=0.25) -> str:
    """The program of the meander part."""
    lines = ["ptp/e (X,Y),0,0", "OUT0.0=1", "MSEG (X,Y),0,0"]
    x = 0.0
    for k in range(legs):
        up = k % 2 == 0
        y = leg_mm if up else 0.0
        lines.append(f"line (X,Y),{x:.6f},{y:.6f}")
        if k < legs - 1:
            sweep = -math.pi if up else math.pi
            lines.append(f"arc2 (X,Y),{x + pitch_mm / 2:.6f},{y:.6f},{sweep:.12f}")
            x += pitch_mm
    lines += ["ENDS (X,Y)", "till ^X_AST.#MOVE", "OUT0.0=0"]
    return "\n".join(lines) + "\n"


class PartVideo:
    """The meander's video: one frame extracted, and the whole video as the command runs."""

    timeout = 900

    def setup_cache(self):
        """The program, the camera file and the rendered video (asv's folder for the class)."""
        import cv2  # writing the video

        from ajtwin.job import read_program_text
        from ajtwin.vision.camera import Camera, save_camera
        from ajtwin.vision.part_render import PartRenderer, PrintTruth

        folder = Path.cwd()
        program = folder / "meander.prg"
        program.write_text(meander())
        job = read_program_text(program.read_text(), process_speed_mm_s=2.0)
        camera = Camera(um_per_px=0.75, offset_mm=(-0.3, 0.0), width_px=1920, height_px=1080)
        save_camera(camera, folder / "camera.toml")
        renderer = PartRenderer(job, camera, PrintTruth.constant(job.duration_s, 43.0, 29.0))
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")
        writer = cv2.VideoWriter(str(folder / "part.mp4"), fourcc, FPS, (1920, 1080), False)
        for k in range(FRAMES):
            writer.write(renderer.frame(START_S + k / FPS))
        writer.release()
        return str(folder)

    def setup(self, folder):
        import cv2  # reading the video

        from ajtwin.job import read_program
        from ajtwin.vision.camera import load_camera
        from ajtwin.vision.part_extract import PartExtractor

        self.folder = Path(folder)
        self.job = read_program(self.folder / "meander.prg", process_speed_mm_s=2.0)
        self.extractor = PartExtractor(self.job, load_camera(self.folder / "camera.toml"))
        capture = cv2.VideoCapture(str(self.folder / "part.mp4"))
        self.frames = []
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            self.frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        capture.release()
        self.times = START_S + np.arange(len(self.frames)) / FPS
        for t, gray in zip(self.times[:5], self.frames[:5], strict=True):
            self.extractor.process(gray, time_s=t)
        self.k = 0
        self.out = tempfile.mkdtemp(prefix="ajtwin-bench-")

    def teardown(self, folder):
        shutil.rmtree(self.out, ignore_errors=True)

    def time_extract_one_frame(self, folder):
        k = self.k % len(self.frames)
        self.extractor.process(self.frames[k], index=k, time_s=self.times[k])
        self.k += 1

    def track_readings_per_frame(self, folder):
        found = [
            self.extractor.process(g, time_s=t).n_readings for t, g in zip(self.times, self.frames)
        ]
        return float(np.mean(found))

    track_readings_per_frame.unit = "readings"

    def track_end_to_end_fps(self, folder):
        """``ajtwin extract VIDEO --job --camera``: program, windows, decoding (second
        thread), extraction, both CSVs."""
        from ajtwin.job import read_program
        from ajtwin.vision.camera import load_camera
        from ajtwin.vision.part_video import extract_part_video

        start = time.perf_counter()
        extract_part_video(
            self.folder / "part.mp4",
            read_program(self.folder / "meander.prg", process_speed_mm_s=2.0),
            load_camera(self.folder / "camera.toml"),
            os.path.join(self.out, "features.csv"),
            start_offset_s=START_S,
            progress=False,
        )
        return FRAMES / (time.perf_counter() - start)

    track_end_to_end_fps.unit = "frames/s"


class PartWindows:
    """Building the extractor's windows for a public program (1920 x 1080, 0.75 µm/px)."""

    params = ["2 and 6-Au.prg", "4-naf 654321.prg"]
    param_names = ["program"]
    timeout = 300

    def setup(self, program):
        from ajtwin.job import read_program
        from ajtwin.vision.camera import Camera

        self.camera = Camera(um_per_px=0.75, width_px=1920, height_px=1080)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.job = read_program(DATA / program)

    def time_build_windows(self, program):
        from ajtwin.vision.part_extract import PartExtractor

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            PartExtractor(self.job, self.camera)
