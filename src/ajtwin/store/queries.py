"""Reads the dashboard needs beyond :class:`~ajtwin.store.registry.Registry`'s own: change
markers, prints committed since a print, one array of a print, a machine's latest alarm.

Each function takes an open registry and runs one or a few queries on its connection;
pages and the registry watcher read through them (never through SQL of their own), so a
schema change stays inside :mod:`ajtwin.store`.
"""

from __future__ import annotations

import json

import numpy as np


def change_marker(registry) -> tuple[int, int, int]:
    """(``PRAGMA data_version``, last print id, last machine id): changes on any commit."""
    conn = registry._conn
    version = conn.execute("PRAGMA data_version").fetchone()[0]
    last_print = conn.execute("SELECT COALESCE(MAX(id), 0) FROM prints").fetchone()[0]
    last_machine = conn.execute("SELECT COALESCE(MAX(id), 0) FROM machines").fetchone()[0]
    return int(version), int(last_print), int(last_machine)


def prints_after(registry, print_id: int) -> list[dict]:
    """Prints committed with an id above ``print_id``: ``print_id``, ``seq``, ``machine``,
    ``duration_s`` [s] and the number of ``anomalies``, oldest first."""
    rows = registry._conn.execute(
        "SELECT p.id, p.seq, m.name, p.duration_s, "
        "(SELECT COUNT(*) FROM anomalies a WHERE a.print_id = p.id) AS n_anomalies "
        "FROM prints p JOIN machines m ON p.machine_id = m.id WHERE p.id > ? "
        "ORDER BY p.id",
        (int(print_id),),
    ).fetchall()
    return [
        {
            "print_id": int(r["id"]),
            "seq": int(r["seq"]),
            "machine": r["name"],
            "duration_s": float(r["duration_s"]),
            "anomalies": int(r["n_anomalies"]),
        }
        for r in rows
    ]


def print_array(registry, print_id: int, name: str) -> np.ndarray | None:
    """One stored array of a print, decoded without loading the others (None: not stored;
    :meth:`ajtwin.store.registry.Registry.print_array`)."""
    return registry.print_array(print_id, name)


def reported_end_std(registry, stored_print: dict) -> np.ndarray:
    """σ (5,) of a stored print's end state as the twin reported it: the last row of its
    ``stds`` array (the filter's σ with what the calibration's and φ_A's level uncertainty
    add), else from its end covariance (the filter's alone, which the next print starts
    from)."""
    stds = print_array(registry, stored_print["id"], "stds")
    if stds is not None and len(stds) and np.all(np.isfinite(stds[-1])):
        return np.asarray(stds[-1], dtype=float)
    return np.sqrt(np.maximum(np.diag(np.asarray(stored_print["end_cov"], float)), 0.0))


def latest_seq(registry, name: str) -> int | None:
    """The seq of the machine's newest print, in the chain or not (None: no print)."""
    machine = registry.machine(name)
    row = registry._conn.execute(
        "SELECT MAX(seq) FROM prints WHERE machine_id = ?", (machine["id"],)
    ).fetchone()
    return row[0]


def newest_print_alarms(registry, name: str) -> list[dict]:
    """The anomalies of the machine's newest print that raised any, in detection order:
    ``seq``, ``ingested_at``, ``detected_s``, ``onset_s`` [s], ``cause``, ``description``
    ([] when no print ever raised one)."""
    machine = registry.machine(name)
    rows = registry._conn.execute(
        "SELECT p.seq, p.ingested_at, a.detected_s, a.onset_s, a.cause, a.description "
        "FROM anomalies a JOIN prints p ON a.print_id = p.id WHERE p.machine_id = ? AND "
        "p.seq = (SELECT MAX(p2.seq) FROM anomalies a2 JOIN prints p2 ON a2.print_id = p2.id "
        "WHERE p2.machine_id = ?) ORDER BY a.detected_s",
        (machine["id"], machine["id"]),
    ).fetchall()
    return [dict(r) for r in rows]


def count_alarms(registry, name: str, seq: int, except_cause: str = "") -> int:
    """Anomalies of print ``seq`` of machine ``name`` whose cause is not ``except_cause``."""
    machine = registry.machine(name)
    return int(
        registry._conn.execute(
            "SELECT COUNT(*) FROM anomalies a JOIN prints p ON a.print_id = p.id "
            "WHERE p.machine_id = ? AND p.seq = ? AND a.cause != ?",
            (machine["id"], seq, except_cause),
        ).fetchone()[0]
    )


def print_summary(registry, print_id: int) -> dict:
    """The summary stored with a print (what the ingest wrote: end state, NIS, status ...)."""
    row = registry._conn.execute(
        "SELECT summary_json FROM prints WHERE id = ?", (print_id,)
    ).fetchone()
    return {} if row is None else json.loads(row[0])
