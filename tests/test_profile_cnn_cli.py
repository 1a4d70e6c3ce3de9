"""``ajtwin cnn``: synthetic data, train/resume, infer Q_m from video, --join."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.io.records import PrintRecord, read_record, write_record
from ajtwin.profile_cnn.data import load_dataset, register_profile
from ajtwin.profile_cnn.infer import infer_video
from ajtwin.profile_cnn.model import ProfileModel
from ajtwin.profile_cnn.network import NetworkConfig, ResNet18Profile
from ajtwin.vision.profile import line_profile
from ajtwin.vision.render import RenderSettings, render_video

R = np.arange(-150.0, 150.0, 0.05)
PX = 0.75


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return result


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """4 frames at 2 fps; the line's area steps from 12 to 20 µm² at t = 1 s."""
    folder = tmp_path_factory.mktemp("cnnvid")
    profiles = [line_profile(R, 40.0, 25.0, 12.0), line_profile(R, 46.0, 28.0, 20.0)]
    path = folder / "line.avi"
    render_video(
        R,
        profiles,
        [0.0, 1.0],
        path,
        fps=2.0,
        duration_s=2.0,
        shape=(320, 400),
        settings=RenderSettings.from_defaults(tilt_deg=2.0, raggedness_um=0.3),
        seed=3,
        progress=False,
    )
    return path, profiles


class _Oracle(torch.nn.Module):
    """Test double: a 'network' that returns a fixed profile (scaled units)."""

    def __init__(self, profile_um, scale):
        super().__init__()
        self.config = NetworkConfig(base_channels=8)
        self.register_buffer("profile", torch.tensor(profile_um / scale, dtype=torch.float32))

    def forward(self, x):
        return self.profile.expand(x.shape[0], -1)


def test_infer_video_integrates_the_predicted_profile(video):
    path, profiles = video
    truth = register_profile(profiles[0], 0.05, PX, level=False)
    model = ProfileModel(_Oracle(truth, 0.4), PX, 0.4)
    table = infer_video(path, model, um_per_px=PX, platen_speed_mm_s=2.0, progress=False)
    assert list(table.columns[:3]) == ["frame", "time_s", "material_flow_mL_s"]
    assert table["frame"].tolist() == [0, 1, 2, 3]
    np.testing.assert_allclose(table["time_s"], [0.0, 0.5, 1.0, 1.5])
    assert (table["status"] == "ok").all() and (table["n_columns"] == 8).all()  # 400 px / 50
    # 12 µm² at 2 mm/s = 2.4e4 µm³/s = 2.4e-8 mL/s
    np.testing.assert_allclose(table["material_flow_mL_s"], 2.4e-8, rtol=1e-3)
    np.testing.assert_allclose(table["cross_section_um2"], 12.0, rtol=1e-3)


def test_infer_video_marks_frames_without_line(tmp_path):
    blank = tmp_path / "frames"
    blank.mkdir()
    import cv2

    cv2.imwrite(str(blank / "f0.png"), np.full((200, 300), 150, np.uint8))
    model = ProfileModel(ResNet18Profile(NetworkConfig(base_channels=8)), PX, 0.4)
    table = infer_video(blank, model, um_per_px=PX, platen_speed_mm_s=1.0, progress=False)
    assert table["status"].iloc[0] != "ok" and np.isnan(table["material_flow_mL_s"].iloc[0])


