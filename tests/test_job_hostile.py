"""Hostile programs: each is refused naming its line, read right, or warned about — never a
traceback, a hang, a clock that swallows strokes or a loop that asks for memory no machine
has. Every case here crashed, hung or gave a wrong result before (the programs of a
held-out attack on the reader, written small)."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.cli.job import job as job_group
from ajtwin.estimation.print_time import job_as_printed
from ajtwin.io.schema import MAX_RECORD_SECONDS
from ajtwin.job import (
    ProgramError,
    ProgramWarning,
    load_reader_settings,
    read_program,
    read_program_text,
    require_printing,
)
from ajtwin.simulation.job_print import read_job
from test_bad_inputs import _no_hang
from test_job_errors import line_of, refused

OPEN = "Start gIntSubBuffer,ShutterOpen;TILL PST(gIntSubBuffer).#RUN = 0"
CLOSE = "Start gIntSubBuffer,ShutterClose;TILL PST(gIntSubBuffer).#RUN = 0"
TILL = "till (^X_AST.#MOVE) & (^Y_AST.#MOVE)"


def stroke(x0, y0, x1, y1) -> str:
    """One stroke in the public programs' style: rapid, open, wait, print, close."""
    return (
        f"ptp/ev (X,Y),{x0},{y0},gDblRapidSpeed\n{OPEN}\nwait 2\nptp/e (X,Y),{x1},{y1}\n"
        f"{TILL}\n{CLOSE}\nwait 2\n"
    )


def program(body: str) -> str:
    return "#0\n" + body + "STOP\n"


GOOD = program(stroke(0, 0, 5, 0) + stroke(5, 1, 0, 1))


# --------------------------------------------------------------------------- #
# Statements that crashed or lied: refused, naming the line
# --------------------------------------------------------------------------- #
DEEP_SUM = "+".join(["0.001"] * 5000)


@pytest.mark.parametrize(
    ("statement", "reason"),
    [
        # a traceback before (RecursionError, OverflowError, ZeroDivisionError, ValueError)
        (f"ptp/e (X,Y),{DEEP_SUM},0", "nested too deeply"),
        (f"ptp/e (X,Y),{'-' * 5000}1,0", "nested too deeply"),
        (f"ptp/e (X,Y),1{'0' * 400}*1,0", "too large (401 digits)"),
        ("!Feature 99999999999999999999999 big", "feature number 99999999999999999999999"),
        ("VEL(1e400) = 5", "not a finite number"),
        ("VEL(nan) = 5", "not a finite number"),
        ("ptp/e (X,Y),APOS(1e200*1e200),0", "not a finite number"),
        ("ptp/ev (X,Y),1e-300,0,1e308", "faster than any Aerosol Jet stage"),
        # a wrong result before: 1_0 read as 10, a stroke swallowed by a 1e297-s clock,
        # 1e300 mm/s accepted (then numpy's "Maximum allowed size exceeded")
        ("ptp/e (X,Y),1_0,0", "unreadable number '1_0'"),
        ("wait 1e300", "clock reaches 1e+297 s"),
        ("ptp/ev (X,Y),5,0,1e-9", "clock reaches 5e+09 s"),
        ("ptp/ev (X,Y),5,0,1e300", "faster than any Aerosol Jet stage"),
        # misleading before: the END was blamed ("End/Else without a matching If")
        ("WHILE gIntRun = 1", "WHILE (a repeated block) is not supported"),
    ],
)
def test_hostile_statements_are_refused_naming_their_line(statement, reason):
    text = program("gIntRun = 1\nptp/ev (X,Y),0,0,10\n" + OPEN + "\n" + statement + "\n" + CLOSE)
    error = refused(text)
    assert reason in error.reason
    assert error.line == line_of(text, statement[:20])
    assert len(str(error)) < 600  # a 30 000-character line is cut in the message


def test_a_gcode_motion_line_is_not_skipped_as_harmless():
    """--skip-unknown once said G1 "does not move the stage" and printed a diagonal."""
    text = "#0\nptp/ev (X,Y),0,0,10\nOUT0.0=1\nptp/e (X,Y),5,0\nG1 X5 Y5 F120\nOUT0.0=0\n"
    for skip in (False, True):
        error = refused(text, skip_unknown=skip)
        assert error.line == 5 and "G-code motion command" in error.reason
    assert read_program_text("G21\nptp/e (X,Y),0,0\nptp/e (X,Y),1,0", skip_unknown=True)


