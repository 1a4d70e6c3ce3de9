"""The job reader: parse time of ACSPL+ programs and throughput of the trace queries.

* Parse: :func:`ajtwin.job.read_program` (file read, the single pass, the job's arrays and
  checks) on the public 154 kB program ``4-naf 654321.prg`` and on programs of ≥ 150 kB and
  ≥ 10 MB built by repeating the public ``1-nafbot.prg`` (its motion body repeated, each copy
  a ``!Feature k``). Aims: 150 kB ≤ 0.2 s, 10 MB ≤ 5 s.
* Queries on ``4-naf 654321.prg``: :meth:`Job.locate` (the trailing camera's question) for
  100,000 points on and beside the traces, radius 10 µm, with and without a time limit;
  :meth:`Job.state_at` for 1,000,000 times; the timeline table; the per-second table.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "prg" / "prg2svg"
PUBLIC = DATA / "4-naf 654321.prg"
POINTS = 100_000
TIMES = 1_000_000


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


class Parse:
    """``read_program`` of the public program and of repeated ones of 150 kB and 10 MB."""

    params = ["public_154kB", "repeated_150kB", "repeated_10MB"]
    param_names = ["program"]
    timeout = 300

    def setup_cache(self):
        """The repeated programs, written once (asv runs this in a folder of its own)."""
        for name, size in (("repeated_150kB", 150_000), ("repeated_10MB", 10_000_000)):
            Path(f"{name}.prg").write_text(repeated_program(DATA / "1-nafbot.prg", size))
        return os.getcwd()

    def setup(self, folder, program):
        self.path = PUBLIC if program == "public_154kB" else Path(folder) / f"{program}.prg"

    def time_read_program(self, folder, program):
        from ajtwin.job import read_program

        read_program(self.path)

    def track_parse_MB_per_s(self, folder, program):
        import time

        from ajtwin.job import read_program

        t0 = time.perf_counter()
        read_program(self.path)
        return self.path.stat().st_size / (time.perf_counter() - t0) / 1e6

    track_parse_MB_per_s.unit = "MB/s"


class Queries:
    """The trace queries on the public program (its cached index built in setup)."""

    timeout = 300

    def setup(self):
        from ajtwin.job import read_program

        job = self.job = read_program(PUBLIC)
        s = job.segments
        rng = np.random.default_rng(1)
        printed = np.flatnonzero(s["shutter_open"] & (s["length_mm"] > 0))
        seg = rng.choice(printed, POINTS)
        self.t = s["t0_s"][seg] + rng.uniform(0, 1, POINTS) * (s["t1_s"][seg] - s["t0_s"][seg])
        state = job.state_at(self.t)
        # half the points on a trace, half up to 20 µm beside it
        beside = np.arange(POINTS) % 2 == 1
        self.x = state.x_mm + np.where(beside, rng.uniform(-0.02, 0.02, POINTS), 0.0)
        self.y = state.y_mm + np.where(beside, rng.uniform(-0.02, 0.02, POINTS), 0.0)
        job.locate(self.x[:10], self.y[:10], 0.01)  # builds the cached index
        self.times = rng.uniform(0, job.duration_s, TIMES)

    def time_trace_index_build(self):
        self.job.trace_index(cell_mm=None).__class__(self.job)

    def time_locate_100k_points(self):
        self.job.locate(self.x, self.y, radius_mm=0.01)

    def time_locate_100k_points_before_a_time(self):
        self.job.locate(self.x, self.y, radius_mm=0.01, before_s=self.t + 1e-6)

    def time_state_at_1M_times(self):
        self.job.state_at(self.times)

    def time_timeline(self):
        self.job.timeline()

    def time_per_second(self):
        self.job.per_second()
