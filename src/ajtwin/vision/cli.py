"""``ajtwin render`` and ``ajtwin extract`` — the shells around the vision core."""

from __future__ import annotations

import csv
import functools
import json
import warnings
from collections import Counter
from pathlib import Path

import click
import numpy as np

from ajtwin.io.cli_options import MAX_PLATEN_SPEED_MM_S, BoundedFloat, join_options
from ajtwin.vision.part_cli import part_extract_options, part_render_options

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


def _parse_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT, e.g. 1280x1024, got {text!r}") from None
    if width < 64 or height < 64:
        raise click.BadParameter(f"frame size {text} is too small (at least 64x64)")
    return height, width


@click.command()
@click.argument("record", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Video to write (.mp4 = mp4v lossy, .avi/.mkv = FFV1 lossless).",
)
@click.option(
    "--truth",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Ground-truth JSON (default: next to the video, .json).",
)
@click.option(
    "--fps", type=BoundedFloat(0.0, None), default=1.0, show_default=True, help="Video frame rate."
)
@click.option("--size", default="1280x1024", show_default=True, help="Frame WIDTHxHEIGHT.")
@click.option(
    "--um-per-px", type=BoundedFloat(0.0, None), default=None, help="Pixel size, µm (optics.toml)."
)
@click.option(
    "--tilt",
    "tilt_deg",
    type=BoundedFloat(-90.0, 90.0, closed=True),
    default=0.0,
    show_default=True,
    help="Line tilt, degrees.",
)
@click.option(
    "--noise",
    "noise_gray",
    type=BoundedFloat(0.0, None, closed=True),
    default=None,
    help="Read noise, gray levels.",
)
@click.option(
    "--blur",
    "blur_px",
    type=BoundedFloat(0.0, None, closed=True),
    default=None,
    help="Blur sigma, pixels.",
)
@click.option(
    "--raggedness",
    "raggedness_um",
    type=BoundedFloat(0.0, None, closed=True),
    default=None,
    help="Edge raggedness along the line, µm (1 sigma).",
)
@click.option(
    "--linewidth",
    "linewidth_um",
    type=BoundedFloat(0.0, None),
    default=43.0,
    show_default=True,
    help="Without RECORD: linewidth, µm.",
)
@click.option(
    "--overspray",
    "overspray_um",
    type=BoundedFloat(0.0, None, closed=True),
    default=29.0,
    show_default=True,
    help="Without RECORD: one-sided overspray, µm.",
)
@click.option(
    "--area",
    "area_um2",
    type=BoundedFloat(0.0, None, closed=True),
    default=15.0,
    show_default=True,
    help="Without RECORD (or where its material flow is NaN): cross-section, µm².",
)
@click.option(
    "--duration",
    "duration_s",
    type=BoundedFloat(0.0, None),
    default=None,
    help="Seconds of print to render (default: whole record, or 10 s).",
)
@click.option(
    "--start",
    "start_s",
    type=BoundedFloat(),
    default=0.0,
    show_default=True,
    help="Print time of the first frame, s.",
)
@click.option(
    "--platen-speed",
    "platen_speed_mm_s",
    type=BoundedFloat(0.0, MAX_PLATEN_SPEED_MM_S, closed=True),
    default=None,
    help="Platen speed, mm/s (default: the record's, else 1).",
)
@click.option("--seed", type=int, default=0, show_default=True)
@part_render_options
def render(
    record,
    out,
    truth,
    fps,
    size,
    um_per_px,
    tilt_deg,
    noise_gray,
    blur_px,
    raggedness_um,
    linewidth_um,
    overspray_um,
    area_um2,
    duration_s,
    start_s,
    platen_speed_mm_s,
    seed,
    **part,
):
    """Render an alignment-camera video (plus ground-truth JSON) of a print.

    With RECORD (a print record, .parquet/.csv) each second's linewidth_um, overspray_um
    and material_flow_mL_s become a line cross-section (cross-section = Q_m / platen
    speed); without it a constant line of --linewidth/--overspray/--area is rendered.
    With --job and --camera: the part under the camera, every trace drawn with the line
    printed at that moment (a job print's true_linewidth_um/true_overspray_um).
    """
    if part["job_path"] is not None or part["camera_path"] is not None:
        from ajtwin.vision.part_cli import run_part_render

        given = click.get_current_context().get_parameter_source("size").name == "COMMANDLINE"
        return run_part_render(
            record,
            out,
            truth_path=truth,
            fps=fps,
            start_s=start_s,
            duration_s=duration_s,
            noise_gray=noise_gray,
            blur_px=blur_px,
            raggedness_um=raggedness_um,
            linewidth_um=linewidth_um,
            overspray_um=overspray_um,
            area_um2=area_um2,
            seed=seed,
            refused={
                "--size": given,
                "--um-per-px": um_per_px is not None,
                "--tilt": tilt_deg != 0.0,
                "--platen-speed": platen_speed_mm_s is not None,
            },
            **part,
        )
    from ajtwin.units import cross_section_um2
    from ajtwin.vision.profile import line_profile, minimum_area_um2
    from ajtwin.vision.render import RenderSettings, render_video

    shape = _parse_size(size)
    overrides = {"tilt_deg": tilt_deg}
    for key, value in (
        ("um_per_px", um_per_px),
        ("noise_sigma_gray", noise_gray),
        ("blur_sigma_px", blur_px),
        ("raggedness_um", raggedness_um),
    ):
        if value is not None:
            overrides[key] = value
    try:
        settings = RenderSettings.from_defaults(**overrides)
        settings.validate()
    except (TypeError, ValueError) as exc:
        raise click.BadParameter(str(exc)) from None
    if fps <= 0:
        raise click.BadParameter(f"--fps must be > 0, got {fps}")

    extra = {}
    if record is not None:
        from ajtwin.io.records import RecordError, read_record

        try:
            rec = read_record(record)
        except (RecordError, FileNotFoundError) as exc:
            raise click.ClickException(str(exc)) from None
        speed = platen_speed_mm_s or float(rec.meta.get("platen_speed_mm_s", 1.0))
        data = rec.data
        data = data[data["time_s"] >= start_s]
        if duration_s is not None:
            data = data[data["time_s"] < start_s + duration_s]
        if data.empty:
            raise click.ClickException(f"{record}: no rows in the requested time window")
        extra = {
            "record": str(record),
            "scenario": rec.meta.get("scenario"),
            "machine_id": rec.meta.get("machine_id"),
        }
        times = data["time_s"].to_numpy(float) - start_s
        lw = data["linewidth_um"].to_numpy(float)
        ov = data["overspray_um"].to_numpy(float)
        flow = data["material_flow_mL_s"].to_numpy(float)
    else:
        speed = platen_speed_mm_s or 1.0
        duration = 10.0 if duration_s is None else duration_s
        times = np.arange(0.0, duration, 1.0)
        lw = np.full(times.size, linewidth_um)
        ov = np.full(times.size, overspray_um)
        flow = np.full(times.size, np.nan)
    area = np.where(np.isfinite(flow), cross_section_um2(flow, speed), area_um2)
    reach = float(np.nanmax(0.5 * lw + 1.6 * ov)) if np.isfinite(lw).any() else 100.0
    r_um = np.arange(-reach - 20.0, reach + 20.0, 0.05)
    # rows without a usable line hold the previous one (the first falls back to the options)
    usable = np.isfinite(lw) & np.isfinite(ov) & (lw > 0) & (ov > 0) & np.isfinite(area)
    source_row = np.where(usable, np.arange(lw.size), -1)
    source_row = np.maximum.accumulate(source_row)
    held = int((~usable).sum())
    small = int(
        np.sum(
            area[usable]
            < [minimum_area_um2(a, b) for a, b in zip(lw[usable], ov[usable], strict=True)]
        )
    )
    if held:
        click.echo(f"note: {held} seconds without linewidth/overspray: previous line held")
    if small:
        click.echo(
            f"note: {small} seconds with too little material for the requested overspray "
            "(its visible part will be shorter)"
        )

    def profile_for(row: int) -> np.ndarray:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # counted above
            if row < 0:
                return line_profile(r_um, linewidth_um, overspray_um, area_um2)
            return line_profile(r_um, lw[row], ov[row], area[row])

    profiles = _LazyProfiles(source_row, profile_for)
    truth_path = render_video(
        r_um,
        profiles,
        times,
        out,
        fps=fps,
        duration_s=float(times[-1]) + 1.0,
        shape=shape,
        settings=settings,
        platen_speed_mm_s=speed,
        seed=seed,
        truth_path=truth,
        extra_truth={**extra, "print_start_s": start_s},
    )
    click.echo(f"wrote {out} and {truth_path}")


