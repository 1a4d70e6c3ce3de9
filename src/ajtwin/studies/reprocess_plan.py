"""How fast ``ajtwin reprocess`` goes, and what a fleet's year of prints would take.

:func:`measure_workers` re-runs the same stored prints (``machines`` × ``prints`` simulated
prints of ``minutes`` each, one registry on a PostgreSQL server of its own) with 1 and
with 2 Dask workers and gives the prints per minute of each (wall time from the first
task given to the last done: the cluster's start and the workers' imports excluded, each
worker's first compilation included) and their ratio.

:func:`simulate_fleet` runs the scheduling of a fleet's reprocessing on Dask with the same
task graph ``ajtwin reprocess`` builds — each machine's prints a chain of tasks, the
machines' chains side by side — where every task only waits as long as a print's re-run
takes (``print_s``, scaled by ``time_scale`` so that a year runs in minutes), and compares
the scheduled wall time with the plan's arithmetic: a machine's chain cannot go faster
than its prints one after the other, the fleet no faster than all its prints shared by
the workers: ``wall ≈ max(prints per machine, all prints / workers) × print_s``.

Run: ``python -m ajtwin.studies.reprocess_plan measure [postgresql|sqlite]`` and ``…
simulate``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

from ajtwin.engine.ingest import ingest_record
from ajtwin.engine.reprocess import reprocess
from ajtwin.simulation import simulate
from ajtwin.store.pg_cluster import LocalCluster
from ajtwin.store.registry import Registry


def measure_workers(machines: int = 4, prints: int = 6, minutes: float = 20.0,
                    workers=(1, 2), database: str = "postgresql") -> dict:  # fmt: skip
    """Prints per minute of ``ajtwin reprocess`` at each worker count (module docstring);
    ``database``: the registry on a PostgreSQL server of its own on this computer, or an
    SQLite file (no server process sharing the cores)."""
    out: dict = {"machines": machines, "prints_per_machine": prints, "print_min": minutes,
                 "database": database}  # fmt: skip
    with LocalCluster() as cluster, tempfile.TemporaryDirectory() as tmp:
        url = cluster.url() if database == "postgresql" else str(Path(tmp) / "r.sqlite")
        reg = Registry(url)
        for m in range(machines):
            name = f"aj{m + 1}"
            reg.add_machine(name)
            previous = None
            for k in range(prints):
                rec = simulate("exp1", seed=100 * m + k, duration_min=minutes,
                               continue_from=previous)  # fmt: skip
                ingest_record(reg, name, rec)
                previous = rec
        reg.close()
        for n in workers:
            done = reprocess(url, workers=n, reason=f"throughput, {n} worker(s)")
            out[f"prints_per_min_{n}_workers"] = round(done["prints_per_min"], 2)
            out[f"wall_s_{n}_workers"] = round(done["seconds"], 1)
            out[f"startup_s_{n}_workers"] = round(done["startup_s"], 1)
            out[f"task_s_per_print_{n}_workers"] = round(done["task_seconds"] / done["prints"], 2)
    if len(workers) == 2:
        a, b = workers
        rate = out[f"prints_per_min_{b}_workers"] / out[f"prints_per_min_{a}_workers"]
        out["speedup"] = round(rate, 2)
    return out


def _task(previous, wait_s):
    time.sleep(wait_s)
    return 0 if previous is None else previous + 1


def simulate_fleet(machines: int = 100, prints: int = 750, print_s: float = 1.8,
                   workers: int = 32, time_scale: float = 0.02) -> dict:  # fmt: skip
    """The scheduling of a fleet's reprocessing on Dask (module docstring): simulated and
    predicted wall time [s of the real run], the tasks' real wall time scaled back."""
    from dask.distributed import Client, wait
    from dask.distributed import LocalCluster as DaskCluster

    wait_s = print_s * time_scale
    with DaskCluster(n_workers=1, threads_per_worker=workers, processes=False,
                     dashboard_address=None) as cluster, Client(cluster) as client:  # fmt: skip
        t0 = time.perf_counter()
        last = []
        for m in range(machines):
            previous = None
            for k in range(prints):
                previous = client.submit(_task, previous, wait_s, key=f"sim-{m}-{k}", pure=False)
            last.append(previous)
        wait(last)
        wall = time.perf_counter() - t0
    predicted = max(prints, machines * prints / workers) * wait_s
    return {
        "machines": machines,
        "prints_per_machine": prints,
        "print_s": print_s,
        "workers": workers,
        "tasks": machines * prints,
        "simulated_wall_s": round(wall, 1),
        "predicted_wall_s": round(predicted, 1),
        "overhead_s_per_task": round(max(0.0, wall - predicted) / (machines * prints), 5),
        # the tasks' waits scale back, the scheduler's own time does not
        "fleet_wall_h": round((predicted / time_scale + max(0.0, wall - predicted)) / 3600, 2),
        "fleet_predicted_h": round(predicted / time_scale / 3600, 2),
    }


if __name__ == "__main__":  # pragma: no cover - run by hand
    import sys

    if sys.argv[1:2] == ["simulate"]:
        print(json.dumps(simulate_fleet(), indent=1))
    else:
        print(json.dumps(measure_workers(database=(sys.argv[2:3] or ["postgresql"])[0]), indent=1))
