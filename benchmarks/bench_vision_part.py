"""Camera on a part: speed of program-guided extraction (``ajtwin extract --job``).

Run alone with ``.venv/bin/python benchmarks/bench_vision_part.py`` (prints a JSON of
figures) or with all benches via ``make bench``.

* Part: a meander of 12 legs, 2 mm long and 0.25 mm apart, joined by U-turns of 125 µm
  radius, printed at 2 mm/s; the camera trails 0.3 mm behind the nozzle along X, so each
  1920 x 1080 frame (0.75 µm/px) shows about six legs: ~100 windows in view, ~60 readings.
* Video: 90 frames at 30 frames/s rendered (:mod:`ajtwin.vision.part_render`, the render's
  own time is reported) and written as mp4 (mp4v).
* ``extract``: :meth:`PartExtractor.process` on decoded frames, one thread, with the
  share of time per stage. ``end_to_end``: reading the program and the camera file, then
  :func:`ajtwin.vision.part_video.extract_part_video` on the mp4, what the command runs
  (decoding in a second thread, extraction, both CSVs), wall and CPU time per frame.
  Aim: at least 100 frames/s end to end on 2 cores.
* ``windows``: building the extractor (windows along every stroke and what spoils each)
  for public programs: the one-time cost before the first frame.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

from ajtwin.job import read_program, read_program_text
from ajtwin.vision.camera import Camera, load_camera, save_camera
from ajtwin.vision.part_extract import PartExtractor
from ajtwin.vision.part_render import PartRenderer, PrintTruth
from ajtwin.vision.part_video import extract_part_video

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "prg" / "prg2svg"
FRAMES = 90
FPS = 30.0
START_S = 3.0


def meander(legs=12, leg_mm=2.0, pitch_mm=0.25) -> str:
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


def render(folder: Path) -> tuple[Path, Path, Path, dict]:
    program = folder / "meander.prg"
    program.write_text(meander())
    job = read_program_text(program.read_text(), process_speed_mm_s=2.0)
    camera = Camera(um_per_px=0.75, offset_mm=(-0.3, 0.0), width_px=1920, height_px=1080)
    camera_path = save_camera(camera, folder / "camera.toml")
    renderer = PartRenderer(job, camera, PrintTruth.constant(job.duration_s, 43.0, 29.0))
    video = folder / "part.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (1920, 1080), False)
    start = time.perf_counter()
    for k in range(FRAMES):
        writer.write(renderer.frame(START_S + k / FPS))
    elapsed = time.perf_counter() - start
    writer.release()
    return program, camera_path, video, {"render_s_per_frame": round(elapsed / FRAMES, 3)}


def extract(program: Path, camera_path: Path, video: Path) -> dict:
    job = read_program(program, process_speed_mm_s=2.0)
    camera = load_camera(camera_path)
    extractor = PartExtractor(job, camera)
    capture = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    capture.release()
    times = START_S + np.arange(len(frames)) / FPS
    for t, gray in zip(times[:5], frames[:5], strict=True):  # warm-up
        extractor.process(gray, time_s=t)
    extractor.stage_seconds.clear()
    readings = windows = 0
    start, cpu_start = time.perf_counter(), time.process_time()
    for k, (t, gray) in enumerate(zip(times, frames, strict=True)):
        result = extractor.process(gray, index=k, time_s=t)
        readings += result.n_readings
        windows += result.windows_in_view
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    stages = extractor.stage_seconds
    total = sum(stages.values())
    return {
        "extract_fps": round(len(frames) / elapsed, 1),
        "extract_ms_per_frame": round(1e3 * elapsed / len(frames), 2),
        "extract_cpu_ms_per_frame": round(1e3 * cpu / len(frames), 2),
        "readings_per_frame": round(readings / len(frames), 1),
        "windows_in_view_per_frame": round(windows / len(frames), 1),
        "stage_percent": {name: round(100 * s / total, 1) for name, s in sorted(stages.items())},
    }


def end_to_end(program: Path, camera_path: Path, video: Path, folder: Path) -> dict:
    best = None
    for _ in range(2):
        start, cpu_start = time.perf_counter(), time.process_time()
        extract_part_video(
            video,
            read_program(program, process_speed_mm_s=2.0),
            load_camera(camera_path),
            folder / "features.csv",
            start_offset_s=START_S,
            progress=False,
        )
        elapsed = time.perf_counter() - start
        cpu = time.process_time() - cpu_start
        if best is None or elapsed < best[0]:
            best = (elapsed, cpu)
    elapsed, cpu = best
    return {
        # what `ajtwin extract VIDEO --job --camera` runs: read the program, build the
        # windows, decode (second thread), extract, write both CSVs
        "end_to_end_fps": round(FRAMES / elapsed, 1),
        "end_to_end_cpu_ms_per_frame": round(1e3 * cpu / FRAMES, 2),
        "end_to_end_fps_if_two_free_cores": round(FRAMES / max(cpu / 2, 1e-9), 1),
    }


def windows() -> dict:
    camera = Camera(um_per_px=0.75, width_px=1920, height_px=1080)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in ("2 and 6-Au.prg", "4-naf 654321.prg"):
            job = read_program(DATA / name)
            start = time.perf_counter()
            extractor = PartExtractor(job, camera)
            key = name.split(".")[0].replace(" ", "_")
            out[f"windows_s_{key}"] = round(time.perf_counter() - start, 2)
            out[f"windows_count_{key}"] = int(extractor.windows.n)
    return out


def main() -> dict:
    figures: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        program, camera_path, video, rendered = render(folder)
        figures.update(rendered)
        figures.update(extract(program, camera_path, video))
        figures.update(end_to_end(program, camera_path, video, folder))
    figures.update(windows())
    return figures


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
