"""Arcs, speeds, shutter, the 1 Hz aggregation, portions and looping against hand figures."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ajtwin.job import read_program, read_program_text

DATA = Path(__file__).parent / "data" / "prg"
PI = math.pi


def one_stroke(body: str, speed: float = 2.0, start=(2.0, 0.0)):
    """A program printing ``body`` (segments) as one stroke from ``start``."""
    text = (
        f"ptp/e (X,Y),{start[0]},{start[1]}\n"
        "Start gIntSubBuffer,ShutterOpen\n"
        f"MSEG (X,Y),{start[0]},{start[1]}\n"
        f"{body}\n"
        "ENDS (X,Y)\n"
        "till ^X_AST.#MOVE\n"
        "Start gIntSubBuffer,ShutterClose\n"
    )
    return read_program_text(text, process_speed_mm_s=speed)


# -- the two arc forms against hand geometry ------------------------------------------------


def test_quarter_circle_arc2_and_arc1_give_the_same_path():
    """Radius 2 around the origin from (2, 0) to (0, 2), counter-clockwise: length π."""
    by_sweep = one_stroke(f"arc2 (X,Y),0,0,{PI / 2!r}")
    by_end = one_stroke("arc1 (X,Y),0,0,0,2,+")
    for job in (by_sweep, by_end):
        summary = job.summary()
        assert summary["printed_length_mm"] == pytest.approx(PI, rel=1e-12)
        assert summary["print_time_s"] == pytest.approx(PI / 2, rel=1e-12)
        middle = job.state_at(PI / 4)  # half way, at 2 mm/s
        assert (middle.x_mm, middle.y_mm) == pytest.approx((math.sqrt(2), math.sqrt(2)), abs=1e-12)
        # moving counter-clockwise: velocity (-√2, √2) at 2 mm/s
        assert (middle.vx_mm_s, middle.vy_mm_s) == pytest.approx(
            (-math.sqrt(2), math.sqrt(2)), abs=1e-12
        )
        assert summary["bbox_mm"] == pytest.approx([0.0, 0.0, 2.0, 2.0], abs=1e-12)
    t = np.linspace(0, PI / 2, 57)
    a, b = by_sweep.state_at(t), by_end.state_at(t)
    np.testing.assert_allclose(a.x_mm, b.x_mm, atol=1e-12)
    np.testing.assert_allclose(a.y_mm, b.y_mm, atol=1e-12)
    np.testing.assert_allclose(np.hypot(a.x_mm, a.y_mm), 2.0, atol=1e-12)


def test_clockwise_arc1_takes_the_long_way_round():
    """From (2, 0) to (0, 2) clockwise: three quarters of the circle, through (0, -2)."""
    job = one_stroke("arc1 (X,Y),0,0,0,2,-")
    assert job.summary()["printed_length_mm"] == pytest.approx(3 * PI, rel=1e-12)
    quarter = job.state_at(PI / 2)  # a quarter of the circle (π mm) later
    assert (quarter.x_mm, quarter.y_mm) == pytest.approx((0.0, -2.0), abs=1e-12)
    assert job.summary()["bbox_mm"] == pytest.approx([-2.0, -2.0, 2.0, 2.0], abs=1e-12)
    same = one_stroke(f"arc2 (X,Y),0,0,{-1.5 * PI!r}")
    t = np.linspace(0, 1.5 * PI, 31)
    np.testing.assert_allclose(same.state_at(t).x_mm, job.state_at(t).x_mm, atol=1e-12)
    np.testing.assert_allclose(same.state_at(t).y_mm, job.state_at(t).y_mm, atol=1e-12)


def test_half_circle_negative_sweep_and_full_circle():
    half = one_stroke(f"arc2 (X,Y),1,0,{-PI!r}", start=(2.0, 0.0))  # radius 1 clockwise
    assert half.summary()["printed_length_mm"] == pytest.approx(PI)
    bottom = half.state_at(PI / 4)  # half way along π mm at 2 mm/s: clockwise, so below
    assert (bottom.x_mm, bottom.y_mm) == pytest.approx((1.0, -1.0), abs=1e-12)
    full = one_stroke("arc1 (X,Y),1,0,2,0,+")  # end point = start point: a full turn
    assert full.summary()["printed_length_mm"] == pytest.approx(2 * PI)
    assert full.summary()["bbox_mm"] == pytest.approx([0.0, -1.0, 2.0, 1.0], abs=1e-12)


def test_the_public_programs_u_turns_are_clockwise_semicircles():
    """`arc2 …,-1.5708` twice after a line going up: a clockwise U-turn over the top."""
    body = "line (X,Y),0,1\narc2 (X,Y),0.5,1,-1.57080\narc2 (X,Y),0.5,1,-1.57080\nline (X,Y),1,0"
    job = one_stroke(body, start=(0.0, 0.0))
    s = job.segments
    arcs = s["kind"] == 1
    assert arcs.sum() == 2
    top = job.state_at(1.0 / 2 + (0.5 * 1.5708) / 2)  # after the line and the first arc
    assert (top.x_mm, top.y_mm) == pytest.approx((0.5, 1.5), abs=1e-5)
    # the arcs end 3.7 nm below y = 1 (1.57080 is not exactly pi/2): the last line is shorter
    end_y = 1 + 0.5 * math.sin(PI - 2 * 1.5708)
    assert job.summary()["printed_length_mm"] == pytest.approx(1 + 1.5708 + end_y, rel=1e-12)


# -- the other post style ---------------------------------------------------------------------


def test_other_post_style_matches_hand_figures():
    """tests/data/prg/other_style.prg, by hand:

    feature 1: open at 0, WAIT OpenDelay (50 ms); MSEG default speed VEL(X)=5:
      LINE/V 3 mm at gDblProcessSpeed=3 (1 s), ARC1 half circle r=1 (π mm at 5 mm/s),
      LINE/V 3 mm at 3 (1 s); close, WAIT CloseDelay (20 ms)
    rapid (1,3)→(10,1) at gDblRapidSpeed=20: √85 mm
    feature 2: open, 50 ms, PTP/E 2 mm at VEL(X)=5 (0.4 s), close, 20 ms.
    """
    job = read_program(DATA / "other_style.prg", process_speed_mm_s=2.0, rapid_speed_mm_s=10.0)
    summary = job.summary()
    assert summary["strokes"] == 2
    assert summary["printed_length_mm"] == pytest.approx(6 + PI + 2, rel=1e-12)
    assert summary["rapid_length_mm"] == pytest.approx(math.sqrt(85), rel=1e-12)
    total = 0.05 + 1 + PI / 5 + 1 + 0.02 + math.sqrt(85) / 20 + 0.05 + 0.4 + 0.02
    assert summary["print_time_s"] == pytest.approx(total, rel=1e-12)
    assert [f["feature"] for f in summary["features"]] == [1, 2]
    assert [f["name"] for f in summary["features"]] == ["outline", "bar"]
    assert job.strokes["feature"].tolist() == [1, 2]
    speeds = {round(u["speed_mm_s"], 9): u for u in summary["print_speeds"]}
    assert speeds[3.0]["length_mm"] == pytest.approx(6.0) and speeds[3.0]["kind"] == "program"
    assert "gDblProcessSpeed = 3" in speeds[3.0]["source"]
    assert speeds[5.0]["length_mm"] == pytest.approx(PI + 2) and "VEL(0)" in speeds[5.0]["source"]
    assert summary["rapid_speeds"][0]["speed_mm_s"] == 20.0
    # the given GUI speeds were not needed, and the reader says so
    assert any("given process speed" in note for note in summary["notes"])
    # ARC1 ... + : counter-clockwise around (4, 2) from (4, 1): through (5, 2)
    mid_arc = job.state_at(0.05 + 1 + PI / 10)
    assert (mid_arc.x_mm, mid_arc.y_mm) == pytest.approx((5.0, 2.0), abs=1e-12)
    assert mid_arc.speed_mm_s == pytest.approx(5.0)


def test_commands_are_case_insensitive():
    text = (DATA / "other_style.prg").read_text()
    a = read_program_text(text).summary()
    b = read_program_text(text.lower()).summary()
    c = read_program_text(text.upper()).summary()
    for key in ("strokes", "printed_length_mm", "rapid_length_mm", "print_time_s"):
        assert a[key] == pytest.approx(b[key]) == pytest.approx(c[key])


# -- shutter, dwells, the 1 Hz record ----------------------------------------------------------

HAND = """
ptp/e (X,Y),0,0
OUT0.0=1
ptp/e (X,Y),1,0
OUT0.0=0
wait 700
OUT0.0=1
ptp/e (X,Y),1,2
wait 300
OUT0.0=0
ptp/ev (X,Y),0,0,10
wait 1500
"""
# timeline by hand at 2 mm/s: stroke 0 [0, 0.5] (1 mm); closed dwell [0.5, 1.2];
# stroke 1 [1.2, 2.5]: 2 mm in [1.2, 2.2], open dwell [2.2, 2.5]; rapid √5 mm in
# [2.5, 2.5 + √5/10]; closed dwell 1.5 s; end at 4.0 + √5/10.


def test_shutter_closed_spans_are_not_strokes():
    text = """
