"""The registry: bytes per print-hour, and what `machine history` / `machine show` read
against the number of stored prints.

* bytes per print-hour: a 30-min exp1 print ingested into an empty registry (file + WAL
  after a checkpoint), and after `machine compact` past the covariance retention;
* CPU time of the queries of `machine history` and `machine show` for a machine with 10,
  100 and 1000 stored prints (synthetic 180-step prints: the queries read the print rows,
  not the arrays, so the print length does not matter).
"""

from __future__ import annotations

import datetime as dt
import shutil
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np


def _fill(reg, name, start, stop):
    rng = np.random.default_rng(start)
    end = np.array([3.5, 0.95, 1e-4, 0.03, 4.6e-7])
    n = 180
    clog = SimpleNamespace(
        detected_s=60.0,
        onset_s=30.0,
        cause="nozzle_clog",
        description="x",
        detectors=["x"],
        evidence={},
    )
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
            },
            anomalies=[clog] if seq % 10 == 0 else [],
            expected_last_seq=None if seq == 1 else seq - 1,
        )


class StoredPrint:
    """Registry bytes per print-hour of a 30-min print, as stored and after retention."""

    timeout = 600

    def setup_cache(self):
        from ajtwin.engine.ingest import ingest_record
        from ajtwin.simulation import simulate
        from ajtwin.store.compaction import compact
        from ajtwin.store.registry import Registry

        path = Path("r.sqlite").resolve()
        reg = Registry(path)
        reg.add_machine("m")
        empty = reg.checkpointed_bytes()
        rec = simulate("exp1", seed=1, duration_min=30.0)
        ingest_record(reg, "m", rec)
        hours = len(rec) / 3600.0
        stored = (reg.checkpointed_bytes() - empty) / hours / 1e6
        later = dt.datetime.now(dt.UTC) + dt.timedelta(days=31)
        stats = compact(reg, "m", 30, now=later)
        reg.close()
        return {"stored": stored, "retained": (stats["bytes_after"] - empty) / hours / 1e6}

    def track_MB_per_print_hour(self, sizes):
        return sizes["stored"]

    def track_MB_per_print_hour_after_retention(self, sizes):
        return sizes["retained"]

    track_MB_per_print_hour.unit = track_MB_per_print_hour_after_retention.unit = "MB"


class MachineQueries:
    """What `machine history` and `machine show` read, 10 / 100 / 1000 stored prints."""

    params = [10, 100, 1000]
    param_names = ["prints"]
    timer = time.process_time
    timeout = 600

    def setup(self, prints):
        from ajtwin.store.registry import Registry

        self.folder = tempfile.mkdtemp(prefix="ajtwin-bench-")
        self.reg = Registry(Path(self.folder) / "q.sqlite")
        self.reg.add_machine("q")
        _fill(self.reg, "q", 1, prints + 1)

    def teardown(self, prints):
        self.reg.close()
        shutil.rmtree(self.folder, ignore_errors=True)

    def time_history(self, prints):
        self.reg.history("q")

    def time_show(self, prints):
        self.reg.machine("q"), self.reg.last_print("q"), self.reg.anomalies("q")
