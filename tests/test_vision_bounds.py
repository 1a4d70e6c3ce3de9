"""Camera files and extraction options out of scale: each refused with the bound and why,
or read right — no traceback, no run out of memory, no reading from an impossible geometry.

Extraction holds only what the video can show: the program cut at the last frame (exactly
the same readings as the whole program gives for those frames), its windows bounded."""

from __future__ import annotations

import time

import numpy as np
import pytest

from ajtwin.job import read_program_text
from ajtwin.vision.calibrate import CalibrationError, calibrate_camera
from ajtwin.vision.camera import Camera, CameraFileError, load_camera
from ajtwin.vision.extract import VisionInputError
from ajtwin.vision.part_extract import PartExtractor, PartSettings
from ajtwin.vision.part_render import PartRenderer, PrintTruth
from ajtwin.vision.part_video import check_window_count
from part_programs import serpentine, stroke

CAMERA = "[camera]\num_per_px = 0.75\nrotation_deg = {}\noffset_mm = [0.1, -0.25]\n" + (
    "width_px = 640\nheight_px = 480\n"
)
SMALL = Camera(um_per_px=0.75, offset_mm=(0.0, -0.35), width_px=480, height_px=360)


def test_a_camera_file_with_a_byte_order_mark_reads_as_without(tmp_path):
    plain, marked = tmp_path / "a.toml", tmp_path / "b.toml"
    plain.write_text(CAMERA.format(12.5), encoding="utf-8")
    marked.write_text("\ufeff" + CAMERA.format(12.5), encoding="utf-8")
    assert load_camera(marked) == load_camera(plain)


@pytest.mark.parametrize("bomb", ["x = " + "[" * 100_000, "x = " + "{a = " * 50_000])
def test_a_toml_bomb_is_refused_not_a_recursion_error(tmp_path, bomb):
    path = tmp_path / "bomb.toml"
    path.write_text(CAMERA.format(0) + bomb)
    with pytest.raises(CameraFileError, match="nested too deeply to read"):
        load_camera(path)


def test_a_rotation_beyond_one_turn_is_refused(tmp_path):
    """1e300° read a 111-µm line from a 43-µm trace."""
    path = tmp_path / "c.toml"
    path.write_text(CAMERA.format("1e300"))
    with pytest.raises(CameraFileError, match="1e.300° is not a camera's angle"):
        load_camera(path)
    path.write_text(CAMERA.format(-359.5))
    assert load_camera(path).rotation_deg == -359.5


def test_a_reach_beyond_the_frame_is_refused_before_any_array():
    """--reach-um 1e9 asked 19.9 GiB."""
    job = read_program_text(stroke(0, 0, 1, 0))
    with pytest.raises(VisionInputError, match=r"more than the camera's frame shows .* 225 µm"):
        PartExtractor(job, SMALL, PartSettings.from_defaults(reach_um=1e9))
    PartExtractor(job, SMALL, PartSettings.from_defaults(reach_um=200.0))


def test_a_calibration_gate_wider_than_the_part_is_refused():
    """--gate-um 1e9 asked 2.22 PiB of the trace index."""
    job = read_program_text(stroke(0, 0, 3, 0) + stroke(1.5, -1.5, 1.5, 1.5))
    with pytest.raises(CalibrationError, match="wider than the whole printed part .4243 µm"):
        calibrate_camera(job, [], SMALL, gate_um=1e9)


def test_a_search_radius_wider_than_the_part_asks_each_cell_once():
    job = read_program_text(serpentine(0.0, 0.0, 6, 1.0, 0.05))
    x, y = np.array([0.3, 40.0, -7.0]), np.array([0.5, 3.0, 0.2])
    wide = job.locate(x, y, radius_mm=100.0)  # wider than every distance here
    started = time.perf_counter()
    huge = job.locate(x, y, radius_mm=1e6)  # cells the size of the radius: 2.5e15 of them
    assert time.perf_counter() - started < 30.0
    assert huge.found.all()
    np.testing.assert_array_equal(huge.segment, wide.segment)
    np.testing.assert_array_equal(huge.distance_mm, wide.distance_mm)


def test_extraction_from_the_program_cut_at_the_last_frame_is_that_of_the_whole_program():
    """What `extract --job` does for a short video of a long (looped) print: the readings,
    skips and statuses of every frame are those the whole program gives."""
    one = read_program_text(serpentine(0.0, 0.0, 3, 1.0, 0.01935), process_speed_mm_s=2.0)
    job = one.repeat(4 * one.duration_s)  # printed over itself: later runs overprint
    last = 1.6 * one.duration_s
    times = np.linspace(0.3, last, 9)
    renderer = PartRenderer(job, SMALL, PrintTruth.constant(job.duration_s, 43.0, 29.0), seed=3)
    whole, cut = PartExtractor(job, SMALL), PartExtractor(job.until(last), SMALL)
    assert cut.windows.n < whole.windows.n
    readings = 0
    for t in times:
        frame = renderer.frame(t)
        a, b = whole.process(frame, time_s=t), cut.process(frame, time_s=t)
        assert (a.status, a.skipped, a.failed) == (b.status, b.skipped, b.failed)
        for name, values in a.readings.items():
            np.testing.assert_array_equal(values, b.readings[name])
        readings += a.n_readings
    assert readings > 0


def test_more_windows_than_the_bound_are_refused_before_they_are_built():
    job = read_program_text(stroke(0, 0, 3, 0))  # 3 mm: 80 windows of 37.5 µm
    settings = PartSettings.from_defaults()
    check_window_count(job, SMALL, settings, "v.avi", "p.prg", limit=80)
    with pytest.raises(VisionInputError, match="80 measurement windows .* more than the 79"):
        check_window_count(job, SMALL, settings, "v.avi", "p.prg", limit=79)


@pytest.mark.slow
def test_extract_on_a_24h_loop_holds_only_what_its_video_shows(tmp_path):
    """The public 1-nafbot looped to 24 h under a 1-s video: `extract --job --repeat-to 86400`
    ran out of memory at 6 GB; now it gives the readings of the program unlooped, in bounded
    memory (run as its own process, its peak RSS read back)."""
    import resource
    import subprocess
    import sys
    from pathlib import Path

    ajtwin = str(Path(sys.executable).parent / "ajtwin")
    program = Path(__file__).resolve().parent / "data" / "prg" / "prg2svg" / "1-nafbot.prg"
    camera = tmp_path / "camera.toml"
    camera.write_text(CAMERA.format(0.0))
    video = tmp_path / "v.avi"
    common = ["--job", str(program), "--camera", str(camera)]
    subprocess.run(
        [ajtwin, "render", *common, "--fps", "5", "--start", "30", "--duration", "1",
         "--out", str(video)],
        check=True, capture_output=True,
    )  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    for name, loop in (("once.csv", []), ("day.csv", ["--repeat-to", "86400"])):
        subprocess.run(
            [ajtwin, "extract", str(video), *common, "--start-offset", "30", "--no-progress",
             *loop, "--out", str(tmp_path / name)],
            check=True, capture_output=True,
        )  # fmt: skip
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    once = (tmp_path / "once.csv").read_text()
    assert once.count("\n") > 5 and once == (tmp_path / "day.csv").read_text()
    assert max(peak_kb, before) < 2_000_000  # kB: the whole loop's windows took over 6 GB
