"""A looped job answered run by run gives the repeated job's answers, and stays small."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from ajtwin.apps.planning.job_preview import JobPreview
from ajtwin.engine.job_samples import JobColumns, live_loop
from ajtwin.estimation.print_time import program_for_record, trailing_delays
from ajtwin.estimation.twin import Twin
from ajtwin.io.schema import MAX_RECORD_SECONDS
from ajtwin.job import LoopedJob, loop_job, read_program, read_program_text
from ajtwin.simulation.job_print import simulate_job

DATA = Path(__file__).parent / "data" / "prg" / "prg2svg"

# (loop length in program runs, wait between runs [s], pitch [mm])
LOOPS = [(3.2, 0.0, None), (2.5, 3.0, None), (3.5, 1.0, (35.0, 10.0))]


@pytest.fixture(scope="module")
def layers():
    """The public seven-layer program: its layers print over each other."""
    return read_program(DATA / "4-naf 654321.prg")


def loops(job, runs, gap, pitch):
    duration = runs * job.duration_s
    return job.repeat(duration, gap, pitch), loop_job(job, duration, gap, pitch)


@pytest.mark.parametrize("runs, gap, pitch", LOOPS)
def test_the_stage_of_a_loop_is_that_of_the_repeated_job(layers, runs, gap, pitch):
    whole, looped = loops(layers, runs, gap, pitch)
    assert isinstance(looped, LoopedJob) and not looped.held_whole
    assert looped.duration_s == whole.duration_s
    assert looped.repetitions == whole.repetitions
    assert looped.end_shutter_open == whole.end_shutter_open
    rng = np.random.default_rng(3)
    # random times, every second, every segment's start, and before and after the loop
    t = np.r_[
        rng.uniform(-5.0, whole.duration_s + 5.0, 5000),
        np.arange(int(whole.duration_s) + 3, dtype=float),
        whole.segments["t0_s"],
    ]
    a, b = whole.state_at(t), looped.state_at(t.reshape(-1, 1))
    for name in a.__dataclass_fields__:
        assert np.array_equal(getattr(a, name), getattr(b, name).ravel()), name


@pytest.mark.parametrize("runs, gap, pitch", LOOPS)
@pytest.mark.parametrize("offset_mm", [(-5.0, 0.0), (0.3, -0.2)])
def test_the_trace_under_a_trailing_camera_is_that_of_the_repeated_job(
    layers, runs, gap, pitch, offset_mm
):
    whole, looped = loops(layers, runs, gap, pitch)
    t = np.random.default_rng(4).uniform(0.0, whole.duration_s - 1.0, 6000)
    state = whole.state_at(t)
    x, y = state.x_mm + offset_mm[0], state.y_mm + offset_mm[1]
    # the repeated job's index at the program's cell (a long one coarsens its own)
    a = whole.trace_index(layers.trace_index().cell_mm).query(x, y, 0.1, before_s=t)
    b = looped.locate(x, y, 0.1, before_s=t)
    assert a.found.sum() > 0.4 * t.size
    assert np.array_equal(a.found, b.found)
    for name in ("stroke", "repetition", "base_stroke", "feature"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    for name in ("print_time_s", "distance_mm", "x_mm", "y_mm", "s_mm"):
        np.testing.assert_allclose(getattr(b, name), getattr(a, name), atol=1e-7, err_msg=name)
    # a point where two segments meet belongs to either: the segment named holds the time
    s, hit = whole.segments, b.found
    segment = b.segment[hit]
    assert np.all(s["t0_s"][segment] <= b.print_time_s[hit] + 1e-9)
    assert np.all(b.print_time_s[hit] <= s["t1_s"][segment] + 1e-9)
    assert np.mean(segment == a.segment[hit]) > 0.99


def test_a_point_asked_without_a_time_finds_the_last_print_over_it(layers):
    whole, looped = loops(layers, 3.5, 0.0, None)
    x, y = np.meshgrid(np.linspace(0.0, 40.0, 60), np.linspace(0.0, 12.0, 30))
    a = whole.trace_index(layers.trace_index().cell_mm).query(x, y, 0.05)
    b = looped.locate(x, y, 0.05)
    assert b.found.shape == x.shape and b.found.sum() > 50
    assert np.array_equal(a.found, b.found)
    assert np.array_equal(a.repetition, b.repetition)
    np.testing.assert_allclose(b.print_time_s, a.print_time_s, atol=1e-7)


def test_a_program_whose_stroke_runs_into_the_next_run_is_held_whole():
    text = "ptp/e (X,Y),0,0\nOUT0.0=1\nptp/e (X,Y),4,0\nptp/e (X,Y),4,3"
    job = read_program_text(text, process_speed_mm_s=2.0)
    assert job.end_shutter_open
    looped = loop_job(job, 60.0)
    whole = job.repeat(60.0)
    assert looped.held_whole
    t = np.linspace(-1.0, 61.0, 500)
    assert np.array_equal(looped.state_at(t).stroke, whole.state_at(t).stroke)
    assert looped.whole().n_strokes == whole.n_strokes


def test_a_loop_asked_over_two_days_holds_what_it_holds_over_half_a_day(layers):
    """The camera's delays over 12 h and over 48 h: the Python memory left held and the peak
    while asking are about the same (the repeated job holds 39 MB more at 48 h than at 24 h)."""
    trailing_delays(loop_job(layers, 3600.0), (-5.0, 0.0), 3600.0)  # the program's index
    figures = {}
    for hours in (12, 48):
        tracemalloc.start()
        looped = loop_job(layers, hours * 3600.0)
        delays = trailing_delays(looped, (-5.0, 0.0), hours * 3600.0)
        held, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        figures[hours] = (held - delays.nbytes, peak - delays.nbytes, looped.repetitions)
    (held_short, peak_short, runs_short), (held_long, peak_long, runs_long) = figures.values()
    assert runs_long > 3 * runs_short
    assert held_long - held_short < 2e6, figures
    assert peak_long - peak_short < 8e6, figures


def test_a_looped_job_print_is_filed_and_run_as_with_every_run_held(tmp_path):
    """A 12-min print of a 166-s public program (four runs and a part), the camera 5 mm
    behind: the twin over the loop answered run by run is the twin over the repeated job."""
    program = DATA / "1-nafbot.prg"
    record = simulate_job(program, "exp1", seed=4, duration_min=12.0)
    runs = {}
    for held in (True, False):
        job = program_for_record(record, program, held=held)
        chunks = []
        run = Twin.default().run(record, job=job, sink=_collect(chunks))
        runs[held] = (job, run, chunks)
    (whole, a, chunks_a), (looped, b, chunks_b) = runs[True], runs[False]
    assert isinstance(looped, LoopedJob) and looped.repetitions == whole.repetitions == 5
    assert a.camera_counts == b.camera_counts and a.camera_counts["filed"] > 300
    assert len(chunks_a) == len(chunks_b) > 1
    for x, y in zip(chunks_a, chunks_b, strict=True):
        np.testing.assert_array_equal(x.filtered.means, y.filtered.means)
        for name in ("measurements", "line_factors", "n_camera"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=name)
    np.testing.assert_array_equal(a.end_mean, b.end_mean)


def _collect(chunks: list):
    """A twin's sink that keeps its chunks."""
    return lambda first, chunk: chunks.append(chunk)


