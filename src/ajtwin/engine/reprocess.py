"""Fleet reprocessing: the twin re-run over stored prints, as a new version of results.

After a model update or a new calibration, ``ajtwin reprocess`` runs each machine's twin
again over every stored print (or those since a date), in the machine's order, and
stores the results beside the old ones as a new version of the registry
(:meth:`~ajtwin.store.registry.Registry.create_version`; version 1 is the prints as
stored, nothing is overwritten; ``ajtwin machine history NAME --version N`` shows one).

A print is re-run as it was ingested — from its stored inputs and the measurements the
filter used (on a job print filed at their print times, with their speed-law factors),
the detectors and the mismatch guard over the run, the chain's judgement — but from the
start the *new* chain gives (:func:`reprocess_print`): the previous print's new end
state and θ, the calibration the machine has now (commissioning's start where it was
fitted, the maintenance done between prints), the detectors' long-run statistics carried
from the previous new result. A print dropped by hand stays dropped.

The work runs on Dask distributed (:func:`reprocess`): each print is a task that reads its
print from the shared registry and writes its result there; a machine's prints form a chain
of tasks (each waits for the previous one's end state), different machines' chains run
side by side on the workers. By default a ``LocalCluster`` of ``workers`` processes on this
computer (an SQLite registry, or PostgreSQL); with ``scheduler`` (``tcp://host:8786``) the
workers of a cluster, which must reach the same PostgreSQL registry (an SQLite file is
refused: a cluster's workers cannot share it).
"""

from __future__ import annotations

import importlib
import json
import time
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.mismatch import (
    assess_run,
    data_share,
    determined_states,
    relabel_events,
)
from ajtwin.engine.chain import ChainStart, carry_over, chain_start, judge_run
from ajtwin.engine.ingest import print_summary, run_arrays
from ajtwin.engine.start import start_of_print
from ajtwin.estimation.twin import Twin
from ajtwin.io.schema import JOB_COLUMNS
from ajtwin.store.calibration import active_calibration
from ajtwin.store.location import parse_store
from ajtwin.store.registry import STATUS_DROPPED, STATUS_OK, NewPrint, Registry, RegistryError

#: a print's arrays that are its samples, kept by the print itself (not by its versions)
SAMPLE_ARRAYS = ("measurements", "inputs", "line_factors", *JOB_COLUMNS)


@dataclass(frozen=True)
class Carry:
    """Where the machine's next print starts after a re-run print (a task's result): the
    chain's rule (:mod:`ajtwin.engine.chain`) over the new results.

    Attributes
    ----------
    seq : int
        The print just re-run (or, for a reprocessing from a date, the one before it).
    start : (mean (5,), cov (5, 5)) or None
        The next print's start: the newest good print's new end, widened between prints
        (:func:`~ajtwin.engine.chain.carry_over`); None: the initial fit.
    theta : array (5,) or None
        Its θ (None: nominal).
    from_seq : int or None
        The print that start comes from.
    long_run_history : dict or None
        The detectors' long-run statistics for the next print.
    seconds : float
        Wall time of the re-run (0 for a print the version held already).
    """

    seq: int
    start: tuple | None
    theta: np.ndarray | None
    from_seq: int | None
    long_run_history: dict | None
    seconds: float = 0.0

    def after(self, seq: int, end=None, theta=None, long_run=None, seconds=0.0) -> Carry:
        """The carry after print ``seq``: its end and θ if it is good (``end`` given), else
        this carry's start, passed on."""
        if end is None:
            return Carry(seq, self.start, self.theta, self.from_seq, self.long_run_history,
                         seconds)  # fmt: skip
        return Carry(seq, carry_over(*end), np.asarray(theta, float), seq, long_run, seconds)


#: the carry before a machine's first print: the initial fit, nominal θ
FIRST = Carry(0, None, None, None, None)


def chain_of(previous: Carry, seq: int) -> ChainStart:
    """The chain's start of print ``seq`` after ``previous``."""
    skipped = []
    if previous.from_seq != previous.seq and previous.seq:
        skipped = [f"print {previous.seq}: not in the chain"]
    return ChainStart(previous.start, previous.theta, previous.from_seq,
                      previous.seq or None, skipped)  # fmt: skip


def stored_carry(registry, machine: str, seq: int) -> Carry:
    """Where print ``seq`` starts in the chain of the prints as stored (version 1): the
    start of a reprocessing from a date."""
    if seq <= 1:
        return FIRST
    chain = chain_start(registry, machine, below_seq=seq)
    history = registry.long_run_history(machine, below_seq=seq)
    return Carry(seq - 1, chain.start, chain.theta, chain.from_seq,
                 None if history is None else history[1])  # fmt: skip


