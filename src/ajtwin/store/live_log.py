"""The live twin's log: samples and published states of prints still running.

A live session (one machine, one print as it happens) writes its samples, the twin's
committed states and its alarms here as it goes, in small transactions, next to the
registry's tables (same database, own tables, created by the registry's migration 3:
:data:`ajtwin.store.schema.MIGRATIONS`), through the registry's methods on a connection
of its own. A client killed mid-print restarts,
finds the open session and replays its samples through the twin: what was committed is
kept, and nothing is written twice (``PRIMARY KEY (session_id, step)``). When the print
ends the engine stores it as an ordinary print of the registry and closes the session in
the same transaction, dropping the session's per-step rows (``live_samples``,
``live_states``): the print holds the samples exactly and the states by the storage
policy, so a live machine costs what an ingested one does (≈ 0.4 MB per print-hour,
against ≈ 9 MB for the per-step log; ``LiveEngine(keep_live_steps=True)`` keeps them
until ``machine compact``). The session row and its alarms stay.

Tables: ``live_sessions`` (machine, start state, θ, status), ``live_samples`` (step,
time, inputs, outputs), ``live_states`` (the published message of each committed step,
JSON), ``live_events`` (raised/final alarms, JSON).

One writer per machine: the log claims the machine when it opens or resumes its session
(:meth:`~ajtwin.store.registry.Registry.claim_machine`) and renews the claim with every
write, so a second twin given the same machine name — on another PC of the lab — is
refused with a sentence instead of interleaving its samples. On PostgreSQL, steps
written while the server is away are kept and written when it is back
(:mod:`ajtwin.store.outbox`).

Examples
--------
>>> import tempfile, os, numpy as np
>>> log = LiveLog(os.path.join(tempfile.mkdtemp(), "r.sqlite"))
>>> sid = log.open_session("m1", source="test", start=None, theta=np.zeros(5))
>>> log.append(sid, [(0, 0.0, np.ones(3), np.ones(5), {"step": 0})], [])
>>> log.n_steps(sid), log.open_session_of("m1")["id"] == sid
(1, True)
"""

from __future__ import annotations

import numpy as np

from ajtwin.store.registry import Registry

#: what claims a machine while a live session of it is open
CLAIMANT = "ajtwin live"


class LiveLog:
    """Live sessions in the registry (see module docstring), on a connection of its own.

    Parameters
    ----------
    path : str, Path or StoreLocation
        The registry (``Registry.path``: an SQLite file or a PostgreSQL location).
    """

    def __init__(self, path, timeout_s: float = 30.0):
        # the tables are the registry's (migration 3): opening it creates or migrates them,
        # and a database that is not an ajtwin registry is refused, never taken over
        self.registry = Registry(path, timeout_s)
        self.path = self.registry.path

    def close(self):
        """Close the log's connection (steps kept while the server was away first)."""
        self.registry.close()

    # ------------------------------------------------------------------ #
    def open_session(
        self, machine: str, *, source: str, start, theta, expected_last_seq=None
    ) -> int:
        """A new open session for ``machine`` (claimed for this process); ``start``
        (mean, cov) or None (initial fit)."""
        self.registry.claim_machine(machine, CLAIMANT)
        return self.registry.live_open_session(
            machine, source=source, start=start, theta=theta, expected_last_seq=expected_last_seq
        )

    def open_session_of(self, machine: str) -> dict | None:
        """The machine's open session (the latest), or None; the machine is claimed for
        this process first (refused while another twin writes it)."""
        self.registry.claim_machine(machine, CLAIMANT)
        return self.registry.live_session_of(machine)

    def sessions(self, machine: str) -> list[dict]:
        """All sessions of a machine (id, started_at, source, status, print_id), oldest first."""
        return [
            {k: v for k, v in s.items() if k != "machine"}
            for s in self.registry.live_sessions(machine)
        ]

    def append(self, session_id: int, steps: list, events: list) -> None:
        """Commit steps [(step, time_s, inputs, outputs, message)] and events in ONE transaction.

        Steps already stored are ignored (a replay after a restart writes nothing twice).
        """
        self.registry.live_append(session_id, steps, events)

    def n_steps(self, session_id: int) -> int:
        """Samples stored of a session."""
        return self.registry.live_n_steps(session_id)

    def samples(self, session_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(time_s (T,), inputs (T, 3), outputs (T, 5)) of a session, in step order."""
        rows = self.registry.live_samples(session_id)
        if [r[0] for r in rows] != list(range(len(rows))):
            raise RuntimeError(f"live session {session_id}: stored steps are not contiguous")
        return _columns(rows)

    def iter_samples(self, session_id: int, batch: int = 3600):
        """(time_s, inputs, outputs) of a session ``batch`` steps at a time, in step order:
        a replay that holds one batch, not the whole print (:meth:`samples`)."""
        first = 0
        while True:
            rows = self.registry.live_samples(session_id, first, int(batch))
            if not rows:
                return
            if [r[0] for r in rows] != list(range(first, first + len(rows))):
                raise RuntimeError(f"live session {session_id}: stored steps are not contiguous")
            yield _columns(rows)
            first += len(rows)

    def states(self, session_id: int) -> list[dict]:
        """The published messages of a session's committed steps, in step order."""
        return self.registry.live_states(session_id)

    def events(self, session_id: int) -> list[dict]:
        """A session's alarm events (raised and final), in detection order."""
        return self.registry.live_events(session_id)

    def close_session(self, session_id: int, print_id: int | None) -> None:
        """Mark a session closed, with the print it became (None: nothing stored)."""
        self.registry.live_close_session(session_id, print_id)


def _columns(rows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        np.array([r[1] for r in rows], dtype=float),
        np.array([r[2] for r in rows], dtype=float).reshape(-1, 3),
        np.array([r[3] for r in rows], dtype=float).reshape(-1, 5),
    )


def live_session_now(registry, machine: str) -> dict | None:
    """The machine's open live session as a command shows it, read through ``registry``
    (no writes): ``id``, ``started_at`` (unix s), ``source``, ``n_samples``, ``latest``
    (the last committed step's published message: ``time_s``, ``states``, ``stds``, ...,
    or None before the first) and ``alarms`` (each event once, its final form when it has
    one, in detection order). None when no live print is running.
    """
    session = registry.live_session_of(machine)
    if session is None:
        return None
    n, latest = registry.live_latest(session["id"])
    events = {}
    for event in registry.live_events(session["id"]):
        key = float(event["detected_s"])
        if key not in events or event.get("state") == "final":
            events[key] = event
    return {
        "id": int(session["id"]),
        "started_at": float(session["started_at"]),
        "source": session["source"],
        "n_samples": int(n),
        "latest": latest,
        "alarms": [events[k] for k in sorted(events)],
    }
