"""Bytes per print-hour of a machine's registry when it runs live (docs/validation.md,
"Storage policy"): one exp1 print fed to the live engine sample by sample; the registry
file (after a WAL checkpoint) while the session is open and after it closed.

Usage (default 90 min, ``./live-storage.sqlite``, overwritten)::

    python -m ajtwin.studies.live_storage [MINUTES] [REGISTRY]
"""

from __future__ import annotations

import os
import sys
import time

from ajtwin.engine.fleet import LiveEngine
from ajtwin.estimation.samples import Sample
from ajtwin.simulation import simulate
from ajtwin.store.compaction import checkpointed_bytes
from ajtwin.store.registry import Registry


def main(minutes: float = 90.0, path: str = "live-storage.sqlite") -> dict:
    """Bytes per print-hour of a registry that runs live: a ``minutes`` virtual print fed to
    the live engine, stored in ``path``.
    """
    for suffix in ("", "-wal", "-shm"):
        if os.path.exists(path + suffix):
            os.remove(path + suffix)
    record = simulate("exp1", seed=1, duration_min=minutes)
    registry = Registry(path)
    registry.add_machine("M")

    def size() -> int:
        return checkpointed_bytes(registry)

    empty = size()
    engine = LiveEngine(registry, asynchronous=False)
    cpu = time.process_time()
    for k in range(len(record.time_s)):
        engine.feed("M", Sample(record.time_s[k], record.inputs[k], record.outputs[k]))
    engine.flush()
    hours = len(record.time_s) / 3600
    open_mb = (size() - empty) / hours / 1e6
    engine.close("M")
    engine.shutdown()
    closed_mb = (size() - empty) / hours / 1e6
    free = registry.free_bytes()
    rows = {t: registry.count_rows(t) for t in ("live_samples", "live_states")}
    return {
        "open_MB_per_print_hour": round(open_mb, 3),
        "closed_MB_per_print_hour": round(closed_mb, 3),
        "free_pages_MB": round(free / 1e6, 3),
        "live_rows_left": rows,
        "cpu_s": round(time.process_time() - cpu, 1),
    }


if __name__ == "__main__":
    args = sys.argv[1:]
    print(main(float(args[0]) if args else 90.0, *(args[1:2] or ["live-storage.sqlite"])))
