"""Accuracy of the camera on a part: program-guided readings against rendered truth.

Run as ``python -m ajtwin.studies.vision_part [--out docs/results/vision_part/accuracy.json]``
(a few minutes on 2 cores). Frames are rendered from jobs with known truth
(:mod:`ajtwin.vision.part_render`) at 1280 x 720 px, 0.75 µm/px, default nuisances (noise
2 gray, blur 0.8 px, raggedness 1 µm, texture, illumination), and measured by
:class:`ajtwin.vision.part_extract.PartExtractor`. Error = reading − reference (the paper's
definitions on the noiseless profile of the line printed at the reading's print time).

* ``straight``: a 1.2 mm stroke at 0-90° (camera not turned, and turned by 30°), 3 seeds x
  8 frames of an inspection pass over it.
* ``arc``: half circles of radius 3, 5 and 10 linewidths (129, 215, 430 µm), 3 seeds.
* ``width``: straight strokes of other lines (30/20 µm and 60/35 µm; cross-section 15 µm²).
* ``part``: a part with every situation (corner, crossing, overprint, fill, neighbours at
  130 µm, traces 60 µm apart) seen by a camera trailing 0.3 mm behind the nozzle; every
  reading checked with :meth:`ajtwin.job.Job.locate` (no other trace within reach of its
  cross-sections: an independent question to the job) and against truth.
* ``public``: the public program ``2 and 6-Au.prg`` (jizhang495/prg2svg, MIT), camera
  trailing 0.3 mm: the share of the traces in view that is measurable and why the rest is
  not, and the readings' error.

* ``cnn`` (with ``--cnn MODEL.pt``, a model from ``ajtwin cnn train``): the height-profile
  CNN on the columns across the stroke of every reading
  (:meth:`~ajtwin.vision.part_extract.PartExtractor.columns`): the cross-section ∫h dr it
  predicts (Q_m = ν ∫h dr) against the true 15 µm², on straight traces and arcs, and on
  the paper's columns of a horizontal line (:func:`ajtwin.profile_cnn.frames.frame_columns`).

Coverage = readings / windows that are measurable (in view, not skipped): the share of
what the program says can be measured that the image analysis did measure.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from ajtwin.job import read_program, read_program_text
from ajtwin.profile_cnn.frames import frame_columns
from ajtwin.profile_cnn.model import ProfileModel
from ajtwin.vision.camera import Camera
from ajtwin.vision.extract import LineExtractor
from ajtwin.vision.part_extract import PartExtractor
from ajtwin.vision.part_render import PartRenderer, PrintTruth

SIZE = dict(width_px=1280, height_px=720)
FRAMES = 8
SEEDS = (0, 1, 2)
PUBLIC = Path(__file__).resolve().parents[3] / "tests" / "data" / "prg" / "prg2svg"


def _stroke(x0, y0, x1, y1):
    return f"ptp/e (X,Y),{x0:.6f},{y0:.6f}\nOUT0.0=1\nptp/e (X,Y),{x1:.6f},{y1:.6f}\nOUT0.0=0\n"


def _path(x0, y0, moves, shutter=True):
    lines = [f"ptp/e (X,Y),{x0:.6f},{y0:.6f}"]
    lines += ["OUT0.0=1"] if shutter else []
    lines.append(f"MSEG (X,Y),{x0:.6f},{y0:.6f}")
    for m in moves:
        if m[0] == "line":
            lines.append(f"line (X,Y),{m[1]:.6f},{m[2]:.6f}")
        else:
            lines.append(f"arc2 (X,Y),{m[1]:.6f},{m[2]:.6f},{m[3]:.12f}")
    lines += ["ENDS (X,Y)", "till ^X_AST.#MOVE"]
    lines += ["OUT0.0=0"] if shutter else []
    return "\n".join(lines) + "\n"


def straight_program(angle_deg, length=1.2):
    """A straight stroke at ``angle_deg`` from the origin, then an inspection pass back."""
    x1 = length * math.cos(math.radians(angle_deg))
    y1 = length * math.sin(math.radians(angle_deg))
    return _stroke(0, 0, x1, y1) + _path(x1, y1, [("line", 0.0, 0.0)], shutter=False)


def arc_program(radius):
    """A printed half circle of ``radius`` mm, then an inspection pass along it."""
    return _path(0, 0, [("arc", 0.0, radius, math.pi)]) + _path(
        0, 2 * radius, [("arc", 0.0, radius, -math.pi)], shutter=False
    )


def part_program():
    """Every situation in one part (mm)."""
    legs = []
    x = 2.0
    for k in range(8):  # a fill: 8 legs 19.35 µm apart
        up = k % 2 == 0
        legs.append(("line", x, 0.6 if up else 0.0))
        if k < 7:
            r = 0.01935 / 2
            legs += [("arc", x + r, 0.6 if up else 0.0, -math.pi / 2 if up else math.pi / 2)] * 2
            x += 0.01935
    return (
        _stroke(0, 0, 1.5, 0)  # a straight stroke ...
        + _stroke(0.75, -0.4, 0.75, 0.4)  # ... crossed
        + _path(0, 0.5, [("line", 1.0, 0.5), ("line", 1.0, 1.2)])  # a corner
        + _stroke(0, 0.63, 1.0, 0.63)  # a neighbour 130 µm away
        + _stroke(0, 1.5, 1.5, 1.5)  # two traces 60 µm apart
        + _stroke(0, 1.56, 1.5, 1.56)
        + _stroke(0, 2.0, 1.5, 2.0)  # a trace printed twice
        + _stroke(0, 2.0, 1.5, 2.0)
        + _path(2.0, 0.0, legs)
    )


def _run(job, camera, truth, times, seed, check_locate=False):
    renderer = PartRenderer(job, camera, truth, seed=seed)
    extractor = PartExtractor(job, camera)
    lw, ov, skipped, failed, spoiled = [], [], Counter(), Counter(), 0
    readings = 0
    for t in times:
        result = extractor.process(renderer.frame(t), time_s=t)
        skipped.update(result.skipped)
        failed.update(result.failed)
        if result.n_readings:
            r = result.readings
            lw_true, ov_true = truth.features_at(r["print_time_s"])
            lw.append(r["linewidth_um"] - lw_true)
            ov.append(r["overspray_um"] - ov_true)
            readings += result.n_readings
            if check_locate:
                spoiled += _spoiled(job, extractor, r, t)
    lw = np.concatenate(lw) if lw else np.zeros(0)
    ov = np.concatenate(ov) if ov else np.zeros(0)
    return lw, ov, skipped, failed, spoiled


def _spoiled(job, extractor, readings, t) -> int:
    """Readings whose cross-sections come within reach of another trace (Job.locate)."""
    cfg = extractor.settings
    half, reach = cfg.half_length_um * 1e-3, cfg.reach_um * 1e-3
    window = extractor.windows.length_mm
    bad = 0
    for stroke, s in zip(readings["stroke"], readings["s_mm"], strict=True):
        pts = job.point_at(np.full(5, stroke), s + np.linspace(-0.5, 0.5, 5) * window)
        d = np.linspace(-half, half, 41)
        hits = job.locate(
            pts.x_mm[:, None] - pts.uy[:, None] * d,
            pts.y_mm[:, None] + pts.ux[:, None] * d,
            radius_mm=reach,
            before_s=t,
        )
        other = hits.found & (
            (hits.stroke != stroke) | (np.abs(hits.s_mm - s) > window + half + reach)
        )
        bad += int(other.any())
    return bad


def _summary(lw, ov, skipped, failed, spoiled=None) -> dict:
    measured = lw.size + sum(failed.values())
    out = {
        "readings": int(lw.size),
        "lw_mean_um": round(float(np.mean(lw)), 3) if lw.size else None,
        "lw_mae_um": round(float(np.mean(np.abs(lw))), 3) if lw.size else None,
        "lw_max_abs_um": round(float(np.max(np.abs(lw))), 3) if lw.size else None,
        "ov_mean_um": round(float(np.mean(ov)), 3) if ov.size else None,
        "ov_mae_um": round(float(np.mean(np.abs(ov))), 3) if ov.size else None,
        "coverage": round(lw.size / measured, 4) if measured else None,
        "skipped": dict(skipped),
        "failed": dict(failed),
    }
    if spoiled is not None:
        out["readings_near_another_trace"] = spoiled
    return out


def pass_times(job):
    """Frame times of an inspection pass over a job's strokes after they are printed."""
    t_end = float(job.strokes["t_end_s"].max())
    return np.linspace(t_end + 0.05, job.duration_s - 0.05, FRAMES)