ptp/e (X,Y),0,0
OUT0.0=1
ptp/e (X,Y),3,0
OUT0.0=0
ptp/e (X,Y),3,3
OUT0.0=1
ptp/e (X,Y),0,3
OUT0.0=0
"""
    job = read_program_text(text, process_speed_mm_s=1.0)
    summary = job.summary()
    assert summary["strokes"] == 2
    assert summary["printed_length_mm"] == pytest.approx(6.0)
    assert summary["rapid_length_mm"] == pytest.approx(3.0)
    closed = job.state_at(4.5)  # on the closed move from (3, 0) to (3, 3)
    assert not closed.shutter_open and closed.stroke == -1 and closed.speed_mm_s == 1.0
    table = job.timeline()
    assert (table.loc[table["shutter_open"] == 0, "stroke"] == -1).all()
    assert not job.locate(3.0, 1.5, radius_mm=0.01).found  # nothing printed there
    assert job.locate(1.5, 0.0, radius_mm=0.01).stroke == 0


def test_per_second_aggregation_on_a_hand_program():
    job = read_program_text(HAND, process_speed_mm_s=2.0)
    end = 4.0 + math.sqrt(5) / 10
    assert job.duration_s == pytest.approx(end)
    table = job.per_second()
    assert len(table) == 5
    np.testing.assert_allclose(
        table["shutter_open_fraction"], [0.5, 0.8, 0.5, 0.0, 0.0], atol=1e-12
    )
    np.testing.assert_allclose(table["printed_length_mm"], [1.0, 1.6, 0.4, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(table["printing_speed_mm_s"][:3], [2.0, 2.0, 0.8], atol=1e-12)
    assert table["printing_speed_mm_s"][3:].isna().all()
    np.testing.assert_allclose(
        table["platen_speed_mm_s"], [1.0, 1.6, 0.4 + math.sqrt(5), 0, 0], atol=1e-12
    )
    assert table["strokes"].tolist() == [(0,), (1,), (1,), (), ()]
    assert table["stroke_first"].tolist() == [0, 1, 1, -1, -1]
    longer = job.per_second(duration_s=7)
    assert len(longer) == 7 and longer["shutter_open_fraction"][5:].eq(0).all()


def test_state_at_follows_the_hand_timeline():
    job = read_program_text(HAND, process_speed_mm_s=2.0)
    state = job.state_at([-1.0, 0.25, 1.0, 1.7, 2.3, 100.0])
    np.testing.assert_allclose(state.x_mm, [0, 0.5, 1, 1, 1, 0], atol=1e-12)
    np.testing.assert_allclose(state.y_mm, [0, 0, 0, 1, 2, 0], atol=1e-12)
    np.testing.assert_allclose(state.vx_mm_s, [0, 2, 0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(state.vy_mm_s, [0, 0, 0, 2, 0, 0], atol=1e-12)
    assert state.shutter_open.tolist() == [False, True, False, True, True, False]
    assert state.stroke.tolist() == [-1, 0, -1, 1, 1, -1]


def test_portions_split_strokes_with_their_print_times():
    job = read_program_text(HAND, process_speed_mm_s=2.0)
    portions = job.portions(max_length_mm=0.5)
    one = portions[portions["stroke"] == 1]
    assert len(one) == 4 and one["length_mm"].tolist() == pytest.approx([0.5] * 4)
    np.testing.assert_allclose(one["y_from_mm"], [0, 0.5, 1, 1.5], atol=1e-12)
    np.testing.assert_allclose(one["y_to_mm"], [0.5, 1, 1.5, 2], atol=1e-12)
    # shutter opens at 1.2 s; 0.25 s per portion; the last ends when the shutter closes
    np.testing.assert_allclose(one["t_from_s"], [1.2, 1.45, 1.7, 1.95], atol=1e-12)
    np.testing.assert_allclose(one["t_to_s"], [1.45, 1.7, 1.95, 2.5], atol=1e-12)
    uneven = job.portions(max_length_mm=0.8)  # 1 mm -> 2 x 0.5; 2 mm -> 3 x 0.667
    assert uneven.groupby("stroke").size().tolist() == [2, 3]
    assert (uneven["length_mm"] <= 0.8).all()


def test_repeating_a_job_to_a_long_run():
    text = "ptp/ev (X,Y),0,0,10\n" + HAND.strip().replace(
        "ptp/ev (X,Y),0,0,10", "ptp/ev (X,Y),5,0,10"
    )
    job = read_program_text(text, process_speed_mm_s=2.0)
    D = job.duration_s  # ends at (5, 0); the program starts at (0, 0): 5 mm back at 10 mm/s
    looped = job.repeat(90 * 60.0)
    period = D + 0.5
    runs = 1 + math.ceil((5400 - D) / period)
    assert looped.repetitions == runs
    np.testing.assert_allclose(looped.repetition_offsets_s, np.arange(runs) * period)
    assert looped.duration_s == pytest.approx(5400.0)
    assert looped.n_strokes == 2 * runs or looped.n_strokes == 2 * runs - 1
    # run k is the program shifted by its offset
    t = np.linspace(0.0, D, 101)[:-1]
    for k in (1, runs // 2):
        a, b = job.state_at(t), looped.state_at(t + looped.repetition_offsets_s[k])
        np.testing.assert_allclose(a.x_mm, b.x_mm, atol=1e-9)
        np.testing.assert_allclose(a.y_mm, b.y_mm, atol=1e-9)
        assert (a.shutter_open == b.shutter_open).all()
    # between runs: the return move (rapid, shutter closed)
    back = looped.state_at(D + 0.25)
    assert (back.x_mm, back.speed_mm_s, back.shutter_open) == pytest.approx((2.5, 10.0, False))
    strokes = looped.strokes
    assert strokes["repetition"].max() == runs - 1
    assert set(strokes["base_stroke"]) == {0, 1}
    per = looped.per_second()
    assert len(per) == 5400
    assert per["printed_length_mm"].sum() == pytest.approx(strokes["length_mm"].sum())
    # the inverse query on a part printed again and again: the latest run before the frame
    hit = looped.locate(1.0, 1.0, radius_mm=0.01, before_s=3 * period + 2.0)
    assert hit.repetition == 3 and hit.base_stroke == 1
    assert hit.print_time_s == pytest.approx(3 * period + 1.7)


def test_dwell_with_open_shutter_belongs_to_its_stroke():
    job = read_program_text(HAND, process_speed_mm_s=2.0)
    stroke = job.strokes.iloc[1]
    assert stroke["t_start_s"] == pytest.approx(1.2) and stroke["t_end_s"] == pytest.approx(2.5)
    assert stroke["length_mm"] == pytest.approx(2.0)
    assert stroke["mean_speed_mm_s"] == pytest.approx(2.0 / 1.3)
