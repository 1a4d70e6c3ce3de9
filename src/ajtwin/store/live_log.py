"""The live twin's log: samples and published states of prints still running.

A live session (one machine, one print as it happens) writes its samples, the twin's
committed states and its alarms here as it goes, in small transactions, next to the
registry's tables (same SQLite file, own tables, created by the registry's migration 3:
:data:`ajtwin.store.registry.MIGRATIONS`). A client killed mid-print restarts,
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

import json
import time
from pathlib import Path

import numpy as np

from ajtwin.store.connection import connect, rollback_if_open
from ajtwin.store.registry import Registry, from_npy, to_npy


class LiveLog:
    """Live sessions in the registry's SQLite file (see module docstring).

    Parameters
    ----------
    path : str or Path
        The registry database (``Registry.path``).
    """

    def __init__(self, path, timeout_s: float = 30.0):
        self.path = Path(path)
        # the tables are the registry's (migration 3): opening it creates or migrates them,
        # and a file that is not an ajtwin registry is refused, never taken over
        Registry(self.path, timeout_s).close()
        self._conn = connect(self.path, timeout_s)
        self._conn.execute("PRAGMA synchronous=NORMAL")

    def close(self):
        """Close the log's connection."""
        self._conn.close()

    # ------------------------------------------------------------------ #
    def open_session(
        self, machine: str, *, source: str, start, theta, expected_last_seq=None
    ) -> int:
        """A new open session for ``machine``; ``start`` (mean, cov) or None (initial fit)."""
        cur = self._conn.execute(
            "INSERT INTO live_sessions (machine, started_at, source, status, start_mean, "
            "start_cov, theta_before, expected_last_seq) VALUES (?, ?, ?, 'open', ?, ?, ?, ?)",
            (
                machine,
                time.time(),
                source,
                None if start is None else to_npy(start[0]),
                None if start is None else to_npy(start[1]),
                to_npy(np.asarray(theta, dtype=float)),
                expected_last_seq,
            ),
        )
        return int(cur.lastrowid)

    def open_session_of(self, machine: str) -> dict | None:
        """The machine's open session (the latest), or None."""
        row = self._conn.execute(
            "SELECT * FROM live_sessions WHERE machine = ? AND status = 'open' "
            "ORDER BY id DESC LIMIT 1",
            (machine,),
        ).fetchone()
        if row is None:
            return None
        out = dict(row)
        start = None
        if row["start_mean"] is not None:
            start = (from_npy(row["start_mean"]), from_npy(row["start_cov"]))
        out["start"] = start
        out["theta_before"] = from_npy(row["theta_before"])
        return out

    def sessions(self, machine: str) -> list[dict]:
        """All sessions of a machine (id, started_at, source, status, print_id), oldest first."""
        rows = self._conn.execute(
            "SELECT id, started_at, source, status, print_id FROM live_sessions "
            "WHERE machine = ? ORDER BY id",
            (machine,),
        ).fetchall()
        return [dict(r) for r in rows]

    def append(self, session_id: int, steps: list, events: list) -> None:
        """Commit steps [(step, time_s, inputs, outputs, message)] and events in ONE transaction.

        Steps already stored are ignored (a replay after a restart writes nothing twice).
        """
        if not steps and not events:
            return
        conn = self._conn
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.executemany(
                "INSERT OR IGNORE INTO live_samples VALUES (?, ?, ?, ?, ?)",
                [
                    (session_id, int(k), float(t), to_npy(np.asarray(u)), to_npy(np.asarray(y)))
                    for k, t, u, y, _ in steps
                ],
            )
            conn.executemany(
                "INSERT OR IGNORE INTO live_states VALUES (?, ?, ?)",
                [(session_id, int(k), json.dumps(m, default=float)) for k, _, _, _, m in steps],
            )
            conn.executemany(
                "INSERT OR REPLACE INTO live_events VALUES (?, ?, ?, ?)",
                [
                    (session_id, float(e["detected_s"]), e["state"], json.dumps(e, default=str))
                    for e in events
                ],
            )
            conn.execute("COMMIT")
        except BaseException:
            rollback_if_open(conn)
            raise

    def n_steps(self, session_id: int) -> int:
        """Samples stored of a session."""
        row = self._conn.execute(
            "SELECT COUNT(*) FROM live_samples WHERE session_id = ?", (session_id,)
        ).fetchone()
        return int(row[0])

    def samples(self, session_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(time_s (T,), inputs (T, 3), outputs (T, 5)) of a session, in step order."""
        rows = self._conn.execute(
            "SELECT step, time_s, inputs, outputs FROM live_samples WHERE session_id = ? "
            "ORDER BY step",
            (session_id,),
        ).fetchall()
        steps = [r["step"] for r in rows]
        if steps != list(range(len(steps))):
            raise RuntimeError(f"live session {session_id}: stored steps are not contiguous")
        t = np.array([r["time_s"] for r in rows], dtype=float)
        u = np.array([from_npy(r["inputs"]) for r in rows], dtype=float).reshape(-1, 3)
        y = np.array([from_npy(r["outputs"]) for r in rows], dtype=float).reshape(-1, 5)
        return t, u, y

    def iter_samples(self, session_id: int, batch: int = 3600):
        """(time_s, inputs, outputs) of a session ``batch`` steps at a time, in step order:
        a replay that holds one batch, not the whole print (:meth:`samples`)."""
        first = 0
        while True:
            rows = self._conn.execute(
                "SELECT step, time_s, inputs, outputs FROM live_samples WHERE session_id = ? "
                "AND step >= ? ORDER BY step LIMIT ?",
                (session_id, first, int(batch)),
            ).fetchall()
            if not rows:
                return
            steps = [r["step"] for r in rows]
            if steps != list(range(first, first + len(steps))):
                raise RuntimeError(f"live session {session_id}: stored steps are not contiguous")
            yield (
                np.array([r["time_s"] for r in rows], dtype=float),
                np.array([from_npy(r["inputs"]) for r in rows], dtype=float).reshape(-1, 3),
                np.array([from_npy(r["outputs"]) for r in rows], dtype=float).reshape(-1, 5),
            )
            first += len(rows)

    def states(self, session_id: int) -> list[dict]:
        """The published messages of a session's committed steps, in step order."""
        rows = self._conn.execute(
            "SELECT message_json FROM live_states WHERE session_id = ? ORDER BY step",
            (session_id,),
        ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def events(self, session_id: int) -> list[dict]:
        """A session's alarm events (raised and final), in detection order."""
        rows = self._conn.execute(
            "SELECT event_json FROM live_events WHERE session_id = ? ORDER BY detected_s, state",
            (session_id,),
        ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def close_session(self, session_id: int, print_id: int | None) -> None:
        """Mark a session closed, with the print it became (None: nothing stored)."""
        self._conn.execute(
            "UPDATE live_sessions SET status = 'closed', print_id = ?, closed_at = ? WHERE id = ?",
            (print_id, time.time(), session_id),
        )


def live_session_now(registry, machine: str) -> dict | None:
    """The machine's open live session as a command shows it, read through ``registry``
    (no writes): ``id``, ``started_at`` (unix s), ``source``, ``n_samples``, ``latest``
    (the last committed step's published message: ``time_s``, ``states``, ``stds``, ...,
    or None before the first) and ``alarms`` (each event once, its final form when it has
    one, in detection order). None when no live print is running.
    """
    conn = registry._conn
    row = conn.execute(
        "SELECT id, started_at, source FROM live_sessions WHERE machine = ? AND status = 'open' "
        "ORDER BY id DESC LIMIT 1",
        (machine,),
    ).fetchone()
    if row is None:
        return None
    session = int(row["id"])
    n = conn.execute(
        "SELECT COUNT(*) FROM live_samples WHERE session_id = ?", (session,)
    ).fetchone()[0]
    latest = conn.execute(
        "SELECT message_json FROM live_states WHERE session_id = ? ORDER BY step DESC LIMIT 1",
        (session,),
    ).fetchone()
    events = {}
    for (text,) in conn.execute(
        "SELECT event_json FROM live_events WHERE session_id = ? ORDER BY detected_s, state",
        (session,),
    ):
        event = json.loads(text)
        key = float(event["detected_s"])
        if key not in events or event.get("state") == "final":
            events[key] = event
    return {
        "id": session,
        "started_at": float(row["started_at"]),
        "source": row["source"],
        "n_samples": int(n),
        "latest": None if latest is None else json.loads(latest[0]),
        "alarms": [events[k] for k in sorted(events)],
    }