def straight() -> dict:
    """Straight strokes at 0-90° under a camera at 0° and 30°."""
    rows = {}
    for rotation in (0.0, 30.0):
        camera = Camera(um_per_px=0.75, rotation_deg=rotation, **SIZE)
        for angle in (0, 15, 30, 45, 60, 75, 90):
            job = read_program_text(straight_program(angle), process_speed_mm_s=2.0)
            truth = PrintTruth.constant(job.duration_s, 43.0, 29.0)
            parts = [_run(job, camera, truth, pass_times(job), seed) for seed in SEEDS]
            rows[f"camera {rotation:g}°, stroke {angle}°"] = _summary(*_merge(parts))
    return rows


def arcs() -> dict:
    """Half circles of 3, 5 and 10 linewidths radius."""
    rows = {}
    camera = Camera(um_per_px=0.75, **SIZE)
    for factor in (3, 5, 10):
        radius = factor * 0.043
        job = read_program_text(arc_program(radius), process_speed_mm_s=2.0)
        truth = PrintTruth.constant(job.duration_s, 43.0, 29.0)
        parts = [_run(job, camera, truth, pass_times(job), seed) for seed in SEEDS]
        rows[f"arc radius {factor} linewidths ({1e3 * radius:.0f} µm)"] = _summary(*_merge(parts))
    return rows


