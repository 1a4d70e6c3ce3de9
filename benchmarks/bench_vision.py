"""Vision benchmark: extraction speed, where the time goes, and accuracy against truth.

Run alone with ``.venv/bin/python benchmarks/bench_vision.py`` (prints a JSON of figures)
or with all benches via ``make bench``.

* Speed: :meth:`LineExtractor.process` on rendered frames (1280x1024 and 1920x1080), as in
  a video (8 distinct frames cycled, line tracking on); decoding is timed separately on an
  mp4 of the same frames.  Wall time on this machine, single process.  End to end, measured:
  the mp4 read by ``open_source`` and every frame extracted, once with the plain iterator
  (one thread) and once with ``FrameSource.prefetched`` (decoding in a second thread).
* Profile: share of the per-frame time per stage (the extractor's own stage clock).
* Accuracy: extracted minus true linewidth/overspray (model reference §9 definitions on the true
  profile, :func:`ajtwin.vision.profile_features`) on 1280x1024 frames, over tilts
  (-10..10°), sensor noise (2 and 6 gray levels) and edge raggedness (0, 0.5, 1, 2 µm),
  3 seeds each; plus the same frames after an mp4 (mp4v) encode/decode round trip.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ajtwin.vision.extract import LineExtractor, open_source
from ajtwin.vision.profile import line_profile, profile_features
from ajtwin.vision.render import RenderSettings, Substrate, render_frame

R = np.arange(-160.0, 160.0, 0.05)
R_FINE = np.arange(-160.0, 160.0, 0.02)
LINE = (43.0, 29.0, 15.0)  # nominal linewidth µm, overspray µm, cross-section µm²


def _frames(shape, count=8, tilt=4.0, seed=0):
    settings = RenderSettings.from_defaults(tilt_deg=tilt)
    rng = np.random.default_rng(seed)
    substrate = Substrate(shape, settings, rng)
    h = line_profile(R, *LINE)
    return [
        render_frame(R, h, shape, settings, rng=rng, substrate=substrate, travel_um=40.0 * k)
        for k in range(count)
    ]


def speed(shape, repeats=60):
    frames = _frames(shape)
    extractor = LineExtractor(0.75)
    for frame in frames:  # warm-up (imports, first Hough without tracking)
        extractor.process(frame)
    extractor.stage_seconds.clear()
    start = time.perf_counter()
    cpu_start = time.process_time()
    for k in range(repeats):
        extractor.process(frames[k % len(frames)])
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    stages = extractor.stage_seconds
    total = sum(stages.values())
    profile = {name: round(100 * t / total, 1) for name, t in sorted(stages.items())}

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "v.mp4"
        writer = cv2.VideoWriter(
            str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30, (shape[1], shape[0]), False
        )
        for k in range(repeats):
            writer.write(frames[k % len(frames)])
        writer.release()
        capture = cv2.VideoCapture(str(path))
        t0 = time.perf_counter()
        decoded = 0
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            decoded += 1
        decode_s = time.perf_counter() - t0
        capture.release()
        serial = _end_to_end(path, frames=lambda source: iter(source))
        # (a checkout from before the pipelined reader existed runs the serial path only)
        pipelined = (
            _end_to_end(path, frames=lambda source: source.prefetched())
            if hasattr(open_source(path), "prefetched")
            else {}
        )
    return {
        "extract_fps": round(repeats / elapsed, 1),
        "extract_ms_per_frame": round(1e3 * elapsed / repeats, 2),
        # CPU seconds of this process (all threads): the cost without other jobs' contention
        "extract_cpu_ms_per_frame": round(1e3 * cpu / repeats, 2),
        "extract_fps_if_cpu_bound": round(repeats / cpu, 1),
        "decode_mp4_ms_per_frame": round(1e3 * decode_s / max(decoded, 1), 2),
        # what `ajtwin extract` runs: decoding in its own thread beside the features
        # (FrameSource.prefetched), measured on the whole video
        "end_to_end_fps": pipelined.get("fps", serial["fps"]),
        # the two stages timed apart and added up (a reader that decodes and extracts in
        # one thread, with nothing overlapping)
        "end_to_end_one_thread_sum_of_stages_fps": round(
            1.0 / (elapsed / repeats + decode_s / max(decoded, 1)), 1
        ),
        # measured: open_source(mp4) -> LineExtractor.process, one thread / decoder thread
        "end_to_end_serial_fps": serial["fps"],
        "end_to_end_serial_cpu_ms_per_frame": serial["cpu_ms"],
        "end_to_end_pipelined_fps": pipelined.get("fps"),
        "end_to_end_pipelined_cpu_ms_per_frame": pipelined.get("cpu_ms"),
        "end_to_end_pipelined_cpu_ms_main_thread": pipelined.get("main_thread_cpu_ms"),
        "end_to_end_pipelined_cpu_ms_other_threads": pipelined.get("other_threads_cpu_ms"),
        "end_to_end_pipelined_fps_if_two_free_cores": pipelined.get("fps_if_two_free_cores"),
        "stage_percent": profile,
    }


def _end_to_end(path, frames) -> dict:
    """Frames/s and CPU ms/frame (all threads) of decode -> features over a whole video."""
    source = open_source(path)
    extractor = LineExtractor(0.75)
    start = time.perf_counter()
    cpu_start = time.process_time()
    main_start = time.thread_time()
    reader = frames(source)
    count = 0
    try:
        for index, time_s, gray in reader:
            extractor.process(gray, index, time_s)
            count += 1
    finally:
        getattr(reader, "close", lambda: None)()
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    main = time.thread_time() - main_start
    # CPU of the calling thread vs all other threads (the decoder thread, FFmpeg's and
    # OpenCV's workers): with two free cores the larger of the two bounds the frame rate
    return {
        "fps": round(count / elapsed, 1),
        "cpu_ms": round(1e3 * cpu / count, 2),
        "main_thread_cpu_ms": round(1e3 * main / count, 2),
        "other_threads_cpu_ms": round(1e3 * (cpu - main) / count, 2),
        "fps_if_two_free_cores": round(count / max(main, cpu - main, cpu / 2), 1),
    }


def _mp4_round_trip(frame):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "f.mp4"
        writer = cv2.VideoWriter(
            str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (frame.shape[1], frame.shape[0]), False
        )
        writer.write(frame)
        writer.release()
        ok, decoded = cv2.VideoCapture(str(path)).read()
    return cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY)


def accuracy(shape=(1024, 1280), seeds=3):
    h = line_profile(R, *LINE)
    lw_true, ov_true = profile_features(R_FINE, line_profile(R_FINE, *LINE))
    rows = []
    for raggedness in (0.0, 0.5, 1.0, 2.0):
        for noise in (2.0, 6.0):
            for tilt in (-10.0, -5.0, 0.0, 5.0, 10.0):
                for seed in range(seeds):
                    settings = RenderSettings.from_defaults(
                        tilt_deg=tilt, noise_sigma_gray=noise, raggedness_um=raggedness
                    )
                    frame = render_frame(
                        R,
                        h,
                        shape,
                        settings,
                        rng=np.random.default_rng(1000 * seed + int(tilt) + 50),
                    )
                    result = LineExtractor(0.75).process(frame)
                    rows.append(
                        (
                            raggedness,
                            noise,
                            tilt,
                            result.linewidth_um - lw_true,
                            result.overspray_um - ov_true,
                            result.status,
                        )
                    )
                    if raggedness == 1.0 and noise == 2.0 and seed == 0:
                        coded = LineExtractor(0.75).process(_mp4_round_trip(frame))
                        rows.append(
                            (
                                "mp4",
                                noise,
                                tilt,
                                coded.linewidth_um - lw_true,
                                coded.overspray_um - ov_true,
                                coded.status,
                            )
                        )
    figures = {}
    for raggedness in (0.0, 0.5, 1.0, 2.0, "mp4"):
        for noise in (2.0, 6.0):
            sel = [r for r in rows if r[0] == raggedness and r[1] == noise]
            if not sel:
                continue
            lw = np.array([r[3] for r in sel])
            ov = np.array([r[4] for r in sel])
            key = f"rag{raggedness}um_noise{noise:g}" if raggedness != "mp4" else "mp4_rag1.0um"
            figures[key] = {
                "linewidth_err_um_mean": round(float(np.nanmean(lw)), 3),
                "linewidth_err_um_maxabs": round(float(np.nanmax(np.abs(lw))), 3),
                "overspray_err_um_mean": round(float(np.nanmean(ov)), 3),
                "overspray_err_um_maxabs": round(float(np.nanmax(np.abs(ov))), 3),
                "frames": len(sel),
                "frames_not_ok": sum(r[5] != "ok" for r in sel),
            }
    per_tilt = {}
    for tilt in (-10.0, -5.0, 0.0, 5.0, 10.0):
        sel = [r for r in rows if r[0] == 1.0 and r[1] == 2.0 and r[2] == tilt]
        per_tilt[f"tilt{tilt:+g}deg"] = {
            "linewidth_err_um": round(float(np.mean([r[3] for r in sel])), 3),
            "overspray_err_um": round(float(np.mean([r[4] for r in sel])), 3),
        }
    figures["rag1.0um_noise2_by_tilt"] = per_tilt
    figures["truth_um"] = {"linewidth": round(lw_true, 3), "overspray": round(ov_true, 3)}
    return figures


def main() -> dict:
    figures = {}
    for name, shape in (("1280x1024", (1024, 1280)), ("1920x1080", (1080, 1920))):
        result = speed(shape)
        for key, value in result.items():
            figures[f"{name}_{key}"] = value
    figures["accuracy_1280x1024"] = accuracy()
    return figures


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
