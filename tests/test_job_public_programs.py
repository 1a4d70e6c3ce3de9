"""The seven public programs (jizhang495/prg2svg, MIT) against an independent tally.

The tally below is written separately from ajtwin.job: it walks the text line by line with
one regular expression, keeps the position as a complex number, turns arc2 by multiplying
with exp(i·sweep), and times every move as if the program waited for each one (the public
programs do: ptp/e, and `till` after every ENDS). It shares no code with the reader.
"""

from __future__ import annotations

import cmath
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.job import read_program, read_timeline

DATA = Path(__file__).parent / "data" / "prg" / "prg2svg"
PROGRAMS = sorted(DATA.glob("*.prg"))
PRINT, RAPID = 2.0, 10.0  # mm/s given to both: the GUI's values

_MOVE = re.compile(r"^(ptp/ev|ptp/e|mseg|line|arc2)\s*\(x,y\)\s*,(.*)$")


def tally(text: str, v_print: float, v_rapid: float) -> dict:
    position = None
    shutter = False
    in_block = False
    strokes = 0
    printed = rapid = seconds = 0.0
    for raw in text.splitlines():
        low = raw.strip().lower()
        if low.startswith("if "):
            in_block = True
            continue
        if in_block:
            in_block = low != "end"
            continue
        if "shutteropen" in low:
            shutter, strokes = True, strokes + 1
            continue
        if "shutterclose" in low:
            shutter = False
            continue
        if low.startswith("wait "):
            seconds += float(low.split()[1]) / 1000.0
            continue
        m = _MOVE.match(low)
        if m is None:
            continue
        words = [w.strip() for w in m.group(2).split(",")]
        numbers = [float(w) for w in words if w != "gdblrapidspeed"]
        if m.group(1) == "mseg":
            assert position is None or abs(complex(*numbers) - position) < 1e-9
            position = complex(*numbers)
            continue
        if m.group(1) == "arc2":
            centre = complex(numbers[0], numbers[1])
            step = abs(position - centre) * abs(numbers[2])
            position = centre + (position - centre) * cmath.exp(1j * numbers[2])
        else:
            target = complex(numbers[0], numbers[1])
            step = 0.0 if position is None else abs(target - position)
            position = target
        if shutter:
            printed += step
            seconds += step / v_print
        else:
            rapid += step
            seconds += step / v_rapid
    return {"strokes": strokes, "printed": printed, "rapid": rapid, "seconds": seconds}


@pytest.fixture(scope="module")
def jobs():
    return {p.name: read_program(p, PRINT, RAPID) for p in PROGRAMS}


def test_the_seven_programs_are_all_there():
    assert [p.name for p in PROGRAMS] == [
        "1-nafbot.prg",
        "2 and 6-Au.prg",
        "3-PPbot.prg",
        "4-naf 654321.prg",
        "4-naf1L.prg",
        "5-PPtop.prg",
        "7-naftop.prg",
    ]
    assert "MIT License" in (DATA / "LICENSE").read_text()


@pytest.mark.parametrize("program", PROGRAMS, ids=lambda p: p.name)
def test_strokes_length_and_time_match_an_independent_tally(program, jobs):
    expected = tally(program.read_text(), PRINT, RAPID)
    summary = jobs[program.name].summary()
    assert summary["strokes"] == expected["strokes"]
    assert summary["printed_length_mm"] == pytest.approx(expected["printed"], rel=1e-12, abs=1e-9)
    assert summary["rapid_length_mm"] == pytest.approx(expected["rapid"], rel=1e-12, abs=1e-9)
    assert summary["print_time_s"] == pytest.approx(expected["seconds"], rel=1e-12, abs=1e-9)


@pytest.mark.parametrize("program", PROGRAMS[:2], ids=lambda p: p.name)
def test_doubling_the_process_speed_halves_the_printing_time_only(program):
    slow = read_program(program, 2.0, 10.0).summary()
    fast = read_program(program, 4.0, 10.0).summary()
    moving_slow = slow["printed_length_mm"] / 2.0
    assert fast["printed_length_mm"] == pytest.approx(slow["printed_length_mm"], rel=1e-12)
    assert slow["print_time_s"] - fast["print_time_s"] == pytest.approx(moving_slow / 2, rel=1e-9)
    assert fast["print_speeds"][0]["kind"] == "given"


def test_the_part_the_issue_describes(jobs):
    """24-84 strokes, 0.3-5.1 m of printed path on a 30.5 x 8.5 mm part."""
    summaries = [job.summary() for job in jobs.values()]
    assert min(s["strokes"] for s in summaries) == 24
    assert max(s["strokes"] for s in summaries) == 84
    lengths = [s["printed_length_mm"] for s in summaries]
    assert 270 < min(lengths) < 300 and 5000 < max(lengths) < 5150
    for s in summaries:
        assert s["bbox_mm"] == pytest.approx([0.0, 0.0, 30.5, 8.5], abs=1e-9)
        assert s["features"] == []
        assert any("If (gIntFindFids = 1)" in note for note in s["notes"])


