"""The virtual printer: a 90-min and an 8-h print simulated (compiled), and the 8-h record
written and read as Parquet and CSV."""

from __future__ import annotations

import os
import shutil
import tempfile


class Simulate:
    """``simulate()`` end to end (truth, measurement layer, record), after compilation."""

    timeout = 600

    def setup(self):
        from ajtwin.simulation import simulate

        self.simulate = simulate
        simulate("exp1", seed=0)
        simulate("clean_long", seed=0)

    def time_simulate_90min(self):
        self.simulate("exp3", seed=1)

    def time_simulate_8h(self):
        self.simulate("clean_long", seed=1)


class RecordFiles:
    """An 8-h record (28,800 rows) written and read back."""

    params = ["parquet", "csv"]
    param_names = ["format"]
    timeout = 600

    def setup_cache(self):
        from ajtwin.io import write_record
        from ajtwin.simulation import simulate

        record = simulate("clean_long", seed=1)
        for suffix in self.params:
            write_record(record, f"long.{suffix}")
        return os.getcwd()

    def setup(self, folder, suffix):
        from ajtwin.io import read_record

        self.path = os.path.join(folder, f"long.{suffix}")
        self.record = read_record(self.path)
        self.out = tempfile.mkdtemp(prefix="ajtwin-bench-")

    def teardown(self, folder, suffix):
        shutil.rmtree(self.out, ignore_errors=True)

    def time_write(self, folder, suffix):
        from ajtwin.io import write_record

        write_record(self.record, os.path.join(self.out, f"copy.{suffix}"))

    def time_read(self, folder, suffix):
        from ajtwin.io import read_record

        read_record(self.path)

    def track_size_MB(self, folder, suffix):
        return os.path.getsize(self.path) / 1e6

    track_size_MB.unit = "MB"