def widths() -> dict:
    """Narrow, nominal and wide lines on a stroke at 20°."""
    rows = {}
    camera = Camera(um_per_px=0.75, **SIZE)
    job = read_program_text(straight_program(20.0), process_speed_mm_s=2.0)
    for lw, ov in ((30.0, 20.0), (43.0, 29.0), (60.0, 35.0)):
        truth = PrintTruth.constant(job.duration_s, lw, ov)
        parts = [_run(job, camera, truth, pass_times(job), seed) for seed in SEEDS]
        rows[f"line {lw:g}/{ov:g} µm"] = _summary(*_merge(parts))
    return rows


def part() -> dict:
    """A part with every situation, under a camera trailing 0.3 mm."""
    job = read_program_text(part_program(), process_speed_mm_s=2.0)
    camera = Camera(um_per_px=0.75, offset_mm=(-0.3, 0.0), **SIZE)
    truth = PrintTruth.constant(job.duration_s, 43.0, 29.0)
    times = np.linspace(0.2, job.duration_s, 120)
    parts = [_run(job, camera, truth, times, seed, check_locate=True) for seed in SEEDS[:2]]
    lw, ov, skipped, failed = _merge([p[:4] for p in parts])
    return {
        "part with every situation": _summary(lw, ov, skipped, failed, sum(p[4] for p in parts))
    }


