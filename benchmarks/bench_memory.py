"""Memory against print length: peak RSS of `ajtwin estimate`, `ajtwin ingest` and the live
engine, for clean exp1 prints of several lengths, and the slope in MB per print-hour.

Each command runs in its own process on a fresh registry; its peak resident set is the
figure: the process's own ``VmHWM`` (``/proc/self/status``) as it exits. Not ``ru_maxrss``
from ``wait4``: Linux carries the parent's peak into a forked child's, so under ``make bench``
(one process that ran the other benchmarks first) every command read the runner's 2.9 GB.
The live engine is fed the record's samples as fast as it takes them
(``LiveEngine.feed_many``, as the OPC UA link feeds it, without the wire; the file read a
piece at a time, so the feeder holds no copy of the print) and closed at the end (the print
stored): ``live`` a minute's samples a call (a burst), ``live-1hz`` one
sample a call with each step written to the live log as it commits (what a machine at 1 Hz
does in real time, without waiting the print's hours). ``ingest-job`` is `ajtwin ingest --job`
of a job print: the public seven-layer program looped to the print's length, the camera
5 mm behind the nozzle (its frames filed at their print times). The slope is
(peak at the longest − peak at the shortest) / their difference in hours: ~0 when memory is
flat in print length. The live engine also says its resident memory every 4 print-hours
(``live_<h>h_rss_MB_by_hour``): one process's course, without the ±10 MB between runs that
blurs a slope over a few hours. The aims: `ingest` and live flat, `estimate` ≤ 1 GB for 7
days.
Each command first runs once, unmeasured, on the shortest print: a first run with an
empty JAX cache compiles, and the compiler's peak (~150 MB more) is not the print's.

    python benchmarks/bench_memory.py [--hours 1 4]
        [--commands estimate ingest ingest-job live live-1hz]
                                      [--records DIR]

asv runs one figure per command on a 1-h print (:class:`PeakMemory`, ``make bench``); this
command runs the sweep over print lengths. The default (1 h and 4 h) takes ~3 min on 2
cores; ``--hours 1 24 168`` gives the 7-day figure (~30 min, most of it simulating the
week; ``--records DIR`` keeps the prints there and reuses them). To measure another tree
(e.g. the code before a change), put its ``src`` first on PYTHONPATH: the children import
``ajtwin`` from there.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

COMMANDS = ("estimate", "ingest", "ingest-job", "live", "live-1hz")
#: the job print of ``ingest-job``: the public seven-layer program looped to the print's
#: length over its own part, the camera trailing 5 mm behind the nozzle (``simulate_job``'s)
PROGRAM = Path(__file__).resolve().parents[1] / "tests/data/prg/prg2svg/4-naf 654321.prg"
#: run by the child process for the live engine (argv: record, store, samples per call,
#: seconds between the live log's commits)
LIVE_CHILD = """
import sys
import pyarrow.parquet as pq
from ajtwin.engine.fleet import LiveEngine
from ajtwin.estimation.samples import Sample
from ajtwin.io.schema import INPUT_COLUMNS, OUTPUT_COLUMNS, TIME_COLUMN
from ajtwin.store.registry import Registry
per_call, commit_every_s = int(sys.argv[3]), float(sys.argv[4])
engine = LiveEngine(Registry(sys.argv[2]), commit_every_s=commit_every_s)
# the print is read a piece at a time, as a machine hands it over: the figure is the engine's,
# not a copy of the whole print held by the feeder
record = pq.ParquetFile(sys.argv[1])
columns = [TIME_COLUMN, *INPUT_COLUMNS, *OUTPUT_COLUMNS]
done = 0
for batch in record.iter_batches(batch_size=60 * per_call, columns=columns):
    rows = batch.to_pandas()
    t = rows[TIME_COLUMN].to_numpy(float)
    u = rows[list(INPUT_COLUMNS)].to_numpy(float)
    y = rows[list(OUTPUT_COLUMNS)].to_numpy(float)
    for first in range(0, len(t), per_call):
        stop = min(first + per_call, len(t))
        engine.feed_many([("M", Sample(float(t[k]), u[k], y[k])) for k in range(first, stop)])
    done += len(t)
    if done % (4 * 3600) < len(t):  # resident memory every 4 print-hours, in this one process
        with open("/proc/self/status") as status:
            kb = next(line.split()[1] for line in status if line.startswith("VmRSS:"))
        print(f"rss_MB_at_h {done // 3600} {int(kb) / 1024:.1f}", flush=True)
engine.close("M")
engine.shutdown()
"""
#: the live engine's feeds (samples per call, seconds between commits): bursts of a minute's
#: samples as fast as it takes them; one sample a call with each step written as it commits,
#: which is what a 1 Hz machine does in real time
LIVE_FEEDS = {"live": ("60", "1.0"), "live-1hz": ("1", "0.0")}


#: prepended to each child's code: at exit it writes its own peak RSS (VmHWM, kB) to the
#: file named by AJTWIN_BENCH_HWM
HWM_AT_EXIT = """
import atexit, os
def _write_hwm():
    with open("/proc/self/status") as status:
        kb = next(line.split()[1] for line in status if line.startswith("VmHWM:"))
    with open(os.environ["AJTWIN_BENCH_HWM"], "w") as out:
        out.write(kb)