def test_cli_synth_train_resume_infer_join(video, tmp_path):
    path, _ = video
    data = tmp_path / "data"
    res = run("cnn", "synth", "--out-dir", data, "--n-pairs", 6, "--n-columns", 20, "--no-progress")
    assert res.exit_code == 0, res.output
    pairs = load_dataset(data / "pairs.npz")
    cols = load_dataset(data / "columns.npz")
    assert len(pairs) == 6 and pairs.profiles_um.shape == (6, 200)
    assert len(cols) == 20 and np.all(np.isfinite(cols.linewidth_um))
    # CV labels of the synthetic columns track the hidden truth
    assert np.mean(np.abs(cols.linewidth_um - cols.extra["true_linewidth_um"])) < 3.0

    model_path = tmp_path / "m.pt"
    args = [
        "cnn",
        "train",
        "--pairs",
        data / "pairs.npz",
        "--columns",
        data / "columns.npz",
        "--width",
        8,
        "--stage1-epochs",
        2,
        "--stage2-epochs",
        1,
        "--batch-size",
        4,
        "--out",
        model_path,
        "--no-progress",
    ]
    res = run(*args)
    assert res.exit_code == 0, res.output
    model = ProfileModel.load(model_path)
    assert model.meta["n_pairs"] == 6 and len(model.meta["history"]) == 3
    # resuming a finished run trains nothing more and reproduces the same model
    res = run(
        *args[:-3],
        "--out",
        tmp_path / "m2.pt",
        "--checkpoint",
        str(model_path) + ".ckpt",
        "--resume",
        "--no-progress",
    )
    assert res.exit_code == 0, res.output
    again = ProfileModel.load(tmp_path / "m2.pt")
    for a, b in zip(
        model.network.state_dict().values(), again.network.state_dict().values(), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=0, atol=0)

    res = run(
        "cnn",
        "score",
        "--model",
        model_path,
        "--pairs",
        data / "pairs.npz",
        "--columns",
        data / "columns.npz",
    )
    assert res.exit_code == 0, res.output
    scores = json.loads(res.output)
    assert scores["pairs"]["n_columns"] == 6 and "qm_rel_error" in scores["pairs"]
    assert "mae_linewidth_vs_cv_um" in scores["columns"]

    record = tmp_path / "print.parquet"
    t = np.arange(3.0)
    df = pd.DataFrame(
        {
            "time_s": t,
            "atomizer_current_mA": 375.0,
            "carrier_flow_sccm": 23.0,
            "sheath_flow_sccm": 50.0,
            "carrier_pressure_Pa": 5661.0,
            "sheath_pressure_Pa": 5641.0,
            "linewidth_um": 43.0,
            "overspray_um": 29.0,
            "material_flow_mL_s": np.nan,
        }
    )
    write_record(PrintRecord(df, {"platen_speed_mm_s": 1.0}), record)
    out = tmp_path / "qm.csv"
    res = run(
        "cnn",
        "infer",
        path,
        "--model",
        model_path,
        "--um-per-px",
        PX,
        "--platen-speed-mm-s",
        1.0,
        "--out",
        out,
        "--join",
        record,
        "--no-progress",
    )
    assert res.exit_code == 0, res.output
    table = pd.read_csv(out)
    assert list(table.columns[:3]) == ["frame", "time_s", "material_flow_mL_s"]
    assert len(table) == 4
    joined = read_record(tmp_path / "print_cnn.parquet")
    # frames at 0, 0.5 s -> second 0; 1.0, 1.5 s -> second 1; none in second 2
    qm = joined.data["material_flow_mL_s"].to_numpy()
    assert np.isfinite(qm[:2]).all() and np.isnan(qm[2])
    assert qm[0] == pytest.approx(table["material_flow_mL_s"][:2].mean(), rel=1e-6)
    assert joined.meta["profile_cnn"]["seconds_filled"] == 2
    assert (joined.data["linewidth_um"] == 43.0).all()


def test_cli_errors_are_clear(tmp_path):
    res = run("cnn", "train", "--out", tmp_path / "m.pt", "--no-progress")
    assert res.exit_code != 0 and "--synthetic" in res.output
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.ones(3))
    res = run("cnn", "train", "--pairs", bad, "--out", tmp_path / "m.pt", "--no-progress")
    assert res.exit_code != 0 and "needs 'columns'" in res.output
    (tmp_path / "junk.pt").write_bytes(b"junk")
    (tmp_path / "v.png").write_bytes(b"")
    res = run(
        "cnn",
        "infer",
        tmp_path / "v.png",
        "--model",
        tmp_path / "junk.pt",
        "--um-per-px",
        PX,
        "--platen-speed-mm-s",
        1.0,
        "--out",
        tmp_path / "q.csv",
    )
    assert res.exit_code != 0 and "junk.pt" in res.output


def test_cv_summary_merges_parts(tmp_path):
    part = {"k": 2, "config": {"seed": 0}, "folds": [{"fold": 0, "after_pairs": {"x": 1.0}}]}
    other = {"k": 2, "config": {"seed": 0}, "folds": [{"fold": 1, "after_pairs": {"x": 3.0}}]}
    (tmp_path / "a.json").write_text(json.dumps(part))
    (tmp_path / "b.json").write_text(json.dumps(other))
    res = run(
        "cnn", "cv-summary", tmp_path / "a.json", tmp_path / "b.json", "--out", tmp_path / "cv.json"
    )
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "cv.json").read_text())["summary"]
    assert s["after_pairs.x.mean"] == 2.0 and s["after_pairs.x.var"] == 1.0


def test_cli_columns_from_video(video, tmp_path):
    path, _ = video
    res = run(
        "cnn", "columns", path, "--um-per-px", PX, "--out", tmp_path / "c.npz", "--no-progress"
    )
    assert res.exit_code == 0, res.output
    data = load_dataset(tmp_path / "c.npz")
    assert data.columns.shape[1] == 200 and len(data) > 20
    assert set(np.unique(data.group)) <= {0, 1, 2, 3}
    # frames 0-1 show the 40 µm line, frames 2-3 the 46 µm one
    first = data.linewidth_um[data.group < 2].mean()
    second = data.linewidth_um[data.group >= 2].mean()
    assert first == pytest.approx(40.0, abs=2.5) and second == pytest.approx(46.0, abs=2.5)
