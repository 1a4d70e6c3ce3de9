"""The inverse query: a point on the part -> the trace there, its stroke and print time."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ajtwin.job import read_program, read_program_text

DATA = Path(__file__).parent / "data" / "prg" / "prg2svg"

stroke_shape = st.tuples(
    st.floats(0.2, 6.0),  # length of the straight part [mm]
    st.floats(0.05, 0.45),  # radius of the arc that follows [mm]
    st.floats(0.2, math.pi),  # its sweep (counter-clockwise) [rad]
    st.floats(0.5, 8.0),  # print speed of the stroke [mm/s]
    st.floats(-3.0, 3.0),  # x of its start [mm]
)


def build(strokes, rapid=12.0):
    """A program of strokes in separate bands (y = 3k), and its hand timeline.

    Each stroke: a line along +x, then a counter-clockwise arc (tangent to the line) —
    MSEG with speeds by /v. Returns the text and, per stroke, the start time of its motion,
    the line's start, its length, the arc's radius and sweep and the speed.
    """
    lines = []
    truth = []
    t = 0.0
    position = None
    for k, (length, radius, sweep, speed, x0) in enumerate(strokes):
        y0 = 3.0 * k
        if position is not None:
            t += math.hypot(x0 - position[0], y0 - position[1]) / rapid
        lines += [
            f"ptp/ev (X,Y),{x0!r},{y0!r},{rapid!r}",
            "OUT0.0=1",
            f"MSEG/v (X,Y),{x0!r},{y0!r},{speed!r}",
            f"line (X,Y),{x0 + length!r},{y0!r}",
            f"arc2 (X,Y),{x0 + length!r},{y0 + radius!r},{sweep!r}",
            "ENDS (X,Y)",
            "till ^X_AST.#MOVE",
            "OUT0.0=0",
        ]
        truth.append((t, x0, y0, length, radius, sweep, speed))
        t += (length + radius * sweep) / speed
        angle = -math.pi / 2 + sweep
        position = (x0 + length + radius * math.cos(angle), y0 + radius + radius * math.sin(angle))
    return "\n".join(lines), truth


def point_on(truth_row, fraction):
    """Point at ``fraction`` of the stroke's length, and when it was printed (by hand)."""
    t0, x0, y0, length, radius, sweep, speed = truth_row
    s = fraction * (length + radius * sweep)
    if s <= length:
        return x0 + s, y0, t0 + s / speed, s
    angle = -math.pi / 2 + (s - length) / radius
    x = x0 + length + radius * math.cos(angle)
    y = y0 + radius + radius * math.sin(angle)
    return x, y, t0 + s / speed, s


