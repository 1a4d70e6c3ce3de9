"""``ajtwin render/extract --job --camera`` end to end, and their refusals of bad input."""

from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.io.records import PrintRecord, read_record, write_record
from ajtwin.job import read_program
from part_programs import job_print_table, park, path, stroke, travel

PART = (
    stroke(0, 0, 1.0, 0)
    + path(0.2, 0.3, ("line", 0.8, 0.3), ("line", 0.8, 0.6))
    + travel(0.8, 0.6, ("line", 0.8, 0.3), ("line", 0.2, 0.3))
    + travel(0.0, 0.0, ("line", 1.0, 0.0))
)
CAMERA = """[camera]
um_per_px = 0.75
rotation_deg = {rotation}
offset_mm = [0.0, 0.0]
width_px = 480
height_px = 360
"""


def _invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def part(tmp_path_factory):
    """A program, its camera file, a job print record and the rendered video."""
    folder = tmp_path_factory.mktemp("part")
    program = folder / "part.prg"
    program.write_text(PART)
    camera = folder / "camera.toml"
    camera.write_text(CAMERA.format(rotation=0.0))
    job = read_program(program)
    table = job_print_table(job, lambda t: 43.0 + 8.0 * (t % 2), 29.0)
    meta = {
        "scenario": "part test",
        "job": {
            "program": program.name,
            "sha256": hashlib.sha256(program.read_bytes()).hexdigest(),
            "process_speed_mm_s": 2.0,
            "rapid_speed_mm_s": 10.0,
        },
        "camera": {"mode": "at_nozzle", "offset_mm": [0.0, 0.0]},
    }
    record = write_record(PrintRecord(table, meta), folder / "print.parquet")
    video = folder / "cam.avi"
    result = _invoke(
        "render", record, "--job", program, "--camera", camera, "--fps", 5, "--out", video
    )
    assert result.exit_code == 0, result.output
    return {
        "folder": folder,
        "program": program,
        "camera": camera,
        "record": record,
        "video": video,
        "job": job,
    }


def test_render_writes_the_part_video_and_its_truth(part):
    capture = cv2.VideoCapture(str(part["video"]))
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    ok, frame = capture.read()
    capture.release()
    assert ok and frame.shape[:2] == (360, 480)
    assert count == int(np.floor(part["job"].duration_s * 5 + 1e-9))
    truth = json.loads(part["video"].with_suffix(".json").read_text())
    assert truth["camera"]["um_per_px"] == 0.75 and truth["fps"] == 5
    assert len(truth["seconds"]["linewidth_um"]) == len(truth["seconds"]["time_s"])


def test_extract_with_the_program_measures_against_truth_and_joins(part):
    folder = part["folder"]
    out = folder / "features.csv"
    joined = folder / "joined.parquet"
    result = _invoke(
        "extract",
        part["video"],
        "--job",
        part["program"],
        "--camera",
        part["camera"],
        "--out",
        out,
        "--annotate",
        folder / "annotated.avi",
        "--join",
        part["record"],
        "--join-out",
        joined,
        "--no-progress",
    )
    assert result.exit_code == 0, result.output
    readings = pd.read_csv(out)
    frames = pd.read_csv(out.with_name("features_frames.csv"))
    assert len(frames) == int(np.floor(part["job"].duration_s * 5 + 1e-9))
    assert frames["readings"].sum() == len(readings) > 20
    assert {"border", "stroke_end"} <= {
        c[5:] for c in frames if c.startswith("skip_") and frames[c].sum() > 0
    }
    truth = json.loads(part["video"].with_suffix(".json").read_text())["seconds"]
    second = np.floor(readings["print_time_s"]).astype(int)
    reference = np.asarray(truth["linewidth_um"])[second]
    # a reading attributed to the wrong second would be 8 µm off
    assert np.mean(np.abs(readings["linewidth_um"] - reference)) < 1.5
    assert (folder / "annotated.avi").stat().st_size > 0
    record = read_record(joined)
    data = record.data
    filled = data["printed_at_s"].notna()
    assert filled.sum() >= 2
    # a camera reading at t_k is of a trace printed by then (record format 2)
    assert (data.loc[filled, "printed_at_s"] <= data.loc[filled, "time_s"]).all()
    assert data["linewidth_um"].notna().sum() == filled.sum()
    assert record.meta["camera"] == {"mode": "at_nozzle", "offset_mm": [0.0, 0.0]}
    assert record.meta["vision"]["readings_used"] > 0
    assert "true_linewidth_um" in data  # the rest of the record is kept


