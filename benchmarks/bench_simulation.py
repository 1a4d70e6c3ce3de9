"""Virtual-printer speed: simulate 90 min and 8 h prints, write/read the records.

Figures (seconds, this machine): the first 90 min call includes JAX compilation;
the others are warm (median of a few runs). Run: .venv/bin/python benchmarks/bench_simulation.py
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path


def _timed(fn, repeats=3):
    times = []
    result = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def main() -> dict:
    from ajtwin.io import read_record, write_record
    from ajtwin.simulation import simulate

    t0 = time.perf_counter()
    simulate("exp1", seed=0)
    first = time.perf_counter() - t0
    warm_90, _ = _timed(lambda: simulate("exp3", seed=1))
    t0 = time.perf_counter()
    simulate("clean_long", seed=0)
    first_8h = time.perf_counter() - t0
    warm_8h, record = _timed(lambda: simulate("clean_long", seed=1), repeats=2)
    with tempfile.TemporaryDirectory() as tmp:
        parquet = Path(tmp) / "long.parquet"
        csv = Path(tmp) / "long.csv"
        write_parquet, _ = _timed(lambda: write_record(record, parquet), repeats=1)
        read_parquet, _ = _timed(lambda: read_record(parquet), repeats=1)
        write_csv, _ = _timed(lambda: write_record(record, csv), repeats=1)
        read_csv, _ = _timed(lambda: read_record(csv), repeats=1)
        sizes = (parquet.stat().st_size / 1e6, csv.stat().st_size / 1e6)
    return {
        "simulate_90min_first_call_s": round(first, 2),
        "simulate_90min_warm_s": round(warm_90, 2),
        "simulate_8h_first_call_s": round(first_8h, 2),
        "simulate_8h_warm_s": round(warm_8h, 2),
        "write_parquet_8h_s": round(write_parquet, 3),
        "read_parquet_8h_s": round(read_parquet, 3),
        "write_csv_8h_s": round(write_csv, 3),
        "read_csv_8h_s": round(read_csv, 3),
        "parquet_8h_MB": round(sizes[0], 2),
        "csv_8h_MB": round(sizes[1], 2),
        "note": "simulate() end to end incl. measurement layer and record assembly; "
        "first calls include JAX compilation for that length",
    }


if __name__ == "__main__":
    for key, value in main().items():
        print(f"{key}: {value}")