def test_the_else_branch_of_a_skipped_if_is_run():
    """If (gIntFindFids = 1) … Else <the print> End: the reader takes the If's condition as
    false (a fiducial block), so the Else branch is what prints."""
    text = program(
        "If (gIntFindFids = 1)\n  ptp/e (X,Y),9,9\nElse\n"
        + stroke(0, 0, 5, 0)
        + "If (gIntFindFids = 1)\n  ptp/e (X,Y),7,7\nEnd\n"  # nested: skipped
        + stroke(5, 1, 0, 1)
        + "End\n"
    )
    job = read_program_text(text, path="part.prg")
    assert job.n_strokes == 2
    assert job.summary()["printed_length_mm"] == pytest.approx(10.0)
    assert any("Else branch from line 4 is run" in w for w in job.warnings)
    error = refused(program("If (gIntFindFids = 1)\nElse\n" + stroke(0, 0, 5, 0)))
    assert error.line == 3 and "Else branch has no End" in error.reason


def test_an_arc1_ending_within_the_join_tolerance_warns_that_it_is_read_as_a_full_turn():
    arc = (
        "ptp/ev (X,Y),0,0,10\nOUT0.0=1\nMSEG (X,Y),0,0\narc1 (X,Y),5,0,{},{},-\nENDS (X,Y)\n"
        "till ^X_AST.#MOVE\n"
    )
    with pytest.warns(ProgramWarning, match=r"0\.5 um apart on a 5 mm radius\): read as full"):
        job = read_program_text(arc.format("0.000000025", "0.0005") + "OUT0.0=0")
    assert job.summary()["printed_length_mm"] == pytest.approx(2 * np.pi * 5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the end written as the start: a full turn, no word
        assert read_program_text(arc.format(0, 0) + "OUT0.0=0").n_strokes == 1


def test_a_first_buffer_that_moves_nothing_names_the_buffer_not_read():
    error = refused("#1\n#0\n" + GOOD)
    assert "moves nothing" in error.reason and "line 2: #0 starts another buffer" in error.reason


# --------------------------------------------------------------------------- #
# The file itself
# --------------------------------------------------------------------------- #
def test_a_program_that_is_no_regular_file_is_refused_unread(tmp_path):
    """A FIFO hung `job show`, `simulate --job` and `estimate --job`; /dev/zero ran to 6 GB."""
    fifo = tmp_path / "f.prg"
    os.mkfifo(fifo)
    for read in (read_program, job_as_printed):
        with pytest.raises(ProgramError, match="f.prg: is a FIFO"):
            _no_hang(lambda read=read: read(fifo), fifo=fifo)
    result = _no_hang(lambda: CliRunner().invoke(job_group, ["show", str(fifo)]), fifo=fifo)
    assert result.exit_code == 1 and "is a FIFO" in result.output
    if os.path.exists("/dev/zero"):
        with pytest.raises(ProgramError, match="/dev/zero: is a device"):
            read_program("/dev/zero")
    huge = tmp_path / "huge.prg"
    with huge.open("wb") as fh:  # sparse: no byte written, refused on its size
        fh.truncate(load_reader_settings().max_program_bytes + 1)
    with pytest.raises(ProgramError, match="larger than any program file"):
        read_program(huge)


@pytest.mark.parametrize("encoding", ["utf-16-le", "utf-16-be"])
def test_a_utf16_program_with_its_byte_order_mark_reads_as_utf8(tmp_path, encoding):
    path = tmp_path / "u.prg"
    path.write_bytes(("\ufeff" + "! µm comment\n" + GOOD).encode(encoding))
    plain = tmp_path / "p.prg"
    plain.write_text("! µm comment\n" + GOOD, encoding="utf-8")
    assert read_program(path).summary()["strokes"] == read_program(plain).summary()["strokes"]


def test_nul_bytes_say_the_file_is_not_text(tmp_path):
    path = tmp_path / "b.prg"
    path.write_bytes(b"#0\nptp/e (X,Y),0,0\n\x00\x01\x02binary")
    with pytest.raises(ProgramError, match=r"byte 19 \(line 3\) is a NUL: this is not a text"):
        read_program(path)


# --------------------------------------------------------------------------- #
# A program that prints nothing
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize(
    ("body", "says"),
    [
        ("ptp/ev (X,Y),0,0,10\nptp/e (X,Y),5,0\n", "never opens the shutter (OUT0.0"),
        ("ptp/ev (X,Y),0,0,10\nOUT1.0=1\nptp/e (X,Y),5,0\nOUT1.0=0\n", "switches OUT1.0 (line 3)"),
        (f"ptp/ev (X,Y),0,0,10\n{CLOSE}\nptp/e (X,Y),5,0\n", "only closes it (line 3)"),
    ],
)
def test_a_program_that_prints_nothing_is_said_in_words(tmp_path, body, says):
    path = tmp_path / "never.prg"
    path.write_text(program(body))
    with pytest.warns(ProgramWarning, match="prints nothing"):
        job = read_program(path)
    with pytest.raises(ProgramError, match=f"prints nothing.*{says.split('(')[0]}"):
        require_printing(job)
    for read in (job_as_printed, read_job):  # the record/registry path, the virtual printer
        with pytest.raises(ProgramError, match="there is no part to print, map or follow"):
            read(path)
    result = CliRunner().invoke(job_group, ["show", str(path)])
    assert result.exit_code == 0 and "warning:" in result.output and says in result.output


# --------------------------------------------------------------------------- #
# Bounded work: loops, parts side by side, portions
# --------------------------------------------------------------------------- #
def test_loops_beyond_their_bounds_are_refused_before_any_array_is_made():
    """A 1-um dot looped to an hour asked 5.6 GB; a 1e9 mm/s program 2 EiB; a loop of 100
    days ran out of memory. Each is refused at once, naming its bound."""
    dot = read_program_text(program(stroke(1, 1, 1.001, 1)), path="dot.prg")
    with pytest.raises(ValueError, match="holds 3,9.* segments .* max_held_segments"):
        dot.repeat(3600.0)
    with pytest.raises(ValueError, match="max_loop_runs"):
        dot.loop_plan(float(MAX_RECORD_SECONDS))
    with pytest.raises(ValueError, match="longer than the 14 days"):
        dot.loop_plan(1e12)
    assert dot.repeat(60.0).repetitions > 1000  # a minute of it is fine


def test_parts_side_by_side_may_not_overlap():
    job = read_program_text(GOOD, path="part.prg")  # 5 x 1 mm printed
    with pytest.raises(ValueError, match=r"5 x 1 mm \(printed\) at a pitch of \(1e-09, 0\)"):
        job.repeat(3 * job.duration_s, pitch_mm=(1e-9, 0.0))
    with pytest.raises(ValueError, match="print over each other"):
        job.repeat(3 * job.duration_s, pitch_mm=(6.0, 0.5))
    assert job.repeat(3 * job.duration_s, pitch_mm=(6.0, 2.0)).repetitions == 3


def test_portions_beyond_their_bound_are_refused_before_they_are_cut():
    job = read_program_text(GOOD, path="part.prg")
    assert job.check_portions(1.0) == len(job.portions(1.0)) == 10
    with pytest.raises(ValueError, match="make 10,000,000 portions, more than the 5,000,000"):
        job.check_portions(1e-6)


def test_a_job_until_a_time_keeps_every_stroke_printed_by_then_whole():
    job = read_program_text(GOOD, path="part.prg").repeat(100.0)
    cut = job.until(job.strokes["t_start_s"][3] + 0.1)  # inside stroke 3
    assert cut.n_strokes == 4 and cut.duration_s == job.strokes["t_end_s"][3]
    columns = ["stroke", "base_stroke", "repetition", "t_start_s", "t_end_s", "length_mm"]
    np.testing.assert_array_equal(cut.strokes[columns], job.strokes[columns].iloc[:4])
    t = np.linspace(0.0, cut.duration_s, 97)
    np.testing.assert_array_equal(cut.state_at(t).x_mm, job.state_at(t).x_mm)
    assert job.until(1e9) is job


def test_job_show_checks_its_outputs_before_the_work_and_makes_their_folder(tmp_path):
    path = tmp_path / "p.prg"
    path.write_text(GOOD)
    runner = CliRunner()
    bad = runner.invoke(job_group, ["show", str(path), "--plot", str(tmp_path / "x.xyz")])
    assert bad.exit_code == 2 and "drawn as .png, .pdf, .svg" in bad.output
    far = runner.invoke(job_group, ["show", str(path), "--repeat-to", "8640000"])
    assert far.exit_code == 2 and "--repeat-to" in far.output
    out = tmp_path / "new" / "t.csv"
    done = runner.invoke(job_group, ["show", str(path), "--out", str(out)])
    assert done.exit_code == 0 and out.is_file()
