"""Job reader: parse time of ACSPL+ programs and throughput of the trace queries.

Run alone with ``.venv/bin/python benchmarks/bench_job.py`` (prints a JSON of figures) or
with all benches via ``make bench``.

* Parse: :func:`ajtwin.job.read_program` (file read, the single pass, the job's arrays and
  checks) on the public 154 kB program ``4-naf 654321.prg`` and on programs of ≥ 150 kB and
  ≥ 10 MB built by repeating the public ``1-nafbot.prg`` (its motion body repeated, each copy
  a ``!Feature k``). Best of several runs, wall time, one process. Targets: 150 kB ≤ 0.2 s,
  10 MB ≤ 5 s.
* Queries on ``4-naf 654321.prg``: :meth:`Job.locate` (the trailing camera's question) for
  100 000 points on and beside the traces, radius 10 µm, with and without a time limit;
  :meth:`Job.state_at` for 1 000 000 times; the timeline table; the per-second table.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ajtwin.job import read_program

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "prg" / "prg2svg"


def _best(function, repeat: int) -> tuple[float, object]:
    best, result = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - t0)
    return best, result


def repeated_program(source: Path, min_bytes: int) -> str:
    """The source's motion body repeated until the program holds ``min_bytes``."""
    lines = source.read_text().splitlines()
    end_block = next(i for i, line in enumerate(lines) if line.strip().lower() == "end")
    stop = max(i for i, line in enumerate(lines) if line.strip().lower() == "stop")
    header, body = lines[: end_block + 1], lines[end_block + 1 : stop]
    body_text = "\n".join(body) + "\n"
    out = ["\n".join(header) + "\n"]
    size, feature = len(out[0]), 0
    while size < min_bytes:
        feature += 1
        chunk = f"!Feature {feature} copy of {source.name}\n" + body_text
        out.append(chunk)
        size += len(chunk)
    out.append("STOP\n")
    return "".join(out)


def parse_figures(tmp: Path) -> dict:
    figures = {}
    public = DATA / "4-naf 654321.prg"
    seconds, job = _best(lambda: read_program(public), 7)
    figures["public_154kB_parse_s"] = round(seconds, 4)
    figures["public_154kB_segments"] = job.n_segments
    for name, size, repeat in (("150kB", 150_000, 7), ("10MB", 10_000_000, 3)):
        path = tmp / f"repeated_{name}.prg"
        path.write_text(repeated_program(DATA / "1-nafbot.prg", size))
        seconds, job = _best(lambda path=path: read_program(path), repeat)
        summary = job.summary()
        figures[f"repeated_{name}_bytes"] = path.stat().st_size
        figures[f"repeated_{name}_lines"] = summary["lines"]
        figures[f"repeated_{name}_parse_s"] = round(seconds, 4)
        figures[f"repeated_{name}_strokes"] = summary["strokes"]
        figures[f"repeated_{name}_features"] = len(summary["features"])
        figures[f"repeated_{name}_parse_MB_per_s"] = round(path.stat().st_size / seconds / 1e6, 2)
    return figures


def query_figures() -> dict:
    figures = {}
    job = read_program(DATA / "4-naf 654321.prg")
    s = job.segments
    seconds, index = _best(lambda: job.trace_index(cell_mm=None).__class__(job), 3)
    figures["locate_index_build_s"] = round(seconds, 4)
    figures["locate_index_chunks"] = int(index.parent.size)
    rng = np.random.default_rng(1)
    printed = np.flatnonzero(s["shutter_open"] & (s["length_mm"] > 0))
    n = 100_000
    seg = rng.choice(printed, n)
    t = s["t0_s"][seg] + rng.uniform(0, 1, n) * (s["t1_s"][seg] - s["t0_s"][seg])
    state = job.state_at(t)
    # half the points on a trace, half up to 20 um beside it
    x = state.x_mm + np.where(np.arange(n) % 2 == 0, 0.0, rng.uniform(-0.02, 0.02, n))
    y = state.y_mm + np.where(np.arange(n) % 2 == 0, 0.0, rng.uniform(-0.02, 0.02, n))
    job.locate(x[:10], y[:10], 0.01)  # build the cached index
    seconds, hits = _best(lambda: job.locate(x, y, radius_mm=0.01), 3)
    figures["locate_points_per_s"] = round(n / seconds)
    figures["locate_found_fraction"] = round(float(hits.found.mean()), 4)
    seconds, _ = _best(lambda: job.locate(x, y, radius_mm=0.01, before_s=t + 1e-6), 3)
    figures["locate_before_points_per_s"] = round(n / seconds)
    times = rng.uniform(0, job.duration_s, 1_000_000)
    seconds, _ = _best(lambda: job.state_at(times), 3)
    figures["state_at_times_per_s"] = round(times.size / seconds)
    seconds, table = _best(job.timeline, 3)
    figures["timeline_s"] = round(seconds, 4)
    figures["timeline_rows"] = len(table)
    seconds, _ = _best(job.per_second, 3)
    figures["per_second_s"] = round(seconds, 4)
    return figures


def main() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        figures = parse_figures(Path(tmp))
    figures.update(query_figures())
    figures["note"] = (
        "wall time, best of 3-7 runs, one process; read_program = read + pass + job arrays"
    )
    return figures


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
