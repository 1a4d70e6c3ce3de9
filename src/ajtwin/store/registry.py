"""The machine registry: one twin per physical printer, kept in SQLite.

Each machine has a history of ingested prints. A print row keeps the print's metadata,
its content hash (idempotency), the twin's start and end state (mean, covariance), θ
before and after, and a summary; the per-second estimates (states, σ, covariances,
predicted outputs, NIS, θ history) are stored as ``.npy`` blobs; anomalies as rows.
The next print of a machine starts from the last print's end state and θ.

Guarantees
----------
* **Crash-safe**: one transaction per ingest (``BEGIN IMMEDIATE`` … ``COMMIT``); a process
  killed inside it leaves the store as it was (SQLite rolls back on the next open).
* **Idempotent**: ``UNIQUE(machine, content_hash)``; ingesting the same print again is
  detected before the twin runs.
* **Readable while written**: WAL journal mode; readers see the last committed state and
  never wait for a writer.

Location: ``--store PATH`` / ``AJTWIN_STORE`` / ``$XDG_DATA_HOME/ajtwin/registry.sqlite``
(default ``~/.local/share/ajtwin/registry.sqlite``).

Examples
--------
>>> import tempfile, os
>>> reg = Registry(os.path.join(tempfile.mkdtemp(), "r.sqlite"))
>>> reg.add_machine("aj300-lab1")["name"]
'aj300-lab1'
>>> reg.last_print("aj300-lab1") is None
True
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import io
import json
import os
import sqlite3
import time
from pathlib import Path

import numpy as np
import pandas as pd

SCHEMA_VERSION = 1
#: environment variable: seconds to sleep inside the ingest transaction (crash tests only)
TEST_SLEEP_ENV = "AJTWIN_STORE_TEST_SLEEP_IN_TRANSACTION"

#: Default operating limits of a machine: the validity range of H's Box–Behnken fit
#: (Q_c 15–35 sccm, I_A 300–440 mA; SPEC §4) and an assumed sheath range around the
#: paper's 48–53 sccm.
DEFAULT_LIMITS = {
    "atomizer_current_mA": [300.0, 440.0],
    "carrier_flow_sccm": [15.0, 35.0],
    "sheath_flow_sccm": [30.0, 80.0],
}

_SCHEMA = """
CREATE TABLE IF NOT EXISTS info (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS machines (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL UNIQUE,
    created_at TEXT NOT NULL,
    limits_json TEXT NOT NULL,
    notes TEXT NOT NULL DEFAULT ''
);
CREATE TABLE IF NOT EXISTS prints (
    id INTEGER PRIMARY KEY,
    machine_id INTEGER NOT NULL REFERENCES machines(id),
    seq INTEGER NOT NULL,
    content_hash TEXT NOT NULL,
    ingested_at TEXT NOT NULL,
    source TEXT NOT NULL,
    n_samples INTEGER NOT NULL,
    duration_s REAL NOT NULL,
    meta_json TEXT NOT NULL,
    summary_json TEXT NOT NULL,
    start_mean BLOB NOT NULL,
    start_cov BLOB NOT NULL,
    end_mean BLOB NOT NULL,
    end_cov BLOB NOT NULL,
    theta_before BLOB NOT NULL,
    theta_after BLOB NOT NULL,
    UNIQUE (machine_id, seq),
    UNIQUE (machine_id, content_hash)
);
CREATE TABLE IF NOT EXISTS print_arrays (
    print_id INTEGER NOT NULL REFERENCES prints(id),
    name TEXT NOT NULL,
    npy BLOB NOT NULL,
    PRIMARY KEY (print_id, name)
);
CREATE TABLE IF NOT EXISTS anomalies (
    id INTEGER PRIMARY KEY,
    print_id INTEGER NOT NULL REFERENCES prints(id),
    detected_s REAL NOT NULL,
    onset_s REAL NOT NULL,
    cause TEXT NOT NULL,
    description TEXT NOT NULL,
    detectors TEXT NOT NULL,
    evidence_json TEXT NOT NULL
);
"""


class RegistryError(RuntimeError):
    """A registry operation that cannot be done (unknown machine, duplicate, ...)."""


def default_store_path() -> Path:
    """``$AJTWIN_STORE``, else ``$XDG_DATA_HOME/ajtwin/registry.sqlite``, else
    ``~/.local/share/ajtwin/registry.sqlite``."""
    env = os.environ.get("AJTWIN_STORE")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base).expanduser() / "ajtwin" / "registry.sqlite"


def to_npy(array) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


def from_npy(blob: bytes) -> np.ndarray:
    return np.load(io.BytesIO(blob), allow_pickle=False)


def record_hash(record) -> str:
    """SHA-256 of a print's table (column names and float64 values) and metadata.

    The same print read from Parquet or CSV gives the same hash; any changed value,
    column or metadata key gives another.
    """
    h = hashlib.sha256()
    data = record.data
    for column in sorted(data.columns):
        h.update(column.encode())
        values = pd.to_numeric(data[column], errors="coerce").to_numpy(dtype=np.float64)
        h.update(np.ascontiguousarray(values).tobytes())
    # where the file was read from is not part of the print
    meta = {k: v for k, v in record.meta.items() if k not in ("assumed_defaults", "source_file")}
    meta = json.loads(json.dumps(meta, default=str))  # numpy scalars and tuples as in a file
    h.update(json.dumps(meta, sort_keys=True).encode())
    return h.hexdigest()


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


class Registry:
    """A SQLite machine registry (see module docstring).

    Parameters
    ----------
    path : str or Path, optional
        Database file (created with its folder); default :func:`default_store_path`.
    timeout_s : float
        How long a writer waits for another writer's transaction.
    """

    def __init__(self, path=None, timeout_s: float = 30.0):
        self.path = Path(path) if path is not None else default_store_path()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._conn = sqlite3.connect(
            str(self.path), timeout=timeout_s, isolation_level=None, check_same_thread=False
        )
        self._conn.row_factory = sqlite3.Row
        try:
            self._conn.execute("PRAGMA journal_mode=WAL")
            self._conn.execute("PRAGMA foreign_keys=ON")
            self._conn.execute("PRAGMA synchronous=NORMAL")
            if not self._has_schema():
                self._conn.execute("BEGIN IMMEDIATE")
                try:
                    # executescript would commit; run the statements inside this transaction
                    for statement in _SCHEMA.split(";"):
                        if statement.strip():
                            self._conn.execute(statement)
                except Exception:
                    self._conn.execute("ROLLBACK")
                    raise
                self._conn.execute(
                    "INSERT OR IGNORE INTO info VALUES ('schema_version', ?)",
                    (str(SCHEMA_VERSION),),
                )
                self._conn.execute("COMMIT")
        except sqlite3.DatabaseError as exc:
            raise RegistryError(f"{self.path}: not a usable ajtwin registry ({exc})") from None
        version = self._conn.execute(
            "SELECT value FROM info WHERE key = 'schema_version'"
        ).fetchone()
        if version is None or int(version[0]) != SCHEMA_VERSION:
            raise RegistryError(f"{self.path}: unknown registry schema version {version}")

    def _has_schema(self) -> bool:
        row = self._conn.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table' AND name = 'prints'"
        ).fetchone()
        return row is not None

    def close(self):
        self._conn.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ machines
    def add_machine(self, name: str, limits: dict | None = None, notes: str = "") -> dict:
        """Register a machine; ``limits`` maps input names to [low, high] (display units)."""
        name = name.strip()
        if not name:
            raise RegistryError("a machine needs a non-empty name")
        merged = {k: list(v) for k, v in DEFAULT_LIMITS.items()}
        for key, value in (limits or {}).items():
            if key not in DEFAULT_LIMITS:
                raise RegistryError(f"unknown input {key!r} in limits (use {list(DEFAULT_LIMITS)})")
            low, high = (float(v) for v in value)
            if not low < high:
                raise RegistryError(f"limits of {key}: low {low} must be below high {high}")
            merged[key] = [low, high]
        try:
            self._conn.execute(
                "INSERT INTO machines (name, created_at, limits_json, notes) VALUES (?, ?, ?, ?)",
                (name, _now(), json.dumps(merged), notes),
            )
        except sqlite3.IntegrityError:
            raise RegistryError(f"machine {name!r} already exists in {self.path}") from None
        return self.machine(name)

    def machine(self, name: str) -> dict:
        row = self._conn.execute("SELECT * FROM machines WHERE name = ?", (name,)).fetchone()
        if row is None:
            known = ", ".join(m["name"] for m in self.machines()) or "none"
            raise RegistryError(
                f"no machine {name!r} in {self.path} (known: {known}); "
                f"add it with `ajtwin machine add {name}`"
            )
        out = dict(row)
        out["limits"] = json.loads(out.pop("limits_json"))
        count = self._conn.execute(
            "SELECT COUNT(*) FROM prints WHERE machine_id = ?", (out["id"],)
        ).fetchone()[0]
        out["n_prints"] = int(count)
        return out

    def machines(self) -> list[dict]:
        rows = self._conn.execute("SELECT name, created_at FROM machines ORDER BY name").fetchall()
        return [dict(r) for r in rows]

    # ------------------------------------------------------------------ prints
    def _print_row(self, row) -> dict:
        out = dict(row)
        for key in (
            "start_mean",
            "start_cov",
            "end_mean",
            "end_cov",
            "theta_before",
            "theta_after",
        ):
            out[key] = from_npy(out[key])
        out["meta"] = json.loads(out.pop("meta_json"))
        out["summary"] = json.loads(out.pop("summary_json"))
        return out

    def last_print(self, name: str) -> dict | None:
        """The machine's latest print (end state, θ, ...), or None."""
        machine = self.machine(name)
        row = self._conn.execute(
            "SELECT * FROM prints WHERE machine_id = ? ORDER BY seq DESC LIMIT 1", (machine["id"],)
        ).fetchone()
        return None if row is None else self._print_row(row)

    def find_print(self, name: str, content_hash: str) -> dict | None:
        machine = self.machine(name)
        row = self._conn.execute(
            "SELECT * FROM prints WHERE machine_id = ? AND content_hash = ?",
            (machine["id"], content_hash),
        ).fetchone()
        return None if row is None else self._print_row(row)

    def get_print(self, print_id: int) -> dict:
        row = self._conn.execute("SELECT * FROM prints WHERE id = ?", (print_id,)).fetchone()
        if row is None:
            raise RegistryError(f"no print with id {print_id}")
        return self._print_row(row)

    def print_arrays(self, print_id: int) -> dict[str, np.ndarray]:
        rows = self._conn.execute(
            "SELECT name, npy FROM print_arrays WHERE print_id = ?", (print_id,)
        ).fetchall()
        return {r["name"]: from_npy(r["npy"]) for r in rows}

    def history(self, name: str) -> pd.DataFrame:
        """One row per print: seq, id, time, duration, source, end states, θ, anomaly count."""
        from ajtwin.model import STATE_NAMES

        machine = self.machine(name)
        rows = self._conn.execute(
            "SELECT p.*, (SELECT COUNT(*) FROM anomalies a WHERE a.print_id = p.id) AS n_anomalies"
            " FROM prints p WHERE machine_id = ? ORDER BY seq",
            (machine["id"],),
        ).fetchall()
        records = []
        for row in rows:
            p = self._print_row(row)
            rec = {
                "seq": p["seq"],
                "print_id": p["id"],
                "ingested_at": p["ingested_at"],
                "source": p["source"],
                "duration_min": p["duration_s"] / 60.0,
                "scenario": p["meta"].get("scenario"),
                "anomalies": int(row["n_anomalies"]),
            }
            for i, state in enumerate(STATE_NAMES):
                rec["end_" + state] = float(p["end_mean"][i])
            for i, state in enumerate(STATE_NAMES):
                rec["theta_" + state] = float(p["theta_after"][i])
            records.append(rec)
        return pd.DataFrame(records)

    def anomalies(self, name: str) -> pd.DataFrame:
        machine = self.machine(name)
        rows = self._conn.execute(
            "SELECT p.seq, a.detected_s, a.onset_s, a.cause, a.description, a.detectors "
            "FROM anomalies a JOIN prints p ON a.print_id = p.id WHERE p.machine_id = ? "
            "ORDER BY p.seq, a.detected_s",
            (machine["id"],),
        ).fetchall()
        return pd.DataFrame(
            [dict(r) for r in rows],
            columns=["seq", "detected_s", "onset_s", "cause", "description", "detectors"],
        )

    def save_print(
        self,
        name: str,
        *,
        content_hash: str,
        source: str,
        meta: dict,
        summary: dict,
        n_samples: int,
        duration_s: float,
        start_mean,
        start_cov,
        end_mean,
        end_cov,
        theta_before,
        theta_after,
        arrays: dict,
        anomalies: list,
        expected_last_seq: int | None,
    ) -> int:
        """Write one print, its arrays and anomalies in ONE transaction; returns its id.

        ``expected_last_seq`` is the seq of the print the twin started from (None: none);
        if another ingest of the same machine committed in between, nothing is written
        and :class:`RegistryError` says so (the run started from a stale state).
        """
        machine = self.machine(name)
        conn = self._conn
        conn.execute("BEGIN IMMEDIATE")
        try:
            row = conn.execute(
                "SELECT MAX(seq) FROM prints WHERE machine_id = ?", (machine["id"],)
            ).fetchone()
            last = row[0]
            if last != expected_last_seq:
                raise RegistryError(
                    f"machine {name!r} got print {last} while this ingest ran from print "
                    f"{expected_last_seq}; ingest again"
                )
            dup = conn.execute(
                "SELECT seq FROM prints WHERE machine_id = ? AND content_hash = ?",
                (machine["id"], content_hash),
            ).fetchone()
            if dup is not None:
                raise RegistryError(f"this print is already print {dup[0]} of {name!r}")
            seq = 1 if last is None else last + 1
            cur = conn.execute(
                "INSERT INTO prints (machine_id, seq, content_hash, ingested_at, source, "
                "n_samples, duration_s, meta_json, summary_json, start_mean, start_cov, "
                "end_mean, end_cov, theta_before, theta_after) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    machine["id"],
                    seq,
                    content_hash,
                    _now(),
                    source,
                    int(n_samples),
                    float(duration_s),
                    json.dumps(meta, default=str),
                    json.dumps(summary, default=str),
                    to_npy(start_mean),
                    to_npy(start_cov),
                    to_npy(end_mean),
                    to_npy(end_cov),
                    to_npy(theta_before),
                    to_npy(theta_after),
                ),
            )
            print_id = cur.lastrowid
            conn.executemany(
                "INSERT INTO print_arrays (print_id, name, npy) VALUES (?, ?, ?)",
                [(print_id, key, to_npy(value)) for key, value in arrays.items()],
            )
            conn.executemany(
                "INSERT INTO anomalies (print_id, detected_s, onset_s, cause, description, "
                "detectors, evidence_json) VALUES (?, ?, ?, ?, ?, ?, ?)",
                [
                    (
                        print_id,
                        ev.detected_s,
                        ev.onset_s,
                        ev.cause,
                        ev.description,
                        ", ".join(ev.detectors),
                        json.dumps(ev.evidence),
                    )
                    for ev in anomalies
                ],
            )
            delay = float(os.environ.get(TEST_SLEEP_ENV, "0") or 0)
            if delay > 0:  # crash-safety tests kill the process here
                time.sleep(delay)
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        return int(print_id)
