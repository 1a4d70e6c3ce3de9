"""The virtual printer prints a job: shutter, platen speed, a camera on the part.

Checked against what the job print's code does not compute itself: the straight-line
print of the same seed (states, today's record), the speed law's constants read from the
data file and raised to their power by hand, the nozzle's position from the job's own
timeline at the print time, a brute-force search of the printed path, and real public
programs (jizhang495/prg2svg, MIT; tests/data/prg/prg2svg/).
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.io.records import (
    JOB_COLUMNS,
    LINE_TRUTH_COLUMNS,
    RECORD_COLUMNS,
    TRUTH_COLUMNS,
    RecordError,
    read_record,
    write_record,
)
from ajtwin.job import read_program, read_program_text
from ajtwin.simulation import simulate
from ajtwin.simulation.job_print import CameraSettings, run_job_print
from ajtwin.simulation.stepper import SteppedPrinter

ROOT = Path(__file__).resolve().parent.parent
PRG = ROOT / "tests" / "data" / "prg" / "prg2svg"
NAFBOT = PRG / "1-nafbot.prg"  # 30 strokes, 166 s at 2 mm/s
NAF654321 = PRG / "4-naf 654321.prg"  # 84 strokes, 43 min 21 s at 2 mm/s
LAW_FILE = ROOT / "src" / "ajtwin" / "data" / "line_speed.toml"

# one stroke at 2 mm/s (25 s), one at 8 mm/s (25 s), a rapid back (25 s)
TWO_SPEEDS = """ptp/e (X,Y),0,0
OUT0.0=1
ptp/ev (X,Y),50,0,2
ptp/ev (X,Y),250,0,8
OUT0.0=0
ptp/ev (X,Y),0,0,10
"""
# one straight stroke at the GUI's 2 mm/s that outlasts the print
STRAIGHT = "ptp/e (X,Y),0,0\nOUT0.0=1\nptp/e (X,Y),250,0\nOUT0.0=0\n"


def law_constants() -> dict:
    with LAW_FILE.open("rb") as handle:
        return tomllib.load(handle)["law"]


def no_draw() -> dict:
    """Scenario overrides: the truth's speed law = the data file's (no seeded spread)."""
    return {"truth": {"line_speed_exponent_sd": 0.0}}


@pytest.fixture(scope="module")
def nafbot_trailing():
    return run_job_print(
        NAFBOT, "exp1", seed=5, duration_min=4.0, camera=CameraSettings(mode="trailing")
    )


# --------------------------------------------------------------------------- #
# The machine and the substrate
# --------------------------------------------------------------------------- #


def test_closed_shutter_spans_carry_no_line_while_the_states_evolve_as_on_an_open_print(
    nafbot_trailing,
):
    record = nafbot_trailing.record
    data = record.data
    closed = data["shutter_open"].to_numpy() == 0
    assert 5 <= closed.sum() <= len(data) - 100  # rapids between strokes, mostly printing
    assert data.loc[closed, "material_flow_mL_s"].isna().all()
    assert data.loc[~closed, "material_flow_mL_s"].notna().all()
    for column in LINE_TRUTH_COLUMNS:
        assert data.loc[closed, column].isna().all()
        assert data.loc[~closed, column].notna().all()
    # the straight-line print of the same scenario and seed: the same machine, bit for bit
    open_print = simulate("exp1", seed=5, duration_min=4.0)
    assert np.array_equal(record.true_states, open_print.true_states)
    assert np.array_equal(record.inputs, open_print.inputs)
    for column in ("carrier_pressure_Pa", "sheath_pressure_Pa"):
        assert np.array_equal(data[column], open_print.data[column])


def test_a_nozzle_camera_sees_no_line_while_the_shutter_is_closed():
    record = run_job_print(
        NAFBOT, "exp1", seed=5, duration_min=4.0, camera=CameraSettings(mode="at_nozzle")
    ).record
    data = record.data
    closed = data["shutter_open"] == 0
    assert closed.sum() >= 5
    for column in ("linewidth_um", "overspray_um", "material_flow_mL_s", "printed_at_s"):
        assert data.loc[closed, column].isna().all(), column
    # printing: the camera measures the line as it is printed, at the row's own time
    assert np.array_equal(data.loc[~closed, "printed_at_s"], data.loc[~closed, "time_s"])


def test_at_nozzle_on_a_straight_line_at_the_reference_speed_is_the_straight_line_record():
    job = read_program_text(STRAIGHT, process_speed_mm_s=2.0)
    job_print = run_job_print(
        job, "exp1", seed=3, duration_min=1.5, camera=CameraSettings(mode="at_nozzle")
    )
    record = job_print.record
    today = simulate("exp1", seed=3, duration_min=1.5)
    for column in (*RECORD_COLUMNS, *TRUTH_COLUMNS):
        assert record.data[column].equals(today.data[column]), column
    assert (record.data["shutter_open"] == 1).all()
    assert (record.data["platen_speed_mm_s"] == 2.0).all()
    assert np.array_equal(record.data["printed_at_s"], record.data["time_s"])
    # the nozzle's line at 2 mm/s is the straight-line truth's noise-free line
    assert np.array_equal(
        record.data[list(LINE_TRUTH_COLUMNS)].to_numpy(), job_print.virtual.outputs_true[:, :2]
    )
    # a trailing camera without offset sees the same line printed a few ms earlier, in the
    # previous second (its input jitter: within 1 %), through the same camera noise
    trailing_print = run_job_print(
        job,
        "exp1",
        seed=3,
        duration_min=1.5,
        camera=CameraSettings(mode="trailing", offset_mm=(0.0, 0.0)),
    )
    trailing = trailing_print.record
    delay = trailing.time_s - trailing.printed_at
    seen = np.isfinite(delay)
    assert seen[1:].all() and not seen[0]  # nothing printed before the first frame
    assert (delay[seen] > 0).all() and (delay[seen] < 0.02).all()
    np.testing.assert_allclose(
        trailing_print.camera_line[seen], job_print.camera_line[seen], rtol=1e-2
    )
    for column, j in (("linewidth_um", 0), ("overspray_um", 1)):
        np.testing.assert_allclose(
            trailing.data[column][seen] / trailing_print.camera_line[seen, j],
            record.data[column][seen] / job_print.camera_line[seen, j],
            rtol=1e-12,
        )


# --------------------------------------------------------------------------- #
# The line and the platen speed
# --------------------------------------------------------------------------- #


def test_speed_changes_move_the_line_as_the_documented_law_says():
    law = law_constants()
    job = read_program_text(TWO_SPEEDS)
    job_print = run_job_print(
        job,
        "exp1",
        seed=2,
        duration_min=2.0,
        overrides=no_draw(),
        camera=CameraSettings(mode="at_nozzle"),
    )
    data = job_print.record.data
    at_reference = job_print.virtual.outputs_true  # the line at 2 mm/s, shutter ignored
    t = data["time_s"].to_numpy()
    slow = (t % 75 > 0) & (t % 75 < 25)
    fast = (t % 75 > 25) & (t % 75 < 50)
    assert (data.loc[slow, "platen_speed_mm_s"] == 2.0).all()
    assert (data.loc[fast, "platen_speed_mm_s"] == 8.0).all()
    ref = law["reference_speed_mm_s"]
    width = data["true_linewidth_um"].to_numpy() / at_reference[:, 0]
    spray = data["true_overspray_um"].to_numpy() / at_reference[:, 1]
    np.testing.assert_allclose(width[slow], 1.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(width[fast], (ref / 8.0) ** law["linewidth_exponent"], rtol=1e-13)
    np.testing.assert_allclose(spray[fast], (ref / 8.0) ** law["overspray_exponent"], rtol=1e-13)
    # 8 mm/s prints a line ~34 % narrower than 2 mm/s: (1/4)^0.3 = 0.66
    assert 0.60 < width[fast].mean() < 0.70


def test_the_truth_draws_its_own_exponents_and_the_line_follows_them():
    law = law_constants()
    job = read_program_text(TWO_SPEEDS)
    job_print = run_job_print(
        job, "exp1", seed=2, duration_min=2.0, camera=CameraSettings(mode="at_nozzle")
    )
    drawn = job_print.record.meta["truth_draws"]["line_speed"]
    assert drawn["form"] == "power"
    assert drawn["linewidth_exponent"] != law["linewidth_exponent"]  # the twin is not handed it
    assert 0.0 <= drawn["linewidth_exponent"] <= 0.5
    data = job_print.record.data
    fast = data["platen_speed_mm_s"].to_numpy() == 8.0
    ratio = data["true_linewidth_um"].to_numpy()[fast] / job_print.virtual.outputs_true[fast, 0]
    np.testing.assert_allclose(ratio, 0.25 ** drawn["linewidth_exponent"], rtol=1e-13)


def test_a_machine_keeps_its_speed_law_from_print_to_print():
    job = read_program_text(TWO_SPEEDS)

    def law(**kwargs):
        return run_job_print(job, "exp1", duration_min=1.0, **kwargs).line_speed_law

    assert law(seed=1, machine_seed=7) == law(seed=2, machine_seed=7)
    assert law(seed=1) != law(seed=2)  # a nominal machine: drawn per print, like its line
    first = run_job_print(job, "exp1", seed=1, duration_min=1.0).record
    assert law(seed=9, continue_from=first) == first.meta["truth_draws"]["line_speed"]


def test_the_second_generator_uses_another_form_of_the_speed_law():
    job = read_program_text(TWO_SPEEDS)
    job_print = run_job_print(
        job,
        "exp1",
        seed=2,
        duration_min=2.0,
        truth_generator="alt",
        camera=CameraSettings(mode="at_nozzle"),
    )
    drawn = job_print.record.meta["truth_draws"]["line_speed"]
    assert drawn["form"] == "beam_plus_spreading"
    phi = drawn["beam_fraction"]
    assert 0.3 <= phi <= 0.7
    data = job_print.record.data
    fast = data["platen_speed_mm_s"].to_numpy() == 8.0
    reference = job_print.virtual.outputs_true[fast]
    np.testing.assert_allclose(
        data["true_linewidth_um"].to_numpy()[fast] / reference[:, 0],
        phi + (1 - phi) * math.sqrt(2.0 / 8.0),
        rtol=1e-13,
    )
    np.testing.assert_allclose(
        data["true_overspray_um"].to_numpy()[fast] / reference[:, 1], 1.0, rtol=1e-15
    )


def test_the_camera_measures_the_line_at_its_print_time_not_at_the_frame_time():
    """A trace printed at 8 mm/s seen while the nozzle prints at 2 mm/s is the narrow one."""
    job = read_program_text(TWO_SPEEDS)
    job_print = run_job_print(
        job,
        "exp1",
        seed=2,
        duration_min=2.5,
        overrides=no_draw(),
        camera=CameraSettings(mode="trailing", offset_mm=(-40.0, 0.0)),
    )
    data = job_print.record.data
    tau = data["printed_at_s"].to_numpy()
    # a spot where the two strokes join belongs to both: leave it out
    seen = np.isfinite(tau) & (np.abs(tau - 25.0 * np.round(tau / 25.0)) > 1e-6)
    assert seen.sum() >= 30
    speed_now = data["platen_speed_mm_s"].to_numpy()
    speed_then = read_program_text(TWO_SPEEDS).repeat(150.0).state_at(tau[seen]).speed_mm_s
    mixed = speed_now[seen] != speed_then
    assert mixed.sum() >= 5  # the nozzle runs at one speed, the trace seen was at the other
    law = law_constants()
    factor = (law["reference_speed_mm_s"] / speed_then) ** law["linewidth_exponent"]
    # the camera's truth at τ divided by the law's factor at ν(τ) is the 2 mm/s line of the
    # second τ fell in (within its sub-second drift), not of the frame's second
    at_reference_then = job_print.camera_line[seen, 0] / factor
    second = np.floor(tau[seen]).astype(int)
    np.testing.assert_allclose(
        at_reference_then, job_print.virtual.outputs_true[second, 0], rtol=2e-3
    )
    # and the measurement carries the usual camera noise around it (log sd 0.04)
    ratio = np.log(data["linewidth_um"].to_numpy()[seen] / job_print.camera_line[seen, 0])
    assert abs(ratio.mean()) < 0.03 and 0.02 < ratio.std() < 0.07


# --------------------------------------------------------------------------- #
# The camera: which trace, printed when
# --------------------------------------------------------------------------- #


def test_printed_at_is_when_the_nozzle_passed_the_spot_under_the_camera(nafbot_trailing):
    record = nafbot_trailing.record
    camera = record.meta["camera"]
    radius = record.meta["virtual_camera"]["field_radius_mm"]
    dx, dy = camera["offset_mm"]
    # the job read again, independently of the print's own plan
    job = read_program(NAFBOT).repeat(len(record))
    t = record.time_s
    tau = record.printed_at
    seen = np.isfinite(tau)
    assert 0.6 < seen.mean() < 0.95
    now = job.state_at(t[seen])
    then = job.state_at(tau[seen])
    assert (tau[seen] < t[seen]).all()
    assert then.shutter_open.all()  # the nozzle was printing then ...
    distance = np.hypot(then.x_mm - (now.x_mm + dx), then.y_mm - (now.y_mm + dy))
    assert (distance <= radius + 1e-9).all()  # ... at the spot the camera sees now

    # brute force over the printed path, sampled every 0.25 ms (0.5 µm at 2 mm/s): no trace
    # printed before the frame lies nearer to the view centre than the one measured, and a
    # frame without a measurement has no printed trace in its field
    grid = np.arange(0.0, len(record), 0.00025)
    path = job.state_at(grid)
    printed = path.shutter_open & (path.speed_mm_s > 0)
    px, py, pt = path.x_mm[printed], path.y_mm[printed], grid[printed]
    rng = np.random.default_rng(0)
    rows = np.sort(rng.choice(len(record), 40, replace=False))
    frame = job.state_at(t[rows])
    for row, cx, cy in zip(rows, frame.x_mm + dx, frame.y_mm + dy, strict=True):
        before = pt < t[row]
        d = np.hypot(px[before] - cx, py[before] - cy)
        if not np.isfinite(tau[row]):
            assert not (d < radius - 1e-3).any(), row
            continue
        at_tau = job.state_at(tau[row])
        found = math.hypot(at_tau.x_mm - cx, at_tau.y_mm - cy)
        assert found <= d.min() + 1e-3, row  # the nearest trace (to the sampling)


def test_an_inspection_pass_attributes_its_measurements_to_times_within_the_print():
    minutes = 4.0
    job_print = run_job_print(
        NAFBOT, "exp1", seed=5, duration_min=minutes, camera=CameraSettings(mode="inspection")
    )
    record = job_print.record
    data = record.data
    n_print = int(minutes * 60)
    assert record.meta["virtual_camera"]["print_end_s"] == n_print
    during, after = data.iloc[:n_print], data.iloc[n_print:]
    assert during["linewidth_um"].isna().all() and during["printed_at_s"].isna().all()
    assert len(after) > 100
    assert (after["shutter_open"] == 0).all()  # nothing printed during the pass
    assert after["material_flow_mL_s"].isna().all()
    tau = after["printed_at_s"].to_numpy()
    assert np.isfinite(tau).all()
    assert (tau >= 0).all() and (tau < n_print).all()
    assert (np.diff(tau) > 0).all()  # the pass walks the strokes in print order
    job = read_program(NAFBOT).repeat(n_print)
    assert job.state_at(tau).shutter_open.all()
    # the pass covers what is visible at the end: every 2 mm of the printed path once,
    # except where a later stroke printed over it
    printed_mm = job.summary()["printed_length_mm"]
    assert 0.5 * printed_mm / 2.0 < len(after) <= printed_mm / 2.0 + job.n_strokes
    # the machine ran on through the pass: the same states as an open print of that length
    open_print = simulate("exp1", seed=5, duration_min=len(data) / 60.0)
    assert np.array_equal(record.true_states, open_print.true_states)


# --------------------------------------------------------------------------- #
# A real program looped; the stepped printer; the record
# --------------------------------------------------------------------------- #


def test_a_public_program_loops_to_a_ten_minute_print(tmp_path):
    job_print = run_job_print(NAFBOT, "exp1", seed=1, duration_min=10.0)
    record = job_print.record
    assert len(record) == 600
    assert job_print.plan.job.repetitions == 4  # 166 s a run
    assert record.meta["job"]["repeat_to_s"] == 600.0
    seen = np.isfinite(record.printed_at)
    assert 0.6 < seen.mean() < 0.95
    delay = record.time_s[seen] - record.printed_at[seen]
    assert 0 < np.median(delay) < 120
    path = write_record(record, tmp_path / "job.parquet")
    back = read_record(path)
    pd.testing.assert_frame_equal(back.data, record.data, check_exact=True)


@pytest.mark.slow
def test_the_seven_layer_program_looped_to_ninety_minutes():
    job_print = run_job_print(NAF654321, "exp1", seed=1)
    record = job_print.record
    assert len(record) == 5400 and job_print.plan.job.repetitions == 3
    seen = np.isfinite(record.printed_at)
    assert 0.55 < seen.mean() < 0.85
    assert (record.printed_at[seen] < record.time_s[seen]).all()
    assert record.data["true_linewidth_um"].notna().sum() > 0.95 * len(record)


@pytest.mark.parametrize(
    ("mode", "truth"), [("trailing", "model"), ("inspection", "model"), ("trailing", "alt")]
)
def test_the_stepped_printer_prints_a_job_as_the_batch_printer_does(mode, truth):
    camera = CameraSettings(mode=mode)
    batch = run_job_print(
        NAFBOT, "exp1", seed=4, duration_min=3.0, camera=camera, truth_generator=truth
    ).record
    printer = SteppedPrinter(
        "exp1", seed=4, duration_min=3.0, truth=truth, job=NAFBOT, camera=camera
    )
    chunks = []
    while not printer.done:
        chunks.append(printer.advance(37))
    stepped = printer.record()
    assert list(stepped.data.columns) == list(batch.data.columns)
    pd.testing.assert_frame_equal(stepped.data, batch.data, check_exact=False, rtol=1e-12)
    for key in ("job", "camera", "platen_speed_mm_s"):
        assert stepped.meta[key] == batch.meta[key]
    assert stepped.meta["truth_draws"]["line_speed"] == batch.meta["truth_draws"]["line_speed"]
    # the chunks carry the job's columns as they go
    shutter = np.concatenate([c.shutter_open for c in chunks])
    printed_at = np.concatenate([c.printed_at_s for c in chunks])
    np.testing.assert_array_equal(shutter, batch.data["shutter_open"])
    np.testing.assert_array_equal(printed_at, batch.data["printed_at_s"])


def test_job_columns_and_metadata_are_written_and_read(tmp_path, nafbot_trailing):
    record = nafbot_trailing.record
    assert list(record.data.columns) == [
        *RECORD_COLUMNS,
        *JOB_COLUMNS,
        *TRUTH_COLUMNS,
        *LINE_TRUTH_COLUMNS,
    ]
    assert set(record.meta["job"]) == {
        "program",
        "sha256",
        "process_speed_mm_s",
        "rapid_speed_mm_s",
        "speed_source",
        "repeat_to_s",
    }
    assert record.meta["job"]["program"] == "1-nafbot.prg"
    import hashlib

    assert record.meta["job"]["sha256"] == hashlib.sha256(NAFBOT.read_bytes()).hexdigest()
    assert record.meta["camera"] == {"mode": "trailing", "offset_mm": [-5.0, 0.0]}
    for suffix in (".parquet", ".csv"):
        back = read_record(write_record(record, tmp_path / f"p{suffix}"))
        pd.testing.assert_frame_equal(back.data, record.data, check_exact=True)
        assert back.meta["format_version"] == 2 and back.meta["camera"] == record.meta["camera"]


def _as_version_1(tmp_path, record, speed=1.5):
    """A CSV record as a version-1 writer left it: no job columns, format_version 1."""
    path = write_record(record, tmp_path / "v2.csv")
    text = path.read_text(encoding="utf-8")
    text = text.replace('"format_version": 2', '"format_version": 1')
    text = text.replace('"platen_speed_mm_s": 2.0', f'"platen_speed_mm_s": {speed}')
    old = tmp_path / "v1.csv"
    old.write_text(text, encoding="utf-8")
    return old


def test_version_1_records_read_with_the_no_job_defaults(tmp_path):
    record = simulate("exp1", seed=2, duration_min=1.0)
    record.data.loc[[3, 7], ["linewidth_um", "overspray_um"]] = np.nan
    back = read_record(_as_version_1(tmp_path, record))
    assert back.meta["format_version"] == 1
    data = back.data
    assert list(data.columns) == [*RECORD_COLUMNS, *JOB_COLUMNS, *TRUTH_COLUMNS]
    assert (data["shutter_open"] == 1).all()
    assert (data["platen_speed_mm_s"] == 1.5).all()
    measured = data["linewidth_um"].notna()
    assert data.loc[measured, "printed_at_s"].equals(data.loc[measured, "time_s"])
    assert data.loc[~measured, "printed_at_s"].isna().all() and (~measured).sum() == 2
    for column in (*RECORD_COLUMNS, *TRUTH_COLUMNS):
        assert np.array_equal(data[column], record.data[column], equal_nan=True), column
    # a record without a job (read or in memory) answers the same through the accessors
    assert np.array_equal(record.shutter_open, np.ones(60))
    assert np.array_equal(record.platen_speed, np.full(60, 2.0))
    assert np.array_equal(back.printed_at, record.printed_at, equal_nan=True)


@pytest.mark.parametrize(
    ("column", "row", "value", "message"),
    [
        ("shutter_open", 4, 2.0, "not 0 (closed) or 1 (open)"),
        ("platen_speed_mm_s", 6, -1.0, "not a speed"),
        ("printed_at_s", 8, 100.0, "after the row's time"),
    ],
)
def test_bad_job_columns_are_refused_naming_row_and_column(tmp_path, column, row, value, message):
    record = run_job_print(
        read_program_text(STRAIGHT, process_speed_mm_s=2.0), "exp1", seed=1, duration_min=0.5
    ).record
    data = record.data.copy()
    data.loc[row, column] = value
    path = tmp_path / "bad.csv"
    write_record(type(record)(data, record.meta), path)
    with pytest.raises(RecordError, match=rf"row {row + 1} .*'{column}'.*{re.escape(message)}"):
        read_record(path)


def test_a_camera_measurement_without_its_print_time_is_refused(tmp_path):
    record = run_job_print(
        read_program_text(STRAIGHT, process_speed_mm_s=2.0), "exp1", seed=1, duration_min=0.5
    ).record
    data = record.data.copy()
    data.loc[5, "printed_at_s"] = np.nan
    path = write_record(type(record)(data, record.meta), tmp_path / "bad.parquet")
    with pytest.raises(RecordError, match="row 6.*without the print time"):
        read_record(path)
    meta = dict(record.meta, camera={"mode": "sideways", "offset_mm": [0, 0]})
    path = write_record(type(record)(record.data, meta), tmp_path / "bad_meta.parquet")
    with pytest.raises(RecordError, match="'camera'"):
        read_record(path)


# --------------------------------------------------------------------------- #
# The command line
# --------------------------------------------------------------------------- #


def test_simulate_job_from_the_command_line(tmp_path):
    from ajtwin.cli.simulate import plot
    from ajtwin.cli.simulate import simulate as simulate_command

    out = tmp_path / "job.parquet"
    result = CliRunner().invoke(
        simulate_command,
        [
            "--job",
            str(NAFBOT),
            "--duration-min",
            "3",
            "--camera-offset-mm",
            "-5",
            "--process-speed",
            "3",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "1-nafbot.prg at 3 mm/s" in result.output and "a measurement in" in result.output
    record = read_record(out)
    assert record.has_job and record.meta["camera"]["offset_mm"] == [-5.0, 0.0]
    assert record.meta["job"]["process_speed_mm_s"] == 3.0
    assert set(np.unique(record.platen_speed)) <= {0.0, 3.0, 10.0}
    png = tmp_path / "job.png"
    result = CliRunner().invoke(plot, [str(out), "-o", str(png), "--no-nominal"])
    assert result.exit_code == 0, result.output
    assert png.stat().st_size > 10_000


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--camera-offset-mm", "5"], "give --job PROGRAM.prg"),
        (["--job", str(NAFBOT), "--camera", "at_nozzle", "--camera-offset-mm", "5"], "no offset"),
        (["--job", str(NAFBOT), "--camera-offset-mm", "5,nan"], "NaN"),
        (["--job", str(NAFBOT), "--camera-offset-mm", "1,2,3"], "DX or DX,DY"),
    ],
)
def test_simulate_job_refuses_bad_options(tmp_path, args, message):
    from ajtwin.cli.simulate import simulate as simulate_command

    result = CliRunner().invoke(simulate_command, [*args, "--out", str(tmp_path / "x.parquet")])
    assert result.exit_code != 0
    assert message in result.output


def test_simulate_job_names_the_line_of_a_bad_program(tmp_path):
    from ajtwin.cli.simulate import simulate as simulate_command

    bad = tmp_path / "bad.prg"
    bad.write_text("ptp/e (X,Y),0,0\nOUT0.0=1\narc2 (X,Y),0,0,1.0\nOUT0.0=0\n")
    result = CliRunner().invoke(
        simulate_command, ["--job", str(bad), "--out", str(tmp_path / "x.parquet")]
    )
    assert result.exit_code == 1
    assert "bad.prg:3" in result.output