def test_video_longer_than_the_job_is_refused(part, tmp_path):
    program = tmp_path / "short.prg"
    program.write_text(stroke(0, 0, 0.4, 0))  # 0.2 s: the video lasts several seconds
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(part["video"]),
            "--job",
            str(program),
            "--camera",
            str(part["camera"]),
            "--out",
            str(tmp_path / "f.csv"),
            "--no-progress",
        ],
    )
    assert result.exit_code == 1
    assert "the video does not belong to this program" in result.output
    assert "short.prg ends at 0.200 s" in result.output


def test_program_other_than_the_records_is_refused(part, tmp_path):
    other = tmp_path / "other.prg"
    other.write_text(PART + park(0, 0))
    result = CliRunner().invoke(
        main,
        [
            "render",
            str(part["record"]),
            "--job",
            str(other),
            "--camera",
            str(part["camera"]),
            "--out",
            str(tmp_path / "v.avi"),
        ],
    )
    assert result.exit_code == 1
    assert "is not the program this print ran" in result.output


def test_camera_file_with_zero_scale_is_refused(part, tmp_path):
    camera = tmp_path / "camera.toml"
    camera.write_text(CAMERA.format(rotation=0.0).replace("0.75", "0.0"))
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(part["video"]),
            "--job",
            str(part["program"]),
            "--camera",
            str(camera),
            "--out",
            str(tmp_path / "f.csv"),
        ],
    )
    assert result.exit_code == 1
    assert "um_per_px = 0" in result.output and "never calibrated" in result.output


def test_video_without_frames_is_refused(part, tmp_path):
    empty = tmp_path / "empty.avi"
    writer = cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"FFV1"), 5, (480, 360), False)
    writer.release()
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(empty),
            "--job",
            str(part["program"]),
            "--camera",
            str(part["camera"]),
            "--out",
            str(tmp_path / "f.csv"),
        ],
    )
    assert result.exit_code == 1
    assert "no decodable frame" in result.output or "empty file" in result.output


def test_job_without_camera_and_options_that_do_not_apply(part, tmp_path):
    base = ["extract", str(part["video"]), "--out", str(tmp_path / "f.csv")]
    result = CliRunner().invoke(main, [*base, "--job", str(part["program"])])
    assert result.exit_code == 2 and "--job needs --camera" in result.output
    result = CliRunner().invoke(
        main,
        [
            *base,
            "--job",
            str(part["program"]),
            "--camera",
            str(part["camera"]),
            "--um-per-px",
            "0.75",
        ],
    )
    assert result.exit_code == 2 and "--um-per-px cannot be used with --job" in result.output
    result = CliRunner().invoke(main, base)
    assert result.exit_code == 2 and "--um-per-px is required" in result.output


def test_camera_turned_by_90_degrees_exits_with_the_reason(part, tmp_path):
    # the video was taken with the camera turned by 90°; the camera file says 0°
    turned = tmp_path / "camera90.toml"
    turned.write_text(CAMERA.format(rotation=90.0).replace("360", "480"))
    flat = tmp_path / "camera0.toml"
    flat.write_text(CAMERA.format(rotation=0.0).replace("360", "480"))
    video = tmp_path / "turned.avi"
    assert (
        _invoke(
            "render",
            part["record"],
            "--job",
            part["program"],
            "--camera",
            turned,
            "--fps",
            5,
            "--out",
            video,
        ).exit_code
        == 0
    )
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(video),
            "--job",
            str(part["program"]),
            "--camera",
            str(flat),
            "--out",
            str(tmp_path / "f.csv"),
            "--no-progress",
        ],
    )
    assert result.exit_code == 1
    assert "not where the program and the camera file put them" in result.output
    assert pd.read_csv(tmp_path / "f.csv").empty


