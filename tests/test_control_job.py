"""Control on a job print: the program's speeds ahead met by feed-forward, moves where the
shutter is closed, the trailing camera's frames used at their print times, limits under
adversarial job timelines, the command line and the job columns of a live link."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ajtwin.apps.planning.job_preview import JobPreview
from ajtwin.apps.planning.mpc import MPC, ControlSettings
from ajtwin.apps.planning.strategies import nominal_state, start_inputs
from ajtwin.apps.planning.twin_control import MPCTwin
from ajtwin.engine.job_samples import JobColumns
from ajtwin.engine.stream import TwinStream
from ajtwin.estimation import Twin
from ajtwin.job import SpeedSchedule, read_program_text
from ajtwin.model.line_speed import line_speed_factors, load_line_speed_law
from ajtwin.simulation.job_print import CameraSettings
from ajtwin.simulation.stepper import SteppedPrinter
from ajtwin.studies.closed_loop import ClosedLoopPlan, job_print_setup, simulate_strategy

TARGET = 55.0
#: the speed law's factor on L_w at 4 mm/s (ν_ref = 2 mm/s, b = 0.3): 0.812
F4 = float(line_speed_factors(4.0, load_line_speed_law())[0])


def serpentine(strokes: int, length_mm: float = 20.0, pitch_mm: float = 0.2) -> str:
    """Strokes back and forth along x, ``pitch_mm`` apart (the moves between at the process
    speed, the shutter closed)."""
    lines = []
    for k in range(strokes):
        x0, x1 = (0.0, length_mm) if k % 2 == 0 else (length_mm, 0.0)
        y = k * pitch_mm
        lines += [f"ptp/e (X,Y),{x0},{y}", "OUT0.0=1", f"ptp/e (X,Y),{x1},{y}", "OUT0.0=0"]
    return "\n".join(lines)


@pytest.fixture(scope="module")
def step_job():
    """24 strokes of 20 mm: 16 at 2 mm/s (160 s), then 8 at 4 mm/s (40 s)."""
    schedule = SpeedSchedule("stroke", ranges=((0, 15, 2.0), (16, 23, 4.0)))
    return read_program_text(serpentine(24), process_speed_mm_s=2.0, speed_schedule=schedule)


@pytest.fixture(scope="module")
def twin():
    return Twin.default()


@pytest.fixture(scope="module")
def mpc(twin):
    controller = MPC(twin, ControlSettings.load())
    controller.warm_up()
    return controller


# --------------------------------------------------------------------------- #
# The job's seconds ahead
# --------------------------------------------------------------------------- #


def test_the_preview_weighs_seconds_by_printed_length_at_their_speed(step_job):
    preview = JobPreview(step_job, horizon_s=60)
    step = float(step_job.strokes["t_start_s"].iloc[16])
    line = preview.line(step - 30.0)
    # 2 mm/s before the step (ℓ = 1, f = 1), 4 mm/s after it (ℓ = 2, f = 0.812); the 0.1-s
    # moves between strokes print nothing
    assert np.all((line[:25, 0] >= 0.9 - 1e-9) & (line[:25, 0] <= 1.0 + 1e-9))
    assert np.all((line[32:60, 0] >= 1.8 - 1e-9) & (line[32:60, 0] <= 2.0 + 1e-9))
    np.testing.assert_allclose(line[:25, 1], 1.0, rtol=1e-12)
    np.testing.assert_allclose(line[32:60, 1], F4, rtol=1e-9)
    # past the end of the job nothing is printed
    assert np.all(preview.line(step_job.duration_s + 5)[:, 0] == 0)


# --------------------------------------------------------------------------- #
# Feed-forward: a planned speed step is met before the line moves
# --------------------------------------------------------------------------- #


def test_a_planned_speed_step_is_met_before_the_line_moves_while_pi_sees_it(step_job):
    """exp1, the camera at the nozzle: at the step from 2 to 4 mm/s the line would narrow to
    0.81 of its width. The MPC on the twin raises the line it makes (the model's line at
    ν_ref) before the stage speeds up and prints the first 10 s at the new speed near the
    target; PI, which only sees the line, prints them ~10 µm narrow and moves after."""
    camera = CameraSettings(mode="at_nozzle")
    u0, _ = start_inputs(Twin.default(), TARGET)
    runs = {
        strategy: simulate_strategy(
            ClosedLoopPlan("exp1", 3, TARGET, duration_min=3.5, u0=u0, job=step_job, camera=camera),
            strategy,
        )
        for strategy in ("pi", "mpc_twin")
    }
    step = int(np.ceil(step_job.strokes["t_start_s"].iloc[16]))
    after = slice(step + 1, step + 11)
    twin, pi = runs["mpc_twin"], runs["pi"]
    # the MPC's own line (at ν_ref) rose by ≥ 5 µm in the 40 s before the step
    assert twin.true_outputs[step - 1, 0] - twin.true_outputs[step - 40, 0] > 5.0
    assert np.all(twin.printed_length[after] > 1.9)  # printing at 4 mm/s
    twin_error = np.abs(twin.true_line[after, 0] - TARGET).mean()
    pi_error = np.abs(pi.true_line[after, 0] - TARGET).mean()
    print(f"first 10 s at 4 mm/s: MPC on the twin {twin_error:.2f} µm, PI {pi_error:.2f} µm off")
    assert pi_error > 6.0
    assert twin_error < 0.5 * pi_error
    # PI did not move before the step (it has nothing to see), and moved after it
    q_c = pi.setpoints[:, 1]
    assert abs(q_c[step - 1] - q_c[step - 40]) < 0.3
    assert q_c[step + 40] - q_c[step] > 0.5
    for run in runs.values():
        assert run.metrics["inside_limits"] and run.metrics["rate_limits_respected"]


# --------------------------------------------------------------------------- #
# Moves where the shutter is closed, when the optimiser is told they are free
# --------------------------------------------------------------------------- #


def test_moves_fall_in_a_closed_span_when_it_is_free(mpc, twin):
    """A layer at 4 mm/s starts in 40 s; the line must be 23 % wider at ν_ref by then, a
    change the rate limits take ~35 s to make. Printing at 2 mm/s until then, the MPC does not
    move toward it now (that would spoil the line printed now) and starts the layer short; with the
    shutter closed until then (ℓ = 0: free) it moves at (or near) the rate limit now and starts
    the layer on target."""
    u0, _ = start_inputs(twin, TARGET)
    mean, _ = nominal_state(twin, u0)
    cov = np.diag([1e-4, 1e-6, 1e-10, 1e-6, (0.005 * mean[4]) ** 2])
    results = {}
    for closed in (False, True):
        line = np.ones((60, 3))
        line[40:, 0], line[40:, 1:] = 2.0, F4
        if closed:
            line[:40, 0] = 0.0
        mpc.reset()
        sol = mpc.solve(mean, cov, np.zeros(5), u0, TARGET, warm_start=False, line=line)
        printed = sol.predicted_linewidth * line[:, 1]
        results[closed] = (sol.command - u0, np.abs(printed[42:] - TARGET).mean())
    (open_move, open_error), (closed_move, closed_error) = results[False], results[True]
    q_c_rate = mpc.rates[1] * mpc.settings.period_s
    assert 0.9 * q_c_rate <= closed_move[1] <= q_c_rate * (1 + 1e-9)  # Q_c near its rate limit now
    assert open_move[1] < 0.3 * q_c_rate  # no move toward the layer's inputs yet
    assert closed_error < 0.5 < 2.0 < open_error


# --------------------------------------------------------------------------- #
# Limits and rate limits under adversarial states and job timelines
# --------------------------------------------------------------------------- #


@settings(
    max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    droplet=st.floats(0.6, 14.0),
    phi=st.floats(0.0, 5e-6),
    log_var=st.floats(-8.0, 2.0),
    z_prev=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3),
    target=st.floats(20.0, 200.0),
    lengths=st.lists(st.sampled_from([0.0, 0.15, 1.0, 2.0, 10.0]), min_size=6, max_size=6),
    speeds=st.lists(st.floats(0.3, 20.0), min_size=6, max_size=6),
)
def test_mpc_respects_limits_under_adversarial_job_timelines(
    mpc, droplet, phi, log_var, z_prev, target, lengths, speeds
):
    """Whatever the state, target and seconds ahead (nothing printed, dwells, speeds from
    0.3 to 20 mm/s in blocks of 10 s): the plan and the command stay inside the limits and
    the rate limits."""
    mean = np.array([droplet, 1.0, 0.0, 0.0, phi])
    cov = np.diag(10.0**log_var * np.array([1.0, 1e-2, 1e-6, 1e-2, 1e-14]))
    u_prev = mpc.lo + np.asarray(z_prev) * mpc.span
    f_w, f_o = line_speed_factors(np.repeat(speeds, 10), load_line_speed_law())
    line = np.stack([np.repeat(lengths, 10), f_w, f_o], axis=1)
    sol = mpc.solve(mean, cov, np.zeros(5), u_prev, target, warm_start=False, line=line)
    plan = np.vstack([u_prev, sol.plan])
    assert np.all(sol.plan >= mpc.lo - 1e-9) and np.all(sol.plan <= mpc.hi + 1e-9)
    max_steps = mpc.rates * mpc.move_gaps[:, None]
    assert np.all(np.abs(np.diff(plan, axis=0)) <= max_steps * (1 + 1e-9) + 1e-9)
    assert np.all(np.abs(sol.command - u_prev) <= mpc.rates * mpc.move_gaps[0] + 1e-9)


def test_a_line_of_the_wrong_shape_is_refused(mpc, twin):
    u = np.array([375.0, 23.0, 50.0])
    mean, cov = nominal_state(twin, u)
    with pytest.raises(ValueError, match=r"line must be \(60, 3\)"):
        mpc.solve(mean, cov, np.zeros(5), u, TARGET, line=np.ones((10, 3)))


# --------------------------------------------------------------------------- #
# The trailing camera's frames at their print times
# --------------------------------------------------------------------------- #


def test_the_delayed_camera_is_used_at_its_print_time(step_job):
    """A trailing camera 5 mm behind: each frame measures a trace printed ~2.5 s earlier. The
    MPC on the twin files every frame at the step of its print time (the engine's delay line),
    commits a step only when its frames can no longer arrive, and plans from the state now."""
    camera = CameraSettings(mode="trailing", offset_mm=(-5.0, 0.0))
    printer = SteppedPrinter("exp1", 1, 3.0, job=step_job, camera=camera)
    setup = job_print_setup(printer)
    context = setup["print_context"]
    assert context.camera_mode == "trailing" and 2 <= context.horizon_s <= 10
    settings = ControlSettings.load()
    u0 = np.array([300.0, 20.22, 80.0])
    twin = Twin.default()
    stream = TwinStream("m", twin, asynchronous=False, print_context=setup["print_context"])
    controller = MPCTwin(
        twin=twin, settings=settings, bounds=None, u0=u0, target=TARGET, stream=stream, **setup
    )
    rows = []
    while not printer.done:
        chunk = printer.advance(10)
        controller.observe(chunk)
        rows.append(chunk)
    printed_at = np.concatenate([c.printed_at_s for c in rows])
    measured = np.concatenate([c.outputs for c in rows])[:, 0]
    times = np.concatenate([c.time_s for c in rows])
    late = times - printed_at
    assert np.nanmedian(late) > 1.5  # the camera sees the line late
    committed = controller.stream.arrays()
    # every committed step holds the frames printed in its second (here one each)
    filed = committed["measurements"][:, 0]
    step_of = np.floor(printed_at + 0.5)
    for k, t in enumerate(committed["time_s"]):
        frames = measured[(step_of == t) & np.isfinite(measured)]
        if frames.size == 1:
            assert filed[k] == pytest.approx(frames[0], rel=1e-12)
        elif frames.size == 0:
            assert np.isnan(filed[k])
    # committed steps lag the newest row by the horizon; the MPC plans from the newest
    assert committed["time_s"][-1] == pytest.approx(times[-1] - context.horizon_s)
    mean, _ = controller.state_now()
    assert controller.stream.provisional[0] == times[-1]
    np.testing.assert_array_equal(mean, controller.stream.provisional[1])


def test_live_job_columns_are_the_virtual_cameras(step_job):
    """A link that carries only time, inputs and outputs (OPC UA): the job's columns filled
    from the program and the camera's geometry are those the virtual printer recorded."""
    camera = CameraSettings(mode="trailing", offset_mm=(-5.0, 0.0))
    printer = SteppedPrinter("exp1", 2, 3.0, job=step_job, camera=camera)
    while not printer.done:
        printer.advance(30)
    record = printer.record()
    columns = JobColumns(printer.plan.job, "trailing", (-5.0, 0.0))
    filled = columns.fill(record.time_s, record.outputs)
    np.testing.assert_array_equal(filled["shutter_open"], record.shutter_open)
    np.testing.assert_allclose(filled["platen_speed_mm_s"], record.platen_speed, rtol=1e-12)
    np.testing.assert_allclose(filled["printed_at_s"], record.printed_at, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(filled["outputs"], record.outputs)


# --------------------------------------------------------------------------- #
# The command line
# --------------------------------------------------------------------------- #


def test_cli_control_simulate_a_job_print(tmp_path):
    from ajtwin.cli import main
    from ajtwin.io.records import read_record

    program = tmp_path / "serpentine.prg"
    program.write_text(serpentine(12))
    out = tmp_path / "ctl"
    args = ["control", "simulate", "--scenario", "exp1", "--target-linewidth", "55"]
    args += ["--out", str(out), "--duration-min", "2", "--strategies", "open_loop,pi"]
    args += ["--job", str(program), "--process-speed", "stroke:2,4", "--camera-offset-mm=-5"]
    result = CliRunner().invoke(main, [*args, "--no-progress"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["job"]["process_speeds"] == "per stroke: 2, 4 mm/s, repeating"
    assert metrics["job"]["camera"] == {"mode": "trailing", "offset_mm": [-5.0, 0.0]}
    record = read_record(out / "exp1" / "seed1" / "pi.parquet")
    for column in ("shutter_open", "platen_speed_mm_s", "true_linewidth_um", "printed_at_s"):
        assert column in record.data
    assert set(np.unique(record.platen_speed[record.shutter_open > 0])) >= {2.0, 4.0}
    m = metrics["scenarios"]["exp1"]["per_seed"]["1"]["pi"]
    # the metrics are per printed length: the length printed after the warm-up
    printed = np.isfinite(record.data["true_linewidth_um"].to_numpy())
    expected = np.sum((record.shutter_open * record.platen_speed)[60:][printed[60:]])
    assert m["printed_length_mm"] == pytest.approx(expected, rel=1e-9)


def test_cli_says_what_an_inspection_pass_only_leaves_the_controllers(tmp_path):
    from ajtwin.cli import main

    program = tmp_path / "serpentine.prg"
    program.write_text(serpentine(12))
    args = ["control", "simulate", "--scenario", "exp1", "--target-linewidth", "55"]
    args += ["--out", str(tmp_path / "ctl"), "--duration-min", "1", "--strategies", "open_loop"]
    args += ["--job", str(program), "--camera", "inspection", "--no-progress"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "inspection pass after the print only" in result.output
    assert "nominal MPC" in result.output
    trailing = [a if a != "inspection" else "trailing" for a in args]
    trailing[trailing.index("--out") + 1] = str(tmp_path / "trailing")
    result = CliRunner().invoke(main, trailing)
    assert result.exit_code == 0, result.output
    assert "inspection pass" not in result.output


def test_cli_job_options_need_a_job(tmp_path):
    from ajtwin.cli import main

    args = ["control", "simulate", "--scenario", "exp1", "--target-linewidth", "55"]
    result = CliRunner().invoke(main, [*args, "--out", str(tmp_path), "--process-speed", "2,4"])
    assert result.exit_code != 0 and "give --job PROGRAM.prg" in result.output
    result = CliRunner().invoke(
        main, [*args, "--out", str(tmp_path), "--job", __file__, "--process-speed", "2,,4"]
    )
    assert result.exit_code != 0 and "give speeds" in result.output