def reprocess_print(registry, version: int, machine: str, print_id: int, previous,
                    detector_settings=None, twin_overrides=None) -> Carry:  # fmt: skip
    """Re-run the twin over stored print ``print_id`` of ``machine`` from the new chain's
    start after ``previous`` (:class:`Carry` of the print before it, None: the first) and
    store the result in ``version``; the carry for the next print.

    A print that ``version`` holds already is not run again (a resumed reprocessing): its
    stored result is the carry."""
    row = registry.get_print(print_id)
    seq = int(row["seq"])
    done = registry.print_version(version, print_id)
    if done is not None:
        return _carry_of(done, previous, seq)
    t0 = time.perf_counter()
    arrays = registry.print_arrays(print_id)
    if "inputs" not in arrays or "measurements" not in arrays:
        raise RegistryError(
            f"print {seq} of {machine!r} keeps no samples (stored by an older ajtwin): it "
            "cannot be re-run"
        )
    active = active_calibration(registry, machine)
    # commissioned between the previous print and this one: it starts where that left it
    commissioned = active is not None and int(active["after_print_seq"]) == seq - 1
    since = active["created_unix"] if commissioned else 0.0
    events = [e["event"] for e in registry.maintenance(machine, seq - 1, since)]
    previous = FIRST if previous is None else previous
    begin = start_of_print(chain_of(previous, seq), active, commissioned, events, twin_overrides)
    long_run = previous.long_run_history
    if commissioned and active.get("long_run"):
        long_run = active["long_run"]
    twin = Twin.default(**begin["twin_kwargs"])
    twin.theta = begin["theta"]
    theta_before = twin.theta.copy()
    line = arrays.get("line_factors")
    run = twin.run(
        inputs=arrays["inputs"],
        measurements=arrays["measurements"],
        time_s=arrays["time_s"],
        line_factors=None if line is None else np.asarray(line, dtype=float).reshape(-1, 4),
        start=begin["start"],
    )
    # the stored metadata says whether the print began with the atomizer's run-in
    record = SimpleNamespace(
        outputs=arrays["measurements"],
        inputs=arrays["inputs"],
        has_job=False,
        data=None,
        meta=row["meta"],
    )
    detection = detect_run(run, record, detector_settings, long_run)
    mismatch = assess_run(run, record)
    found = relabel_events(detection.events, mismatch)
    status, reason = judge_run(run)
    if row["status"] == STATUS_DROPPED:  # taken out by hand: it stays out
        status, reason = row["status"], row["status_reason"]
    kept = {k: v for k, v in run_arrays(run, record).items() if k not in SAMPLE_ARRAYS}
    summary = print_summary(run.end_mean, run.end_cov, kept["nis"], kept["reinitialised"],
                            len(found), len(kept["theta_history_time_s"]),
                            begin["started_from"], status, reason)  # fmt: skip
    summary.update(
        calibration_id=begin["calibration_id"],
        maintenance=begin["maintenance"],
        mismatch=mismatch.to_dict(),
        data_share=determined_states(data_share(run.filtered)[-1:]),
        version=int(version),
    )
    learnt = (row.get("summary") or {}).get("speed_exponents")
    if learnt:  # its stored frames were filed with them: the belief stays the print's
        summary["speed_exponents"] = learnt
    result = NewPrint(
        content_hash=row["content_hash"],
        source=row["source"],
        meta=row["meta"],
        summary=summary,
        n_samples=int(row["n_samples"]),
        duration_s=float(row["duration_s"]),
        start_mean=run.start_mean,
        start_cov=run.start_cov,
        end_mean=run.end_mean,
        end_cov=run.end_cov,
        theta_before=theta_before,
        theta_after=twin.theta,
        arrays=kept,
        anomalies=found,
        status=status,
        status_reason=reason,
        long_run_history=detection.long_run_history,
    )
    registry.save_print_version(version, print_id, result)
    seconds = time.perf_counter() - t0
    if status != STATUS_OK:
        return previous.after(seq, seconds=seconds)
    return previous.after(seq, (run.end_mean, run.end_cov), twin.theta,
                          detection.long_run_history, seconds)  # fmt: skip


def _carry_of(done: dict, previous, seq: int) -> Carry:
    """The carry of a print the version held already."""
    previous = FIRST if previous is None else previous
    if done["status"] != STATUS_OK:
        return previous.after(seq)
    return previous.after(seq, (done["end_mean"], done["end_cov"]), done["theta_after"],
                          json.loads(done.get("long_run_json") or "null"))  # fmt: skip


# ---------------------------------------------------------------------- on Dask
#: each worker process keeps one registry connection per location
_OPEN: dict = {}


def _worker_registry(location) -> Registry:
    registry = _OPEN.get(location)
    if registry is None:
        registry = _OPEN[location] = Registry(location, create=False)
    return registry


def reprocess_task(location, version: int, machine: str, print_id: int, previous, settings):
    """One print's re-run on a Dask worker (:func:`reprocess_print` on the worker's own
    connection to the registry)."""
    return reprocess_print(_worker_registry(location), version, machine, print_id, previous,
                           **settings)  # fmt: skip


