"""The applications in one process, warm (compiled): ingest of a 30-min print (twin + detectors
+ one SQLite transaction), the duplicate check of a print already stored, a 30-min forecast
and input advice. The detectors' accuracy (delay per fault, false alarms on clean prints)
is a study: ``python -m ajtwin.studies.detection``."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path


class Ingest:
    """``ingest_record`` of a 30-min print that carries on from the one stored before it."""

    timeout = 900
    number = 1
    repeat = (2, 5, 120.0)

    def setup_cache(self):
        from ajtwin.io import write_record
        from ajtwin.simulation import simulate

        first = simulate("exp1", seed=5, duration_min=30)
        second = simulate("exp1", seed=6, duration_min=30, continue_from=first)
        write_record(first, "first.parquet")
        write_record(second, "second.parquet")
        return os.getcwd()

    def setup(self, folder):
        from ajtwin.engine.ingest import ingest_record
        from ajtwin.io import read_record
        from ajtwin.store.registry import Registry

        self.ingest = ingest_record
        self.work = tempfile.mkdtemp(prefix="ajtwin-bench-")
        self.reg = Registry(Path(self.work) / "r.sqlite")
        self.reg.add_machine("bench")
        self.first = read_record(Path(folder) / "first.parquet")
        ingest_record(self.reg, "bench", self.first)
        self.second = read_record(Path(folder) / "second.parquet")

    def teardown(self, folder):
        self.reg.close()
        shutil.rmtree(self.work, ignore_errors=True)

    def time_ingest_30min_print(self, folder):
        self.ingest(self.reg, "bench", self.second)

    def time_ingest_duplicate_check(self, folder):
        """The first print again: found by its content hash, nothing run."""
        self.ingest(self.reg, "bench", self.first)


class Planning:
    """A 30-min forecast (Q_c 26 sccm from +60 s) and advice for 45 µm, from a stored state."""

    timeout = 900

    def setup_cache(self):
        from ajtwin.engine.ingest import ingest_record
        from ajtwin.simulation import simulate
        from ajtwin.store.registry import Registry

        reg = Registry(Path("r.sqlite").resolve())
        reg.add_machine("bench")
        ingest_record(reg, "bench", simulate("exp1", seed=5, duration_min=30))
        last = reg.last_print("bench")
        reg.close()
        return {key: last[key] for key in ("theta_after", "end_mean", "end_cov")}

    def setup(self, last):
        from ajtwin.apps.planning.advice import advise
        from ajtwin.apps.planning.forecast import forecast, input_schedule, parse_change
        from ajtwin.estimation import Twin

        self.twin = Twin.default()
        self.twin.theta = last["theta_after"]
        self.start = (last["end_mean"], last["end_cov"])
        self.u = input_schedule([375, 23, 50], [parse_change("Q_c=26@+60s")], 1800)
        self.forecast, self.advise = forecast, advise
        self.time_forecast_30min(last)
        self.time_advise_45um(last)

    def time_forecast_30min(self, last):
        self.forecast(self.twin, *self.start, self.u)

    def time_advise_45um(self, last):
        self.advise(self.twin, *self.start, [375, 23, 50], 45.0)
