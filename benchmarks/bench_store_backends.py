"""The registry's throughput on SQLite and PostgreSQL, side by side in one run.

:func:`measure_store_backends` times, on an SQLite file and on a PostgreSQL server of its
own (Debian's server, ``initdb`` + ``pg_ctl`` in a temporary folder, commits flushed to
disk as a production server does; :class:`ajtwin.store.pg_cluster.LocalCluster`):

* **live burst** — three machines' live twins catching up on a backlog (a printer's sample
  buffer after a reconnection): a 10-min print of each fed to one
  :class:`~ajtwin.engine.fleet.LiveEngine` as fast as it steps, the live log committed as
  ``ajtwin live`` does (``commit_every_s=1``: a transaction a second per machine, whatever
  the steps in it), then the prints stored; steps per second, twin included. Also the
  worst case, a transaction per step (``commit_every_s=0``), and the live log's writes
  alone (:meth:`ajtwin.store.live_log.LiveLog.append`, one transaction a step);
* **ingest of a 90-min print** — :func:`ajtwin.engine.ingest.ingest_record` of one
  simulated 90-minute print (its arrays written in parts as the twin runs, then one
  transaction), wall seconds.

The aims: PostgreSQL within 1.5× of SQLite for the live burst and within 1.2×
for the ingest; the ``*_ratio`` figures are PostgreSQL's time over SQLite's. Timings on a
shared 2-core machine are noisy: the ratios, measured in one run, are what to read.

Run: ``python benchmarks/bench_store_backends.py`` (or through ``make bench``).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path


def _live_burst(location, records, commit_every_s: float) -> tuple[float, int]:
    """(wall s, steps) of three machines' prints fed to one engine, the live log committed
    every ``commit_every_s``, the prints then stored."""
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.estimation.samples import Sample
    from ajtwin.store.registry import Registry

    registry = Registry(location)
    engine = LiveEngine(registry, asynchronous=False, commit_every_s=commit_every_s)
    engine.warm_up(len(records))
    names = [f"aj{k}" for k in range(len(records))]
    for name in names:
        engine.open(name)
    t0 = time.perf_counter()
    steps = 0
    for k in range(len(records[0].time_s)):
        batch = [(n, Sample(r.time_s[k], r.inputs[k], r.outputs[k])) for n, r in
                 zip(names, records)]  # fmt: skip
        engine.feed_many(batch)
        steps += len(batch)
    for name in names:
        engine.close(name)
    seconds = time.perf_counter() - t0
    engine.shutdown()
    engine.log.close()
    registry.close()
    return seconds, steps


def _log_writes(location, n_steps: int) -> float:
    """Wall s of ``n_steps`` live-log steps, one transaction each (the store alone)."""
    import numpy as np

    from ajtwin.model import STATE_NAMES
    from ajtwin.store.live_log import LiveLog

    log = LiveLog(location)
    sid = log.open_session("burst", source="bench", start=None, theta=np.zeros(5))
    states = dict(zip(STATE_NAMES, [3.5, 0.95, 1e-4, 0.03, 4.6e-7]))
    message = {"machine": "burst", "time_s": 0.0, "states": states, "stds": states,
               "predicted_outputs": {"L_w": 40.0}, "nis": 1.0, "status": "ok"}  # fmt: skip
    t0 = time.perf_counter()
    for k in range(n_steps):
        log.append(sid, [(k, float(k), np.ones(3), np.ones(5), {**message, "step": k})], [])
    seconds = time.perf_counter() - t0
    log.close()
    return seconds


def _ingest(location, record) -> float:
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.store.registry import Registry

    registry = Registry(location)
    registry.add_machine("ingest")
    t0 = time.perf_counter()
    ingest_record(registry, "ingest", record)
    seconds = time.perf_counter() - t0
    registry.close()
    return seconds


def measure_store_backends(burst_minutes: float = 10.0, ingest_minutes: float = 90.0) -> dict:
    """The figures of the module docstring (SQLite and PostgreSQL in one run)."""
    from ajtwin.simulation import simulate
    from ajtwin.store.pg_cluster import LocalCluster

    records = [simulate("exp1", seed=s, duration_min=burst_minutes) for s in (1, 2, 3)]
    long_print = simulate("exp1", seed=4, duration_min=ingest_minutes)
    figures: dict = {}
    with tempfile.TemporaryDirectory(prefix="ajtwin-bench-") as tmp, LocalCluster() as cluster:
        made = iter(range(10**6))

        def new_store(kind):
            n = next(made)
            if kind == "sqlite":
                return Path(tmp) / f"r{n}.sqlite"
            return _new_database(cluster, f"r{n}")

        # one warm-up of each path so that neither database pays the twin's compilations
        warm = simulate("exp1", seed=5, duration_min=5.0)
        _ingest(new_store("sqlite"), warm)
        _live_burst(new_store("sqlite"), [warm.window(0, 60)] * 3, 1.0)
        for name, commit_s in (("live_burst", 1.0), ("live_burst_every_step", 0.0)):
            for kind in KINDS:
                seconds, steps = _live_burst(new_store(kind), records, commit_s)
                figures[f"{name}_steps_per_s_{kind}"] = round(steps / seconds, 1)
        for kind in KINDS:
            log_s = _log_writes(new_store(kind), 2000)
            figures[f"live_log_steps_per_s_{kind}"] = round(2000 / log_s, 1)
        ingest = {kind: [] for kind in KINDS}
        for _ in range(2):  # alternated, the faster of two each
            for kind in KINDS:
                ingest[kind].append(_ingest(new_store(kind), long_print))
        for kind in KINDS:
            figures[f"ingest_90min_s_{kind}"] = round(min(ingest[kind]), 2)
    for name in ("live_burst", "live_burst_every_step", "live_log"):
        figures[f"{name}_ratio"] = round(
            figures[f"{name}_steps_per_s_sqlite"] / figures[f"{name}_steps_per_s_postgresql"], 3
        )
    figures["ingest_90min_ratio"] = round(
        figures["ingest_90min_s_postgresql"] / figures["ingest_90min_s_sqlite"], 3
    )
    figures["note"] = (
        "PostgreSQL: a server of its own on 127.0.0.1, each commit flushed to disk; SQLite: "
        "WAL, synchronous=NORMAL; ratios are PostgreSQL's time over SQLite's (aims: live "
        "burst <= 1.5 at ajtwin live's commit every second, ingest <= 1.2); a shared "
        "2-core machine"
    )
    return figures


KINDS = ("sqlite", "postgresql")


def _new_database(cluster, name: str) -> str:
    cluster.psql("postgres", f"CREATE DATABASE {name} OWNER ajtwin")
    return cluster.url(name)


def main() -> dict:
    """The figures for ``benchmarks/run_all.py``."""
    return measure_store_backends()


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