def public() -> dict:
    """The public program 2 and 6-Au.prg under a camera trailing 0.3 mm."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        job = read_program(PUBLIC / "2 and 6-Au.prg")
    camera = Camera(um_per_px=0.75, offset_mm=(-0.3, 0.0), **SIZE)
    truth = PrintTruth.constant(job.duration_s, 43.0, 29.0)
    times = np.linspace(1.0, job.duration_s, 150)
    lw, ov, skipped, failed, spoiled = _run(job, camera, truth, times, 0, check_locate=True)
    return {
        "public 2 and 6-Au.prg, camera trailing 0.3 mm": _summary(lw, ov, skipped, failed, spoiled)
    }


def cnn(model_path: Path) -> dict:
    """Cross-section from the CNN on columns across straight traces and arcs."""
    model = ProfileModel.load(model_path)
    camera = Camera(um_per_px=0.75, **SIZE)
    rows = {}
    cases = [(f"straight {a}°", straight_program(a)) for a in (0, 45, 90)]
    cases += [(f"arc radius {f} linewidths", arc_program(f * 0.043)) for f in (3, 5, 10)]
    for name, text in cases:
        job = read_program_text(text, process_speed_mm_s=2.0)
        truth = PrintTruth.constant(job.duration_s, 43.0, 29.0)
        areas = []
        for seed in SEEDS:
            renderer = PartRenderer(job, camera, truth, seed=seed)
            extractor = PartExtractor(job, camera)
            for t in pass_times(job):
                result = extractor.process(renderer.frame(t), time_s=t)
                columns = extractor.columns(result, model.n_pixels, model.um_per_px)
                if len(columns):
                    areas.append(model.predict_um(columns).sum(axis=1) * model.um_per_px)
        rows[name] = _area_summary(np.concatenate(areas), truth.area_um2[0])
    # the paper's path: a horizontal line, columns cut by the straight-line extractor, on
    # the frames the line crosses from edge to edge (it has no notion of a stroke's end: its
    # batches past an end are read as a line of no material)
    job = read_program_text(straight_program(0), process_speed_mm_s=2.0)
    truth = PrintTruth.constant(job.duration_s, 43.0, 29.0)
    half_width = 0.5 * camera.width_px * camera.mm_per_px
    times = np.linspace(job.strokes["t_end_s"].max() + 0.05, job.duration_s - 0.05, 40)
    x = job.state_at(times).x_mm
    times = times[(x > half_width) & (x < 1.2 - half_width)][:FRAMES]
    areas = []
    for seed in SEEDS:
        renderer = PartRenderer(job, camera, truth, seed=seed)
        for t in times:
            fc = frame_columns(
                renderer.frame(t),
                LineExtractor(0.75),
                n_pixels=model.n_pixels,
                model_um_per_px=model.um_per_px,
            )
            ok = fc.cv_ok if len(fc.columns) else np.zeros(0, dtype=bool)
            if ok.any():  # the batches the camera algorithm measured (not past an end)
                areas.append(model.predict_um(fc.columns[ok]).sum(axis=1) * model.um_per_px)
    rows["paper's columns, horizontal line across the frame"] = _area_summary(
        np.concatenate(areas), truth.area_um2[0]
    )
    return rows


def _area_summary(areas, true_area) -> dict:
    error = areas / true_area - 1.0
    return {
        "columns": int(areas.size),
        "true_area_um2": float(true_area),
        "mean_error_percent": round(100 * float(np.mean(error)), 2),
        "mae_percent": round(100 * float(np.mean(np.abs(error))), 2),
    }


def _merge(parts):
    lw = np.concatenate([p[0] for p in parts])
    ov = np.concatenate([p[1] for p in parts])
    skipped, failed = Counter(), Counter()
    for p in parts:
        skipped.update(p[2])
        failed.update(p[3])
    return lw, ov, skipped, failed


def table(results: dict) -> str:
    """The results as the Markdown table of docs/validation.md."""
    lines = [
        "| case | readings | L_w mean / MAE / max abs (µm) | L_o mean / MAE (µm) | coverage |",
        "|---|---|---|---|---|",
    ]
    for group in results.values():
        if not isinstance(group, dict):
            continue
        for name, r in group.items():
            if not isinstance(r, dict) or "readings" not in r:
                continue
            if not r["readings"]:
                lines.append(f"| {name} | 0 | | | |")
                continue
            lines.append(
                f"| {name} | {r['readings']} | {r['lw_mean_um']:+.2f} / {r['lw_mae_um']:.2f} / "
                f"{r['lw_max_abs_um']:.2f} | {r['ov_mean_um']:+.2f} / {r['ov_mae_um']:.2f} | "
                f"{100 * r['coverage']:.1f} % |"
            )
    return "\n".join(lines)


def main(argv=None) -> dict:
    """Run the study, write its JSON and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/results/vision_part/accuracy.json"))
    parser.add_argument("--cnn", type=Path, default=None, help="a model from ajtwin cnn train")
    parser.add_argument("--only", choices=["cnn"], default=None, help="run only this part")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    if args.only == "cnn":
        if args.cnn is None:
            parser.error("--only cnn needs --cnn MODEL.pt")
        results = json.loads(args.out.read_text()) if args.out.exists() else {}
        results["cnn"] = cnn(args.cnn)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2))
        for name, r in results["cnn"].items():
            print(f"{name}: {r}")
        return results
    results = {
        "straight": straight(),
        "arc": arcs(),
        "width": widths(),
        "part": part(),
        "public": public(),
    }
    if args.cnn is not None:
        results["cnn"] = cnn(args.cnn)
    results["seconds"] = round(time.perf_counter() - start, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2))
    print(table(results))
    for group in ("part", "public"):
        for name, r in results[group].items():
            print(
                f"{name}: skipped {r['skipped']}, failed {r['failed']}, "
                f"readings near another trace {r['readings_near_another_trace']}"
            )
    print(f"wrote {args.out} ({results['seconds']} s)")
    return results


if __name__ == "__main__":
    main()
