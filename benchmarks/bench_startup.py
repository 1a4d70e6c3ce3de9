"""The commands a user waits on, each a new process: ``ajtwin --help``, a group's ``--help``,
``ajtwin estimate`` of a 90-min print, ``forecast`` and ``advise`` on a machine that ingested
it, warm (the compilation cache filled by an earlier run), and their ratios to the import
floor.

The **import floor** is a new process that only imports the libraries the twin cannot run
without and starts JAX's CPU backend: ``import jax, jax.numpy as jnp, pandas, scipy.linalg``,
64-bit on, ``jnp.zeros(3)`` computed. What a command takes beyond it is ajtwin's own cost that a
change can move, so ``track_*_to_import_floor`` is the figure to compare between commits: the
floor and the command are timed one after the other, several times, and the median of the
pairs' ratios is taken, which cancels most of a shared machine's speed of the day (a bare
wall time on it varies 2-3 x). ``…_cpu_…`` is the same in CPU seconds (user + system, all
threads), which other processes on the machine disturb less than a wall clock.

The commands run as ``python -c "from ajtwin.cli import run; run()" …`` so that whichever
ajtwin is first on the path is the one timed (``scripts/asv_at_commit.py`` puts an older
commit's source there).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CLI = [sys.executable, "-c", "from ajtwin.cli import run; run()"]
FLOOR = [
    sys.executable,
    "-c",
    "import jax, jax.numpy as jnp, pandas, scipy.linalg; "
    "jax.config.update('jax_enable_x64', True); jnp.zeros(3).block_until_ready()",
]
PAIRS = 5  # floor/command pairs per ratio


def _env(work: str) -> dict:
    """The process environment: the cache and the registry inside the benchmark's folder."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AJTWIN_")}
    env["AJTWIN_CACHE_DIR"] = str(Path(work) / "cache")
    env["AJTWIN_STORE"] = str(Path(work) / "registry.sqlite")
    return env


def _run(args: list[str], work: str) -> tuple[float, float]:
    """(wall seconds from launch to exit, CPU seconds — user + system, all its threads) of
    ``args`` run in ``work``; a failure raises."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(args, cwd=work, env=_env(work), capture_output=True, timeout=600)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        out = (done.stdout + done.stderr).decode(errors="replace")[-2000:]
        raise RuntimeError(f"{args[3:]} exited {done.returncode}: {out}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def _wall(args: list[str], work: str) -> float:
    """Seconds from launching ``args`` (in ``work``) to its exit."""
    return _run(args, work)[0]


def _ratio_to_floor(args: list[str], work: str, cpu: bool = False) -> float:
    """The median over :data:`PAIRS` pairs of ``args``' time over the import floor's, each
    pair run one after the other, wall time or (``cpu``) CPU time. A pair shares the
    machine's speed of the moment, so its ratio cancels it; the median keeps one lucky or
    one slow run from moving the figure (a ratio of the fastest runs did: one fast floor
    run swung it by 0.2). The CPU time a process is given does not shrink when other
    processes share the cores, so it is the steadier of the two on a busy machine."""
    ratios = []
    for _ in range(PAIRS):
        floor = _run(FLOOR, work)[cpu]
        ratios.append(_run(args, work)[cpu] / floor)
    return float(np.median(ratios))


ESTIMATE = [*CLI, "estimate", "print.parquet", "--out", "states.csv"]
FORECAST = [
    *CLI,
    "forecast",
    "--machine",
    "bench",
    "--set",
    "carrier_flow_sccm=26@+60s",
    "--horizon",
    "30min",
]
ADVISE = [*CLI, "advise", "--machine", "bench", "--target-linewidth", "65"]


def _ratio_unit(method):
    method.unit = "x import floor"
    return method


class CommandStart:
    """``ajtwin --help``, a group's ``--help`` and the import floor, each a new process."""

    number = 1
    repeat = (3, 10, 30.0)
    warmup_time = 0.0

    def setup(self):
        self.work = os.getcwd()

    def time_help(self):
        _wall([*CLI, "--help"], self.work)

    def time_estimate_help(self):
        _wall([*CLI, "estimate", "--help"], self.work)

    def time_import_floor(self):
        _wall(FLOOR, self.work)


class EstimateStart:
    """``ajtwin estimate`` of a 90-min print in a new process, warm."""

    timeout = 900
    number = 1
    repeat = (2, 5, 120.0)
    warmup_time = 0.0

    def setup_cache(self) -> str:
        """A 90-min exp1 print (seed 1); estimate run once on it (the caches warm). asv runs
        this in a temporary folder of its own, removed after the class's benchmarks."""
        work = os.path.abspath("estimate")
        os.makedirs(work)
        _wall(
            [*CLI, "simulate", "--scenario", "exp1", "--seed", "1", "--out", "print.parquet"], work
        )
        _wall(ESTIMATE, work)
        return work

    def time_estimate_90min_print(self, work):
        _wall(ESTIMATE, work)

    @_ratio_unit
    def track_estimate_to_import_floor(self, work):
        return _ratio_to_floor(ESTIMATE, work)

    @_ratio_unit
    def track_estimate_cpu_to_import_floor(self, work):
        """The same ratio in CPU seconds."""
        return _ratio_to_floor(ESTIMATE, work, cpu=True)

    def track_estimate_cpu_s(self, work):
        """CPU seconds of the fastest of :data:`PAIRS` runs."""
        return min(_run(ESTIMATE, work)[1] for _ in range(PAIRS))

    track_estimate_cpu_s.unit = "s"


class MachineCommandStart:
    """``ajtwin forecast`` and ``ajtwin advise`` in a new process, warm, on a machine that
    ingested a 90-min print."""

    timeout = 900
    number = 1
    repeat = (2, 5, 120.0)
    warmup_time = 0.0

    def setup_cache(self) -> str:
        """A 90-min exp1 print (seed 1) ingested into machine ``bench``; forecast and advise
        run once (the caches warm)."""
        work = os.path.abspath("machine")
        os.makedirs(work)
        _wall(
            [*CLI, "simulate", "--scenario", "exp1", "--seed", "1", "--out", "print.parquet"], work
        )
        _wall([*CLI, "machine", "add", "bench"], work)
        _wall([*CLI, "ingest", "--machine", "bench", "print.parquet"], work)
        _wall(FORECAST, work)
        _wall(ADVISE, work)
        return work

    def time_forecast_30min(self, work):
        _wall(FORECAST, work)

    def time_advise(self, work):
        _wall(ADVISE, work)

    @_ratio_unit
    def track_forecast_to_import_floor(self, work):
        return _ratio_to_floor(FORECAST, work)

    @_ratio_unit
    def track_advise_to_import_floor(self, work):
        return _ratio_to_floor(ADVISE, work)