def test_speeds_say_where_they_came_from():
    job = read_program(PROGRAMS[0])
    summary = job.summary()
    assert summary["process_speed_mm_s"] == 2.0 and summary["process_speed_source"].startswith(
        "default"
    )
    assert summary["rapid_speed_mm_s"] == 10.0 and "stage.toml" in summary["rapid_speed_source"]
    given = read_program(PROGRAMS[0], 3.0, 25.0).summary()
    assert given["process_speed_mm_s"] == 3.0 and given["process_speed_source"].startswith("given")
    assert given["rapid_speed_mm_s"] == 25.0


def test_segments_cover_the_run_without_gaps_and_strokes_hold_the_printed_length(jobs):
    for job in jobs.values():
        s = job.segments
        assert s["t0_s"][0] == 0.0
        np.testing.assert_array_equal(s["t0_s"][1:], s["t1_s"][:-1])
        assert np.all(s["t1_s"] > s["t0_s"])
        # each segment ends where the next starts (arcs to the last digit of the program)
        gap = np.hypot(s["x0_mm"][1:] - s["x1_mm"][:-1], s["y0_mm"][1:] - s["y1_mm"][:-1])
        assert gap.max() < 1e-4
        strokes = job.strokes
        assert strokes["length_mm"].sum() == pytest.approx(job.summary()["printed_length_mm"])
        assert (strokes["t_start_s"].diff().dropna() > 0).all()
        # with the shutter open the stroke's speed is the process speed (or still)
        printed = s["shutter_open"] & (s["kind"] != 2)
        assert np.all(s["speed_mm_s"][printed] == PRINT)
        assert np.all(s["stroke"][~s["shutter_open"]] == -1)


def test_per_second_open_time_and_length_add_up(jobs):
    job = jobs["4-naf1L.prg"]
    table = job.per_second()
    summary = job.summary()
    assert len(table) == int(np.ceil(job.duration_s))
    assert table["shutter_open_fraction"].sum() == pytest.approx(summary["printing_time_s"])
    assert table["printed_length_mm"].sum() == pytest.approx(summary["printed_length_mm"])
    moved = summary["printed_length_mm"] + summary["rapid_length_mm"]
    assert table["platen_speed_mm_s"].sum() == pytest.approx(moved)
    printing = table["shutter_open_fraction"] > 0
    assert table.loc[~printing, "printing_speed_mm_s"].isna().all()
    assert (table.loc[printing, "printing_speed_mm_s"] <= PRINT + 1e-9).all()
    # every stroke appears in the seconds it was printed
    seen = sorted({k for strokes in table["strokes"] for k in strokes})
    assert seen == list(range(job.n_strokes))


def test_timeline_round_trips_through_parquet_and_csv(jobs, tmp_path):
    job = jobs["5-PPtop.prg"]
    table = job.timeline()
    assert list(table.columns) == [
        "time_s",
        "x_mm",
        "y_mm",
        "speed_mm_s",
        "shutter_open",
        "stroke",
        "feature",
        "line",
        "segment",
    ]
    assert table["time_s"].is_monotonic_increasing
    assert table["time_s"].iloc[-1] == pytest.approx(job.duration_s)
    # chords of the timeline stay within the documented tolerance of the exact arc
    mid_t = 0.5 * (table["time_s"].to_numpy()[:-1] + table["time_s"].to_numpy()[1:])
    exact = job.state_at(mid_t)
    chord_x = 0.5 * (table["x_mm"].to_numpy()[:-1] + table["x_mm"].to_numpy()[1:])
    chord_y = 0.5 * (table["y_mm"].to_numpy()[:-1] + table["y_mm"].to_numpy()[1:])
    assert np.hypot(exact.x_mm - chord_x, exact.y_mm - chord_y).max() <= 0.0005 + 1e-12
    for name in ("t.parquet", "t.csv"):
        job.write_timeline(tmp_path / name)
        back, meta = read_timeline(tmp_path / name)
        pd.testing.assert_frame_equal(back, table, check_dtype=False, atol=1e-9, rtol=1e-9)
        assert meta["strokes"] == job.n_strokes


def test_job_show_prints_the_summary_and_writes_timeline_and_plot(tmp_path):
    from ajtwin.cli import main

    program = DATA / "2 and 6-Au.prg"
    runner = CliRunner()
    result = runner.invoke(
        main, ["job", "show", str(program), "--process-speed", "2", "--rapid-speed", "10", "--json"]
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    expected = tally(program.read_text(), 2.0, 10.0)
    assert summary["strokes"] == expected["strokes"] == 24
    assert summary["printed_length_mm"] == pytest.approx(expected["printed"])
    assert summary["rapid_length_mm"] == pytest.approx(expected["rapid"])
    assert summary["print_time_s"] == pytest.approx(expected["seconds"])
    assert summary["bbox_mm"] == pytest.approx([0.0, 0.0, 30.5, 8.5])

    out, plot = tmp_path / "timeline.csv", tmp_path / "part.png"
    result = runner.invoke(
        main, ["job", "show", str(program), "--out", str(out), "--plot", str(plot)]
    )
    assert result.exit_code == 0, result.output
    assert "24 printed" in result.output
    assert "pass --process-speed" in result.output  # the default speed says it is one
    assert out.stat().st_size > 0 and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
