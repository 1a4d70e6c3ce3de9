"""Every bad program is refused with an error naming the file, the line and its text."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from ajtwin.job import ProgramError, ProgramWarning, read_program, read_program_text

GOOD_START = "ptp/ev (X,Y),0,0,gDblRapidSpeed\nStart gIntSubBuffer,ShutterOpen\n"
CLOSE = "Start gIntSubBuffer,ShutterClose\n"


def refused(text: str, **kwargs) -> ProgramError:
    with pytest.raises(ProgramError) as caught:
        read_program_text(text, path="part.prg", **kwargs)
    return caught.value


def line_of(text: str, needle: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


@pytest.mark.parametrize(
    ("body", "bad", "reason"),
    [
        ("frobnicate 3", "frobnicate", "unknown command 'frobnicate'"),
        ("ptp/e (X,Y),1.2.3,4", "1.2.3", "unreadable number"),
        ("ptp/e (X,Y),1,4a", "4a", "unreadable number"),
        ("ptp/e (X,Y),nan,1", "nan", "not a finite number"),
        ("ptp/e (X,Y),1,inf", "inf", "not a finite number"),
        ("ptp/e (X,Y),1", "ptp/e (X,Y),1", "needs 2 values, got 1"),
        ("ptp/q (X,Y),1,1", "ptp/q", "switch /q"),
        ("ptp/e (X,W),1,1", "(X,W)", "unknown axis 'W'"),
        ("wait -5", "wait -5", "negative wait"),
        ("wait later", "wait later", "unknown variable later"),
        ("line/v (X,Y),1,1,gDblFoo", "gDblFoo", "unknown variable gDblFoo"),
        (
            "gDblProcessSpeed = 0\nptp/ev (X,Y),1,1,gDblProcessSpeed",
            "ptp/ev (X,Y),1,1",
            "not a positive",
        ),
        ("VEL(X) = -2\nptp/e (X,Y),1,1", "ptp/e (X,Y),1,1", "not a positive"),
        ("LOOP 3\nptp/e (X,Y),1,1\nEND", "LOOP", "LOOP (a repeated block) is not supported"),
        ("JOG X", "JOG", "JOG"),
        ("MSEG (X,Y),0,0\nptp/e (X,Y),1,1", "ptp/e (X,Y),1,1", "inside the segmented path"),
        ("ENDS (X,Y)", "ENDS", "ENDS without"),
        ("End", "End", "without a matching If"),
    ],
)
def test_bad_statements_name_their_line(body, bad, reason):
    text = GOOD_START + body + "\nStart gIntSubBuffer,ShutterClose\n"
    error = refused(text)
    assert error.path == "part.prg"
    assert error.line == line_of(text, bad)
    assert reason in error.reason
    assert f"part.prg:{error.line}:" in str(error) and bad in str(error)


def test_arc1_end_off_its_circle_is_refused():
    text = GOOD_START + "MSEG (X,Y),0,0\narc1 (X,Y),1,0,1,1.01,+\nENDS (X,Y)\n"
    error = refused(text)
    assert error.line == 4 and "not on the circle" in error.reason and "10 um" in error.reason
    # within the documented tolerance (1 um) it is read
    ok = (
        GOOD_START
        + "MSEG (X,Y),0,0\narc1 (X,Y),1,0,1,1.0009,+\nENDS (X,Y)\ntill ^X_AST.#MOVE\n"
        + CLOSE
    )
    assert read_program_text(ok).summary()["printed_length_mm"] > 0


@pytest.mark.parametrize("arc", ["arc2 (X,Y),0,0,1.0", "arc1 (X,Y),0,0,1,0,+"])
def test_zero_radius_arcs_are_refused(arc):
    text = GOOD_START + "MSEG (X,Y),0,0\n" + arc + "\nENDS (X,Y)\n"
    error = refused(text)
    assert error.line == 4 and "zero-radius" in error.reason


def test_arc_in_degrees_is_refused():
    text = GOOD_START + "MSEG (X,Y),0,0\narc2 (X,Y),1,0,90\nENDS (X,Y)\n"
    error = refused(text)
    assert error.line == 4 and "radians" in error.reason


def test_path_that_does_not_start_where_the_arc_left_the_stage():
    """An arc2 with the wrong sweep ends elsewhere than the next path expects."""
    text = (
        GOOD_START
        + "MSEG (X,Y),0,0\narc2 (X,Y),1,0,-1.5708\nENDS (X,Y)\ntill ^X_AST.#MOVE\n"
        + "MSEG (X,Y),2,0\nline (X,Y),3,0\nENDS (X,Y)\n"  # expects a half circle (sweep -pi)
    )
    error = refused(text)
    assert error.line == 7 and "the segmented path starts at (2, 0)" in error.reason
    assert "(line 4) left the stage at (1, 1), 1.414 mm away" in error.reason


@pytest.mark.parametrize(
    ("path", "line"),
    [
        # the public programs' U-turn with the sign of the sweep flipped
        ("line (X,Y),0,1\narc2 (X,Y),0.5,1,1.5708\narc2 (X,Y),0.5,1,1.5708\nline (X,Y),1,0", 5),
        # arc1 with the wrong direction after a line along +x (tangent reversed)
        ("line (X,Y),2,0\narc1 (X,Y),2,1,2,2,-\nline (X,Y),0,2", 5),
    ],
)
def test_arc_that_retraces_its_neighbour_is_refused(path, line):
    text = GOOD_START + "MSEG (X,Y),0,0\n" + path + "\nENDS (X,Y)\n"
    error = refused(text)
    assert error.line == line and "turns back" in error.reason


def test_motion_beyond_the_stage_travel_is_refused():
    text = GOOD_START + "ptp/e (X,Y),100,0\nptp/e (X,Y),250,0\nptp/e (X,Y),310,5\n"
    error = refused(text)
    assert error.line == 5 and "travel" in error.reason and "310.000 mm" in error.reason
    assert "Optomec Aerosol Jet 300" in error.reason
    # inside the travel it is read; with the stage origin given, absolute limits count
    inside = GOOD_START + "ptp/e (X,Y),100,0\nptp/e (X,Y),-150,0\n" + CLOSE
    assert read_program_text(inside).summary()["travel_bbox_mm"][0] == -150
    error = refused(inside, stage_origin_mm=(100.0, 100.0))
    assert error.line == 4 and "outside the 0-300 mm" in error.reason


def test_unclosed_blocks_and_paths_name_where_they_open():
    error = refused("If (gIntFindFids = 1)\n  gDblFidX(1) = 0\n")
    assert error.line == 1 and "no End" in error.reason
    error = refused(GOOD_START + "MSEG (X,Y),0,0\nline (X,Y),1,0\n")
    assert error.line == 3 and "never closed" in error.reason


def test_a_program_that_moves_nothing_is_refused():
    with pytest.raises(ProgramError, match="moves nothing"):
        read_program_text("wait 10\nOUT0.0=1\nwait 10\nOUT0.0=0\n")


def test_skip_unknown_skips_what_does_not_move_the_stage_with_one_warning_per_kind():
    text = (
        GOOD_START
        + 'DISP "a"\nptp/e (X,Y),1,0\nDISP "b"\nENABLE X\nStart gIntSubBuffer,Purge\n'
        + "Start gIntSubBuffer,ShutterClose\n"
    )
    refused(text)
    with pytest.warns(ProgramWarning) as caught:
        job = read_program_text(text, skip_unknown=True)
    assert len(caught) == 3 and all(str(w.message).startswith("<text>: skipped") for w in caught)
    assert job.summary()["printed_length_mm"] == pytest.approx(1.0)
    kinds = job.warnings
    assert len(kinds) == 3
    assert any("2 'disp'" in w and "line 3" in w for w in kinds)
    assert any("'enable'" in w for w in kinds) and any("start Purge" in w for w in kinds)
    # a command that moves the stage is never skipped
    with pytest.raises(ProgramError, match="TRACK"):
        read_program_text(text + "TRACK X\n", skip_unknown=True)


def test_if_block_with_motion_is_skipped_with_a_warning():
    block = "If (gIntFindFids = 1)\n  ptp/e (X,Y),5,5\n  Stop\nEnd\n"
    text = GOOD_START + block + "ptp/e (X,Y),1,0\n" + CLOSE
    with pytest.warns(ProgramWarning, match="1 motion command"):
        job = read_program_text(text)
    assert job.summary()["travel_bbox_mm"] == [0.0, 0.0, 1.0, 0.0]
    assert any("lines 3-6" in w and "1 motion command" in w for w in job.warnings)


def test_file_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.prg"
    bad.write_text("ptp/e (X,Y),0,0\nptp/e (X,Y),1,zz\n")
    with pytest.raises(ProgramError) as caught:
        read_program(bad)
    assert str(caught.value).startswith(f"{bad}:2: ")
    assert "2 | ptp/e (X,Y),1,zz" in str(caught.value)


def test_job_show_reports_a_bad_program_without_a_traceback(tmp_path):
    from ajtwin.cli import main

    bad = tmp_path / "bad.prg"
    bad.write_text(GOOD_START + "MSEG (X,Y),0,0\narc2 (X,Y),0,0,1\nENDS (X,Y)\n")
    result = CliRunner().invoke(main, ["job", "show", str(bad)])
    assert result.exit_code == 1
    assert f"{bad}:4: arc2: zero-radius arc" in result.output
    assert "Traceback" not in result.output
    skipped = tmp_path / "skip.prg"
    skipped.write_text(GOOD_START + 'DISP "x"\nptp/e (X,Y),1,0\n')
    result = CliRunner().invoke(main, ["job", "show", str(skipped), "--skip-unknown"])
    assert result.exit_code == 0
    assert f"warning: {skipped}: skipped 1 'disp' statement(s)" in result.output


def test_a_program_ending_with_the_shutter_open_is_read_with_a_warning():
    with pytest.warns(ProgramWarning, match="ends with the shutter open"):
        job = read_program_text(GOOD_START + "ptp/e (X,Y),1,0\n")
    assert job.end_shutter_open and job.state_at(5.0).shutter_open


def test_shutter_switched_while_the_stage_moves_acts_mid_move_with_a_warning():
    """Without till, ACSPL+ runs on past ENDS: the shutter closes as the path starts."""
    text = GOOD_START + "MSEG (X,Y),0,0\nline (X,Y),4,0\nENDS (X,Y)\nwait 500\n" + CLOSE
    with pytest.warns(ProgramWarning, match="while the stage is still moving"):
        job = read_program_text(text, process_speed_mm_s=2.0)
    assert job.summary()["printed_length_mm"] == pytest.approx(1.0)  # 0.5 s at 2 mm/s
    assert job.summary()["rapid_length_mm"] == pytest.approx(3.0)
    assert job.state_at(1.0).x_mm == pytest.approx(2.0) and not job.state_at(1.0).shutter_open
