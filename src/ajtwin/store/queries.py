"""Reads the dashboard needs beyond :class:`~ajtwin.store.registry.Registry`'s history and
prints: change markers, prints committed since a print, one array of a print, a machine's
latest alarm, what a live print shows now.

Pages and the registry watcher read through these (never through SQL of their own); each
is one of the registry's methods, or a few of them put together, so a schema change stays
inside :mod:`ajtwin.store`.
"""

from __future__ import annotations

import numpy as np


def change_marker(registry) -> tuple[int, int, int]:
    """(a number that changes on any commit, last print id, last machine id)."""
    return registry.change_marker()


def prints_after(registry, print_id: int) -> list[dict]:
    """Prints committed with an id above ``print_id``: ``print_id``, ``seq``, ``machine``,
    ``duration_s`` [s] and the number of ``anomalies``, oldest first."""
    return registry.prints_after(print_id)


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
    return registry.latest_seq(name)


def newest_print_alarms(registry, name: str) -> list[dict]:
    """The anomalies of the machine's newest print that raised any, in detection order:
    ``seq``, ``ingested_at``, ``detected_s``, ``onset_s`` [s], ``cause``, ``description``
    ([] when no print ever raised one)."""
    return registry.newest_print_alarms(name)


def count_alarms(registry, name: str, seq: int, except_cause: str = "") -> int:
    """Anomalies of print ``seq`` of machine ``name`` whose cause is not ``except_cause``."""
    return registry.count_alarms(name, seq, except_cause)


def print_summary(registry, print_id: int) -> dict:
    """The summary stored with a print (what the ingest wrote: end state, NIS, status ...)."""
    return registry.print_summary(print_id)


def open_live_states(registry, seen: dict) -> tuple[list[dict], list[str]]:
    """What live prints published since the last look, for a dashboard in another process
    than the live twins: (the new published messages of every open live session, in step
    order per session; the machines whose session closed since). ``seen`` (session id →
    last step read, with ``"_machines"``: session id → machine) is kept by the caller and
    updated here."""
    machines = seen.setdefault("_machines", {})
    messages = []
    open_now = {s["id"]: s["machine"] for s in registry.live_sessions(open_only=True)}
    for session_id, machine in open_now.items():
        if session_id not in seen:
            # a session found open: start from its latest step, not its whole past
            n, latest = registry.live_latest(session_id)
            seen[session_id] = -1 if latest is None else int(latest.get("step", n - 1)) - 1
            machines[session_id] = machine
        new = registry.live_states(session_id, after_step=seen[session_id])
        if new:
            seen[session_id] = int(new[-1].get("step", seen[session_id] + len(new)))
        messages += new
    ended = [machines.pop(s) for s in list(machines) if s not in open_now]
    for session_id in [s for s in seen if s != "_machines" and s not in open_now]:
        del seen[session_id]
    return messages, ended
