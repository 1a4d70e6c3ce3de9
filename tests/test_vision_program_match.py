"""The verdict of a video against its program: frames with lines where it prints nothing.

The command's cases (a video of another program refused, its own read) are in
``test_vision_part_cli.py``.
"""

from __future__ import annotations

import pytest

from ajtwin.vision.program_match import ForeignLine, MatchSettings, ProgramMatch


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
