"""``ajtwin render`` and ``ajtwin extract`` — the shells around the vision core.

Both take a part's program: ``ajtwin extract VIDEO --job PROGRAM.prg --camera camera.toml``
and ``ajtwin render RECORD --job PROGRAM.prg --camera camera.toml`` are the same commands
with the program's options added (:func:`part_extract_options`, :func:`part_render_options`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import click
import numpy as np
import pandas as pd

from ajtwin.cli.options import (
    BoundedFloat,
    join_options,
    load_camera_option,
    load_job_option,
)
from ajtwin.engine.video import join_part_video
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


def _job_options(command, *, render: bool):
    options = [
        click.option(
            "--job",
            "job_path",
            type=click.Path(dir_okay=False, path_type=Path),
            default=None,
            help="The program (.prg) the video's part was printed with: traces at any angle, "
            "arcs, skips of corners, ends, crossings, fills and neighbours.",
        ),
        click.option(
            "--camera",
            "camera_path",
            type=click.Path(dir_okay=False, path_type=Path),
            default=None,
            help="With --job: the camera file (camera.toml: µm/px, rotation, offset, frame "
            "size; `ajtwin camera calibrate` writes one).",
        ),
        click.option(
            "--process-speed",
            "process_speed_mm_s",
            type=BoundedFloat(0.0, None),
            default=None,
            help="With --job: the GUI's process speed, mm/s (default: the record's, else "
            "stage.toml).",
        ),
        click.option(
            "--rapid-speed",
            "rapid_speed_mm_s",
            type=BoundedFloat(0.0, None),
            default=None,
            help="With --job: the GUI's rapid speed, mm/s.",
        ),
        click.option(
            "--repeat-to",
            "repeat_to_s",
            type=BoundedFloat(0.0, None),
            default=None,
            help="With --job: the program was looped to this many seconds.",
        ),
    ]
    if not render:
        options += [
            click.option(
                "--reach-um",
                type=BoundedFloat(0.0, None),
                default=None,
                help="With --job: a trace's deposit (linewidth/2 + overspray) ends within "
                "this distance of its centre line, µm (default vision/part.toml: 75).",
            ),
            click.option(
                "--fiducial",
                "fiducials",
                multiple=True,
                metavar="X,Y[,R]",
                help="With --job: a fiducial mark at (X, Y) mm (radius R mm) whose "
                "surroundings are not measured; repeatable.",
            ),
        ]
    for option in reversed(options):
        command = option(command)
    return command


def part_extract_options(command):
    """The options ``ajtwin extract`` takes for a part (``--job``, ``--camera`` ...)."""
    return _job_options(command, render=False)


def part_render_options(command):
    """The options ``ajtwin render`` takes for a part (``--job``, ``--camera`` ...)."""
    return _job_options(command, render=True)


def _parse_fiducials(items) -> list[tuple[float, ...]]:
    out = []
    for text in items:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
            raise click.BadParameter(f"--fiducial expects X,Y or X,Y,R in mm, got {text!r}")
        if len(values) == 3 and values[2] <= 0:
            raise click.BadParameter(f"--fiducial radius must be > 0, got {text!r}")
        out.append(values)
    return out


def _refuse(given: dict, what: str) -> None:
    wrong = [name for name, value in given.items() if value]
    if wrong:
        raise click.UsageError(f"{', '.join(wrong)} cannot be used with --job: {what}")


def _read_record(path, csv_dialect=None):
    try:
        return read_record(path, dialect=csv_dialect)
    except (RecordError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None


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
        given = click.get_current_context().get_parameter_source("size").name == "COMMANDLINE"
        return _render_part(
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
    # lazy CLI loading: rendering loads OpenCV, `render --help` must not
    from ajtwin.vision.record_render import ConstantLine, render_record_video
    from ajtwin.vision.render import RenderSettings, TruthFile

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
            truth=TruthFile(truth, {} if record is None else {"record": str(record)}),
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
    csv_dialect,
    **part,
):
    """Linewidth and overspray from alignment-camera video (paper App. A).

    SOURCE is a video (mp4/avi/...), a folder of images or one PNG/TIFF.  Frames are
    streamed one at a time.  The CSV has one row per frame: frame, time_s, linewidth_um,
    overspray_um, linewidth_std_um, overspray_std_um (spread over the batches), n_batches
    (batches measured) and status (ok, or why the frame gave no value).  Lines must lie
    within 45° of the image's horizontal.  The method: docs/reference/model.md §9.

    With --job PROGRAM.prg --camera camera.toml: every trace of the part in view, at any
    angle and on arcs, measured across the stroke; OUT has one row per reading (frame,
    time_s, stroke, s_mm, print_time_s, linewidth_um, overspray_um, quality figures) and
    OUT_frames.csv one row per frame with the windows skipped or failed, per reason.
    A video whose frames show lines where the program prints nothing (another program's
    video, or a wrong --start-offset) is refused and no table is written; a few such frames
    give a warning.
    """
    if part["job_path"] is not None or part["camera_path"] is not None:
        return _extract_part(
            source,
            out,
            annotate=annotate,
            fps=fps,
            batch=batch,
            join_record=join_record,
            join_out=join_out,
            start_offset_s=start_offset_s,
            progress=progress,
            csv_dialect=csv_dialect,
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


def _extract_part(
    source: Path,
    out: Path,
    *,
    annotate=None,
    fps=None,
    batch=50,
    join_record=None,
    join_out=None,
    start_offset_s=0.0,
    progress=True,
    csv_dialect=None,
    job_path=None,
    camera_path=None,
    process_speed_mm_s=None,
    rapid_speed_mm_s=None,
    repeat_to_s=None,
    reach_um=None,
    fiducials=(),
    refused: dict | None = None,
) -> None:
    """``ajtwin extract VIDEO --job ... --camera ...``: readings CSV, frames CSV, join."""
    # lazy CLI loading: the part's extraction loads OpenCV, `extract --help` must not
    from ajtwin.vision.extract import VisionInputError
    from ajtwin.vision.join import check_linewidth_scale
    from ajtwin.vision.part_extract import PartSettings
    from ajtwin.vision.part_video import extract_part_video

    _refuse(
        refused or {},
        "the pixel size and the camera's offset come from --camera, the speed from the program",
    )
    camera = load_camera_option(camera_path)
    record = None if join_record is None else _read_record(join_record, csv_dialect)
    job = load_job_option(
        job_path,
        meta=record.meta if record is not None else None,
        process_speed=process_speed_mm_s,
        rapid_speed=rapid_speed_mm_s,
        repeat_to=repeat_to_s,
    )
    fiducials = _parse_fiducials(fiducials)
    try:
        done = extract_part_video(
            source,
            job,
            camera,
            out,
            settings=PartSettings.from_defaults(batch=batch, reach_um=reach_um),
            fiducials=fiducials,
            start_offset_s=start_offset_s,
            fps=fps,
            annotate_to=annotate,
            progress=progress,
            program_name=Path(job_path).name,
        )
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(
        f"wrote {out} ({done.n_readings} readings from {done.n_frames} frames) and "
        f"{done.frames_path}\n{done.summary()}"
    )
    if done.annotated is not None:
        click.echo(f"wrote {done.annotated}")
    if done.n_readings == 0:
        raise click.ClickException(done.no_reading_reason(source))
    for warning in (done.misplaced_warning(), done.doubt_warning(source, Path(job_path).name)):
        if warning:
            click.echo(f"warning: {warning}", err=True)
    try:
        check_linewidth_scale(np.concatenate(done.widths), camera.um_per_px, source)
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    if record is not None:
        _join_part(record, join_record, join_out, out, camera, camera_path, job_path, source)


def _join_part(record, record_path, join_out, readings_path, camera, camera_path, job_path, src):
    joined, summary = join_part_video(
        record,
        pd.read_csv(readings_path),
        camera,
        source=src,
        program=job_path,
        camera_file=camera_path,
    )
    if join_out is None:
        join_out = record_path.with_name(record_path.stem + "_vision.parquet")
    path = write_record(joined, join_out)
    click.echo(f"wrote {path} ({json.dumps(summary)})")
    if summary["seconds_filled"] == 0:
        raise click.ClickException(
            "no reading fell inside the record's time span: check --start-offset and that the "
            "record and the video belong to the same print"
        )


def _render_part(
    record_path,
    out: Path,
    *,
    truth_path=None,
    fps=1.0,
    start_s=0.0,
    duration_s=None,
    noise_gray=None,
    blur_px=None,
    raggedness_um=None,
    linewidth_um=43.0,
    overspray_um=29.0,
    area_um2=None,
    seed=0,
    job_path=None,
    camera_path=None,
    process_speed_mm_s=None,
    rapid_speed_mm_s=None,
    repeat_to_s=None,
    refused: dict | None = None,
) -> None:
    """``ajtwin render [RECORD] --job ... --camera ...``: the part under the camera."""
    # lazy CLI loading: rendering loads OpenCV, `render --help` must not
    from ajtwin.vision.part_render import PrintTruth, render_part_video
    from ajtwin.vision.render import RenderSettings

    _refuse(refused or {}, "the frame size, pixel size and angle come from --camera")
    camera = load_camera_option(camera_path)
    record = _read_record(record_path) if record_path is not None else None
    job = load_job_option(
        job_path,
        meta=record.meta if record is not None else None,
        process_speed=process_speed_mm_s,
        rapid_speed=rapid_speed_mm_s,
        repeat_to=repeat_to_s,
    )
    try:
        if record is not None:
            truth = PrintTruth.from_table(record.data, job=job)
        else:
            truth = PrintTruth.constant(job.duration_s, linewidth_um, overspray_um, area_um2)
    except ValueError as exc:
        where = f"{record_path}: " if record_path is not None else ""
        raise click.ClickException(f"{where}{exc}") from None
    if truth.raised_area:
        click.echo(
            f"note: {truth.raised_area} seconds carry too little material for their overspray "
            "to be visible: drawn with the least cross-section that shows it"
        )
    overrides = {
        key: value
        for key, value in (
            ("noise_sigma_gray", noise_gray),
            ("blur_sigma_px", blur_px),
            ("raggedness_um", raggedness_um),
        )
        if value is not None
    }
    settings = RenderSettings.from_defaults(um_per_px=camera.um_per_px, **overrides)
    if duration_s is None:
        duration_s = job.duration_s - start_s
    if start_s + duration_s > job.duration_s + 1e-9:
        raise click.ClickException(
            f"--start {start_s:g} + --duration {duration_s:g} s goes beyond the end of "
            f"{Path(job_path).name} ({job.duration_s:.3f} s)"
        )
    try:
        written = render_part_video(
            job,
            camera,
            truth,
            out,
            fps=fps,
            start_s=start_s,
            duration_s=duration_s,
            settings=settings,
            seed=seed,
            truth_path=truth_path,
            extra_truth={
                "record": str(record_path) if record_path is not None else None,
                "camera_file": str(camera_path),
            },
        )
    except (ValueError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"wrote {out} and {written}")
