"""The camera on a part, on the command line: ``extract --job``, ``render --job``, ``camera``.

``ajtwin extract VIDEO --job PROGRAM.prg --camera camera.toml`` and ``ajtwin render RECORD
--job PROGRAM.prg --camera camera.toml`` are the existing commands with the program's
options added (:func:`part_extract_options`, :func:`part_render_options`); the work is done
by :func:`run_part_extract` and :func:`run_part_render`. ``ajtwin camera calibrate`` fits the
camera file. Commands parse options and call library functions.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from collections import Counter
from pathlib import Path

import click
import numpy as np

from ajtwin.io.cli_options import BoundedFloat

FAIL_HINTS = {
    "no_line": "no dark band where the program puts the trace",
    "off_program": "the line's centre is away from the program's path",
    "no_shoulder": "no shoulder peak (iii)",
    "overspray_outside": "the overspray does not end within the cross-section",
    "beyond_reach": "the overspray ends beyond --reach-um",
}


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


# -- shared loading -------------------------------------------------------------------------
def load_camera_option(camera_path):
    from ajtwin.vision.camera import CameraFileError, load_camera

    if camera_path is None:
        raise click.UsageError("--job needs --camera camera.toml (the camera's geometry)")
    try:
        return load_camera(camera_path)
    except (CameraFileError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None


def load_job_option(job_path, *, meta=None, process_speed=None, rapid_speed=None, repeat_to=None):
    """Read the program as the print ran it (speeds and looping from the record if known)."""
    from ajtwin.job import ProgramError, read_program

    if job_path is None:
        raise click.UsageError("--camera needs --job PROGRAM.prg")
    job_meta = (meta or {}).get("job") or {}
    if not isinstance(job_meta, dict):
        job_meta = {}
    try:
        data = Path(job_path).read_bytes()
    except OSError as exc:
        raise click.ClickException(f"{job_path}: cannot read the program: {exc.strerror}") from None
    sha = job_meta.get("sha256")
    if sha and sha != hashlib.sha256(data).hexdigest():
        raise click.ClickException(
            f"{job_path} is not the program this record was printed with (the record names "
            f"{job_meta.get('program', '?')!r}, sha256 {sha[:12]}…; this file's differs)"
        )
    process_speed = process_speed or job_meta.get("process_speed_mm_s")
    rapid_speed = rapid_speed or job_meta.get("rapid_speed_mm_s")
    repeat_to = repeat_to or job_meta.get("repeat_to_s")
    try:
        job = read_program(job_path, process_speed, rapid_speed)
        if repeat_to and repeat_to > job.duration_s:
            job = job.repeat(float(repeat_to))
    except (ProgramError, ValueError) as exc:
        raise click.ClickException(str(exc)) from None
    return job


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


# -- extract -------------------------------------------------------------------------------
def run_part_extract(
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
    from tqdm import tqdm

    from ajtwin.vision.extract import VisionInputError, open_source
    from ajtwin.vision.join import check_linewidth_scale
    from ajtwin.vision.part_extract import (
        FRAME_COLUMNS,
        READING_COLUMNS,
        PartExtractor,
        PartSettings,
        annotate_part,
    )

    _refuse(
        refused or {},
        "the pixel size and the camera's offset come from --camera, the speed from the program",
    )
    camera = load_camera_option(camera_path)
    record = None
    if join_record is not None:
        record = _read_record(join_record)
    job = load_job_option(
        job_path,
        meta=record.meta if record is not None else None,
        process_speed=process_speed_mm_s,
        rapid_speed=rapid_speed_mm_s,
        repeat_to=repeat_to_s,
    )
    try:
        settings = PartSettings.from_defaults(batch=batch, reach_um=reach_um)
        frames = open_source(source, fps)
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    _check_duration(frames, start_offset_s, job, source, job_path)
    extractor = PartExtractor(job, camera, settings, fiducials=_parse_fiducials(fiducials))
    frames_path = out.with_name(out.stem + "_frames.csv")
    out.parent.mkdir(parents=True, exist_ok=True)
    statuses: Counter = Counter()
    skipped: Counter = Counter()
    failed: Counter = Counter()
    widths: list[np.ndarray] = []
    n_readings = 0
    writer = None
    limit = job.duration_s + 1.0 / frames.fps
    try:
        with (
            frames.prefetched() as decoded,
            out.open("w", newline="") as fh,
            frames_path.open("w", newline="") as ffh,
        ):
            table = _ReadingsWriter(fh, READING_COLUMNS)
            frame_table = csv.DictWriter(ffh, fieldnames=FRAME_COLUMNS)
            frame_table.writeheader()
            bar = tqdm(
                decoded,
                total=frames.count,
                unit="frame",
                desc=f"extract {source.name}",
                disable=not progress,
            )
            try:
                for index, video_time, gray in bar:
                    t = start_offset_s + video_time
                    if t > limit:
                        raise click.ClickException(
                            f"{source}: frame {index} is at job time {t:.3f} s, after the end of "
                            f"{Path(job_path).name} ({job.duration_s:.3f} s): the video does not "
                            "belong to this program, --start-offset is wrong, or the program was "
                            "looped (--repeat-to)"
                        )
                    result = extractor.process(gray, index=index, time_s=t)
                    statuses[result.status] += 1
                    skipped.update(result.skipped)
                    failed.update(result.failed)
                    frame_table.writerow(_formatted(result.row()))
                    readings = result.readings
                    if result.n_readings:
                        n_readings += result.n_readings
                        widths.append(readings["linewidth_um"])
                        table.add(readings)
                    if annotate is not None:
                        canvas = annotate_part(gray, result, extractor)
                        writer = _write_annotated(annotate, writer, index, canvas, frames.fps)
            finally:  # what waits is written, also when a frame is refused
                table.flush()
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    finally:
        if writer is not None:
            writer.release()
    total = sum(statuses.values())
    click.echo(
        f"wrote {out} ({n_readings} readings from {total} frames) and {frames_path}\n"
        f"  frames: {_counts(statuses)}\n"
        f"  windows skipped: {_counts(skipped) or 'none'}\n"
        f"  windows measured without a reading: {_counts(failed) or 'none'}"
    )
    if annotate is not None:
        click.echo(f"wrote {annotate}")
    if n_readings == 0:
        raise click.ClickException(_no_reading_reason(source, statuses, skipped, failed))
    measured = n_readings + sum(failed.values())
    lost = failed.get("no_line", 0) + failed.get("off_program", 0)
    if lost > 0.5 * measured:
        click.echo(
            f"warning: {lost} of {measured} measured windows found no line where the program "
            "and the camera file put it: check rotation_deg and offset_mm (ajtwin camera "
            "calibrate) and --start-offset",
            err=True,
        )
    try:
        check_linewidth_scale(np.concatenate(widths), camera.um_per_px, source)
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    if record is not None:
        _join_part(record, join_record, join_out, out, camera, camera_path, job_path, source)


class _ReadingsWriter:
    """Readings to CSV in blocks of frames (pandas' writer: ~10x faster than row by row).

    At most ``FRAMES_PER_BLOCK`` frames' readings wait in memory; an error or a stop
    (Ctrl-C) writes what waits before leaving (the caller's ``finally``).
    """

    FRAMES_PER_BLOCK = 32
    #: written to 1 µs, 1 nm (positions in mm), 1e-4 µm and 0.01 (SNR): far below what
    #: the figures can resolve, and short lines that pandas writes fast
    DECIMALS = {
        "time_s": 6,
        "print_time_s": 6,
        "s_mm": 6,
        "x_mm": 6,
        "y_mm": 6,
        "linewidth_um": 4,
        "overspray_um": 4,
        "linewidth_se_um": 4,
        "offset_um": 4,
        "snr": 2,
    }

    def __init__(self, handle, columns):
        self.handle, self.columns = handle, list(columns)
        self.pending: list[dict] = []
        handle.write(",".join(self.columns) + "\n")

    def add(self, readings: dict) -> None:
        self.pending.append(readings)
        if len(self.pending) >= self.FRAMES_PER_BLOCK:
            self.flush()

    def flush(self) -> None:
        import pandas as pd

        if not self.pending:
            return
        block = {c: np.concatenate([r[c] for r in self.pending]) for c in self.columns}
        self.pending = []
        for column, decimals in self.DECIMALS.items():
            block[column] = np.round(block[column], decimals)
        pd.DataFrame(block, columns=self.columns).to_csv(
            self.handle, header=False, index=False, lineterminator="\n"
        )
        self.handle.flush()


def _check_duration(frames, start_offset_s, job, source, job_path) -> None:
    """A video longer than the job is the wrong program (or clock, or a looped job)."""
    if not frames.count:
        return
    last = start_offset_s + (frames.count - 1) / frames.fps
    if last > job.duration_s + 1.0 / frames.fps:
        raise click.ClickException(
            f"{source}: {frames.count} frames at {frames.fps:g} frames/s from job time "
            f"{start_offset_s:g} s last until {last:.3f} s, but {Path(job_path).name} ends at "
            f"{job.duration_s:.3f} s: the video does not belong to this program, --start-offset "
            "is wrong, or the program was looped (--repeat-to)"
        )


def _no_reading_reason(source, statuses, skipped, failed) -> str:
    if sum(skipped.values()) + sum(failed.values()) == 0:
        return (
            f"no frame of {source} had a printed trace in view: check offset_mm in the camera "
            "file, --start-offset, and that the video belongs to this program"
        )
    if sum(failed.values()) == 0:
        return (
            f"no frame of {source} gave a reading: every trace in view was in a situation that "
            f"cannot be measured honestly ({_counts(skipped)})"
        )
    hints = "; ".join(f"{k} ({v}): {FAIL_HINTS.get(k, k)}" for k, v in failed.most_common())
    return (
        f"no frame of {source} gave a reading: the traces are not where the program and the "
        f"camera file put them — {hints}. Check rotation_deg and offset_mm (ajtwin camera "
        "calibrate), --start-offset, and that the video belongs to this program"
    )


def _counts(counter: Counter) -> str:
    return ", ".join(f"{k} {v}" for k, v in counter.most_common())


def _format(value):
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.6g}" if abs(value) < 1e5 else f"{float(value):.10g}"
    if isinstance(value, np.integer):
        return int(value)
    return value


def _formatted(row: dict) -> dict:
    return {k: _format(v) for k, v in row.items()}


def _write_annotated(path: Path, writer, index, canvas, fps):
    import cv2

    if path.suffix.lower() in (".mp4", ".avi", ".mkv"):
        if writer is None:
            from ajtwin.vision.cli import _open_writer

            writer = _open_writer(path, fps, canvas.shape)
        writer.write(canvas)
        return writer
    path.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path / f"frame_{index:06d}.png"), canvas)
    return writer


def _read_record(path):
    from ajtwin.io.records import RecordError, read_record

    try:
        return read_record(path)
    except (RecordError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None


def _join_part(record, record_path, join_out, readings_path, camera, camera_path, job_path, src):
    import pandas as pd

    from ajtwin.io.records import PrintRecord, write_record
    from ajtwin.vision.part_join import join_part_readings

    readings = pd.read_csv(readings_path)
    joined, summary = join_part_readings(record.data, readings)
    meta = dict(record.meta)
    previous = meta.get("camera") if isinstance(meta.get("camera"), dict) else {}
    offset = [float(v) for v in camera.offset_mm]
    meta["camera"] = {
        "mode": previous.get("mode") or ("at_nozzle" if offset == [0.0, 0.0] else "trailing"),
        "offset_mm": offset,
    }
    meta["vision"] = {
        "source": str(src),
        "program": Path(job_path).name,
        "camera_file": str(camera_path),
        "um_per_px": camera.um_per_px,
        "rotation_deg": camera.rotation_deg,
        **summary,
    }
    if join_out is None:
        join_out = record_path.with_name(record_path.stem + "_vision.parquet")
    path = write_record(PrintRecord(joined, meta), join_out)
    click.echo(f"wrote {path} ({json.dumps(summary)})")
    if summary["seconds_filled"] == 0:
        raise click.ClickException(
            "no reading fell inside the record's time span: check --start-offset and that the "
            "record and the video belong to the same print"
        )


# -- render --------------------------------------------------------------------------------
def run_part_render(
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


# -- camera calibrate ------------------------------------------------------------------------
@click.group()
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
    from ajtwin.vision.calibrate import CalibrationError, calibrate_camera
    from ajtwin.vision.camera import Camera, CameraFileError, save_camera
    from ajtwin.vision.extract import VisionInputError, open_source
    from ajtwin.vision.part_extract import PartSettings, Windows

    job = load_job_option(
        job_path,
        process_speed=process_speed_mm_s,
        rapid_speed=rapid_speed_mm_s,
        repeat_to=repeat_to_s,
    )
    try:
        frames = open_source(source, fps)
    except VisionInputError as exc:
        raise click.ClickException(str(exc)) from None
    start = _starting_camera(camera_path, um_per_px, rotation_deg, offset_mm, frames)
    try:
        start = Camera(**{**start, "calibration": {}})
    except CameraFileError as exc:
        raise click.ClickException(f"starting camera: {exc}") from None
    settings = PartSettings.from_defaults()
    windows = Windows(job, start, settings)
    if not frames.count:
        raise click.ClickException(f"{source}: the video does not state its frame count")
    times = start_offset_s + np.arange(frames.count) / frames.fps
    _check_duration(frames, start_offset_s, job, source, job_path)
    radius = start.half_diagonal_mm
    state = job.state_at(times)
    centre = np.column_stack([state.x_mm, state.y_mm]) + np.asarray(start.offset_mm)
    seen = np.array(
        [
            np.any(windows.t_to[windows.near(x, y, radius)] < t)
            for (x, y), t in zip(centre, times, strict=True)
        ]
    )
    candidates = np.flatnonzero(seen)
    if candidates.size < 2:
        raise click.ClickException(
            f"{source}: under the starting camera only {candidates.size} frame(s) show a printed "
            "trace: give a starting --offset-mm (or --camera) closer to the machine's, and the "
            "right --start-offset"
        )
    chosen = set(candidates[np.linspace(0, candidates.size - 1, n_frames).round().astype(int)])
    picked = []
    with frames.prefetched() as decoded:
        for index, video_time, gray in decoded:
            if index in chosen:
                picked.append((start_offset_s + video_time, gray))
            if len(picked) == len(chosen):
                break
    try:
        result = calibrate_camera(
            job,
            picked,
            start,
            reach_um=settings.reach_um,
            gate_um=gate_um,
            search=search,
            clean=windows.usable,
        )
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
    from ajtwin.vision.camera import CameraFileError, load_camera

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