@pytest.mark.parametrize("runs, gap, pitch", LOOPS)
def test_the_seconds_of_a_loop_are_those_of_the_repeated_job(layers, runs, gap, pitch):
    whole, looped = loops(layers, runs, gap, pitch)
    D = layers.duration_s
    # windows inside a run, across a run's end and the move to the next, and over the end
    for start, seconds in (
        (0.0, 50),
        (D - 20.0, 60),
        (2 * D - 7.0, 400),
        (whole.duration_s - 30, 90),
    ):
        a = whole.per_second(seconds, start)
        b = looped.per_second(seconds, start)
        assert list(a.columns) == list(b.columns)
        for name in ("stroke_first", "stroke_last", "strokes"):
            assert a[name].tolist() == b[name].tolist(), (start, name)
        for name in ("shutter_open_fraction", "printing_speed_mm_s", "printed_length_mm",
                     "platen_speed_mm_s", "time_s"):  # fmt: skip
            np.testing.assert_allclose(b[name], a[name], atol=1e-9, err_msg=f"{start} {name}")


def test_the_mpc_reads_the_seconds_ahead_of_a_loop_over_days_as_of_the_repeated_job(layers):
    """Three days of the seven-layer program: the preview of the loop answered run by run is
    the repeated job's, late in the print too (it is worked out an hour at a time)."""
    whole, looped = loops(layers, 3 * 86400.0 / layers.duration_s, 0.0, None)
    a, b = JobPreview(whole, horizon_s=60), JobPreview(looped, horizon_s=60)
    for t in (0.0, 3590.0, 2.5 * 86400.0, whole.duration_s - 20.0, whole.duration_s + 5.0):
        np.testing.assert_allclose(b.line(t), a.line(t), atol=1e-9, err_msg=str(t))
    assert b.line(2.5 * 86400.0)[:, 0].sum() > 10  # it prints then


def test_a_live_job_print_past_a_day_still_follows_the_program(layers):
    """The live twin's loop spans the longest record (14 days) without holding it: the
    columns it fills 30 h in are those of the program repeated to then (a loop of one day
    left the stage still at its end)."""
    looped = live_loop(layers)
    assert isinstance(looped, LoopedJob) and looped.duration_s == MAX_RECORD_SECONDS
    t = 30 * 3600.0 + np.arange(0.0, 600.0)
    whole = layers.repeat(31 * 3600.0)
    y = np.full((t.size, 5), np.nan)
    y[:, :2] = 50.0
    a = JobColumns(whole, "trailing", (-5.0, 0.0)).fill(t, y)
    b = JobColumns(looped, "trailing", (-5.0, 0.0)).fill(t, y)
    assert b["shutter_open"].mean() > 0.5
    for name in ("shutter_open", "platen_speed_mm_s"):
        np.testing.assert_array_equal(b[name], a[name], err_msg=name)
    assert np.isfinite(b["printed_at_s"]).sum() > 100