atexit.register(_write_hwm)
"""


def peak_mb(argv: list[str], env: dict) -> tuple[float, float, str]:
    """(peak RSS [MB], wall [s], what it printed) of ``argv`` (``python -c CODE …``) run to
    its end (it must succeed)."""
    with tempfile.NamedTemporaryFile(suffix=".hwm", delete=False) as handle:
        hwm = Path(handle.name)
    argv = [argv[0], "-c", HWM_AT_EXIT + argv[2], *argv[3:]]
    t0 = time.perf_counter()
    proc = subprocess.run(
        argv, env={**env, "AJTWIN_BENCH_HWM": str(hwm)}, capture_output=True, check=False,
    )  # fmt: skip
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        err = proc.stderr.decode(errors="replace")
        raise RuntimeError(f"{argv[3:6]} failed ({proc.returncode}): {err[-1500:]}")
    kb = float(hwm.read_text())
    hwm.unlink()
    return kb / 1024.0, wall, proc.stdout.decode(errors="replace")


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-c", "from ajtwin.cli import run; run()", *args]


def measure(command: str, record: Path, work: Path, env: dict) -> tuple[float, float, str]:
    """Peak RSS [MB], wall [s] and what it printed (the live engine: its resident memory
    every 4 print-hours) of one command over ``record`` on a fresh registry."""
    store = work / f"{command}.sqlite"
    store.unlink(missing_ok=True)
    if command == "estimate":
        return peak_mb(_cli("estimate", str(record), "--out", str(work / "s.csv")), env)
    subprocess.run(_cli("machine", "add", "M", "--store", str(store)), env=env, check=True,
                   capture_output=True)  # fmt: skip
    if command.startswith("ingest"):
        argv = _cli("ingest", "--machine", "M", "--store", str(store), "--no-progress")
        if command == "ingest-job":
            argv += ["--job", str(PROGRAM)]
        return peak_mb([*argv, str(record)], env)
    feed = LIVE_FEEDS[command]
    return peak_mb([sys.executable, "-c", LIVE_CHILD, str(record), str(store), *feed], env)


def _record(command: str, hours: float, seed: int, folder: Path) -> Path:
    """The exp1 print ``command`` reads (a job print for ``ingest-job``), simulated once."""
    kind = "job-" if command == "ingest-job" else ""
    record = folder / f"{kind}exp1-seed{seed}-{hours:g}h.parquet"
    if not record.exists():
        from ajtwin.io.records import write_record
        from ajtwin.simulation import simulate
        from ajtwin.simulation.job_print import simulate_job

        record.parent.mkdir(parents=True, exist_ok=True)
        if kind:
            printed = simulate_job(PROGRAM, "exp1", seed=seed, duration_min=60.0 * hours)
        else:
            printed = simulate("exp1", seed=seed, duration_min=60.0 * hours)
        write_record(printed, record)
    return record


class PeakMemory:
    """Each command's own peak resident set [MB] over a clean 1-h exp1 print (seed 5), on a
    fresh registry; the JAX cache filled by an unmeasured run first."""

    params = list(COMMANDS)
    param_names = ["command"]
    timeout = 900

    def setup_cache(self):
        work = Path.cwd()
        env = dict(os.environ, JAX_PLATFORMS="cpu", AJTWIN_CACHE_DIR=str(work / "cache"))
        figures = {}
        for command in COMMANDS:
            record = _record(command, 1.0, 5, work)
            measure(command, record, work, env)  # compiles: the compiler's peak is not the print's
            figures[command] = measure(command, record, work, env)[0]
        return figures

    def track_peak_MB_1h_print(self, figures, command):
        return figures[command]

    track_peak_MB_1h_print.unit = "MB"


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, nargs="+", default=[1.0, 4.0])
    parser.add_argument("--commands", nargs="+", default=list(COMMANDS), choices=COMMANDS)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--records", type=Path, help="keep the simulated prints here, reuse them")
    args = parser.parse_args()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    figures: dict = {}
    hours = sorted(args.hours)
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        work = Path(tmp)
        peaks = {c: [] for c in args.commands}
        for i, h in enumerate(hours):
            records = {c: _record(c, h, args.seed, args.records or work) for c in args.commands}
            for command in args.commands if i == 0 else ():
                measure(command, records[command], work, env)  # fills the JAX cache
            for command in args.commands:
                mb, wall, said = measure(command, records[command], work, env)
                peaks[command].append(mb)
                figures[f"{command}_{h:g}h_peak_MB"] = round(mb, 1)
                figures[f"{command}_{h:g}h_wall_s"] = round(wall, 1)
                # a live print's resident memory as it goes: flat once the step logs are full
                trace = [line.split()[1:] for line in said.splitlines() if line.startswith("rss_")]
                if trace:
                    figures[f"{command}_{h:g}h_rss_MB_by_hour"] = {
                        int(hour): float(mb) for hour, mb in trace
                    }
            if args.records is None:
                for record in set(records.values()):
                    record.unlink()
        if len(hours) > 1:
            for command, values in peaks.items():
                slope = (values[-1] - values[0]) / (hours[-1] - hours[0])
                figures[f"{command}_MB_per_print_hour"] = round(slope, 2)
    figures["note"] = (
        f"peak RSS of each command on exp1 seed {args.seed} prints of {hours} h; slope between "
        "the shortest and the longest"
    )
    return figures


if __name__ == "__main__":
    for key, value in main().items():
        print(f"{key}: {value}")
