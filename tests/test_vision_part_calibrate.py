"""``ajtwin camera calibrate``: the camera's geometry recovered from frames of known strokes."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.job import read_program_text
from ajtwin.vision.calibrate import CalibrationError, calibrate_camera
from ajtwin.vision.camera import Camera, load_camera
from ajtwin.vision.part_extract import PartSettings, Windows
from ajtwin.vision.part_render import PartRenderer, PrintTruth, render_part_video
from part_programs import path, stroke, travel

# an L, a straight stroke, and an inspection pass over both: traces in two directions
PART = (
    stroke(0, 0, 1.0, 0)
    + path(0.2, 0.3, ("line", 0.8, 0.3), ("line", 0.8, 0.6))
    + travel(0.8, 0.6, ("line", 0.8, 0.3), ("line", 0.2, 0.3))
    + travel(0.0, 0.0, ("line", 1.0, 0.0))
)


def _frames(job, camera, count, seed):
    renderer = PartRenderer(job, camera, PrintTruth.constant(job.duration_s, 43.0, 29.0), seed=seed)
    times = np.linspace(0.3, job.duration_s - 0.1, count)
    return [(t, renderer.frame(t)) for t in times]


@pytest.mark.parametrize("rotation, seed", [(12.0, 1), (93.0, 2)])
def test_calibration_recovers_a_known_rotation_and_scale_within_its_standard_errors(rotation, seed):
    job = read_program_text(PART, process_speed_mm_s=2.0)
    true = Camera(
        um_per_px=0.8, rotation_deg=rotation, offset_mm=(0.02, -0.015), width_px=640, height_px=480
    )
    # the camera file's nominal values: 0.75 µm/px, not turned (a camera mounted at 90°
    # is found by the search)
    start = Camera(um_per_px=0.75, rotation_deg=0.0, width_px=640, height_px=480)
    windows = Windows(job, start, PartSettings.from_defaults())
    result = calibrate_camera(job, _frames(job, true, 10, seed), start, clean=windows.usable)
    cam = result.camera
    assert abs(cam.um_per_px - 0.8) < 3 * cam.um_per_px_se
    assert abs(cam.rotation_deg - rotation) < 3 * cam.rotation_deg_se
    for fitted, known, se in zip(cam.offset_mm, true.offset_mm, cam.offset_mm_se, strict=True):
        assert abs(fitted - known) < 3 * se
    # and the standard errors are small enough to be useful
    assert cam.um_per_px_se / cam.um_per_px < 0.005
    assert cam.rotation_deg_se < 0.2
    assert max(cam.offset_mm_se) < 2e-3
    assert result.residual_um < 2.0


def test_calibration_is_refused_when_the_traces_run_in_one_direction_only():
    # frames that only ever see one straight stroke along X: the offset along X and the
    # pixel size cannot be told apart from nothing
    job = read_program_text(
        stroke(0, 0, 1.5, 0) + travel(1.5, 0, ("line", 0, 0)), process_speed_mm_s=2.0
    )
    true = Camera(um_per_px=0.75, rotation_deg=3.0, width_px=480, height_px=360)
    start = Camera(um_per_px=0.75, width_px=480, height_px=360)
    frames = [(t, f) for t, f in _frames(job, true, 8, 3) if t > 0.8]
    with pytest.raises(CalibrationError, match="cannot determine the camera's") as info:
        calibrate_camera(job, frames, start, search=False)
    assert "offset x" in str(info.value)


def test_calibration_is_refused_when_no_line_is_near_a_trace():
    job = read_program_text(PART, process_speed_mm_s=2.0)
    true = Camera(um_per_px=0.75, width_px=480, height_px=360)
    start = Camera(um_per_px=0.75, offset_mm=(3.0, 3.0), width_px=480, height_px=360)
    with pytest.raises(CalibrationError, match="no line point lies within 60 µm"):
        calibrate_camera(job, _frames(job, true, 4, 4), start)


def test_calibrate_command_writes_a_camera_file_that_extract_uses(tmp_path):
    program = tmp_path / "part.prg"
    program.write_text(PART)
    job = read_program_text(PART, process_speed_mm_s=2.0)
    true = Camera(
        um_per_px=0.78, rotation_deg=-7.0, offset_mm=(0.01, 0.0), width_px=640, height_px=480
    )
    video = tmp_path / "cal.avi"
    render_part_video(
        job,
        true,
        PrintTruth.constant(job.duration_s, 43.0, 29.0),
        video,
        fps=5,
        seed=5,
        progress=False,
    )
    out = tmp_path / "camera.toml"
    result = CliRunner().invoke(
        main,
        [
            "camera",
            "calibrate",
            str(video),
            "--job",
            str(program),
            "--um-per-px",
            "0.75",
            "--offset-mm",
            "0,0",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    cam = load_camera(out)
    assert abs(cam.rotation_deg + 7.0) < 3 * cam.rotation_deg_se
    assert cam.calibration["video"] == "cal.avi" and cam.calibration["points"] > 30
    features = tmp_path / "f.csv"
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(video),
            "--job",
            str(program),
            "--camera",
            str(out),
            "--out",
            str(features),
            "--no-progress",
        ],
    )
    assert result.exit_code == 0, result.output
    # a starting offset far from the machine's is refused with the reason
    result = CliRunner().invoke(
        main,
        [
            "camera",
            "calibrate",
            str(video),
            "--job",
            str(program),
            "--um-per-px",
            "0.75",
            "--offset-mm",
            "5,5",
            "--out",
            str(tmp_path / "bad.toml"),
        ],
    )
    assert result.exit_code == 1 and "closer to the machine's" in result.output