@dataclass
class ReprocessPlan:
    """The prints a reprocessing re-runs, per machine in seq order, with the carry each
    machine's first one starts from (None: the machine's first print)."""

    prints: dict
    first_carry: dict

    @property
    def n_prints(self) -> int:
        """How many prints in all."""
        return sum(len(v) for v in self.prints.values())


def plan(registry, machines=None, since: str | None = None) -> ReprocessPlan:
    """The prints of ``machines`` (None: every machine) ingested at or after ``since`` (ISO
    date or time; None: all). A machine whose re-run starts after its first print starts
    from the print before it as stored (version 1)."""
    names = [m["name"] for m in registry.machines()] if not machines else list(machines)
    prints, first = {}, {}
    for name in names:
        registry.machine(name)  # an unknown machine: RegistryError naming it
        rows = registry.print_rows(name)
        if since is not None:
            rows = [r for r in rows if str(r["ingested_at"]) >= str(since)]
        if not rows:
            continue
        prints[name] = [int(r["id"]) for r in rows]
        first[name] = stored_carry(registry, name, int(rows[0]["seq"]))
    return ReprocessPlan(prints, first)


def reprocess(location, *, machines=None, since=None, workers: int = 2, scheduler=None,
              reason: str = "", progress=None, settings: dict | None = None) -> dict:  # fmt: skip
    """Re-run the twin over the stored prints on Dask and store a new version (module
    docstring).

    Parameters
    ----------
    location : path, URL or StoreLocation
        The registry (every worker opens it).
    machines : list of str, optional
        Only these machines (default: all).
    since : str, optional
        Only prints ingested at or after this ISO date or time.
    workers : int
        Worker processes of the ``LocalCluster`` (one thread each) when no ``scheduler``.
    scheduler : str, optional
        A Dask scheduler's address (``tcp://host:8786``): its workers do the work.
    reason : str
        Why (kept with the version: "new calibration of aj2", "model 0.2").
    progress : callable(done, total), optional
        Called as prints finish.
    settings : dict, optional
        ``detector_settings``, ``twin_overrides`` for :func:`reprocess_print`.

    Returns
    -------
    dict: ``version``, ``prints``, ``machines``, ``seconds`` (wall, from the first task given
    to the last done), ``startup_s`` (the local cluster's start and the workers' imports
    before), ``prints_per_min``, ``task_seconds`` (the re-runs' own time, summed), ``workers``.
    """
    from dask.distributed import Client, LocalCluster, as_completed

    location = parse_store(location)
    if scheduler is not None and location.is_sqlite:
        raise RegistryError(
            f"--scheduler {scheduler}: a cluster's workers cannot share the SQLite file "
            f"{location.path}; copy the registry to PostgreSQL (`ajtwin store copy`) and give "
            "its URL"
        )
    registry = Registry(location, create=False, write=True)
    work = plan(registry, machines, since)
    version = registry.create_version(
        reason or "reprocess",
        {"machines": sorted(work.prints), "since": since, "scheduler": scheduler,
         "workers": None if scheduler else int(workers),
         "calibrations": {m: _calibration_id(registry, m) for m in work.prints}},
    )  # fmt: skip
    cluster = None
    t_start = time.perf_counter()
    try:
        if scheduler is None:
            cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1,
                                   processes=True, dashboard_address=None)  # fmt: skip
        with Client(scheduler or cluster) as client:
            n_workers = len(client.scheduler_info()["workers"])
            # each worker loads the twin before the clock starts (imports: seconds each)
            client.run(importlib.import_module, __name__)
            t0 = time.perf_counter()
            futures = []
            for machine, print_ids in work.prints.items():
                previous = work.first_carry[machine]
                for print_id in print_ids:
                    previous = client.submit(
                        reprocess_task, location, version, machine, print_id, previous,
                        dict(settings or {}), key=f"reprocess-v{version}-{print_id}",
                        pure=False,
                    )  # fmt: skip
                    futures.append(previous)
            task_seconds, done = 0.0, 0
            for future in as_completed(futures):
                task_seconds += future.result().seconds
                done += 1
                if progress is not None:
                    progress(done, len(futures))
            seconds = time.perf_counter() - t0
    except BaseException:
        registry.finish_version(version, "stopped")
        raise
    finally:
        if cluster is not None:
            cluster.close()
    registry.finish_version(version, "done")
    return {
        "version": version,
        "prints": work.n_prints,
        "machines": len(work.prints),
        "seconds": seconds,
        "startup_s": t0 - t_start,
        "prints_per_min": 60.0 * work.n_prints / seconds if seconds > 0 else float("nan"),
        "task_seconds": task_seconds,
        "workers": n_workers,
    }


def _calibration_id(registry, machine: str):
    active = active_calibration(registry, machine)
    return None if active is None else int(active["id"])
