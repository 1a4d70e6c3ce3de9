"""``ajtwin render`` / ``ajtwin extract``: files, streaming, bad inputs, --join."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.io.records import PrintRecord, read_record, write_record
from ajtwin.vision import extract as extract_module
from ajtwin.vision.join import frame_print_times, join_features
from ajtwin.vision.profile import line_profile
from ajtwin.vision.render import RenderSettings, render_frame, render_video

R = np.arange(-160.0, 160.0, 0.05)


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return result


def _record(n=6, linewidth=None, overspray=None):
    t = np.arange(float(n))
    df = pd.DataFrame(
        {
            "time_s": t,
            "atomizer_current_mA": 375.0,
            "carrier_flow_sccm": 23.0,
            "sheath_flow_sccm": 50.0,
            "carrier_pressure_Pa": 5661.0,
            "sheath_pressure_Pa": 5641.0,
            "linewidth_um": np.linspace(40, 50, n) if linewidth is None else linewidth,
            "overspray_um": np.linspace(25, 35, n) if overspray is None else overspray,
            "material_flow_mL_s": 1.5e-8,
        }
    )
    return PrintRecord(df, {"platen_speed_mm_s": 1.0, "scenario": "test"})


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """A 6-frame lossless video at 2 fps of a line whose width steps at t = 1.5 s."""
    folder = tmp_path_factory.mktemp("vid")
    profiles = [line_profile(R, 40.0, 25.0, 12.0), line_profile(R, 50.0, 32.0, 20.0)]
    path = folder / "line.avi"
    truth = render_video(
        R,
        profiles,
        [0.0, 1.5],
        path,
        fps=2.0,
        duration_s=3.0,
        shape=(360, 480),
        settings=RenderSettings.from_defaults(tilt_deg=4.0, raggedness_um=0.5),
        seed=1,
        progress=False,
    )
    return path, json.loads(truth.read_text())


def test_render_video_truth_json(video):
    path, truth = video
    assert truth["n_frames"] == 6 and truth["fps"] == 2.0 and truth["um_per_px"] == 0.75
    assert truth["platen_speed_mm_s"] == 1.0
    assert [f["profile"] for f in truth["frames"]] == [0, 0, 0, 1, 1, 1]
    assert truth["profiles"][1]["linewidth_um"] == pytest.approx(50.0, abs=0.1)
    assert truth["profiles"][1]["area_um2"] == pytest.approx(20.0, rel=1e-3)
    capture = cv2.VideoCapture(str(path))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 6
    capture.release()


def test_extract_video_against_truth(video, tmp_path):
    path, truth = video
    out = tmp_path / "f.csv"
    result = run(
        "extract",
        path,
        "--um-per-px",
        0.75,
        "--out",
        out,
        "--per-batch",
        "--annotate",
        tmp_path / "ann.mp4",
        "--no-progress",
    )
    assert result.exit_code == 0, result.output
    table = pd.read_csv(out)
    assert list(table.columns) == [
        "frame",
        "time_s",
        "linewidth_um",
        "overspray_um",
        "linewidth_std_um",
        "overspray_std_um",
        "n_batches",
        "status",
    ]
    assert (table["status"] == "ok").all()
    np.testing.assert_allclose(table["time_s"], np.arange(6) / 2.0)
    true_lw = np.array([f["linewidth_um"] for f in truth["frames"]])
    true_ov = np.array([f["overspray_um"] for f in truth["frames"]])
    assert np.abs(table["linewidth_um"] - true_lw).max() <= 1.0
    assert np.abs(table["overspray_um"] - true_ov).max() <= 3.0
    batches = pd.read_csv(tmp_path / "f_batches.csv")
    assert len(batches) == 6 * (480 // 50)
    annotated = cv2.VideoCapture(str(tmp_path / "ann.mp4"))
    ok, frame = annotated.read()
    annotated.release()
    assert ok and frame.shape == (360, 480, 3)


def test_extract_reads_image_folder_png_and_16bit_tiff(tmp_path):
    h = line_profile(R, 43.0, 29.0, 15.0)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(3):
        frame = render_frame(R, h, (300, 400), rng=np.random.default_rng(k))
        cv2.imwrite(str(folder / f"f{k:02d}.png"), frame)
    cv2.imwrite(str(tmp_path / "one.tif"), frame.astype(np.uint16) * 257)
    out = tmp_path / "folder.csv"
    assert (
        run(
            "extract", folder, "--um-per-px", 0.75, "--out", out, "--fps", 4, "--no-progress"
        ).exit_code
        == 0
    )
    table = pd.read_csv(out)
    assert len(table) == 3 and (table["status"] == "ok").all()
    np.testing.assert_allclose(table["time_s"], [0.0, 0.25, 0.5])
    single = tmp_path / "single.csv"
    assert (
        run(
            "extract", tmp_path / "one.tif", "--um-per-px", 0.75, "--out", single, "--no-progress"
        ).exit_code
        == 0
    )
    assert abs(pd.read_csv(single)["linewidth_um"][0] - 43.0) < 1.5


def test_frames_are_streamed(video, monkeypatch):
    """Reading the first frame must not decode the whole video."""
    path, _ = video
    reads = []
    original = cv2.VideoCapture

    class Counting:
        def __init__(self, *a):
            self._c = original(*a)

        def read(self):
            reads.append(1)
            return self._c.read()

        def __getattr__(self, name):
            return getattr(self._c, name)

    source = extract_module.open_source(path)
    monkeypatch.setattr(extract_module.cv2, "VideoCapture", Counting)
    first = next(iter(source))
    assert first[0] == 0 and len(reads) == 1


@pytest.mark.parametrize(
    "content,message",
    [(b"", "empty file"), (b"\x00garbage" * 100, "cannot open|no decodable frame")],
)
def test_extract_bad_video(tmp_path, content, message):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(content)
    result = CliRunner().invoke(
        main, ["extract", str(bad), "--um-per-px", "0.75", "--out", str(tmp_path / "x.csv")]
    )
    assert result.exit_code != 0
    assert "bad.mp4" in result.output
    assert pytest.importorskip("re").search(message, result.output)


def test_extract_missing_and_unknown_inputs(tmp_path):
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(tmp_path / "nope.mp4"),
            "--um-per-px",
            "1",
            "--out",
            str(tmp_path / "x.csv"),
        ],
    )
    assert result.exit_code != 0 and "no such file" in result.output
    (tmp_path / "notes.txt").write_text("hi")
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(tmp_path / "notes.txt"),
            "--um-per-px",
            "1",
            "--out",
            str(tmp_path / "x.csv"),
        ],
    )
    assert result.exit_code != 0 and "unknown input type" in result.output
    empty = tmp_path / "empty"
    empty.mkdir()
    result = CliRunner().invoke(
        main, ["extract", str(empty), "--um-per-px", "1", "--out", str(tmp_path / "x.csv")]
    )
    assert result.exit_code != 0 and "holds no images" in result.output
    result = CliRunner().invoke(
        main, ["extract", str(empty), "--um-per-px", "-2", "--out", str(tmp_path / "x.csv")]
    )
    assert result.exit_code != 0


def test_extract_all_dark_video_is_an_error(tmp_path):
    path = tmp_path / "dark.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 5, (320, 240), False)
    for _ in range(4):
        writer.write(np.zeros((240, 320), np.uint8))
    writer.release()
    out = tmp_path / "dark.csv"
    result = CliRunner().invoke(
        main, ["extract", str(path), "--um-per-px", "0.75", "--out", str(out), "--no-progress"]
    )
    assert result.exit_code != 0
    assert "dark_frame (4 frames)" in result.output and "lighting" in result.output
    assert (pd.read_csv(out)["status"] == "dark_frame").all()  # the CSV is still written


def test_extract_line_wider_than_frame_is_an_error(tmp_path):
    h = line_profile(R, 43.0, 29.0, 15.0)
    frame = render_frame(
        R, h, (240, 320), RenderSettings.from_defaults(um_per_px=0.12), rng=np.random.default_rng(0)
    )
    cv2.imwrite(str(tmp_path / "wide.png"), frame)
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(tmp_path / "wide.png"),
            "--um-per-px",
            "0.12",
            "--out",
            str(tmp_path / "w.csv"),
        ],
    )
    assert result.exit_code != 0 and "--um-per-px" in result.output


def test_extract_implausible_pixel_size_is_an_error(tmp_path):
    h = line_profile(R, 43.0, 29.0, 15.0)
    cv2.imwrite(
        str(tmp_path / "f.png"), render_frame(R, h, (300, 400), rng=np.random.default_rng(0))
    )
    result = CliRunner().invoke(
        main,
        [
            "extract",
            str(tmp_path / "f.png"),
            "--um-per-px",
            "0.0005",
            "--out",
            str(tmp_path / "f.csv"),
        ],
    )
    assert result.exit_code != 0 and "check the pixel size" in result.output


# ---------------------------------------------------------------- join
def test_frame_print_times_hand_computed():
    # 500 µm behind the nozzle at 2 mm/s -> the line seen was printed 0.25 s earlier
    times = frame_print_times(
        [0.0, 1.0], start_offset_s=5.0, camera_offset_um=500.0, platen_speed_mm_s=2.0
    )
    np.testing.assert_allclose(times, [4.75, 5.75])
    with pytest.raises(ValueError):
        frame_print_times([0.0], platen_speed_mm_s=0.0)


def test_join_features_bins_frames_by_second():
    record = _record(6).data
    features = pd.DataFrame(
        {
            "time_s": [0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 9.0],
            "linewidth_um": [40.0, 42.0, 44.0, 46.0, 48.0, np.nan, 99.0],
            "overspray_um": [20.0, 22.0, 24.0, 26.0, 28.0, 30.0, 99.0],
            "status": ["ok", "ok", "ok", "ok", "no_line", "ok", "ok"],
        }
    )
    joined, summary = join_features(record, features, start_offset_s=2.0)
    # print times 2.0, 2.5, 3.0, 3.5, (4.0 not ok), 4.5 (NaN linewidth), 11.0 (outside)
    # second 2: [2, 3) -> 2.0, 2.5 ; second 3: 3.0, 3.5 ; second 4: 4.5 (overspray only)
    np.testing.assert_allclose(joined["linewidth_um"], [np.nan, np.nan, 41.0, 45.0, np.nan, np.nan])
    np.testing.assert_allclose(joined["overspray_um"], [np.nan, np.nan, 21.0, 25.0, 30.0, np.nan])
    assert summary["frames_outside_record"] == 1 and summary["frames_not_ok"] == 1
    assert joined["carrier_flow_sccm"].eq(23.0).all()  # everything else kept


def test_render_from_record_then_extract_and_join(tmp_path):
    record_path = write_record(_record(4), tmp_path / "print.parquet")
    video = tmp_path / "print.avi"
    # raggedness 0.5 µm: the paper's batch averaging widens ragged lines
    # (docs/howto/measure-lines-from-video.md)
    result = run(
        "render",
        record_path,
        "--out",
        video,
        "--fps",
        2,
        "--size",
        "480x360",
        "--tilt",
        -6,
        "--raggedness",
        0.5,
    )
    assert result.exit_code == 0, result.output
    truth = json.loads((tmp_path / "print.json").read_text())
    wanted = np.linspace(40, 50, 4)
    got = [p["linewidth_um"] for p in truth["profiles"]]
    np.testing.assert_allclose(got, wanted, atol=0.1)
    np.testing.assert_allclose([p["area_um2"] for p in truth["profiles"]], 15.0, rtol=1e-3)
    joined_path = tmp_path / "joined.parquet"
    result = run(
        "extract",
        video,
        "--um-per-px",
        0.75,
        "--out",
        tmp_path / "f.csv",
        "--join",
        record_path,
        "--join-out",
        joined_path,
        "--no-progress",
    )
    assert result.exit_code == 0, result.output
    joined = read_record(joined_path)
    assert np.abs(joined.data["linewidth_um"].to_numpy() - wanted).max() <= 1.0
    assert joined.meta["vision"]["seconds_filled"] == 4
    assert read_record(record_path).data["linewidth_um"].tolist() == pytest.approx(wanted)