@settings(max_examples=60, deadline=None)
@given(
    strokes=st.lists(stroke_shape, min_size=1, max_size=6),
    pick=st.integers(0, 10_000),
    fraction=st.floats(0.0, 1.0),
)
def test_a_point_on_a_stroke_returns_that_stroke_and_its_print_time(strokes, pick, fraction):
    text, truth = build(strokes)
    job = read_program_text(text)
    k = pick % len(strokes)
    x, y, t, s = point_on(truth[k], fraction)
    hit = job.locate(x, y, radius_mm=0.02)
    assert hit.found
    assert hit.stroke == k
    assert hit.distance_mm == pytest.approx(0.0, abs=1e-9)
    assert hit.print_time_s == pytest.approx(t, abs=1e-9)
    assert hit.s_mm == pytest.approx(s, abs=1e-9)
    # the direction of travel: +x on the line, then turning counter-clockwise
    turned = max(0.0, s - strokes[k][0]) / strokes[k][1]
    assert (hit.ux, hit.uy) == pytest.approx((math.cos(turned), math.sin(turned)), abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(
    strokes=st.lists(stroke_shape, min_size=2, max_size=5),
    pick=st.integers(0, 10_000),
    fraction=st.floats(0.0, 1.0),
    offset=st.floats(0.01, 0.2),
)
def test_a_point_beside_a_stroke_gives_its_distance_and_nothing_beyond_the_radius(
    strokes, pick, fraction, offset
):
    text, truth = build(strokes)
    job = read_program_text(text)
    k = pick % len(strokes)
    t0, x0, y0, length, radius, sweep, speed = truth[k]
    s = fraction * length  # on the straight part, move the point down (away from the arc)
    hit = job.locate(x0 + s, y0 - offset, radius_mm=0.25)
    assert hit.found and hit.stroke == k
    assert hit.distance_mm == pytest.approx(offset, abs=1e-9)
    assert hit.print_time_s == pytest.approx(t0 + s / speed, abs=1e-9)
    miss = job.locate(x0 + s, y0 - offset, radius_mm=offset * 0.99)
    assert not miss.found and miss.stroke == -1 and np.isnan(miss.print_time_s)


@settings(max_examples=25, deadline=None)
@given(strokes=st.lists(stroke_shape, min_size=1, max_size=4), fraction=st.floats(0.05, 0.95))
def test_only_traces_printed_before_the_frame_are_seen(strokes, fraction):
    text, truth = build(strokes)
    job = read_program_text(text)
    x, y, t, _ = point_on(truth[-1], fraction)
    speed = truth[-1][-1]
    assert job.locate(x, y, radius_mm=1e-4, before_s=t + 1e-9).found
    # 1 um of trace before the point: more than the radius away, even along the arc
    assert not job.locate(x, y, radius_mm=1e-4, before_s=t - 1e-3 / speed).found


@pytest.fixture(scope="module")
def fill_job():
    return read_program(DATA / "4-naf 654321.prg")


def test_many_points_on_the_public_fills(fill_job):
    """Random points on printed segments of the densest public program (19 um fills).

    This program prints the same Nafion area up to six times (samples of 1 to 6 layers),
    so most points lie on several coincident traces: asked at the moment a point is
    printed, the answer is the trace being printed; asked without a time, the last one.
    """
    job = fill_job
    s = job.segments
    rng = np.random.default_rng(7)
    printed = np.flatnonzero(s["shutter_open"] & (s["length_mm"] > 0))
    seg = rng.choice(printed, 20_000)
    f = rng.uniform(0, 1, seg.size)
    t = s["t0_s"][seg] + f * (s["t1_s"][seg] - s["t0_s"][seg])
    state = job.state_at(t)
    hits = job.locate(state.x_mm, state.y_mm, radius_mm=0.005, before_s=t + 1e-9)
    assert hits.found.all()
    assert np.abs(hits.distance_mm).max() < 1e-9
    np.testing.assert_array_equal(hits.stroke, s["stroke"][seg])
    np.testing.assert_allclose(hits.print_time_s, t, atol=1e-9)
    latest = job.locate(state.x_mm, state.y_mm, radius_mm=0.005)
    assert latest.found.all() and (latest.print_time_s >= t - 1e-9).all()
    reprinted = latest.stroke != hits.stroke
    assert 0.5 < reprinted.mean() < 1.0  # most of this part is printed more than once
    np.testing.assert_allclose(latest.x_mm, state.x_mm, atol=1e-9)
    np.testing.assert_allclose(latest.y_mm, state.y_mm, atol=1e-9)


def test_between_the_fill_lines_the_nearest_line_wins(fill_job):
    """Fill pitch 19.35 um: a point 5 um right of a line is 14.35 um from the next one."""
    job = fill_job
    hits = job.locate(np.array([2.14194 + 0.005]), np.array([2.0]), radius_mm=0.05)
    assert hits.found[0] and hits.distance_mm[0] == pytest.approx(0.005, abs=1e-6)
    assert hits.x_mm[0] == pytest.approx(2.14194, abs=1e-6)


def test_a_job_looped_over_its_part_is_queried_in_batches_that_fit(monkeypatch):
    """Where the traces pile up (the program looped over its own part: every run adds its
    traces to the same cells), a batch sized by the mean density held millions of pairs
    (1.4 GB for a 4-h print's camera horizon). Each batch now holds at most _BATCH_PAIRS
    pairs, and the hits are those of one unbounded batch."""
    import ajtwin.job.locate as locate

    job = read_program(DATA / "4-naf 654321.prg").repeat(4 * 3600.0)
    t = np.arange(0.0, 4 * 3600.0, 7.0)
    state = job.state_at(t)
    x, y = state.x_mm - 5.0, state.y_mm

    monkeypatch.setattr(locate, "_BATCH_PAIRS", 10**12)
    whole = job.trace_index().query(x, y, 0.3, before_s=t)
    sizes = []
    closest = locate.closest_point

    def counted(px, *args):
        sizes.append(len(px))
        return closest(px, *args)

    monkeypatch.setattr(locate, "closest_point", counted)
    monkeypatch.setattr(locate, "_BATCH_PAIRS", 100_000)
    batched = job.trace_index().query(x, y, 0.3, before_s=t)
    assert max(sizes) <= 100_000 and len(sizes) > 1
    for name in ("found", "print_time_s", "distance_mm"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(batched, name))
