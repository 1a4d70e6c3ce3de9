"""The command line never waits in silence: one progress bar at a time, a word while the twin
starts, and a subcommand's ``--help`` that loads no JAX."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"


def test_job_report_shows_one_bar_at_a_time_and_says_the_twin_is_starting(monkeypatch):
    from ajtwin.cli.job import _bars

    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    twin_step, line_step, close = _bars(True)
    twin_step(0)  # the twin starts: compiling on a first run, nothing else to show
    assert "starting" in err.getvalue()
    twin_step(3600)
    line_step(0, 500)
    twin_step(3600)  # the twin's last report comes after the line began
    line_step(500, 500)
    close()
    text = err.getvalue()
    assert "\x1b[A" not in text  # no cursor moves: bars never share or redraw two lines
    twin_part, line_part = text.split("line along strokes", 1)
    assert twin_part.rstrip("\r").endswith("\n")  # the twin's bar was finished first
    assert "3600s" in twin_part.rstrip("\r\n").rsplit("\r", 1)[-1]  # ... on its final count
    assert "twin" not in line_part


#: commands whose --help must not import JAX, SciPy, PyTorch or OpenCV (~1 s of a --help)
HELP_COMMANDS = [
    "estimate", "job report", "simulate", "dashboard", "machine", "ingest", "live", "openloop",
]  # fmt: skip


@pytest.mark.parametrize("command", HELP_COMMANDS)
def test_a_subcommand_help_loads_no_jax_nor_other_heavy_library(command):
    code = (
        "import sys, json\n"
        "from ajtwin.cli import main\n"
        "try:\n"
        f"    main({command.split()!r} + ['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "print(json.dumps([m for m in ('jax', 'torch', 'cv2', 'scipy') "
        "if m in sys.modules]))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env={"PYTHONPATH": str(SRC), "PATH": "/usr/bin:/bin"},
        check=True,
    ).stdout
    assert "Usage:" in out
    assert json.loads(out.strip().splitlines()[-1]) == [], out


def test_the_install_says_each_step_and_its_size_and_shows_pip_progress():
    root = Path(__file__).resolve().parents[1]
    lines = subprocess.run(
        ["make", "-n", "-B", ".venv/.installed"],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout.splitlines()
    installs = [i for i, line in enumerate(lines) if "pip install" in line]
    assert installs
    for i in installs:
        assert lines[i - 1].startswith("echo "), lines[i - 1]  # said before it starts
    big = [lines[i] for i in installs if "torch" in lines[i] or "-e " in lines[i]]
    assert len(big) == 2 and not any("--quiet" in line for line in big)  # pip's own progress
    said = " ".join(line for line in lines if line.startswith("echo "))
    assert "GB" in said and "MB" in said  # how big
