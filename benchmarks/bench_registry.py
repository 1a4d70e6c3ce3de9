"""Registry: bytes per print-hour, and `machine history`/`show` time vs number of prints.

* bytes per print-hour: a 30-min exp1 print ingested into an empty registry (file + WAL
  growth after a checkpoint), and after `machine compact` past the covariance retention;
* query CPU time of what `machine history` and `machine show` read, for a machine with
  10, 100 and 1000 stored prints (synthetic 180-step prints: the queries read the print
  rows, not the arrays, so the print length does not matter).
"""

from __future__ import annotations

import datetime as dt
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np


def _fill(reg, name, start, stop):
    rng = np.random.default_rng(start)
    end = np.array([3.5, 0.95, 1e-4, 0.03, 4.6e-7])
    n = 180
    for seq in range(start, stop):
        covs = np.tile(np.diag((0.01 * end) ** 2), (n, 1, 1))
        reg.save_print(
            name,
            content_hash=f"h{seq}",
            source="bench",
            meta={},
            summary={},
            n_samples=n,
            duration_s=float(n),
            start_mean=end,
            start_cov=covs[0],
            end_mean=end,
            end_cov=covs[-1],
            theta_before=np.zeros(5),
            theta_after=np.zeros(5),
            arrays={
                "time_s": np.arange(n, dtype=float),
                "means": end * (1 + 1e-4 * rng.normal(size=(n, 5))),
                "covariances": covs,
            },  # fmt: skip
            anomalies=[
                SimpleNamespace(
                    detected_s=60.0,
                    onset_s=30.0,
                    cause="nozzle_clog",
                    description="x",
                    detectors=["x"],
                    evidence={},
                )
            ]
            if seq % 10 == 0
            else [],  # fmt: skip
            expected_last_seq=None if seq == 1 else seq - 1,
        )


def _cpu(fn, repeat=5):
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def main() -> dict:
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.simulation import simulate
    from ajtwin.store.compaction import compact
    from ajtwin.store.registry import Registry

    figures = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "r.sqlite"
        reg = Registry(path)
        reg.add_machine("m")
        empty = reg.checkpointed_bytes()
        rec = simulate("exp1", seed=1, duration_min=30.0)
        ingest_record(reg, "m", rec)
        hours = len(rec) / 3600.0
        figures["MB_per_print_hour"] = round((reg.checkpointed_bytes() - empty) / hours / 1e6, 3)
        later = dt.datetime.now(dt.UTC) + dt.timedelta(days=31)
        stats = compact(reg, "m", 30, now=later)
        figures["MB_per_print_hour_after_retention"] = round(
            (stats["bytes_after"] - empty) / hours / 1e6, 3
        )

        reg = Registry(Path(tmp) / "q.sqlite")
        reg.add_machine("q")
        done = 1
        for n in (10, 100, 1000):
            _fill(reg, "q", done, n + 1)
            done = n + 1
            figures[f"history_cpu_ms_{n}_prints"] = round(_cpu(lambda: reg.history("q")) * 1e3, 2)
            figures[f"show_cpu_ms_{n}_prints"] = round(
                _cpu(lambda: (reg.machine("q"), reg.last_print("q"), reg.anomalies("q"))) * 1e3,
                2,
            )
    figures["note"] = "CPU time (process_time), best of 5; bytes: file + WAL after checkpoint"
    return figures


if __name__ == "__main__":
    for key, value in main().items():
        print(f"{key}: {value}")
