"""The camera algorithm's accuracy on rendered frames: extracted minus true linewidth and
overspray (model reference §9 definitions on the true profile,
:func:`ajtwin.vision.profile_features`) on 1280 x 1024 frames, over tilts (−10…10°), sensor
noise (2 and 6 gray levels) and edge raggedness (0, 0.5, 1, 2 µm), 3 seeds each; plus the same
frames after an mp4 (mp4v) encode/decode round trip. Its speed is a benchmark
(``benchmarks/bench_vision.py``).

    python -m ajtwin.studies.vision_accuracy          # prints the figures as JSON (~1 min)
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from ajtwin.vision.extract import LineExtractor
from ajtwin.vision.profile import line_profile, profile_features
from ajtwin.vision.render import RenderSettings, render_frame

R = np.arange(-160.0, 160.0, 0.05)
R_FINE = np.arange(-160.0, 160.0, 0.02)
LINE = (43.0, 29.0, 15.0)  # nominal linewidth µm, overspray µm, cross-section µm²


def _mp4_round_trip(frame):
    """The frame after an mp4 (mp4v) encode and decode."""
    import cv2  # OpenCV: only the video round trip needs it

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "f.mp4"
        writer = cv2.VideoWriter(
            str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (frame.shape[1], frame.shape[0]), False
        )
        writer.write(frame)
        writer.release()
        ok, decoded = cv2.VideoCapture(str(path)).read()
    return cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY)


def accuracy(shape=(1024, 1280), seeds=3) -> dict:
    """Extracted minus true linewidth and overspray [µm] per raggedness and sensor noise
    (mean and largest error, frames not ok), per tilt, and the truth itself."""
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


def main() -> None:
    """Print the figures of :func:`accuracy` as JSON."""
    print(json.dumps(accuracy(), indent=2))


if __name__ == "__main__":
    main()
