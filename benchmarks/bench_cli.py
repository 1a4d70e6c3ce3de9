"""Speed of the command line's start: ``ajtwin --help`` and a command group's ``--help``.

Each is a fresh process (``python -m ajtwin.cli``), timed wall-clock from launch to exit,
the median of a few runs. ``ajtwin --help`` lists the commands from a table and imports
no command module; a group's ``--help`` imports that group's module only (its library is
imported when a command runs).

    .venv/bin/python benchmarks/bench_cli.py
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import time

RUNS = 7
CASES = {
    "help_s": ["--help"],
    "machine_help_s": ["machine", "--help"],
    "estimate_help_s": ["estimate", "--help"],
}


def _wall(args: list[str]) -> float:
    """Seconds from launching ``python -m ajtwin.cli ARGS`` to its exit."""
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "ajtwin.cli", *args], check=True, capture_output=True, timeout=120
    )
    return time.perf_counter() - t0


def _interpreter() -> float:
    """Seconds of a bare ``python -c pass`` (what any command pays before ajtwin)."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "pass"], check=True, timeout=60)
    return time.perf_counter() - t0


def main() -> dict:
    """The median wall time of each case over :data:`RUNS` runs [s]."""
    figures = {"python_startup_s": round(statistics.median(_interpreter() for _ in range(RUNS)), 3)}
    for name, args in CASES.items():
        _wall(args)  # the first run warms the file-system cache
        figures[name] = round(statistics.median(_wall(args) for _ in range(RUNS)), 3)
    figures["note"] = f"median of {RUNS} fresh processes, wall clock, after one warm-up run"
    return figures


if __name__ == "__main__":
    print(main())
