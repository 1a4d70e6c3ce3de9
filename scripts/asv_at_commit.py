"""Run today's asv benchmarks against an earlier commit's code, in this environment.

``asv run --python=same`` times whatever ajtwin is importable; this script puts the source
of each named commit first on the path (``git archive`` into a temporary folder, handed to
asv as ``ASV_PYTHONPATH``) and files the results under that commit
(``--set-commit-hash``), so ``asv compare A B`` can then set two commits side by side.
The benchmarks themselves are today's (``benchmarks/``), so they must run on the older code:
the command-line benchmarks (``bench_startup``) do, the library ones only as far as the
functions they call existed.

    .venv/bin/python scripts/asv_at_commit.py 937868b 0c94f0e --bench EstimateStart
    .venv/bin/asv compare 937868b 0c94f0e

Options after the commits go to ``asv run`` (``--bench REGEX``, ``--quick``, ``-a
repeat=…``); ``--times N`` runs each commit N times in turn (A B A B …), which on a shared
machine spreads its slow spells over both sides. The package's dependencies are this
environment's: a commit that needed others cannot be timed this way (``asv continuous``
builds an environment per commit instead, at the cost of a full install each).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ASV = Path(sys.executable).with_name("asv")


def full_hash(commit: str) -> str:
    """The full hash of ``commit`` (a name git understands)."""
    return subprocess.run(
        ["git", "rev-parse", "--verify", f"{commit}^{{commit}}"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()


def run_at(commit: str, asv_args: list[str]) -> int:
    """asv's run of today's benchmarks on ``commit``'s ``src/``; asv's exit code."""
    sha = full_hash(commit)
    with tempfile.TemporaryDirectory(prefix=f"ajtwin-{sha[:8]}-") as tmp:
        archive = subprocess.run(
            ["git", "archive", sha, "src"], cwd=ROOT, check=True, capture_output=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        env = {**os.environ, "ASV_PYTHONPATH": str(Path(tmp) / "src")}
        print(f"== {sha[:8]}: {' '.join(asv_args)}", flush=True)
        # --append-samples: a second round adds its samples to the first instead of replacing
        command = [str(ASV), "run", "--python=same", f"--set-commit-hash={sha}", "--append-samples"]
        command += asv_args
        return subprocess.run(command, cwd=ROOT, env=env).returncode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("commits", nargs="+", help="commits to time (hashes, tags, branches)")
    parser.add_argument("--times", type=int, default=1, help="rounds over the commits")
    args, asv_args = parser.parse_known_args(argv)
    failed = 0
    for _ in range(args.times):
        for commit in args.commits:
            failed |= run_at(commit, asv_args) != 0
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
