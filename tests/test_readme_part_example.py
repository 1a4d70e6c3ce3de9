"""The README's part example runs as written and tells the story it promises.

The ``ajtwin`` lines of the README's part block that use the public program kept in the
source tree (``tests/data/prg/...``) are read from the README itself and run in order through
the command line, as written (the print is already short: 75 min, 15 after the clog's onset).
The story: the report names the nozzle clog, and only a few traces are flagged (not none,
not all), every one printed after the clog's onset.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
from click.testing import CliRunner

from ajtwin.cli import main
from doc_commands import ajtwin_commands

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: the clog scenario's onset [s] (src/ajtwin/simulation/scenarios/nozzle_clog.toml)
CLOG_ONSET_S = 3600.0


def readme_part_commands() -> list[list[str]]:
    """The README's part-example command lines (without ``ajtwin``) that run the public
    program, in order."""
    text = README.read_text(encoding="utf-8")
    part = text[text.index("A part printed from its program") : text.index("## In Python")]
    return [args for args in ajtwin_commands(part) if any("tests/data/prg/" in w for w in args)]


def test_the_readme_part_example_flags_a_few_traces_after_the_clog(tmp_path, monkeypatch):
    commands = readme_part_commands()
    assert [args[:2] for args in commands] == [
        ["job", "show"],
        ["simulate", "--job"],
        ["job", "report"],
    ]
    (tmp_path / "tests").symlink_to(ROOT / "tests")  # the README's paths, from the source tree
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    said = []
    for args in commands:
        result = runner.invoke(main, args, catch_exceptions=False)
        assert result.exit_code == 0, f"ajtwin {' '.join(args)}:\n{result.output}"
        said.append(result.output)
    report = said[-1]
    assert "nozzle_clog" in report or "nozzle clog" in report, report
    portions = pd.read_csv(tmp_path / "part" / "strokes.csv")
    flagged = portions[portions["flagged"]]
    # a few traces go out: not none, not the whole part
    assert 0 < len(flagged) < 0.05 * len(portions), (len(flagged), len(portions))
    # ... and only after the clog began (the line is inside the tolerance before it)
    assert flagged["printed_from_s"].min() > CLOG_ONSET_S
    assert (tmp_path / "part" / "report.html").is_file()
