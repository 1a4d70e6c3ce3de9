"""``ajtwin render`` and ``ajtwin extract`` — the shells around the vision core."""

from __future__ import annotations

import json
from pathlib import Path

import click
import pandas as pd

from ajtwin.cli.options import BoundedFloat, join_options
from ajtwin.io.records import (  # one bound for options and metadata
    MAX_PLATEN_SPEED_MM_S,
    PrintRecord,
    RecordError,
    read_record,
    write_record,
)


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
):
    """Render an alignment-camera video (plus ground-truth JSON) of a print.

    With RECORD (a print record, .parquet/.csv) each second's linewidth_um, overspray_um
    and material_flow_mL_s become a line cross-section (cross-section = Q_m / platen
    speed); without it a constant line of --linewidth/--overspray/--area is rendered.
    """
    # lazy CLI loading: rendering loads OpenCV, `render --help` must not
    from ajtwin.vision.record_render import ConstantLine, render_record_video
    from ajtwin.vision.render import RenderSettings

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
    rec = None
    if record is not None:
        try:
            rec = read_record(record)
        except (RecordError, FileNotFoundError) as exc:
            raise click.ClickException(str(exc)) from None
    try:
        video = render_record_video(
            rec,
            out,
            fps=fps,
            shape=shape,
            settings=settings,
            start_s=start_s,
            duration_s=duration_s,
            platen_speed_mm_s=platen_speed_mm_s,
            constant=ConstantLine(linewidth_um, overspray_um, area_um2),
            seed=seed,
            truth_path=truth,
            extra_truth={} if record is None else {"record": str(record)},
        )
    except ValueError as exc:  # no row of the record in the time window
        raise click.ClickException(f"{record}: {exc}") from None
    for note in video.notes:
        click.echo(f"note: {note}")
    click.echo(f"wrote {out} and {video.truth_path}")


@click.command()
@click.argument("source", type=click.Path(path_type=Path))
@click.option(
    "--um-per-px",
    "um_per_px",
    type=BoundedFloat(0.0, None),
    required=True,
    help="Pixel size on the substrate, µm.",
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
    csv_dialect,
):
    """Linewidth and overspray from alignment-camera video (paper App. A).

    SOURCE is a video (mp4/avi/...), a folder of images or one PNG/TIFF.  Frames are
    streamed one at a time.  The CSV has one row per frame: frame, time_s, linewidth_um,
    overspray_um, linewidth_std_um, overspray_std_um (spread over the batches), n_batches
    (batches measured) and status (ok, or why the frame gave no value).  The method:
    docs/reference/model.md §9.
    """
    # lazy CLI loading: OpenCV is imported when the command runs, not for --help
    from ajtwin.vision.extract import VisionInputError
    from ajtwin.vision.join import check_linewidth_scale
    from ajtwin.vision.video_features import extract_video

    try:
        done = extract_video(
            source,
            um_per_px,
            out,
            batch=batch,
            per_batch=per_batch,
            annotate_to=annotate,
            fps=fps,
            progress=progress,
        )
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    summary = ", ".join(f"{k}: {v}" for k, v in done.statuses.most_common())
    click.echo(f"wrote {out} ({done.n_frames} frames; {summary})")
    if done.batch_path:
        click.echo(f"wrote {done.batch_path}")
    if done.annotated is not None:
        click.echo(f"wrote {done.annotated}")
    if done.n_measured == 0:
        raise click.ClickException(
            f"no frame of {source} gave a linewidth — {done.failure_reasons()}"
        )
    try:
        check_linewidth_scale(done.widths, um_per_px, source)
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
            csv_dialect,
        )


def _join(
    record_path,
    join_out,
    features,
    start_offset_s,
    camera_offset_um,
    platen_speed_mm_s,
    source,
    um_per_px,
    csv_dialect=None,
):
    # lazy CLI loading: the join loads OpenCV's vision package
    from ajtwin.vision.join import join_features

    try:
        rec = read_record(record_path, dialect=csv_dialect)
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