@click.command()
@click.argument("source", type=click.Path(path_type=Path))
@click.option(
    "--um-per-px",
    "um_per_px",
    type=BoundedFloat(0.0, None),
    default=None,
    help="Pixel size on the substrate, µm (required without --job).",
)
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Features CSV to write.",
)
@click.option("--batch", type=int, default=50, show_default=True, help="Columns per batch (n).")
@click.option(
    "--per-batch",
    is_flag=True,
    help="Also write every batch's values to OUT with suffix _batches.csv.",
)
@click.option(
    "--annotate",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Annotated video (.mp4/.avi) or image folder: Hough fit (green), linewidth "
    "(red), overspray (blue).",
)
@click.option(
    "--fps",
    type=BoundedFloat(0.0, None),
    default=None,
    help="Frame rate (videos: overrides the file's; image folders: default 1).",
)
@join_options("linewidth_um/overspray_um", "vision", must_exist=False)
@click.option(
    "--platen-speed",
    "platen_speed_mm_s",
    type=BoundedFloat(0.0, MAX_PLATEN_SPEED_MM_S, closed=True),
    default=None,
    help="Platen speed, mm/s (default: the record's).",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
@part_extract_options
def extract(
    source,
    um_per_px,
    out,
    batch,
    per_batch,
    annotate,
    fps,
    join_record,
    join_out,
    start_offset_s,
    camera_offset_um,
    platen_speed_mm_s,
    progress,
    **part,
):
    """Linewidth and overspray from alignment-camera video (paper App. A, SPEC §9).

    SOURCE is a video (mp4/avi/...), a folder of images or one PNG/TIFF.  Frames are
    streamed one at a time.  The CSV has one row per frame: frame, time_s, linewidth_um,
    overspray_um, linewidth_std_um, overspray_std_um (spread over the batches), n_batches
    (batches measured) and status (ok, or why the frame gave no value).  Lines must lie
    within 45° of the image's horizontal.

    With --job PROGRAM.prg --camera camera.toml: every trace of the part in view, at any
    angle and on arcs, measured across the stroke; OUT has one row per reading (frame,
    time_s, stroke, s_mm, print_time_s, linewidth_um, overspray_um, quality figures) and
    OUT_frames.csv one row per frame with the windows skipped or failed, per reason.
    """
    if part["job_path"] is not None or part["camera_path"] is not None:
        from ajtwin.vision.part_cli import run_part_extract

        return run_part_extract(
            source,
            out,
            annotate=annotate,
            fps=fps,
            batch=batch,
            join_record=join_record,
            join_out=join_out,
            start_offset_s=start_offset_s,
            progress=progress,
            refused={
                "--um-per-px": um_per_px is not None,
                "--per-batch": per_batch,
                "--camera-offset": camera_offset_um != 0.0,
                "--platen-speed": platen_speed_mm_s is not None,
            },
            **part,
        )
    if um_per_px is None:
        raise click.UsageError("--um-per-px is required (or --job and --camera for a part)")
    import pandas as pd
    from tqdm import tqdm

    from ajtwin.vision.extract import LineExtractor, VisionInputError, open_source
    from ajtwin.vision.extract import annotate as draw
    from ajtwin.vision.join import check_linewidth_scale

    try:
        frames = open_source(source, fps)
        extractor = LineExtractor(um_per_px, batch=batch)
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    columns = [
        "frame",
        "time_s",
        "linewidth_um",
        "overspray_um",
        "linewidth_std_um",
        "overspray_std_um",
        "n_batches",
        "status",
    ]
    out.parent.mkdir(parents=True, exist_ok=True)
    batch_path = out.with_name(out.stem + "_batches.csv") if per_batch else None
    statuses: Counter = Counter()
    widths = []
    writer = None
    annotated_dir = None
    try:
        with (
            # decoding runs in a background thread, beside the feature extraction below
            frames.prefetched() as decoded,
            out.open("w", newline="") as fh,
            batch_path.open("w", newline="") if batch_path else _Null() as bfh,
        ):
            table = csv.DictWriter(fh, fieldnames=columns)
            table.writeheader()
            batch_table = None
            if batch_path:
                batch_table = csv.writer(bfh)
                batch_table.writerow(
                    [
                        "frame",
                        "time_s",
                        "batch",
                        "col_start",
                        "col_end",
                        "linewidth_um",
                        "overspray_um",
                        "status",
                    ]
                )
            bar = tqdm(
                decoded,
                total=frames.count,
                unit="frame",
                desc=f"extract {source.name}",
                disable=not progress,
            )
            for index, time_s, gray in bar:
                result = extractor.process(gray, index=index, time_s=time_s)
                row = result.row()
                table.writerow(
                    {k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in row.items()}
                )
                statuses[result.status] += 1
                if np.isfinite(result.linewidth_um):
                    widths.append(result.linewidth_um)
                if batch_table is not None:
                    for number, b in enumerate(result.batches):
                        batch_table.writerow(
                            [
                                index,
                                f"{time_s:.4f}",
                                number,
                                b.col_start,
                                b.col_end,
                                f"{b.linewidth_um:.4f}",
                                f"{b.overspray_um:.4f}",
                                b.status,
                            ]
                        )
                if annotate is not None:
                    canvas = draw(gray, result)
                    if annotate.suffix.lower() in (".mp4", ".avi", ".mkv"):
                        if writer is None:
                            writer = _open_writer(annotate, frames.fps, canvas.shape)
                        writer.write(canvas)
                    else:
                        import cv2

                        annotated_dir = annotate
                        annotate.mkdir(parents=True, exist_ok=True)
                        cv2.imwrite(str(annotate / f"frame_{index:06d}.png"), canvas)
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    finally:
        if writer is not None:
            writer.release()
    total = sum(statuses.values())
    summary = ", ".join(f"{k}: {v}" for k, v in statuses.most_common())
    click.echo(f"wrote {out} ({total} frames; {summary})")
    if batch_path:
        click.echo(f"wrote {batch_path}")
    if annotate is not None:
        click.echo(f"wrote {annotated_dir or annotate}")
    good = sum(statuses[s] for s in ("ok", "few_batches"))
    if good == 0:
        reasons = "; ".join(
            f"{k} ({v} frames): {STATUS_HINTS.get(k, k)}" for k, v in statuses.most_common()
        )
        raise click.ClickException(f"no frame of {source} gave a linewidth — {reasons}")
    try:
        check_linewidth_scale(widths, um_per_px, source)
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    if join_record is not None:
        _join(
            join_record,
            join_out,
            pd.read_csv(out),
            start_offset_s,
            camera_offset_um,
            platen_speed_mm_s,
            source,
            um_per_px,
        )


class _LazyProfiles:
    """A sequence of profiles computed on demand (a 90-min print never sits in memory)."""

    def __init__(self, rows: np.ndarray, make):
        self.rows = rows
        self.make = functools.lru_cache(maxsize=8)(make)

    def __len__(self) -> int:
        return int(self.rows.size)

    def __getitem__(self, index: int) -> np.ndarray:
        return self.make(int(self.rows[index]))


class _Null:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def _open_writer(path: Path, fps: float, shape):
    import cv2

    fourcc = "mp4v" if path.suffix.lower() == ".mp4" else "FFV1"
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(
        str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (shape[1], shape[0]), True
    )
    if not writer.isOpened():
        raise click.ClickException(f"{path}: OpenCV cannot write this video here")
    return writer


def _join(
    record_path,
    join_out,
    features,
    start_offset_s,
    camera_offset_um,
    platen_speed_mm_s,
    source,
    um_per_px,
):
    from ajtwin.io.records import PrintRecord, RecordError, read_record, write_record
    from ajtwin.vision.join import join_features

    try:
        rec = read_record(record_path)
    except (RecordError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    speed = platen_speed_mm_s or float(rec.meta.get("platen_speed_mm_s", 1.0))
    try:
        joined, summary = join_features(
            rec.data,
            features,
            start_offset_s=start_offset_s,
            camera_offset_um=camera_offset_um,
            platen_speed_mm_s=speed,
        )
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    meta = dict(rec.meta)
    meta["vision"] = {
        "source": str(source),
        "um_per_px": um_per_px,
        "start_offset_s": start_offset_s,
        "camera_offset_um": camera_offset_um,
        "platen_speed_mm_s": speed,
        **summary,
    }
    if join_out is None:
        join_out = record_path.with_name(record_path.stem + "_vision.parquet")
    path = write_record(PrintRecord(joined, meta), join_out)
    click.echo(f"wrote {path} ({json.dumps(summary)})")
    if summary["seconds_filled"] == 0:
        raise click.ClickException(
            "no video frame fell inside the record's time span: check --start-offset, "
            "--camera-offset and the frame rate"
        )
