"""Process speeds per layer, stroke or feature: layers found in the geometry, the job re-timed
by hand-computed figures, schedules read from text and files, and kept through a record."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ajtwin.estimation.print_time import program_for_record
from ajtwin.job import SpeedSchedule, apply_speed_schedule, read_program, read_program_text
from ajtwin.job.speeds import stroke_layers
from ajtwin.simulation.job_print import JobSettings, simulate_job

PUBLIC = Path(__file__).parent / "data" / "prg" / "prg2svg" / "4-naf 654321.prg"


def stroke(x0, y0, x1, y1) -> str:
    """One straight stroke from (x0, y0) to (x1, y1), the rapid to its start included."""
    return f"ptp/e (X,Y),{x0},{y0}\nOUT0.0=1\nptp/e (X,Y),{x1},{y1}\nOUT0.0=0\n"


# A bar and a cross-bar over its middle, drawn twice: two layers of two strokes each (the
# cross-bar crosses the bar at one point only, so it stays in its layer).
TWO_LAYERS = (stroke(0, 0, 4, 0) + stroke(2, -1, 2, 1)) * 2


def test_a_part_drawn_again_is_a_new_layer_and_a_crossing_stroke_is_not():
    job = read_program_text(TWO_LAYERS, process_speed_mm_s=2.0)
    assert stroke_layers(job).tolist() == [0, 0, 1, 1]


def test_the_public_program_has_six_layers_of_six_to_one_samples():
    """`4-naf 654321.prg`: six Nafion samples of 6, 5, 4, 3, 2 and 1 layers, each pass an
    alignment L, a cross (two strokes) and a fill: 24, 20, 16, 12, 8 and 4 strokes per layer."""
    layers = stroke_layers(read_program(PUBLIC))
    assert np.bincount(layers).tolist() == [24, 20, 16, 12, 8, 4]
    assert np.all(np.diff(layers) >= 0)


def test_a_stroke_schedule_retimes_the_printed_moves_and_shifts_what_follows():
    """Strokes of 4, 2 and 1 mm at 2 mm/s; the second stroke at 4 mm/s takes 0.5 s instead
    of 1 s, and everything after it starts 0.5 s earlier; the moves between strokes keep
    their speed."""
    text = stroke(0, 0, 4, 0) + stroke(0, 1, 2, 1) + stroke(0, 2, 1, 2)
    job = read_program_text(text, process_speed_mm_s=2.0, rapid_speed_mm_s=10.0)
    fast = apply_speed_schedule(job, SpeedSchedule("stroke", ranges=((1, 1, 4.0),)))
    before, after = job.strokes, fast.strokes
    assert after["duration_s"].tolist() == pytest.approx([2.0, 0.5, 0.5], abs=1e-12)
    assert after["t_start_s"].iloc[2] == pytest.approx(before["t_start_s"].iloc[2] - 0.5, abs=1e-12)
    assert fast.duration_s == pytest.approx(job.duration_s - 0.5, abs=1e-12)
    # geometry and lengths unchanged; the rapids keep their speed
    assert after["length_mm"].tolist() == pytest.approx(before["length_mm"].tolist(), abs=1e-12)
    middle = fast.state_at(after["t_start_s"].iloc[1] + 0.25)
    assert (float(middle.x_mm), float(middle.speed_mm_s)) == pytest.approx((1.0, 4.0))
    closed = ~fast.segments["shutter_open"]
    np.testing.assert_array_equal(
        fast.segments["speed_mm_s"][closed],
        job.segments["speed_mm_s"][~job.segments["shutter_open"]],
    )
    sources = fast.summary()["print_speeds"]
    assert {s["speed_mm_s"]: s["kind"] for s in sources} == {2.0: "given", 4.0: "schedule"}


def test_successive_layer_speeds_repeat_and_keep_the_printed_length():
    job = read_program(PUBLIC)
    fast = read_program(PUBLIC, speed_schedule=SpeedSchedule.parse("2,4,3"))
    layers = stroke_layers(job)
    seg = fast.segments
    printing = seg["shutter_open"] & (seg["length_mm"] > 0)
    expected = np.array([2.0, 4.0, 3.0])[layers[seg["stroke"][printing]] % 3]
    np.testing.assert_array_equal(seg["speed_mm_s"][printing], expected)
    # a move of the stroke lasts its length over its speed
    duration = (seg["t1_s"] - seg["t0_s"])[printing]
    np.testing.assert_allclose(
        duration, seg["length_mm"][printing] / expected, rtol=1e-9, atol=1e-12
    )
    assert fast.summary()["printed_length_mm"] == pytest.approx(
        job.summary()["printed_length_mm"], rel=1e-12
    )
    # the time saved is the printed length of each layer over its speed, against 2 mm/s
    length = np.bincount(layers, weights=job.strokes["length_mm"].to_numpy())
    saved = sum(length[k] * (1 / 2.0 - 1 / [2.0, 4.0, 3.0][k % 3]) for k in range(6))
    assert job.duration_s - fast.duration_s == pytest.approx(saved, rel=1e-9)


def test_a_looped_job_restarts_the_schedule_on_every_run():
    fast = read_program(PUBLIC, speed_schedule=SpeedSchedule.parse("2,4,3"))
    looped = fast.repeat(2.9 * fast.duration_s, pitch_mm=(35.0, 10.0))
    assert looped.speed_schedule == fast.speed_schedule
    seg = looped.segments
    printing = seg["shutter_open"] & (seg["length_mm"] > 0)
    for base, speed in ((3, 2.0), (24, 4.0), (47, 3.0)):  # fills of layers 0, 1 and 2
        mine = printing & (seg["base_stroke"] == base)
        assert np.unique(seg["repetition"][mine]).tolist() == [0, 1, 2]
        np.testing.assert_array_equal(seg["speed_mm_s"][mine], speed)


def test_schedules_from_text_and_files(tmp_path):
    assert SpeedSchedule.parse("2,4,3") == SpeedSchedule("layer", (2.0, 4.0, 3.0))
    assert SpeedSchedule.parse("stroke: 1.5, 2").speeds_mm_s == (1.5, 2.0)
    path = tmp_path / "speeds.toml"
    path.write_text(
        'per = "stroke"\n[[range]]\nfirst = 0\nlast = 3\nspeed_mm_s = 4\n'
        "[[range]]\nfirst = 4\nlast = 7\nspeed_mm_s = 3.0\n"
    )
    schedule = SpeedSchedule.parse(str(path))
    assert schedule.ranges == ((0, 3, 4.0), (4, 7, 3.0))
    assert schedule.unit_speeds([0, 3, 4, 8, -1]).tolist()[:3] == [4.0, 4.0, 3.0]
    assert np.isnan(schedule.unit_speeds([8, -1])).all()
    assert SpeedSchedule.from_meta(schedule.to_meta()) == schedule
    assert SpeedSchedule.from_meta(None) is None


@pytest.mark.parametrize(
    "text, says",
    [
        ("2,,3", "give speeds"),
        ("2,0", "positive"),
        ("2,-1", "positive"),
        ("2,nan", "positive"),
        ("layer:abc", "not a speed"),
        ("run:2,4", "choose one of layer, stroke, feature"),
    ],
)
def test_bad_schedules_are_refused_saying_why(text, says):
    with pytest.raises(ValueError, match=says):
        SpeedSchedule.parse(text)


def test_a_schedule_file_with_both_forms_or_a_bad_range_is_refused(tmp_path):
    both = tmp_path / "both.toml"
    both.write_text("speeds_mm_s = [2]\n[[range]]\nfirst = 0\nlast = 1\nspeed_mm_s = 3\n")
    with pytest.raises(ValueError, match="both.toml.*not both"):
        SpeedSchedule.parse(str(both))
    backwards = tmp_path / "backwards.toml"
    backwards.write_text("[[range]]\nfirst = 3\nlast = 1\nspeed_mm_s = 3\n")
    with pytest.raises(ValueError, match="first <= last"):
        SpeedSchedule.parse(str(backwards))
    missing = tmp_path / "missing.toml"
    missing.write_text("[[range]]\nfirst = 3\n")
    with pytest.raises(ValueError, match="needs first, last and speed_mm_s"):
        SpeedSchedule.parse(str(missing))


def test_speeds_per_feature_need_features():
    job = read_program_text(TWO_LAYERS, process_speed_mm_s=2.0)
    with pytest.raises(ValueError, match="names no features"):
        apply_speed_schedule(job, SpeedSchedule.parse("feature:2,4"))


def test_a_looped_job_cannot_be_rescheduled():
    job = read_program_text(TWO_LAYERS, process_speed_mm_s=2.0).repeat(60.0)
    with pytest.raises(ValueError, match="then loop it"):
        apply_speed_schedule(job, SpeedSchedule.parse("2,4"))


def test_a_job_print_keeps_its_schedule_and_the_twin_reads_the_program_as_it_ran(tmp_path):
    program = tmp_path / "two_layers.prg"
    program.write_text(TWO_LAYERS)
    schedule = SpeedSchedule.parse("2,4")
    record = simulate_job(
        program, "exp1", seed=1, duration_min=0.5, job_settings=JobSettings(speed_schedule=schedule)
    )
    assert record.meta["job"]["process_speed_schedule"] == schedule.to_meta()
    job = program_for_record(record, program)
    assert job.speed_schedule == schedule
    expected = read_program(program, speed_schedule=schedule).repeat(30.0)
    np.testing.assert_array_equal(job.segments["t1_s"], expected.segments["t1_s"])
    # the record's speed column is the schedule's: layer 1 printed at 4 mm/s
    speeds = record.platen_speed[record.shutter_open > 0]
    assert set(np.round(speeds, 9)) <= {0.0, 2.0, 4.0} and 4.0 in speeds
