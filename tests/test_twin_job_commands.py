"""A job print as a user meets it: parts side by side, `ajtwin estimate`, the live engine."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.engine.fleet import LiveEngine
from ajtwin.engine.messages import StepMessage
from ajtwin.estimation.print_time import camera_horizon_s, print_context, program_for_record
from ajtwin.estimation.samples import Sample
from ajtwin.io.records import write_record
from ajtwin.job import read_program
from ajtwin.simulation.job_print import CameraSettings, JobSettings, run_job_print

ROOT = Path(__file__).resolve().parent.parent
PRG = ROOT / "tests" / "data" / "prg" / "prg2svg"
NAFBOT = PRG / "1-nafbot.prg"  # 30 strokes on a 30.5 x 8.5 mm part, 166 s at 2 mm/s


def test_a_looped_job_side_by_side_is_an_array_of_parts_inside_the_stage():
    job = read_program(NAFBOT)
    over = job.repeat(1200.0)
    side = job.repeat(1200.0, pitch_mm=(35.0, 10.0))
    assert side.repetitions == over.repetitions == 8
    # run k is the program moved by its place; columns fill X first (300 mm: 8 of 35 mm)
    np.testing.assert_allclose(side.repetition_offsets_mm[:3], [[0, 0], [35, 0], [70, 0]])
    t = np.linspace(0.0, job.duration_s, 50, endpoint=False)
    for k in (1, 5):
        a, b = job.state_at(t), side.state_at(t + side.repetition_offsets_s[k])
        np.testing.assert_allclose(b.x_mm - a.x_mm, side.repetition_offsets_mm[k, 0], atol=1e-9)
        np.testing.assert_allclose(b.y_mm, a.y_mm, atol=1e-9)
        assert (a.shutter_open == b.shutter_open).all()
    # between runs: the move from the program's end to the next part's start, at 10 mm/s
    seg = job.segments
    end, start = (seg["x1_mm"][-1], seg["y1_mm"][-1]), (seg["x0_mm"][0], seg["y0_mm"][0])
    move = np.hypot(start[0] + 35.0 - end[0], start[1] - end[1]) / 10.0
    assert side.repetition_offsets_s[1] == pytest.approx(job.duration_s + move, rel=1e-12)
    back = np.hypot(start[0] - end[0], start[1] - end[1]) / 10.0
    assert over.repetition_offsets_s[1] == pytest.approx(job.duration_s + back, rel=1e-12)
    # the timeline stays continuous in time and place
    seg = side.segments
    assert np.abs(seg["t0_s"][1:] - seg["t1_s"][:-1]).max() < 1e-9
    assert (
        np.hypot(seg["x0_mm"][1:] - seg["x1_mm"][:-1], seg["y0_mm"][1:] - seg["y1_mm"][:-1]).max()
        < 1e-9
    )
    long = job.repeat(5400.0, pitch_mm=(35.0, 10.0))  # 32 parts: 8 a row, 4 rows
    assert long.repetition_offsets_mm[-1].tolist() == [245.0, 30.0]
    with pytest.raises(ValueError, match=r"do not fit in the 300 x 300 mm travel"):
        job.repeat(5400.0, pitch_mm=(35.0, 0.0))
    with pytest.raises(ValueError, match="pitch_mm"):
        job.repeat(600.0, pitch_mm=(0.0, 0.0))


def test_an_inspection_pass_after_a_looped_print_sees_every_part_side_by_side():
    camera = CameraSettings(mode="inspection")
    kwargs = dict(scenario="exp1", seed=3, duration_min=10.0, camera=camera)
    over = run_job_print(NAFBOT, **kwargs).record
    side_by_side = JobSettings(repeat_pitch_mm=(35.0, 10.0))
    side = run_job_print(NAFBOT, **kwargs, job_settings=side_by_side).record
    assert side.meta["job"]["repeat_pitch_mm"] == [35.0, 10.0]
    tau_over = over.printed_at[np.isfinite(over.printed_at)]
    tau_side = side.printed_at[np.isfinite(side.printed_at)]
    # printed over each other, the pass sees the last run only; side by side, every run
    assert tau_over.min() > 600 - 200
    assert tau_side.min() < 5 and len(tau_side) > 3 * len(tau_over)
    printed_mm = read_program(NAFBOT).repeat(600.0).summary()["printed_length_mm"]
    assert len(tau_side) == pytest.approx(printed_mm / 2.0, rel=0.1)  # a frame every 2 mm


@pytest.fixture(scope="module")
def job_print_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("job")
    record = run_job_print(
        NAFBOT,
        "exp1",
        seed=2,
        duration_min=5.0,
        job_settings=JobSettings(repeat_pitch_mm=(35.0, 10.0)),
    ).record
    return write_record(record, folder / "print.parquet"), record


def test_estimate_on_a_job_print_with_and_without_its_program(job_print_file, tmp_path):
    path, record = job_print_file
    runner = CliRunner()
    out = tmp_path / "states.csv"
    result = runner.invoke(
        main, ["estimate", str(path), "--out", str(out), "--job", str(NAFBOT), "--smooth"]
    )
    assert result.exit_code == 0, result.output
    assert "camera frames filed at their print times" in result.output
    assert "speeds from the program" in result.output
    frame = pd.read_csv(out)
    assert len(frame) == len(record)
    filed = frame["filed_linewidth_um"].to_numpy()
    assert np.isfinite(filed).sum() == frame["camera_frames_linewidth"].gt(0).sum() > 100
    # the horizon from the program's geometry: its 99 % delay (28 s) + the margin
    job = program_for_record(record, NAFBOT)
    assert camera_horizon_s(record.meta["camera"], job, len(record)) == 30.0
    assert "horizon 30 s" in result.output
    # without the program: the record's columns (the same filing here: one speed)
    plain = runner.invoke(main, ["estimate", str(path), "--out", str(tmp_path / "b.csv")])
    assert plain.exit_code == 0, plain.output
    assert "speeds from the record" in plain.output and "horizon 600 s" in plain.output
    other = pd.read_csv(tmp_path / "b.csv")
    np.testing.assert_allclose(other["filed_linewidth_um"], filed, equal_nan=True)


def test_estimate_refuses_a_program_the_print_did_not_run(job_print_file, tmp_path):
    path, _ = job_print_file
    wrong = PRG / "4-naf1L.prg"
    result = CliRunner().invoke(
        main, ["estimate", str(path), "--out", str(tmp_path / "s.csv"), "--job", str(wrong)]
    )
    assert result.exit_code != 0
    digest = hashlib.sha256(wrong.read_bytes()).hexdigest()[:12]
    assert f"sha256 {digest}" in result.output and "1-nafbot.prg" in result.output
    straight = tmp_path / "straight.parquet"
    assert CliRunner().invoke(main, ["simulate", "--duration-min", "1", "--out", str(straight)])
    result = CliRunner().invoke(
        main, ["estimate", str(straight), "--out", str(tmp_path / "t.csv"), "--job", str(NAFBOT)]
    )
    assert result.exit_code != 0 and "not a job print" in result.output


def test_the_live_engine_runs_a_job_print_with_its_context(job_print_file):
    _, record = job_print_file
    engine = LiveEngine(twin_overrides={"em": False}, asynchronous=False)
    context = print_context(record, None, 40.0)
    engine.open("aj-1", print_context=context)
    engine.open("aj-2")  # an ordinary machine beside it
    messages = []
    for k in range(120):
        row = (record.time_s[k], record.inputs[k], record.outputs[k])
        job_columns = (record.shutter_open[k], record.platen_speed[k], record.printed_at[k])
        messages += engine.feed_many([("aj-1", Sample(*row, *job_columns)), ("aj-2", Sample(*row))])
    steps = [m for m in messages if isinstance(m, StepMessage)]
    committed = {m.machine: m.step for m in steps if not m.provisional}
    assert committed == {"aj-1": 119 - 40, "aj-2": 119}  # final 40 s later
    now = [m.to_dict() for m in steps if m.machine == "aj-1" and m.provisional]
    assert now[-1]["step"] == 119
    engine.shutdown()


def test_the_job_study_runs_a_small_real_instance(tmp_path):
    """`python -m ajtwin.studies.job_twin` on 2-min prints of one program, one seed: every
    configuration in the table, finite figures, the frames filed."""
    from ajtwin.studies.job_twin import STATES, markdown, run_all

    results = run_all([1], 2.0, [NAFBOT], progress=lambda _: None)
    for group in ("model", "alt"):
        table = results["groups"][group]["table"]
        assert set(table) == {"straight", "1-nafbot.prg trailing", "1-nafbot.prg inspection"}
        for estimators in table.values():
            for metrics in estimators.values():
                for state in STATES:
                    m = metrics[state]
                    assert np.isfinite([m["rms_error"], m["rms_z"]]).all()
                    assert 0.0 <= m["coverage"] <= 1.0
        assert results["groups"][group]["camera"]["1-nafbot.prg trailing"]["filed"] > 50
    text = markdown(results, "python -m ajtwin.studies.job_twin --minutes 2")
    assert "| 1-nafbot.prg inspection | smoothed |" in text