def test_a_job_print_of_the_virtual_printer_is_rendered_measured_and_joined(tmp_path):
    """The whole path on a print of ``ajtwin simulate --job`` (not a hand-made table): the
    render stops where the print cut the program, and the readings joined into the record
    match the record's own truth of the line printed in each second."""
    program = tmp_path / "part.prg"
    program.write_text(PART + park(0.5, 0.3, 3000))  # 5.5 s: the 4-s print cuts it
    camera = tmp_path / "camera.toml"
    camera.write_text(CAMERA.format(rotation=0.0))
    record = tmp_path / "print.parquet"
    result = _invoke(
        "simulate", "--job", program, "--camera", "at_nozzle", "--machine", "paper",
        "--duration-min", 4 / 60, "--seed", 2, "--out", record,
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    printed = read_record(record)
    assert printed.meta["job"]["repeat_to_s"] == 4.0
    video = tmp_path / "cam.avi"
    result = _invoke("render", record, "--job", program, "--camera", camera, "--fps", 5,
                     "--out", video)  # fmt: skip
    assert result.exit_code == 0, result.output
    capture = cv2.VideoCapture(str(video))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 4 * 5  # the print, not the program
    capture.release()
    out, joined = tmp_path / "readings.csv", tmp_path / "joined.parquet"
    result = _invoke(
        "extract", video, "--job", program, "--camera", camera, "--out", out,
        "--join", record, "--join-out", joined, "--no-progress",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    readings = pd.read_csv(out)
    assert len(readings) > 20
    truth = printed.data.set_index("time_s")["true_linewidth_um"]
    second = np.floor(readings["print_time_s"]).to_numpy()
    error = readings["linewidth_um"].to_numpy() - truth.loc[second].to_numpy()
    assert np.nanmean(np.abs(error)) < 1.5  # the render's +0.5 µm bias and the noise
    data = read_record(joined).data
    filled = data["printed_at_s"].notna()
    assert filled.sum() >= 2
    assert (data.loc[filled, "printed_at_s"] <= data.loc[filled, "time_s"]).all()
    rows = np.floor(data.loc[filled, "printed_at_s"]).to_numpy()
    joined_error = data.loc[filled, "linewidth_um"].to_numpy() - truth.loc[rows].to_numpy()
    assert np.max(np.abs(joined_error)) < 2.0


# -- a video of another program ---------------------------------------------------------
# A cross of two traces filmed by a camera trailing the second one, extracted with another
# program (an L and a Z) whose trace near the camera moves the same way: every window that
# program puts in view finds a line; only the rest of the frames (the cross's first trace, the
# L's corner that never comes) tells the programs apart.
CROSS = """#0
! a cross of two 3 mm traces, the second printed across the first
ptp/ev (X,Y),0,0,10
OUT0.0=1
ptp/e (X,Y),3,0
OUT0.0=0
ptp/ev (X,Y),1.5,-1.5,10
OUT0.0=1
ptp/e (X,Y),1.5,1.5
OUT0.0=0
STOP
"""
L_AND_Z = """#0
! two directions for the camera: an L and a Z, 2 mm/s
gDblRapidSpeed = 10
ptp/ev (X,Y),0,0,gDblRapidSpeed
OUT0.0=1
wait 2
MSEG (X,Y),0,0
line (X,Y),3,0
line (X,Y),3,3
line (X,Y),0,3
ENDS (X,Y)
till (^X_AST.#MOVE) & (^Y_AST.#MOVE)
OUT0.0=0
wait 2
ptp/ev (X,Y),0,1,gDblRapidSpeed
OUT0.0=1
wait 2
ptp/e (X,Y),2,1
ptp/e (X,Y),2,2
till (^X_AST.#MOVE) & (^Y_AST.#MOVE)
OUT0.0=0
STOP
"""
# 640 x 480 px at 0.75 µm/px, trailing 0.25 mm behind a nozzle printing towards +y
CROSS_CAMERA = """[camera]
um_per_px = 0.75
rotation_deg = 0.0
offset_mm = [0.1, -0.25]
width_px = 640
height_px = 480
"""


@pytest.fixture(scope="module")
def cross(tmp_path_factory):
    """The cross's video: 18 frames at 20 frames/s from job time 2.3 s (the second trace)."""
    folder = tmp_path_factory.mktemp("cross")
    (folder / "cross.prg").write_text(CROSS)
    (folder / "cal.prg").write_text(L_AND_Z)
    (folder / "camx.toml").write_text(CROSS_CAMERA)
    video = folder / "vx.avi"
    result = _invoke("render", "--job", folder / "cross.prg", "--camera", folder / "camx.toml",
                     "--fps", 20, "--duration", 0.9, "--start", 2.3, "--out", video)  # fmt: skip
    assert result.exit_code == 0, result.output
    return folder


def _extract(folder, program, out, *options, start_offset=2.3):
    return _invoke("extract", folder / "vx.avi", "--job", folder / program, "--camera",
                   folder / "camx.toml", "--start-offset", start_offset, "--out", out,
                   "--no-progress", *options)  # fmt: skip


def test_a_video_of_another_program_is_refused_and_nothing_is_written(cross, tmp_path):
    out = tmp_path / "f.csv"
    out.write_text("an earlier table\n")
    result = _extract(cross, "cal.prg", out)
    assert result.exit_code == 1, result.output
    message = " ".join(result.output.split())
    assert "does not show what cal.prg prints" in message
    # the cross's first trace, seen across frames 4-7, lies where cal.prg prints nothing
    assert "frames 4–7, job time 2.50–2.65 s" in message
    assert "at 0°" in message
    # the L's corner never comes: its next leg is not where cal.prg prints it
    assert "show no line where it prints one" in message
    assert "--start-offset" in message and "--job" in message
    assert out.read_text() == "an earlier table\n"  # left as it was
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.csv"]


@pytest.mark.parametrize(
    ("start_offset", "readings"),
    [(2.3, 147), (2.2, 137), (2.4, 135)],  # the clock right, 0.1 s early, 0.1 s late
)
def test_the_program_the_video_was_filmed_over_is_read_without_a_word(
    cross, tmp_path, start_offset, readings
):
    out = tmp_path / "g.csv"
    result = _extract(cross, "cross.prg", out, start_offset=start_offset)
    assert result.exit_code == 0, result.output
    assert "warning" not in result.output
    assert f"{readings} readings from 18 frames" in result.output
    frames = pd.read_csv(tmp_path / "g_frames.csv")
    assert frames["foreign_line_um"].tolist() == [0.0] * 18


def test_a_clock_off_by_more_than_a_tenth_of_a_second_is_refused(cross, tmp_path):
    # 0.2 s early: the first trace, crossed in frames 4-7, is 400 µm from where it is seen
    result = _extract(cross, "cross.prg", tmp_path / "h.csv", start_offset=2.1)
    assert result.exit_code == 1, result.output
    message = " ".join(result.output.split())
    assert "does not show what cross.prg prints" in message and "frames 4–7" in message
    assert "--start-offset is wrong" in message
    assert not (tmp_path / "h.csv").exists()


def test_a_program_without_the_trace_the_video_crosses_warns_unless_it_is_a_mark(cross, tmp_path):
    # the cross's first stroke moved over without the shutter: only its second is printed
    program = cross / "second_only.prg"
    program.write_text(CROSS.replace("OUT0.0=1\nptp/e (X,Y),3,0\n", "ptp/e (X,Y),3,0\n", 1))
    result = _extract(cross, "second_only.prg", tmp_path / "h.csv")
    assert result.exit_code == 0, result.output
    message = " ".join(result.stderr.split())
    assert message.startswith("warning: ")
    assert "may not show what second_only.prg prints" in message
    assert "4 show a line where second_only.prg prints nothing (frames 4–7" in message
    assert pd.read_csv(tmp_path / "h.csv").shape[0] > 100
    # the line given as a mark on the substrate: no word (and no reading near it)
    result = _extract(cross, "second_only.prg", tmp_path / "h.csv", "--fiducial", "1.6,0,0.4")
    assert result.exit_code == 0, result.output
    assert "warning" not in result.output and "fiducial 85" in result.output


def test_a_loop_beyond_the_record_limit_is_refused_before_the_video_is_read(cross, tmp_path):
    out = tmp_path / "f.csv"
    result = _extract(cross, "cross.prg", out, "--repeat-to", "1e12")
    assert result.exit_code != 0
    assert "a loop of 1e+12 s is longer than the 14 days a print record may last" in result.output
    assert not list(tmp_path.iterdir())
