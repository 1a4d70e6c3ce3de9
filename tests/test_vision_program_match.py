"""``ajtwin extract --job``: a video filmed over another program is refused, its own is read.

The case: a cross of two traces filmed by a camera trailing the second one, extracted with
another program (an L and a Z) whose trace near the camera moves the same way. Every window
that program puts in view finds a line; only the rest of the frames (the cross's first trace,
the L's corner that never comes) tells the programs apart.
"""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.vision.program_match import ForeignLine, MatchSettings, ProgramMatch

CROSS = """#0
! a cross of two 3 mm traces, the second printed across the first
ptp/ev (X,Y),0,0,10
OUT0.0=1
ptp/e (X,Y),3,0
OUT0.0=0
ptp/ev (X,Y),1.5,-1.5,10
OUT0.0=1
ptp/e (X,Y),1.5,1.5
OUT0.0=0
STOP
"""
L_AND_Z = """#0
! two directions for the camera: an L and a Z, 2 mm/s
gDblRapidSpeed = 10
ptp/ev (X,Y),0,0,gDblRapidSpeed
OUT0.0=1
wait 2
MSEG (X,Y),0,0
line (X,Y),3,0
line (X,Y),3,3
line (X,Y),0,3
ENDS (X,Y)
till (^X_AST.#MOVE) & (^Y_AST.#MOVE)
OUT0.0=0
wait 2
ptp/ev (X,Y),0,1,gDblRapidSpeed
OUT0.0=1
wait 2
ptp/e (X,Y),2,1
ptp/e (X,Y),2,2
till (^X_AST.#MOVE) & (^Y_AST.#MOVE)
OUT0.0=0
STOP
"""
# 640 x 480 px at 0.75 µm/px, trailing 0.25 mm behind a nozzle printing towards +y
CAMERA = """[camera]
um_per_px = 0.75
rotation_deg = 0.0
offset_mm = [0.1, -0.25]
width_px = 640
height_px = 480
"""


def _invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def cross(tmp_path_factory):
    """The cross's video: 18 frames at 20 frames/s from job time 2.3 s (the second trace)."""
    folder = tmp_path_factory.mktemp("cross")
    (folder / "cross.prg").write_text(CROSS)
    (folder / "cal.prg").write_text(L_AND_Z)
    (folder / "camx.toml").write_text(CAMERA)
    video = folder / "vx.avi"
    result = _invoke("render", "--job", folder / "cross.prg", "--camera", folder / "camx.toml",
                     "--fps", 20, "--duration", 0.9, "--start", 2.3, "--out", video)  # fmt: skip
    assert result.exit_code == 0, result.output
    return folder


def _extract(folder, program, out, start_offset=2.3):
    return _invoke("extract", folder / "vx.avi", "--job", folder / program, "--camera",
                   folder / "camx.toml", "--start-offset", start_offset, "--out", out,
                   "--no-progress")  # fmt: skip


def test_a_video_of_another_program_is_refused_and_nothing_is_written(cross, tmp_path):
    out = tmp_path / "f.csv"
    out.write_text("an earlier table\n")
    result = _extract(cross, "cal.prg", out)
    assert result.exit_code == 1, result.output
    message = " ".join(result.output.split())
    assert "does not show what cal.prg prints" in message
    # the cross's first trace, seen across frames 4-7, lies where cal.prg prints nothing
    assert "frames 4–7, job time 2.50–2.65 s" in message
    assert "at 0°" in message
    # the L's corner never comes: its next leg is not where cal.prg prints it
    assert "show no line where it prints one" in message
    assert "--start-offset" in message and "--job" in message
    assert out.read_text() == "an earlier table\n"  # left as it was
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.csv"]


def test_the_program_the_video_was_filmed_over_is_read_without_a_word(cross, tmp_path):
    out = tmp_path / "g.csv"
    result = _extract(cross, "cross.prg", out)
    assert result.exit_code == 0, result.output
    assert "warning" not in result.output
    assert "147 readings from 18 frames" in result.output
    frames = (tmp_path / "g_frames.csv").read_text().splitlines()
    header = frames[0].split(",")
    foreign = [float(row.split(",")[header.index("foreign_line_um")]) for row in frames[1:]]
    assert foreign == [0.0] * 18


def test_a_clock_one_frame_off_is_read_with_a_warning_naming_the_frames(cross, tmp_path):
    # 50 ms early: the first trace, crossed in frames 4-7, is 100 µm from where it is seen
    result = _extract(cross, "cross.prg", tmp_path / "h.csv", start_offset=2.25)
    assert result.exit_code == 0, result.output
    message = " ".join(result.stderr.split())
    assert message.startswith("warning: ")
    assert "may not show what cross.prg prints" in message and "frames 4–7" in message
    assert (tmp_path / "h.csv").exists()


def _line():
    return ForeignLine(300.0, 40.0, 1.0, 2.0, 90.0)


@pytest.mark.parametrize(
    ("foreign", "missing", "verdict"),
    [
        ((), (), "agree"),
        ((3,), (), "doubtful"),  # one frame: a fibre passing
        ((3, 4, 9), (), "mismatch"),  # 3 of 10 frames
        ((3, 4), (5, 6, 7), "doubtful"),  # lines in 2 frames only
        ((), tuple(range(10)), "agree"),  # no line anywhere: a clog, not another program
    ],
)
def test_verdict_counts_frames_with_lines_off_the_program(foreign, missing, verdict):
    match = ProgramMatch(MatchSettings.from_defaults())
    for frame in range(10):
        lines = [_line()] if frame in foreign else []
        missed = 4 if frame in missing else 0
        match.add(frame, 0.1 * frame, lines, missing=missed, measured=5, in_view=5)
    assert match.verdict == verdict


def test_blank_frames_where_the_program_prints_nothing_in_view_are_not_counted():
    match = ProgramMatch(MatchSettings.from_defaults())
    for frame in range(40):  # 30 blank frames, then 10 with a trace, 3 of them off
        in_view = 5 if frame >= 30 else 0
        match.add(frame, frame / 20, [_line()] if frame in (31, 32, 33) else [], 0, 5, in_view)
    assert match.frames == 10 and match.verdict == "mismatch"


def test_verdict_needs_a_quarter_of_the_frames():
    match = ProgramMatch(MatchSettings.from_defaults())
    for frame in range(40):  # lines in 3 frames of 40: 7.5 %
        match.add(frame, frame / 20, [_line()] if frame in (1, 2, 30) else [], 0, 5, 5)
    assert match.verdict == "doubtful"
    text = match.explain("v.avi", "p.prg")
    assert "3 of the 40 frames where a trace is seen or expected" in text
    assert "frames 1–2, job time 0.05–0.10 s: 300 µm long at 90° around x 1.000, y 2.000 mm" in text
    assert "frame 30, job time 1.50 s" in text
