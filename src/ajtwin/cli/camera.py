"""``ajtwin camera``: the alignment camera's geometry over the part (camera.toml).

``ajtwin camera calibrate VIDEO --job PROGRAM.prg`` fits the pixel size, the rotation and
the offset of the camera file to frames of known strokes (:mod:`ajtwin.vision.calibrate`).
"""

from __future__ import annotations

from pathlib import Path

import click

from ajtwin.cli.options import BoundedFloat, load_job_option
from ajtwin.vision.camera import Camera, CameraFileError, load_camera, save_camera
from ajtwin.vision.errors import VisionInputError

__all__ = ["camera"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def camera():
    """The alignment camera's geometry over the part (camera.toml)."""


@camera.command()
@click.argument("source", type=click.Path(path_type=Path))
@click.option(
    "--job",
    "job_path",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="The program (.prg) the video's part was printed with.",
)
@click.option(
    "--camera",
    "camera_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Starting geometry (a camera file); the options below override its fields.",
)
@click.option(
    "--um-per-px",
    type=BoundedFloat(0.0, None),
    default=None,
    help="Starting pixel size, µm (searched within ±25 %).",
)
@click.option(
    "--rotation-deg",
    type=BoundedFloat(-360.0, 360.0, closed=True),
    default=None,
    help="Starting rotation, degrees (the whole turn is searched).",
)
@click.option(
    "--offset-mm",
    default=None,
    metavar="DX,DY",
    help="Starting view centre relative to the nozzle, mm (must be right to "
    "within about --gate-um).",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("camera.toml"),
    show_default=True,
    help="Camera file to write.",
)
@click.option(
    "--frames",
    "n_frames",
    type=click.IntRange(2, 500),
    default=12,
    show_default=True,
    help="Frames used, spread over the video where traces are in view.",
)
@click.option(
    "--start-offset",
    "start_offset_s",
    type=BoundedFloat(),
    default=0.0,
    show_default=True,
    help="Job time (s) of the video's first frame.",
)
@click.option(
    "--fps",
    type=BoundedFloat(0.0, None),
    default=None,
    help="Frame rate (videos: overrides the file's).",
)
@click.option(
    "--gate-um",
    type=BoundedFloat(0.0, None),
    default=60.0,
    show_default=True,
    help="Line points further than this from every trace are not used.",
)
@click.option(
    "--search/--no-search",
    default=True,
    show_default=True,
    help="Search rotation and pixel size before the fit.",
)
@click.option(
    "--process-speed",
    "process_speed_mm_s",
    type=BoundedFloat(0.0, None),
    default=None,
    help="The GUI's process speed, mm/s.",
)
@click.option(
    "--rapid-speed",
    "rapid_speed_mm_s",
    type=BoundedFloat(0.0, None),
    default=None,
    help="The GUI's rapid speed, mm/s.",
)
@click.option(
    "--repeat-to",
    "repeat_to_s",
    type=BoundedFloat(0.0, None),
    default=None,
    help="The program was looped to this many seconds.",
)
def calibrate(
    source,
    job_path,
    camera_path,
    um_per_px,
    rotation_deg,
    offset_mm,
    out,
    n_frames,
    start_offset_s,
    fps,
    gate_um,
    search,
    process_speed_mm_s,
    rapid_speed_mm_s,
    repeat_to_s,
):
    """Fit µm/px, rotation and offset (with standard errors) to a video of known strokes.

    The lines seen in a few frames are put onto the program's traces: the fit moves,
    turns and scales the camera's view until they lie on them. The starting offset must
    be right to within about --gate-um; rotation and pixel size are searched. Refused,
    with the reason, when the frames cannot determine the geometry (traces of one
    direction only, too few points, residuals too large for the program's traces).
    """
    # lazy CLI loading: calibration loads OpenCV, `camera calibrate --help` must not
    from ajtwin.vision.calibrate import CalibrationError, calibrate_video
    from ajtwin.vision.extract import open_source

    job = load_job_option(
        job_path,
        process_speed=process_speed_mm_s,
        rapid_speed=rapid_speed_mm_s,
        repeat_to=repeat_to_s,
    )
    try:
        frames = open_source(source, fps)
        start = _starting_camera(camera_path, um_per_px, rotation_deg, offset_mm, frames)
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    try:
        start = Camera(**{**start, "calibration": {}})
    except CameraFileError as exc:
        raise click.ClickException(f"starting camera: {exc}") from None
    try:
        result = calibrate_video(
            frames,
            job,
            start,
            start_offset_s=start_offset_s,
            n_frames=n_frames,
            gate_um=gate_um,
            search=search,
            program_name=Path(job_path).name,
        )
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    except CalibrationError as exc:
        raise click.ClickException(f"{source}: calibration refused: {exc}") from None
    fitted = result.camera
    fitted = Camera(
        **{
            **{k: getattr(fitted, k) for k in fitted.__dataclass_fields__},
            "calibration": {
                **fitted.calibration,
                "video": Path(source).name,
                "program": Path(job_path).name,
                "start_offset_s": start_offset_s,
            },
        }
    )
    save_camera(fitted, out)
    relative = 100 * fitted.um_per_px_se / fitted.um_per_px
    se_x, se_y = (1e3 * v for v in fitted.offset_mm_se)
    click.echo(
        f"wrote {out}\n"
        f"  um_per_px    {fitted.um_per_px:.5f} ± {fitted.um_per_px_se:.5f} ({relative:.2f} %)\n"
        f"  rotation_deg {fitted.rotation_deg:.3f} ± {fitted.rotation_deg_se:.3f}\n"
        f"  offset_mm    [{fitted.offset_mm[0]:.5f}, {fitted.offset_mm[1]:.5f}] "
        f"± [{se_x:.2f}, {se_y:.2f}] µm\n"
        f"  from {result.points} line points in {result.frames} frames; residual "
        f"{result.residual_um:.2f} µm (robust sigma)"
    )


def _starting_camera(camera_path, um_per_px, rotation_deg, offset_mm, frames) -> dict:
    """The starting geometry: the camera file, then the options, then the video's size."""
    fields: dict = {}
    if camera_path is not None:
        try:
            loaded = load_camera(camera_path)
        except (CameraFileError, FileNotFoundError) as exc:
            raise click.ClickException(str(exc)) from None
        fields = {
            "um_per_px": loaded.um_per_px,
            "rotation_deg": loaded.rotation_deg,
            "offset_mm": loaded.offset_mm,
            "width_px": loaded.width_px,
            "height_px": loaded.height_px,
        }
    if um_per_px is not None:
        fields["um_per_px"] = um_per_px
    if rotation_deg is not None:
        fields["rotation_deg"] = rotation_deg
    if offset_mm is not None:
        try:
            dx, dy = (float(v) for v in offset_mm.split(","))
        except ValueError:
            raise click.BadParameter(
                f"--offset-mm expects DX,DY in mm, got {offset_mm!r}"
            ) from None
        fields["offset_mm"] = (dx, dy)
    if "um_per_px" not in fields:
        raise click.UsageError("give a starting --um-per-px (or --camera start.toml)")
    fields.setdefault("rotation_deg", 0.0)
    fields.setdefault("offset_mm", (0.0, 0.0))
    with frames.prefetched() as decoded:
        _, _, gray = next(iter(decoded))
    fields["width_px"], fields["height_px"] = int(gray.shape[1]), int(gray.shape[0])
    return fields
