"""The machine registry: one twin per physical printer, in SQLite or PostgreSQL.

Each machine has a history of ingested prints. A print row keeps the print's metadata,
its content hash (idempotency), the twin's start and end state (mean, covariance), θ
before and after, a summary and a chain status; the per-second estimates (states, σ,
predicted outputs, NIS, θ history, covariance key frames) are stored as compressed
array blobs (:mod:`ajtwin.store.arrays`); anomalies as rows. The next print of a machine
starts from the end state and θ of the last print *in the chain* (``status = 'ok'``): a
print whose states left the physical range is kept for history but marked
``excluded`` and never becomes a start (:mod:`ajtwin.engine.chain`).

:class:`Registry` is the store's one interface: it owns the schema and its migrations
(:mod:`ajtwin.store.schema`) and every statement; the store's other modules
(calibrations, the live log, compaction, archives, copies) and everything above read and
write through its methods, never through a connection. Where the registry is — an
SQLite file (the embedded default) or a PostgreSQL database (a lab's server) — is said
by ``--store`` (:mod:`ajtwin.store.location`); the two behave the same
(:mod:`ajtwin.store.database` holds what differs).

Guarantees
----------
* **Crash-safe**: one transaction per ingest; a process killed inside it leaves the
  store as it was (SQLite rolls back on the next open, PostgreSQL at once).
* **Idempotent**: ``UNIQUE(machine, content_hash)``; ingesting the same print again is
  detected before the twin runs.
* **Readable while written**: readers see the last committed state and never wait for a
  writer (SQLite's WAL journal; PostgreSQL's snapshots).
* **Many writers**: writes of one machine's prints are serialised (SQLite: the file's
  one writer; PostgreSQL: a lock per machine), a print started from a stale state is
  refused; a machine's live print has one writer at a time (:meth:`claim_machine`).
* **Never takes over another database**: a file or schema that is not an ajtwin
  registry (an unrelated SQLite database, a FIFO, a directory, a schema with other
  tables) is refused with a message and left untouched. Read-only commands never create
  a registry (``create=False``).
* **Versioned**: ``info.schema_version``; an older registry is migrated in one
  transaction on open (with a message in :attr:`Registry.migrated`), a newer one refused.

Location: ``--store PATH|URL`` / ``AJTWIN_STORE`` / ``$XDG_DATA_HOME/ajtwin/registry.sqlite``
(default ``~/.local/share/ajtwin/registry.sqlite``).

Example
-------
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
import logging
import os
import socket
import sqlite3
import time
import unicodedata
import zlib
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ajtwin.model.limits import DEFAULT_LIMITS
from ajtwin.model.names import STATE_NAMES
from ajtwin.store import arrays as _arrays
from ajtwin.store.connection import RegistryError
from ajtwin.store.database import ConnectionLost, ConstraintError, open_database
from ajtwin.store.location import parse_store
from ajtwin.store.outbox import Outbox
from ajtwin.store.schema import (
    APPLICATION,
    LIVE_SESSION_TABLES,
    MACHINE_TABLES,
    MIGRATIONS,
    PRINT_TABLES,
    SCHEMA_V1,
    SCHEMA_VERSION,
    STATUS_DROPPED,
    STATUS_EXCLUDED,
    STATUS_OK,
    V1_TABLES,
    VERSION_TABLES,
    exclude_impossible_ends,
    get_info,
    set_info,
)

__all__ = [
    "APPLICATION",
    "LIVE_SESSION_TABLES",
    "MACHINE_TABLES",
    "MIGRATIONS",
    "NewPrint",
    "PRINT_TABLES",
    "Registry",
    "RegistryError",
    "SCHEMA_VERSION",
    "STATUS_DROPPED",
    "STATUS_EXCLUDED",
    "STATUS_OK",
    "check_new_name",
    "clean_name",
    "default_store_path",
    "from_npy",
    "printable",
    "record_hash",
    "to_npy",
]

log = logging.getLogger("ajtwin.store")

#: environment variable: seconds to sleep inside the ingest transaction (crash tests only)
TEST_SLEEP_ENV = "AJTWIN_STORE_TEST_SLEEP_IN_TRANSACTION"
#: a live writer's claim on a machine lapses this long after it was last heard from [s]
#: (longer than a network outage a twin rides out, :mod:`ajtwin.store.outbox`)
CLAIM_STALE_S = 300.0
#: how long a print's final write waits for an absent database server [s]
SAVE_WAIT_S = 600.0


def default_store_path():
    """Where a command's registry is without ``--store``: ``$AJTWIN_STORE`` (a path, or
    the :class:`~ajtwin.store.location.StoreLocation` of a URL), else
    ``$XDG_DATA_HOME/ajtwin/registry.sqlite``, else ``~/.local/share/ajtwin/registry.sqlite``."""
    location = parse_store(None)
    return location.path if location.is_sqlite else location


@dataclass(frozen=True)
class NewPrint:
    """What the registry keeps of one print: its identity, the twin's run over it and what
    the run concluded (:meth:`Registry.save_print`).

    Attributes
    ----------
    content_hash : str
        :func:`record_hash` of the print (a print is stored once per machine).
    source : str
        Where it came from (a file, "live session 12 (opc.tcp://…)").
    meta : dict
        The record's metadata (JSON-ready).
    summary : dict
        The summary the history and pages show (end state, NIS, status …).
    n_samples : int
    duration_s : float
    start_mean, end_mean : array (5,)
    start_cov, end_cov : array (5, 5)
    theta_before, theta_after : array (5,)
    arrays : dict
        Per-second arrays (stored by the registry's :class:`~ajtwin.store.arrays.
        StoragePolicy`); with a draft, only those not written in parts (the θ history).
    anomalies : list of AnomalyEvent
    status, status_reason : str
        In the chain (``ok``) or not (``excluded``, ``dropped``) and why.
    long_run_history : dict, optional
        The detectors' long-run statistics at the print's end, for the next print.
    job : dict, optional
        The machine program the print ran: ``program`` (file name), ``program_bytes``,
        ``settings`` (JSON-ready).
    """

    content_hash: str
    source: str
    meta: dict
    summary: dict
    n_samples: int
    duration_s: float
    start_mean: object
    start_cov: object
    end_mean: object
    end_cov: object
    theta_before: object
    theta_after: object
    arrays: dict = field(default_factory=dict)
    anomalies: list = field(default_factory=list)
    status: str = STATUS_OK
    status_reason: str = ""
    long_run_history: dict | None = None
    job: dict | None = None


#: a print's six state columns, and their shapes
_STATE_COLUMNS = {
    "start_mean": (5,),
    "start_cov": (5, 5),
    "end_mean": (5,),
    "end_cov": (5, 5),
    "theta_before": (5,),
    "theta_after": (5,),
}


def _state_blobs(entry) -> dict:
    return {key: to_npy(np.asarray(getattr(entry, key), dtype=float)) for key in _STATE_COLUMNS}


def _check_status(status: str) -> None:
    if status not in (STATUS_OK, STATUS_EXCLUDED, STATUS_DROPPED):
        raise RegistryError(f"unknown print status {status!r}")


def to_npy(array) -> bytes:
    """An array as ``.npy`` bytes (no pickle)."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


def from_npy(blob: bytes) -> np.ndarray:
    """The array of ``.npy`` bytes (no pickle)."""
    return np.load(io.BytesIO(blob), allow_pickle=False)


def record_hash(record) -> str:
    """SHA-256 of a print's table (column names and float64 values) and metadata.

    The same print read from Parquet or CSV, or held on disk, gives the same hash; any
    changed value, column or metadata key gives another.
    """
    h = hashlib.sha256()
    # a record held on disk (ajtwin.io.records.SpooledRecord) gives its columns in pieces:
    # the same bytes in the same order, so the same hash as the record loaded whole
    pieces = getattr(record, "column_pieces", None)
    columns = record.columns if pieces is not None else record.data.columns
    for column in sorted(columns):
        h.update(column.encode())
        if pieces is None:
            parts = [pd.to_numeric(record.data[column], errors="coerce").to_numpy(np.float64)]
        else:
            parts = pieces(column)
        for values in parts:
            h.update(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    # where the file was read from is not part of the print
    meta = {k: v for k, v in record.meta.items() if k not in ("assumed_defaults", "source_file")}
    meta = json.loads(json.dumps(meta, default=str))  # numpy scalars and tuples as in a file
    h.update(json.dumps(meta, sort_keys=True).encode())
    return h.hexdigest()


def clean_name(name: str) -> str:
    """A machine name as stored and looked up: stripped; control characters refused.

    Raises RegistryError for an empty name or one with control/format characters (ANSI
    escapes, newlines, bidi overrides), which would garble or fake terminal output.
    """
    name = str(name).strip()
    if not name:
        raise RegistryError("a machine needs a non-empty name")
    bad = [c for c in name if unicodedata.category(c) in ("Cc", "Cf", "Zl", "Zp")]
    if bad:
        shown = ", ".join(sorted({repr(c) for c in bad}))
        raise RegistryError(
            f"machine name {printable(name)!r} contains control characters ({shown}); "
            "use letters, digits, '-', '_', '.'"
        )
    return name


#: characters a new machine name may not hold: it is one segment of its pages' addresses
#: (/machine/NAME; a web server splits paths at '/', and browsers read '\\' as '/') and of
#: file names derived from it
NAME_FORBIDDEN = "/\\"


def check_new_name(name: str) -> str:
    """A name for a new machine (:func:`clean_name`), one that can name its pages.

    Refused with the rule named: ``/`` or ``\\`` anywhere (the dashboard's page of
    ``a/b`` would be ``/machine/a/b``, which no route can serve), or the names ``.`` and
    ``..`` (browsers resolve them away in a path). Other characters are fine: the pages
    percent-encode names in their links.

    >>> check_new_name("aj300 lab-1")
    'aj300 lab-1'
    """
    name = clean_name(name)
    bad = sorted({c for c in name if c in NAME_FORBIDDEN})
    if bad or name in (".", ".."):
        what = f"contains {' and '.join(repr(c) for c in bad)}" if bad else "is a path step"
        raise RegistryError(
            f"machine name {printable(name)!r} {what}: a machine's name is one part of its "
            "pages' addresses (/machine/NAME), so it may not contain '/' or '\\' nor be "
            "'.' or '..'; use e.g. letters, digits, '-', '_', '.' and spaces"
        )
    return name


def printable(text) -> str:
    """``text`` with control/format characters escaped (``\\x1b``), safe for a terminal."""
    out = []
    for c in str(text):
        if unicodedata.category(c) in ("Cc", "Cf", "Zl", "Zp"):
            code = ord(c)
            out.append(f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}")
        else:
            out.append(c)
    return "".join(out)


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _process_alive(pid) -> bool:
    """Whether process ``pid`` of this computer runs (a draft's writer)."""
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True  # another user's process, or no way to tell: keep its draft
    return True


class Registry:
    """A machine registry in SQLite or PostgreSQL (see module docstring).

    Parameters
    ----------
    path : str, Path or StoreLocation, optional
        An SQLite file's path, or a PostgreSQL URL (:func:`~ajtwin.store.location.
        parse_store`); default :func:`default_store_path`.
    timeout_s : float
        How long a writer waits for another writer's transaction.
    create : bool
        Create the registry (its file and folder, or its tables) when it does not exist;
        read-only commands pass False and get a :class:`RegistryError` instead.
    policy : arrays.StoragePolicy, optional
        How per-second arrays are stored (default :class:`ajtwin.store.arrays.StoragePolicy`).
    write : bool
        The caller will write: refuse at once (:class:`~ajtwin.store.connection.StoreError`)
        when this process cannot (the file, its journal or folder; the role's privileges),
        before any work is done.
    end_state_check : callable, optional
        ``end_state_check(end_mean (5,)) -> list of problems``: when a version-1 registry is
        migrated, its prints whose end state this rejects are excluded from the chain
        (:func:`ajtwin.engine.chain.open_registry` passes the physical range check).
        Without it they keep their status (the engine's chain start refuses such a start
        anyway).

    Attributes
    ----------
    path : Path or StoreLocation
        The SQLite file, or the PostgreSQL location (its ``str()`` is the URL, no password).
    location : StoreLocation
    migrated : list of str
        One message per migration applied while opening (empty when none).
    """

    def __init__(
        self,
        path=None,
        timeout_s: float = 30.0,
        *,
        create: bool = True,
        policy=None,
        end_state_check=None,
        write: bool = False,
    ):
        self.location = parse_store(path)
        self.path = self.location.path if self.location.is_sqlite else self.location
        self.policy = policy or _arrays.StoragePolicy()
        self.end_state_check = end_state_check
        self.timeout_s = float(timeout_s)
        self.migrated: list[str] = []
        self._db = None
        self._next_part: dict[int, int] = {}
        try:
            self._db = open_database(self.location, timeout_s=timeout_s, create=create, write=write)
            self._open(create, write)
        except RegistryError:
            self.close()
            raise
        except sqlite3.Error as exc:
            self.close()
            raise RegistryError(f"{self.path}: not a usable ajtwin registry ({exc})") from None
        self.outbox = Outbox(self.path)

    @property
    def kind(self) -> str:
        """``sqlite`` or ``postgresql``."""
        return self.location.kind

    # ------------------------------------------------------------------ opening
    def _recognise(self, tables: set[str]) -> int | None:
        """Schema version of an ajtwin registry, None for an empty database; refuse others."""
        if not tables:
            return None
        if "info" not in tables:
            raise RegistryError(self._foreign(tables))
        try:
            version_text = get_info(self._db, "schema_version")
            application = get_info(self._db, "application")
        except sqlite3.Error:
            raise RegistryError(self._foreign(tables)) from None
        if application is None and not (V1_TABLES <= tables and version_text == "1"):
            # version 1 had no application marker: recognise it by its exact tables
            raise RegistryError(self._foreign(tables))
        if application is not None and application != APPLICATION:
            raise RegistryError(self._foreign(tables))
        if not V1_TABLES <= tables:
            raise RegistryError(
                f"{self.path}: registry damaged: tables {sorted(V1_TABLES - tables)} are "
                "missing; restore it from a backup (`ajtwin machine import`)"
            )
        try:
            version = int(str(version_text))
        except ValueError:
            raise RegistryError(
                f"{self.path}: registry damaged: schema_version {printable(version_text)!r} "
                "is not a number; restore it from a backup (`ajtwin machine import`)"
            ) from None
        if version > SCHEMA_VERSION:
            raise RegistryError(
                f"{self.path}: written by a newer ajtwin (registry schema {version}; this one "
                f"knows up to {SCHEMA_VERSION}); upgrade ajtwin to open it"
            )
        if version < 1:
            raise RegistryError(f"{self.path}: registry damaged: schema_version {version}")
        return version

    def _foreign(self, tables) -> str:
        shown = ", ".join(sorted(printable(t) for t in tables)[:8])
        what = "an SQLite database" if self.location.is_sqlite else "a PostgreSQL schema"
        return (
            f"{self.path}: {what} but not an ajtwin registry (tables: {shown}); "
            "refusing to change it; give another --store"
        )

    def _open(self, create: bool, write: bool):
        db = self._db
        version = self._recognise(db.tables())
        if version is None and not create:
            what = "an empty file" if self.location.is_sqlite else "no ajtwin tables"
            raise RegistryError(
                f"no registry in {self.path} ({what}); create one with "
                f"`ajtwin machine add NAME --store {self.path}`"
            )
        db.prepare(empty=version is None)  # only now, on our own database
        if version != SCHEMA_VERSION:
            self._migrate()
        if write:
            db.check_write()

    def _migrate(self) -> None:
        db = self._db
        try:
            with db.write("schema"):
                # another process may have created or migrated it while we waited
                version = self._recognise(db.tables())
                fresh = version is None
                if fresh:
                    for statement in db.ddl(SCHEMA_V1):
                        db.execute(statement)
                    db.execute("INSERT INTO info VALUES ('schema_version', '1')")
                    version = 1
                for target, what, function in MIGRATIONS:
                    if target <= version:
                        continue
                    function(db)
                    set_info(db, "schema_version", target)
                    if not fresh:
                        self.migrated.append(
                            f"{self.path}: migrated registry schema {version} → {target} ({what})"
                        )
                    if target == 2 and not fresh and self.end_state_check is not None:
                        exclude_impossible_ends(db, self.end_state_check)
                    version = target
                if not fresh:
                    missing = V1_TABLES - db.tables()
                    if missing:
                        raise RegistryError(
                            f"{self.path}: registry damaged: tables {sorted(missing)} are missing"
                        )
        except BaseException:
            self.migrated = []
            raise

    def close(self):
        """Close the connection (a closed registry cannot be used again); writes kept
        while the server was away are stored first if it answers within a minute."""
        outbox = getattr(self, "outbox", None)
        if outbox is not None and len(outbox) and self._db is not None:
            try:
                outbox.drain(60.0)
            except ConnectionLost as exc:
                log.error("%s; they are lost", exc)
        if self._db is not None:
            self._db.close()
            self._db = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def self_contained(self) -> None:
        """An SQLite registry as one file without a journal beside it (an archive's
        member); nothing to do on PostgreSQL."""
        if self.location.is_sqlite:
            self._db.self_contained()

    def info(self, key: str):
        """The registry's ``info`` value of ``key`` (``schema_version``, ``registry_id`` …)."""
        return get_info(self._db, key)

    # ------------------------------------------------------------------ machines
    def add_machine(self, name: str, limits: dict | None = None, notes: str = "") -> dict:
        """Register a machine; ``limits`` maps input names to [low, high] (display units).

        The name follows :func:`check_new_name` (no ``/`` or ``\\``)."""
        name = check_new_name(name)
        merged = {k: list(v) for k, v in DEFAULT_LIMITS.items()}
        for key, value in (limits or {}).items():
            if key not in DEFAULT_LIMITS:
                raise RegistryError(f"unknown input {key!r} in limits (use {list(DEFAULT_LIMITS)})")
            low, high = (float(v) for v in value)
            if not low < high:
                raise RegistryError(f"limits of {key}: low {low} must be below high {high}")
            merged[key] = [low, high]
        try:
            self._db.execute(
                "INSERT INTO machines (name, created_at, limits_json, notes) VALUES (?, ?, ?, ?)",
                (name, _now(), json.dumps(merged), notes),
            )
        except ConstraintError:
            raise RegistryError(
                f"machine {printable(name)!r} already exists in {self.path}"
            ) from None
        return self.machine(name)

    def machine(self, name: str) -> dict:
        """The machine's row with its limits and print count (RegistryError: unknown)."""
        name = str(name).strip()
        row = self._db.execute("SELECT * FROM machines WHERE name = ?", (name,)).fetchone()
        if row is None:
            known = ", ".join(printable(m["name"]) for m in self.machines()) or "none"
            raise RegistryError(
                f"no machine {printable(name)!r} in {self.path} (known: {known}); "
                f"add it with `ajtwin machine add {printable(name)}`"
            )
        out = dict(row)
        try:
            out["limits"] = json.loads(out.pop("limits_json"))
        except ValueError as exc:
            raise RegistryError(
                f"{self.path}: registry damaged at machine {printable(name)!r}, "
                f"column limits_json ({exc})"
            ) from None
        count = self._db.execute(
            "SELECT COUNT(*) FROM prints WHERE machine_id = ?", (out["id"],)
        ).fetchone()[0]
        out["n_prints"] = int(count)
        return out

    def machines(self) -> list[dict]:
        """Every machine's name and creation time, by name."""
        rows = self._db.execute("SELECT name, created_at FROM machines ORDER BY name").fetchall()
        return [dict(r) for r in rows]

    # ------------------------------------------------------------------ a machine's writer
    def claim_machine(self, name: str, what: str, stale_after_s: float = CLAIM_STALE_S) -> None:
        """Make this process the one writer of machine ``name``'s live print.

        Refused (:class:`RegistryError`, a sentence) while another process holds it: one of
        this computer that still runs, or one of another computer heard from within
        ``stale_after_s`` — two twins given the same machine name would interleave their
        samples. A claim of a process that died (this computer) or went silent (another)
        is taken over. ``what`` says who claims ("ajtwin live").
        """
        host, pid, now = socket.gethostname(), os.getpid(), time.time()
        with self._db.write(f"writer/{name}"):
            row = self._db.execute(
                "SELECT * FROM machine_writers WHERE machine = ?", (name,)
            ).fetchone()
            if row is not None and (row["host"], int(row["pid"])) != (host, pid):
                if row["host"] == host:
                    alive = _process_alive(row["pid"])
                else:
                    alive = now - float(row["heard_unix"]) < stale_after_s
                if alive:
                    raise RegistryError(
                        f"machine {printable(name)!r} is being written by {row['what']} on host "
                        f"{printable(row['host'])} (pid {row['pid']}, last heard "
                        f"{max(0.0, now - float(row['heard_unix'])):.0f} s ago); two twins "
                        "may not write one machine: give this printer its own machine name, "
                        f"or stop the other twin (its claim lapses {stale_after_s:.0f} s after "
                        "it was last heard)"
                    )
            self._db.execute(
                "INSERT INTO machine_writers (machine, host, pid, what, started_unix, "
                "heard_unix) VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (machine) DO UPDATE SET "
                "host = excluded.host, pid = excluded.pid, what = excluded.what, "
                "started_unix = excluded.started_unix, heard_unix = excluded.heard_unix",
                (name, host, pid, what, now, now),
            )

    def release_machine(self, name: str) -> None:
        """Give up this process's claim on machine ``name`` (nothing if it holds none)."""
        self._db.execute(
            "DELETE FROM machine_writers WHERE machine = ? AND host = ? AND pid = ?",
            (name, socket.gethostname(), os.getpid()),
        )

    def machine_writer(self, name: str) -> dict | None:
        """Who claims machine ``name``'s live print (``host``, ``pid``, ``what``,
        ``started_unix``, ``heard_unix``), or None."""
        row = self._db.execute(
            "SELECT * FROM machine_writers WHERE machine = ?", (name,)
        ).fetchone()
        return None if row is None else dict(row)

    def _heard(self, name: str) -> bool:
        """Inside a write: renew this process's claim on ``name``; False (said in the log)
        when another process holds it now — its writes then win, this one's are not made."""
        host, pid = socket.gethostname(), os.getpid()
        updated = self._db.execute(
            "UPDATE machine_writers SET heard_unix = ? WHERE machine = ? AND host = ? AND pid = ?",
            (time.time(), name, host, pid),
        ).rowcount
        if updated:
            return True
        row = self.machine_writer(name)
        if row is not None:
            log.error(
                "machine %s was taken over by %s on host %s (pid %s) while this twin could not "
                "reach the registry; this twin's samples of it are not written",
                printable(name), row["what"], printable(row["host"]), row["pid"],
            )  # fmt: skip
            return False
        now = time.time()
        self._db.execute(
            "INSERT INTO machine_writers (machine, host, pid, what, started_unix, "
            "heard_unix) VALUES (?, ?, ?, 'ajtwin live', ?, ?) ON CONFLICT DO NOTHING",
            (name, host, pid, now, now),
        )
        return True

    # ------------------------------------------------------------------ prints
    def _damaged(self, row, column, exc) -> RegistryError:
        return RegistryError(
            f"{self.path}: registry damaged at print {row['seq']} (id {row['id']}), "
            f"column {column}: {exc}; drop it with `ajtwin machine drop` or restore a backup"
        )

    def _print_row(self, row) -> dict:
        out = dict(row)
        for key, expected in _STATE_COLUMNS.items():
            if key not in out:  # a query that selected only some columns
                continue
            try:
                value = _arrays.decode(out[key], _arrays.NPY)
                if value.shape != expected or value.dtype.kind != "f":
                    raise ValueError(f"expected float {expected}, got {value.dtype} {value.shape}")
            except ValueError as exc:
                raise self._damaged(row, key, exc) from None
            out[key] = value
        for key, column in (("meta", "meta_json"), ("summary", "summary_json")):
            if column not in out:
                continue
            try:
                out[key] = json.loads(out.pop(column))
            except (ValueError, TypeError) as exc:
                raise self._damaged(row, column, exc) from None
        out.setdefault("status", STATUS_OK)
        out.setdefault("status_reason", "")
        return out

    def last_print(self, name: str, *, in_chain: bool = True) -> dict | None:
        """The machine's latest print in the chain (its end state is the twin's current
        state), or with ``in_chain=False`` the latest of all; None when there is none."""
        machine = self.machine(name)
        where = " AND status = ?" if in_chain else ""
        args = (machine["id"], STATUS_OK) if in_chain else (machine["id"],)
        row = self._db.execute(
            f"SELECT * FROM prints WHERE machine_id = ?{where} ORDER BY seq DESC LIMIT 1", args
        ).fetchone()
        return None if row is None else self._print_row(row)

    def chain_prints(self, name: str, below_seq: int | None = None):
        """Prints in the chain, newest first (a generator; stops where the caller stops)."""
        machine = self.machine(name)
        query = "SELECT * FROM prints WHERE machine_id = ? AND status = ?"
        args = [machine["id"], STATUS_OK]
        if below_seq is not None:
            query += " AND seq < ?"
            args.append(below_seq)
        for row in self._db.execute(query + " ORDER BY seq DESC", args).fetchall():
            yield self._print_row(row)

    def prints(self, name: str, since: str | None = None) -> list[dict]:
        """The machine's prints in seq order (every status), each as :meth:`get_print`
        gives it; ``since``: only those ingested at or after this ISO time."""
        machine = self.machine(name)
        query, args = "SELECT * FROM prints WHERE machine_id = ?", [machine["id"]]
        if since is not None:
            query += " AND ingested_at >= ?"
            args.append(str(since))
        rows = self._db.execute(query + " ORDER BY seq", args).fetchall()
        return [self._print_row(r) for r in rows]

    def find_print(self, name: str, content_hash: str) -> dict | None:
        """The machine's print with this content hash (None: not ingested)."""
        machine = self.machine(name)
        row = self._db.execute(
            "SELECT * FROM prints WHERE machine_id = ? AND content_hash = ?",
            (machine["id"], content_hash),
        ).fetchone()
        return None if row is None else self._print_row(row)

    def get_print(self, print_id: int) -> dict:
        """The print with this id (RegistryError when there is none)."""
        row = self._db.execute("SELECT * FROM prints WHERE id = ?", (int(print_id),)).fetchone()
        if row is None:
            raise RegistryError(f"no print with id {print_id}")
        return self._print_row(row)

    def print_by_seq(self, name: str, seq: int) -> dict:
        """The machine's print number ``seq`` (RegistryError saying how many it has)."""
        machine = self.machine(name)
        row = None
        if -(2**63) <= int(seq) < 2**63:  # beyond 64-bit integers there is no print
            row = self._db.execute(
                "SELECT * FROM prints WHERE machine_id = ? AND seq = ?", (machine["id"], int(seq))
            ).fetchone()
        if row is None:
            raise RegistryError(
                f"machine {printable(machine['name'])!r} has no print #{seq} "
                f"(it has {machine['n_prints']})"
            )
        return self._print_row(row)

    def latest_seq(self, name: str) -> int | None:
        """The seq of the machine's newest print, in the chain or not (None: no print)."""
        machine = self.machine(name)
        row = self._db.execute(
            "SELECT MAX(seq) FROM prints WHERE machine_id = ?", (machine["id"],)
        ).fetchone()
        return None if row[0] is None else int(row[0])

    def print_summary(self, print_id: int) -> dict:
        """The summary stored with a print ({} when there is no such print)."""
        row = self._db.execute(
            "SELECT summary_json FROM prints WHERE id = ?", (int(print_id),)
        ).fetchone()
        return {} if row is None else json.loads(row[0])

    def print_arrays(self, print_id: int) -> dict[str, np.ndarray]:
        """The print's per-second arrays, decoded (see :mod:`ajtwin.store.arrays`).

        ``predicted_means`` is rebuilt from the stored means and corrections; covariances
        are ``covariance_keyframes`` (K, 5, 5) at ``covariance_steps`` (K,) unless the
        print was stored with the whole sequence (``covariances``, T × 5 × 5).
        """
        rows = self._db.execute(
            "SELECT name, npy, codec FROM print_arrays WHERE print_id = ?", (int(print_id),)
        ).fetchall()
        out = {r["name"]: self._decoded(print_id, r["name"], r["npy"], r["codec"]) for r in rows}
        parts: dict[str, list] = {}
        for r in self._db.execute(
            "SELECT name, codec, blob FROM print_array_parts WHERE print_id = ? "
            "ORDER BY name, part",
            (int(print_id),),
        ).fetchall():
            decoded = self._decoded(print_id, r["name"], r["blob"], r["codec"])
            parts.setdefault(r["name"], []).append(decoded)
        out.update(_arrays.join_parts(parts))
        return _arrays.expand(out)

    def print_array(self, print_id: int, name: str) -> np.ndarray | None:
        """One stored array of a print, decoded without loading the others, whether it was
        written whole or in parts (None: not stored)."""
        row = self._db.execute(
            "SELECT npy, codec FROM print_arrays WHERE print_id = ? AND name = ?",
            (int(print_id), name),
        ).fetchone()
        if row is not None:
            return self._decoded(print_id, name, row["npy"], row["codec"])
        parts = [
            self._decoded(print_id, name, r["blob"], r["codec"])
            for r in self._db.execute(
                "SELECT codec, blob FROM print_array_parts WHERE print_id = ? AND name = ? "
                "ORDER BY part",
                (int(print_id), name),
            ).fetchall()
        ]
        return _arrays.join_parts({name: parts})[name] if parts else None

    def _decoded(self, print_id: int, name: str, blob, codec: str) -> np.ndarray:
        """A stored array decoded (RegistryError naming the print and array if damaged)."""
        try:
            return _arrays.decode(bytes(blob), codec)
        except ValueError as exc:
            seq = self._db.execute(
                "SELECT seq FROM prints WHERE id = ?", (int(print_id),)
            ).fetchone()
            raise RegistryError(
                f"{self.path}: registry damaged at print {seq[0] if seq else '?'} "
                f"(id {print_id}), array {printable(name)}: {exc}"
            ) from None

    # ------------------------------------------------------------------ drafts
    def open_draft(self, machine: str, label: str) -> int:
        """A draft for the arrays of a print of ``machine`` still running (``label`` says
        which: "ingest of FILE", "live session 12"); its id for :meth:`append_draft` and
        :meth:`save_print`. Drafts of processes that died are removed first."""
        self.discard_stale_drafts()
        draft = self._db.insert(
            "array_drafts",
            {
                "machine": str(machine),
                "label": str(label),
                "created_unix": time.time(),
                "pid": os.getpid(),
                "host": socket.gethostname(),
            },
        )
        self._next_part[draft] = 0
        return draft

    def append_draft(self, draft: int, arrays: dict, part: dict, alarm_times=()) -> int:
        """Write one part of a running print's arrays (consecutive steps) to ``draft``, in
        its own short transaction; the bytes written.

        ``part``: ``first_step``, ``origin_s``, ``after_s``, ``last`` as
        :func:`ajtwin.store.arrays.encode_all` takes them; the arrays are stored by
        :attr:`policy` (key frames of the covariances as the whole print would have them).
        The part's number is fixed here, so a write kept while the database server is away
        (:attr:`outbox`) is stored later in its place, once.
        """
        encoded = _arrays.encode_all(arrays, self.policy, alarm_times, part=part)
        draft = int(draft)
        if draft not in self._next_part:  # a draft of this process opened elsewhere
            row = self._db.execute(
                "SELECT COALESCE(MAX(part), -1) + 1 FROM print_array_parts WHERE print_id = ?",
                (-draft,),
            ).fetchone()
            self._next_part[draft] = int(row[0])
        number = self._next_part[draft]
        self._next_part[draft] = number + 1
        rows = [(-draft, key, number, c, b) for key, (c, b) in encoded.items()]

        def write():
            with self._db.write(None):
                found = self._db.execute("SELECT 1 FROM array_drafts WHERE id = ?", (draft,))
                if found.fetchone() is None:
                    raise RegistryError(f"draft {draft} is not open (stored or discarded)")
                self._db.executemany(
                    "INSERT INTO print_array_parts (print_id, name, part, codec, blob) "
                    "VALUES (?, ?, ?, ?, ?) ON CONFLICT DO NOTHING",
                    rows,
                )

        self.outbox.submit(write)
        return sum(len(b) for _, b in encoded.values())

    def discard_draft(self, draft: int) -> None:
        """Remove a draft and its parts (a print that failed or was refused)."""
        self.outbox.drain(SAVE_WAIT_S)
        with self._db.write(None):
            self._db.execute("DELETE FROM print_array_parts WHERE print_id = ?", (-int(draft),))
            self._db.execute("DELETE FROM array_drafts WHERE id = ?", (int(draft),))
        self._next_part.pop(int(draft), None)

    def discard_drafts(self, machine: str, label: str) -> int:
        """Remove the drafts of ``machine`` with ``label`` (a live session replayed from its
        samples writes its parts again); how many."""
        rows = self._db.execute(
            "SELECT id FROM array_drafts WHERE machine = ? AND label = ?", (machine, label)
        ).fetchall()
        for (draft,) in rows:
            self.discard_draft(draft)
        return len(rows)

    def discard_stale_drafts(self) -> int:
        """Remove the drafts of processes of this computer that no longer run (a killed
        ingest: its print was never stored); how many."""
        host = socket.gethostname()
        stale = [
            r["id"]
            for r in self._db.execute("SELECT id, pid, host FROM array_drafts").fetchall()
            if r["host"] == host and not _process_alive(r["pid"])
        ]
        for draft in stale:
            self.discard_draft(draft)
        return len(stale)

    def long_run_history(self, name: str, below_seq: int | None = None) -> tuple[int, dict] | None:
        """(seq, statistics) of the detectors' long-run statistics stored with the newest
        print in the chain that has them (``below_seq``: among the prints before that one;
        None: no such print)."""
        machine = self.machine(name)
        limit = 2**62 if below_seq is None else int(below_seq)
        row = self._db.execute(
            "SELECT id, seq, long_run_json FROM prints WHERE machine_id = ? AND status = ? "
            "AND long_run_json != 'null' AND seq < ? ORDER BY seq DESC LIMIT 1",
            (machine["id"], STATUS_OK, limit),
        ).fetchone()
        if row is None:
            return None
        try:
            return int(row["seq"]), json.loads(row["long_run_json"])
        except ValueError as exc:
            raise self._damaged(row, "long_run_json", exc) from None

    def history(self, name: str, version: int | None = None) -> pd.DataFrame:
        """One row per print: seq, id, time, duration, source, the program it ran ("" when
        stored without a job), status, end states, θ, anomaly count, the alarms' causes
        (comma-separated, first raised first) and whether the mismatch guard found the
        model not fitting the machine.

        ``version``: the results of a reprocessing (:meth:`create_version`) instead of the
        prints as stored (version 1 or None); only the prints that version holds, with
        its end states, θ, status and anomalies.
        """
        machine = self.machine(name)
        if version is not None and int(version) != 1:
            self._version_row(version)
            query = (
                "SELECT p.id, p.seq, p.ingested_at, p.source, p.duration_s, p.meta_json,"
                " v.summary_json, v.status, v.status_reason, v.end_mean, v.theta_after, j.program,"
                " (SELECT COUNT(*) FROM print_version_anomalies a"
                "  WHERE a.print_version_id = v.id) AS n_anomalies"
                " FROM print_versions v JOIN prints p ON p.id = v.print_id"
                " LEFT JOIN print_jobs j ON j.print_id = p.id"
                " WHERE p.machine_id = ? AND v.version_id = ? ORDER BY p.seq"
            )
            args = (machine["id"], int(version))
            causes_query = (
                "SELECT v.print_id, a.cause FROM print_version_anomalies a JOIN print_versions v"
                " ON a.print_version_id = v.id JOIN prints p ON p.id = v.print_id"
                " WHERE p.machine_id = ? AND v.version_id = ? ORDER BY a.detected_s"
            )
        else:
            query = (
                "SELECT p.id, p.seq, p.ingested_at, p.source, p.duration_s, p.meta_json,"
                " p.summary_json, p.status, p.status_reason, p.end_mean, p.theta_after, j.program,"
                " (SELECT COUNT(*) FROM anomalies a WHERE a.print_id = p.id) AS n_anomalies"
                " FROM prints p LEFT JOIN print_jobs j ON j.print_id = p.id"
                " WHERE machine_id = ? ORDER BY seq"
            )
            args = (machine["id"],)
            causes_query = (
                "SELECT a.print_id, a.cause FROM anomalies a JOIN prints p ON a.print_id = p.id"
                " WHERE p.machine_id = ? ORDER BY a.detected_s"
            )
        causes: dict[int, list[str]] = {}
        for row in self._db.execute(causes_query, args).fetchall():
            found = causes.setdefault(int(row["print_id"]), [])
            if row["cause"] not in found:
                found.append(row["cause"])
        records = []
        for row in self._db.execute(query, args).fetchall():
            p = self._print_row(row)
            summary = p["summary"] if isinstance(p["summary"], dict) else {}
            rec = {
                "seq": p["seq"],
                "print_id": p["id"],
                "ingested_at": p["ingested_at"],
                "source": p["source"],
                "duration_min": p["duration_s"] / 60.0,
                "scenario": p["meta"].get("scenario") if isinstance(p["meta"], dict) else None,
                "program": row["program"] or "",
                "anomalies": int(row["n_anomalies"]),
                "causes": ",".join(causes.get(int(p["id"]), [])),
                "mismatch": bool((summary.get("mismatch") or {}).get("mismatch")),
                "status": p["status"],
                "status_reason": p["status_reason"],
            }
            for i, state in enumerate(STATE_NAMES):
                rec["end_" + state] = float(p["end_mean"][i])
            for i, state in enumerate(STATE_NAMES):
                rec["theta_" + state] = float(p["theta_after"][i])
            records.append(rec)
        return pd.DataFrame(records)

    def anomalies(self, name: str) -> pd.DataFrame:
        """One row per anomaly of the machine's prints: seq, detected_s, onset_s, cause,
        description, detectors."""
        machine = self.machine(name)
        rows = self._db.execute(
            "SELECT p.seq, a.detected_s, a.onset_s, a.cause, a.description, a.detectors "
            "FROM anomalies a JOIN prints p ON a.print_id = p.id WHERE p.machine_id = ? "
            "ORDER BY p.seq, a.detected_s",
            (machine["id"],),
        ).fetchall()
        return pd.DataFrame(
            [dict(r) for r in rows],
            columns=["seq", "detected_s", "onset_s", "cause", "description", "detectors"],
        )

    def newest_print_alarms(self, name: str) -> list[dict]:
        """The anomalies of the machine's newest print that raised any, in detection order:
        ``seq``, ``ingested_at``, ``detected_s``, ``onset_s`` [s], ``cause``, ``description``
        ([] when no print ever raised one)."""
        machine = self.machine(name)
        rows = self._db.execute(
            "SELECT p.seq, p.ingested_at, a.detected_s, a.onset_s, a.cause, a.description "
            "FROM anomalies a JOIN prints p ON a.print_id = p.id WHERE p.machine_id = ? AND "
            "p.seq = (SELECT MAX(p2.seq) FROM anomalies a2 JOIN prints p2 ON a2.print_id = p2.id "
            "WHERE p2.machine_id = ?) ORDER BY a.detected_s",
            (machine["id"], machine["id"]),
        ).fetchall()
        return [dict(r) for r in rows]

    def count_alarms(self, name: str, seq: int, except_cause: str = "") -> int:
        """Anomalies of print ``seq`` of machine ``name`` whose cause is not ``except_cause``."""
        machine = self.machine(name)
        row = self._db.execute(
            "SELECT COUNT(*) FROM anomalies a JOIN prints p ON a.print_id = p.id "
            "WHERE p.machine_id = ? AND p.seq = ? AND a.cause != ?",
            (machine["id"], seq, except_cause),
        ).fetchone()
        return int(row[0])

    def set_status(self, name: str, seq: int, status: str, reason: str = "") -> dict:
        """Put print ``seq`` in (``ok``) or out of (``dropped``/``excluded``) the chain.

        The print and its arrays stay (history); only the next ingest's start changes.
        """
        _check_status(status)
        p = self.print_by_seq(name, seq)
        self._db.execute(
            "UPDATE prints SET status = ?, status_reason = ? WHERE id = ?",
            (status, reason, p["id"]),
        )
        return self.get_print(p["id"])

    # ------------------------------------------------------------------ storing a print
    def save_print(
        self,
        name: str,
        entry: NewPrint,
        *,
        expected_last_seq: int | None,
        draft: int | None = None,
        live_session: int | None = None,
        keep_live_steps: bool = False,
    ) -> int:
        """Write one print (``entry``), its arrays, anomalies and job in ONE transaction;
        returns its id.

        ``expected_last_seq`` is the seq of the machine's latest print (in the chain or
        not) when the twin started (None: none); if another ingest of the same machine
        committed in between, nothing is written and :class:`RegistryError` says so (the
        run started from a stale state). ``entry.arrays`` are stored by :attr:`policy`
        (full covariances only at key frames, alarms and the end; see
        :mod:`ajtwin.store.arrays`).

        ``draft``: the print's per-step arrays written in parts as it ran (:meth:`open_draft`,
        :meth:`append_draft`), made this print's in the same transaction (``entry.arrays``:
        the rest, the θ history); parts kept while the server was away are stored first.

        ``live_session``: the live session (:meth:`live_open_session`) this print ends; in
        the same transaction it is closed with this print's id, the machine's writer claim
        is given up and, unless ``keep_live_steps``, its per-step rows (``live_samples``,
        ``live_states``) are deleted: the print now holds its samples exactly and its
        states by the storage policy, and a session is only replayed while open. Its
        session row and alarms stay. A kill before the COMMIT leaves the session open and
        whole (resumable).

        With PostgreSQL away, the write waits for it (up to :data:`SAVE_WAIT_S`) and is
        made once it answers; a COMMIT whose answer was lost is recognised (the print is
        found by its content hash) and not made twice.
        """
        _check_status(entry.status)
        alarm_times = [t for ev in entry.anomalies for t in (ev.detected_s, ev.onset_s)]
        encoded = _arrays.encode_all(entry.arrays, self.policy, alarm_times)
        row = {
            "content_hash": entry.content_hash,
            "source": entry.source,
            "n_samples": int(entry.n_samples),
            "duration_s": float(entry.duration_s),
            "meta_json": json.dumps(entry.meta, default=str),
            "summary_json": json.dumps(entry.summary, default=str),
            **_state_blobs(entry),
            "status": entry.status,
            "status_reason": entry.status_reason,
            "long_run_json": json.dumps(entry.long_run_history),
        }
        deadline = time.monotonic() + SAVE_WAIT_S
        while True:
            try:
                self.outbox.drain(max(0.0, deadline - time.monotonic()))
                row["machine_id"] = self.machine(name)["id"]
                print_id, dropped = self._save_print_once(
                    name, row, entry, encoded, expected_last_seq, draft, live_session,
                    keep_live_steps,
                )  # fmt: skip
                break
            except ConnectionLost as exc:
                if time.monotonic() >= deadline:
                    raise
                log.warning("%s; the print is stored when it answers", exc)
                time.sleep(2.0)
                stored = self._stored_before(name, entry.content_hash)
                if stored is not None:  # the COMMIT got through, its answer did not
                    print_id, dropped = stored, 0
                    break
        if draft is not None:
            self._next_part.pop(int(draft), None)
        if dropped or draft is not None:  # the draft's parts were moved: their old pages
            self._db.release_free_pages()
        return int(print_id)

    def _stored_before(self, name: str, content_hash: str) -> int | None:
        try:
            found = self.find_print(name, content_hash)
        except ConnectionLost:
            return None
        return None if found is None else int(found["id"])

    def _save_print_once(
        self, name, row, entry, encoded, expected_last_seq, draft, live_session, keep_live_steps
    ) -> tuple[int, int]:
        """save_print's transaction: (print id, live steps dropped)."""
        db = self._db
        with db.write(f"machine/{row['machine_id']}"):
            last = db.execute(
                "SELECT MAX(seq) FROM prints WHERE machine_id = ?", (row["machine_id"],)
            ).fetchone()[0]
            if last != expected_last_seq:
                raise RegistryError(
                    f"machine {printable(name)!r} got print {last} while this ingest ran from "
                    f"print {expected_last_seq}; ingest again"
                )
            dup = db.execute(
                "SELECT seq FROM prints WHERE machine_id = ? AND content_hash = ?",
                (row["machine_id"], entry.content_hash),
            ).fetchone()
            if dup is not None:
                raise RegistryError(f"this print is already print {dup[0]} of {printable(name)!r}")
            values = {**row, "seq": 1 if last is None else last + 1, "ingested_at": _now()}
            print_id = db.insert("prints", values)
            self._insert_results(print_id, encoded, entry.anomalies)
            if draft is not None:
                self._adopt_draft(draft, print_id)
            if entry.job is not None:
                self._insert_job(print_id, entry.job)
            dropped = 0
            if live_session is not None:
                dropped = self._end_live_session(live_session, print_id, keep_live_steps)
            delay = float(os.environ.get(TEST_SLEEP_ENV, "0") or 0)
            if delay > 0:  # crash-safety tests kill the process here
                time.sleep(delay)
        return print_id, dropped

    def _insert_results(self, print_id: int, encoded: dict, anomalies: list) -> None:
        """Inside save_print's transaction: the print's encoded arrays and its anomalies."""
        self._db.executemany(
            "INSERT INTO print_arrays (print_id, name, npy, codec) VALUES (?, ?, ?, ?)",
            [(print_id, key, blob, codec) for key, (codec, blob) in encoded.items()],
        )
        self._db.executemany(
            "INSERT INTO anomalies (print_id, detected_s, onset_s, cause, description, "
            "detectors, evidence_json) VALUES (?, ?, ?, ?, ?, ?, ?)",
            [(print_id, *_anomaly_values(ev)) for ev in anomalies],
        )

    def _adopt_draft(self, draft: int, print_id: int) -> None:
        """Inside save_print's transaction: the draft's parts become the print's."""
        gone = self._db.execute("DELETE FROM array_drafts WHERE id = ?", (int(draft),))
        if gone.rowcount != 1:
            raise RegistryError(f"draft {draft} is not open (stored or discarded); nothing stored")
        self._db.execute(
            "UPDATE print_array_parts SET print_id = ? WHERE print_id = ?", (print_id, -int(draft))
        )

    def _insert_job(self, print_id: int, job: dict) -> None:
        """Inside save_print's transaction: the job the print ran (compressed program)."""
        raw = bytes(job["program_bytes"])
        self._db.execute(
            "INSERT INTO print_jobs (print_id, program, sha256, program_blob, settings_json) "
            "VALUES (?, ?, ?, ?, ?)",
            (
                print_id,
                str(job["program"]),
                hashlib.sha256(raw).hexdigest(),
                zlib.compress(raw, 9),
                json.dumps(job.get("settings") or {}, default=str),
            ),
        )

    def print_job(self, print_id: int) -> dict | None:
        """The job print ``print_id`` ran (None: it was stored without one): ``program``
        (file name), ``sha256``, ``program_bytes`` (checked against the SHA-256) and
        ``settings``. A damaged row is a RegistryError naming the print."""
        row = self._db.execute(
            "SELECT p.seq, j.* FROM print_jobs j JOIN prints p ON p.id = j.print_id "
            "WHERE j.print_id = ?",
            (int(print_id),),
        ).fetchone()
        if row is None:
            return None
        try:
            raw = zlib.decompress(bytes(row["program_blob"]))
            if hashlib.sha256(raw).hexdigest() != row["sha256"]:
                raise ValueError("the program's SHA-256 does not match the stored one")
            settings = json.loads(row["settings_json"])
        except (zlib.error, ValueError, TypeError) as exc:
            raise RegistryError(
                f"{self.path}: registry damaged at print {row['seq']} (id {print_id}), "
                f"its job: {exc}"
            ) from None
        return {
            "program": row["program"],
            "sha256": row["sha256"],
            "program_bytes": raw,
            "settings": settings,
        }

    def _end_live_session(self, session_id: int, print_id: int, keep_steps: bool) -> int:
        """Inside save_print's transaction: close the open live session with its print and
        give up the machine's writer claim; drop its per-step rows unless ``keep_steps``.
        Returns the number of steps dropped."""
        closed = self._db.execute(
            "UPDATE live_sessions SET status = 'closed', print_id = ?, closed_at = ? "
            "WHERE id = ? AND status = 'open'",
            (print_id, time.time(), session_id),
        ).rowcount
        if closed != 1:
            raise RegistryError(f"live session {session_id} is not open; nothing stored")
        machine = self._db.execute(
            "SELECT machine FROM live_sessions WHERE id = ?", (session_id,)
        ).fetchone()[0]
        self.release_machine(machine)
        if keep_steps:
            return 0
        dropped = self._db.execute(
            "DELETE FROM live_samples WHERE session_id = ?", (session_id,)
        ).rowcount
        self._db.execute("DELETE FROM live_states WHERE session_id = ?", (session_id,))
        return dropped

    def release_free_pages(self) -> None:
        """Give freed space back to the file system (SQLite registries made with
        ``auto_vacuum=INCREMENTAL``: every new one, and any after ``machine compact``;
        PostgreSQL's autovacuum does it by itself)."""
        self._db.release_free_pages()

    # ------------------------------------------------------------------ versions
    def create_version(self, reason: str, settings: dict) -> int:
        """A new version of results (``ajtwin reprocess``): its number (2, 3, …; version 1
        is the prints as stored). ``settings``: what the run used (JSON-ready)."""
        with self._db.write("versions"):
            row = self._db.execute("SELECT COALESCE(MAX(id), 1) + 1 FROM versions").fetchone()
            version = int(row[0])
            self._db.insert(
                "versions",
                {
                    "id": version,
                    "created_at": _now(),
                    "reason": str(reason),
                    "settings_json": json.dumps(settings, default=str),
                    "status": "running",
                },
                returning_id=False,
            )
            self._db.identity_set("versions")
        return version

    def finish_version(self, version: int, status: str = "done") -> None:
        """Mark a version's run as ended (``done``, or ``stopped`` when it did not finish)."""
        self._db.execute("UPDATE versions SET status = ? WHERE id = ?", (status, int(version)))

    def versions(self) -> list[dict]:
        """Every version of results: ``id``, ``created_at``, ``reason``, ``settings``,
        ``status``, ``n_prints`` (version 1, the prints as stored, first)."""
        n_stored = self._db.execute("SELECT COUNT(*) FROM prints").fetchone()[0]
        out = [{"id": 1, "created_at": "", "reason": "as stored", "settings": {},
                "status": "done", "n_prints": int(n_stored)}]  # fmt: skip
        rows = self._db.execute(
            "SELECT v.*, (SELECT COUNT(*) FROM print_versions p WHERE p.version_id = v.id) "
            "AS n_prints FROM versions v ORDER BY v.id"
        ).fetchall()
        for r in rows:
            entry = dict(r)
            entry["settings"] = json.loads(entry.pop("settings_json"))
            entry["n_prints"] = int(entry["n_prints"])
            out.append(entry)
        return out

    def _version_row(self, version: int) -> dict:
        row = self._db.execute("SELECT * FROM versions WHERE id = ?", (int(version),)).fetchone()
        if row is None:
            known = ", ".join(str(v["id"]) for v in self.versions())
            raise RegistryError(f"{self.path}: no version {version} of results (known: {known})")
        return dict(row)

    def save_print_version(self, version: int, print_id: int, result: NewPrint) -> bool:
        """Store the reprocessed result of print ``print_id`` in ``version`` (its start, end,
        θ, summary, status, per-second arrays — the twin's results; the print keeps its
        samples — and anomalies; ``result``'s identity fields are the print's) in one
        transaction; False when that version already holds it (nothing is overwritten)."""
        _check_status(result.status)
        alarm_times = [t for ev in result.anomalies for t in (ev.detected_s, ev.onset_s)]
        encoded = _arrays.encode_all(result.arrays, self.policy, alarm_times)
        with self._db.write(f"version/{int(version)}/{int(print_id)}"):
            found = self._db.execute(
                "SELECT 1 FROM print_versions WHERE version_id = ? AND print_id = ?",
                (int(version), int(print_id)),
            ).fetchone()
            if found is not None:
                return False
            row_id = self._db.insert(
                "print_versions",
                {
                    "version_id": int(version),
                    "print_id": int(print_id),
                    "computed_at": _now(),
                    "summary_json": json.dumps(result.summary, default=str),
                    **_state_blobs(result),
                    "status": result.status,
                    "status_reason": result.status_reason,
                    "long_run_json": json.dumps(result.long_run_history),
                },
            )
            self._db.executemany(
                "INSERT INTO print_version_arrays (print_version_id, name, codec, blob) "
                "VALUES (?, ?, ?, ?)",
                [(row_id, key, codec, blob) for key, (codec, blob) in encoded.items()],
            )
            self._db.executemany(
                "INSERT INTO print_version_anomalies (print_version_id, detected_s, onset_s, "
                "cause, description, detectors, evidence_json) VALUES (?, ?, ?, ?, ?, ?, ?)",
                [(row_id, *_anomaly_values(ev)) for ev in result.anomalies],
            )
        return True

    def print_version(self, version: int, print_id: int, arrays: bool = False) -> dict | None:
        """Print ``print_id``'s result in ``version`` (as :meth:`get_print` gives a print:
        ``start_mean`` … ``theta_after``, ``summary``, ``status``; with ``arrays`` its
        per-second ``arrays`` too), None when that version does not hold it."""
        row = self._db.execute(
            "SELECT v.*, p.seq FROM print_versions v JOIN prints p ON p.id = v.print_id "
            "WHERE v.version_id = ? AND v.print_id = ?",
            (int(version), int(print_id)),
        ).fetchone()
        if row is None:
            return None
        out = self._print_row(row)
        if arrays:
            stored = self._db.execute(
                "SELECT name, codec, blob FROM print_version_arrays WHERE print_version_id = ?",
                (out["id"],),
            ).fetchall()
            decoded = {
                r["name"]: self._decoded(print_id, r["name"], r["blob"], r["codec"]) for r in stored
            }
            out["arrays"] = _arrays.expand(decoded)
        return out

    # ------------------------------------------------------------------ calibrations
    def add_calibration(self, machine: str, row: dict) -> int:
        """Store a calibration row of ``machine`` (the columns of ``calibrations`` but its
        ids and times, made by :func:`ajtwin.store.calibration.save_calibration`); its id."""
        now = time.time()
        values = {
            "machine_id": self.machine(machine)["id"],
            "created_at": _iso(now),
            "created_unix": now,
            "after_print_seq": self.latest_seq(machine) or 0,
            **row,
        }
        return self._db.insert("calibrations", values)

    def calibrations(self, machine: str, newest_only: bool = False) -> list[dict]:
        """The machine's calibration rows, oldest first (``newest_only``: the active one)."""
        machine_id = self.machine(machine)["id"]
        if newest_only:
            query = "SELECT * FROM calibrations WHERE machine_id = ? ORDER BY id DESC LIMIT 1"
        else:
            query = "SELECT * FROM calibrations WHERE machine_id = ? ORDER BY id"
        return [dict(r) for r in self._db.execute(query, (machine_id,)).fetchall()]

    def calibration(self, calibration_id: int) -> dict | None:
        """The calibration row ``calibration_id`` (None: there is none)."""
        row = self._db.execute(
            "SELECT * FROM calibrations WHERE id = ?", (int(calibration_id),)
        ).fetchone()
        return None if row is None else dict(row)

    def add_maintenance(self, machine: str, event: dict) -> str:
        """Store a maintenance event (JSON-ready) of ``machine``, after its newest print;
        when (ISO time)."""
        now = time.time()
        created = _iso(now)
        self._db.insert(
            "maintenance_events",
            {
                "machine_id": self.machine(machine)["id"],
                "created_at": created,
                "created_unix": now,
                "after_print_seq": self.latest_seq(machine) or 0,
                "event_json": json.dumps(event),
            },
        )
        return created

    def maintenance(
        self, machine: str, after_print_seq: int | None = None, since_unix: float = 0.0
    ) -> list[dict]:
        """The machine's maintenance events, oldest first: ``id``, ``created_at``,
        ``created_unix``, ``after_print_seq``, ``event`` (dict); ``after_print_seq``: only
        those done after that print (and at or after ``since_unix``)."""
        machine_id = self.machine(machine)["id"]
        query = "SELECT * FROM maintenance_events WHERE machine_id = ? AND created_unix >= ?"
        args = [machine_id, float(since_unix)]
        if after_print_seq is not None:
            query += " AND after_print_seq = ?"
            args.append(int(after_print_seq))
        rows = self._db.execute(query + " ORDER BY id", args).fetchall()
        out = []
        for r in rows:
            entry = dict(r)
            entry["event"] = json.loads(entry.pop("event_json"))
            out.append(entry)
        return out

    # ------------------------------------------------------------------ changes
    def change_marker(self) -> tuple[int, int, int]:
        """(a number that changes on any commit, last print id, last machine id)."""
        token = self._db.change_token()
        last_print = self._db.execute("SELECT COALESCE(MAX(id), 0) FROM prints").fetchone()[0]
        last_machine = self._db.execute("SELECT COALESCE(MAX(id), 0) FROM machines").fetchone()[0]
        return int(token), int(last_print), int(last_machine)

    def prints_after(self, print_id: int) -> list[dict]:
        """Prints committed with an id above ``print_id``: ``print_id``, ``seq``, ``machine``,
        ``duration_s`` [s] and the number of ``anomalies``, oldest first."""
        rows = self._db.execute(
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

    # ------------------------------------------------------------------ the live log
    def live_open_session(
        self, machine: str, *, source: str, start, theta, expected_last_seq=None
    ) -> int:
        """A new open live session for ``machine``; ``start`` (mean, cov) or None (the
        print's initial fit); its id (:mod:`ajtwin.store.live_log`)."""
        return self._db.insert(
            "live_sessions",
            {
                "machine": machine,
                "started_at": time.time(),
                "source": source,
                "status": "open",
                "start_mean": None if start is None else to_npy(start[0]),
                "start_cov": None if start is None else to_npy(start[1]),
                "theta_before": to_npy(np.asarray(theta, dtype=float)),
                "expected_last_seq": expected_last_seq,
            },
        )

    def live_session_of(self, machine: str) -> dict | None:
        """The machine's open live session (the latest) with its ``start`` and
        ``theta_before`` decoded, or None."""
        row = self._db.execute(
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

    def live_sessions(self, machine: str | None = None, open_only: bool = False) -> list[dict]:
        """Live sessions (``id``, ``machine``, ``started_at``, ``source``, ``status``,
        ``print_id``), oldest first: of ``machine`` (None: every machine), or only those
        still ``open``."""
        query = "SELECT id, machine, started_at, source, status, print_id FROM live_sessions"
        clauses, args = [], []
        if machine is not None:
            clauses.append("machine = ?")
            args.append(machine)
        if open_only:
            clauses.append("status = 'open'")
        if clauses:
            query += " WHERE " + " AND ".join(clauses)
        return [dict(r) for r in self._db.execute(query + " ORDER BY id", args).fetchall()]

    def live_append(self, session_id: int, steps: list, events: list) -> None:
        """Commit steps [(step, time_s, inputs, outputs, message)] and events of an open
        session in ONE transaction, and renew this process's claim on its machine.

        Steps already stored are ignored (a replay after a restart writes nothing twice);
        steps of a session closed meanwhile are dropped (its print holds them). While the
        database server is away the write is kept (:attr:`outbox`) and made when it is back.
        """
        if not steps and not events:
            return
        sid = int(session_id)
        samples = [
            (sid, int(k), float(t), to_npy(np.asarray(u)), to_npy(np.asarray(y)))
            for k, t, u, y, _ in steps
        ]
        states = [(sid, int(k), json.dumps(m, default=float)) for k, _, _, _, m in steps]
        alarms = [
            (sid, float(e["detected_s"]), e["state"], json.dumps(e, default=str)) for e in events
        ]

        def write():
            with self._db.write(None):
                row = self._db.execute(
                    "SELECT machine, status FROM live_sessions WHERE id = ?", (sid,)
                ).fetchone()
                if row is None or row["status"] != "open" or not self._heard(row["machine"]):
                    return
                self._db.executemany(
                    "INSERT INTO live_samples VALUES (?, ?, ?, ?, ?) ON CONFLICT DO NOTHING",
                    samples,
                )
                self._db.executemany(
                    "INSERT INTO live_states VALUES (?, ?, ?) ON CONFLICT DO NOTHING", states
                )
                self._db.executemany(
                    "INSERT INTO live_events VALUES (?, ?, ?, ?) ON CONFLICT (session_id, "
                    "detected_s, state) DO UPDATE SET event_json = excluded.event_json",
                    alarms,
                )

        self.outbox.submit(write)

    def live_n_steps(self, session_id: int) -> int:
        """Samples stored of a session."""
        row = self._db.execute(
            "SELECT COUNT(*) FROM live_samples WHERE session_id = ?", (int(session_id),)
        ).fetchone()
        return int(row[0])

    def live_samples(self, session_id: int, first: int = 0, limit: int | None = None) -> list:
        """(step, time_s, inputs (3,), outputs (5,)) of a session's stored samples from step
        ``first`` on, in step order (at most ``limit``)."""
        query = (
            "SELECT step, time_s, inputs, outputs FROM live_samples WHERE session_id = ? "
            "AND step >= ? ORDER BY step"
        )
        args = [int(session_id), int(first)]
        if limit is not None:
            query += " LIMIT ?"
            args.append(int(limit))
        return [
            (int(r["step"]), float(r["time_s"]), from_npy(r["inputs"]), from_npy(r["outputs"]))
            for r in self._db.execute(query, args).fetchall()
        ]

    def live_states(self, session_id: int, after_step: int = -1) -> list[dict]:
        """The published messages of a session's committed steps after ``after_step``, in
        step order."""
        rows = self._db.execute(
            "SELECT message_json FROM live_states WHERE session_id = ? AND step > ? ORDER BY step",
            (int(session_id), int(after_step)),
        ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def live_events(self, session_id: int) -> list[dict]:
        """A session's alarm events (raised and final), in detection order."""
        rows = self._db.execute(
            "SELECT event_json FROM live_events WHERE session_id = ? ORDER BY detected_s, state",
            (int(session_id),),
        ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def live_close_session(self, session_id: int, print_id: int | None) -> None:
        """Mark a session closed, with the print it became (None: nothing stored), and give
        up the claim on its machine."""
        self.outbox.drain(SAVE_WAIT_S)
        with self._db.write(None):
            self._db.execute(
                "UPDATE live_sessions SET status = 'closed', print_id = ?, closed_at = ? "
                "WHERE id = ?",
                (print_id, time.time(), int(session_id)),
            )
            row = self._db.execute(
                "SELECT machine FROM live_sessions WHERE id = ?", (int(session_id),)
            ).fetchone()
            if row is not None:
                self.release_machine(row[0])

    def live_latest(self, session_id: int) -> tuple[int, dict | None]:
        """(samples stored, the last committed step's published message or None) of a
        session."""
        n = self.live_n_steps(session_id)
        row = self._db.execute(
            "SELECT message_json FROM live_states WHERE session_id = ? ORDER BY step DESC LIMIT 1",
            (int(session_id),),
        ).fetchone()
        return n, None if row is None else json.loads(row[0])

    # ------------------------------------------------------------------ compaction
    def print_rows(self, name: str) -> list[dict]:
        """``id``, ``seq``, ``ingested_at`` of the machine's prints, in seq order (nothing
        decoded)."""
        machine = self.machine(name)
        rows = self._db.execute(
            "SELECT id, seq, ingested_at FROM prints WHERE machine_id = ? ORDER BY seq",
            (machine["id"],),
        ).fetchall()
        return [dict(r) for r in rows]

    def stored_arrays(self, print_id: int, parts: bool = False) -> list[dict]:
        """The encoded array rows of a print (``name``, ``codec``, ``blob``): those stored
        whole, or with ``parts`` those written in parts (also ``part``), in order."""
        if parts:
            query = (
                "SELECT name, part, codec, blob FROM print_array_parts WHERE print_id = ? "
                "ORDER BY name, part"
            )
        else:
            query = "SELECT name, codec, npy AS blob FROM print_arrays WHERE print_id = ?"
        rows = self._db.execute(query, (int(print_id),)).fetchall()
        return [{**dict(r), "blob": bytes(r["blob"])} for r in rows]

    def print_bytes(self, print_id: int) -> int:
        """Bytes of a print's stored arrays (whole and in parts): what the storage policy
        keeps of it, whatever the database adds around it (pages, indexes)."""
        total = 0
        for table, column in (("print_arrays", "npy"), ("print_array_parts", "blob")):
            row = self._db.execute(
                f"SELECT COALESCE(SUM(LENGTH({column})), 0) FROM {table} WHERE print_id = ?",
                (int(print_id),),
            ).fetchone()
            total += int(row[0])
        return total

    def alarm_times(self, print_id: int) -> list[float]:
        """Detection and onset times [s] of a print's anomalies."""
        rows = self._db.execute(
            "SELECT detected_s, onset_s FROM anomalies WHERE print_id = ?", (int(print_id),)
        ).fetchall()
        return [float(t) for r in rows for t in (r[0], r[1])]

    def rewrite_arrays(self, print_id: int, rows: dict, *, from_parts: bool = False) -> None:
        """Replace a print's stored arrays by ``rows`` (name → (codec, blob)) in one
        transaction: all of them, or with ``from_parts`` the named ones, its parts then
        removed (the parts joined into whole arrays)."""
        pid = int(print_id)
        with self._db.write(f"print/{pid}"):
            if from_parts:
                self._db.execute(
                    "DELETE FROM print_arrays WHERE print_id = ? AND name IN "
                    f"({', '.join('?' * len(rows))})",
                    (pid, *rows),
                )
                self._db.execute("DELETE FROM print_array_parts WHERE print_id = ?", (pid,))
            else:
                self._db.execute("DELETE FROM print_arrays WHERE print_id = ?", (pid,))
            self._db.executemany(
                "INSERT INTO print_arrays (print_id, name, npy, codec) VALUES (?, ?, ?, ?)",
                [(pid, key, blob, codec) for key, (codec, blob) in rows.items()],
            )

    def drop_closed_live_steps(self, name: str) -> int:
        """Per-step rows (samples, published states) of machine ``name``'s closed live
        sessions whose print is stored; how many steps were dropped. One transaction."""
        machine = self.machine(name)
        with self._db.write(f"machine/{machine['id']}"):
            sessions = [
                r[0]
                for r in self._db.execute(
                    "SELECT s.id FROM live_sessions s JOIN prints p ON p.id = s.print_id "
                    "WHERE s.machine = ? AND s.status = 'closed' AND p.machine_id = ?",
                    (machine["name"], machine["id"]),
                ).fetchall()
            ]
            dropped = 0
            for session_id in sessions:
                dropped += self._db.execute(
                    "DELETE FROM live_samples WHERE session_id = ?", (session_id,)
                ).rowcount
                self._db.execute("DELETE FROM live_states WHERE session_id = ?", (session_id,))
        return dropped

    def size_bytes(self) -> int:
        """Bytes the registry takes: the SQLite file and its write-ahead log, or the
        registry's tables (rows, large values, indexes) on the PostgreSQL server."""
        return self._db.size_bytes(sorted(self._db.tables()))

    def free_bytes(self) -> int:
        """Bytes of an SQLite file's free pages (kept for later rows; 0 on PostgreSQL,
        whose autovacuum reuses space by itself)."""
        return self._db.free_bytes()

    def count_rows(self, table: str) -> int:
        """Rows of one of the registry's tables."""
        if table not in self._db.tables():
            raise RegistryError(f"{self.path}: no table {printable(table)!r}")
        return int(self._db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])

    def checkpointed_bytes(self) -> int:
        """Bytes of the registry once an SQLite file's write-ahead log is moved into it
        (PostgreSQL: :meth:`size_bytes`)."""
        if self.location.is_sqlite:
            self._db.checkpoint()
        return self.size_bytes()

    def compact_storage(self) -> None:
        """Rewrite the storage so that freed space is given back (SQLite: VACUUM, and
        incremental vacuum from then on; PostgreSQL: VACUUM of the registry's tables)."""
        self._db.compact_storage()

    # ------------------------------------------------------------------ copying
    def machine_rows(self, name: str, *, versions: bool = False):
        """Every row of machine ``name`` as (table, row dict), read in one snapshot, in an
        order a copy can insert them in: the machine; each print followed by its arrays,
        parts, anomalies and job (and with ``versions`` its reprocessed results and their
        rows); its calibrations and maintenance events; each live session followed by its
        samples, states and events. Drafts of running prints are not rows of a machine."""
        db = self._db
        with db.snapshot():
            machine = db.execute("SELECT * FROM machines WHERE name = ?", (name,)).fetchone()
            if machine is None:
                raise RegistryError(f"no machine {printable(name)!r} to copy")
            yield "machines", dict(machine)
            tables = db.tables()
            print_ids = [
                r[0]
                for r in db.execute(
                    "SELECT id FROM prints WHERE machine_id = ? ORDER BY id", (machine["id"],)
                ).fetchall()
            ]
            for print_id in print_ids:
                row = db.execute("SELECT * FROM prints WHERE id = ?", (print_id,)).fetchone()
                yield "prints", dict(row)
                for table in PRINT_TABLES:
                    if table in tables:
                        for r in db.execute(
                            f"SELECT * FROM {table} WHERE print_id = ?", (print_id,)
                        ).fetchall():
                            yield table, dict(r)
                if versions and "print_versions" in tables:
                    for r in db.execute(
                        "SELECT * FROM print_versions WHERE print_id = ? ORDER BY id", (print_id,)
                    ).fetchall():
                        yield "print_versions", dict(r)
                        for table in VERSION_TABLES:
                            for s in db.execute(
                                f"SELECT * FROM {table} WHERE print_version_id = ?", (r["id"],)
                            ).fetchall():
                                yield table, dict(s)
            for table in MACHINE_TABLES[1:]:
                if table in tables:
                    for r in db.execute(
                        f"SELECT * FROM {table} WHERE machine_id = ? ORDER BY id", (machine["id"],)
                    ).fetchall():
                        yield table, dict(r)
            if "live_sessions" in tables:
                sessions = db.execute(
                    "SELECT * FROM live_sessions WHERE machine = ? ORDER BY id", (name,)
                ).fetchall()
                for r in sessions:
                    yield "live_sessions", dict(r)
                    for table in LIVE_SESSION_TABLES:
                        if table in tables:
                            for s in db.execute(
                                f"SELECT * FROM {table} WHERE session_id = ?", (r["id"],)
                            ).fetchall():
                                yield table, dict(s)

    def load_machine(self, rows, new_name: str, *, keep_ids: bool = False, progress=None) -> dict:
        """Insert the rows of :meth:`machine_rows` (of another registry) as machine
        ``new_name``.

        Without ``keep_ids`` (``machine import``): new ids, in ONE transaction; refused if
        ``new_name`` exists or has an open live session here. With ``keep_ids``
        (``store copy``): every row keeps its id, each print with its rows in a transaction
        of its own, rows already here skipped — a copy stopped midway goes on where it
        stopped. ``progress(table)``: called after each print and session.

        Returns
        -------
        dict: ``prints``, ``live_sessions``, ``open_live_sessions`` (copied counts).
        """
        load = _MachineLoad(self._db, new_name, keep_ids)
        transaction = None
        try:
            if not keep_ids:
                transaction = self._db.write("import")
                transaction.__enter__()
            for table, row in rows:
                if keep_ids and table in ("prints", "live_sessions"):
                    if transaction is not None:  # the previous print or session is whole
                        transaction.__exit__(None, None, None)
                        if progress is not None:
                            progress(table)
                    load.skipping = table == "prints" and row["id"] in load.known_prints
                    transaction = None
                    if not load.skipping:
                        transaction = self._db.write(f"copy/{table}/{row['id']}")
                        transaction.__enter__()
                load.add(table, dict(row))
            if transaction is not None:
                transaction.__exit__(None, None, None)
                transaction = None
                if progress is not None and keep_ids:
                    progress("end")
        except BaseException as exc:
            if transaction is not None:
                transaction.__exit__(type(exc), exc, exc.__traceback__)
            raise
        finally:
            close = getattr(rows, "close", None)
            if close is not None:  # the source's read snapshot ends here
                close()
        if keep_ids:
            for table in ("machines", "prints", "anomalies", "calibrations",
                          "maintenance_events", "live_sessions", "print_versions",
                          "print_version_anomalies"):  # fmt: skip
                if table in load.columns:
                    self._db.identity_set(table)
        return load.counts

    def version_rows(self) -> list[dict]:
        """The ``versions`` rows (what ``store copy`` carries before the machines)."""
        return [dict(r) for r in self._db.execute("SELECT * FROM versions ORDER BY id")]

    def load_versions(self, rows) -> None:
        """Insert ``versions`` rows of another registry, ids kept (``store copy``)."""
        with self._db.write("versions"):
            for row in rows:
                keys = list(row)
                self._db.execute(
                    f"INSERT INTO versions ({', '.join(keys)}) VALUES "
                    f"({', '.join('?' * len(keys))}) ON CONFLICT DO NOTHING",
                    [row[k] for k in keys],
                )
            self._db.identity_set("versions")

    def mark_copy(self, source_id: str, state: str) -> None:
        """Note in this registry that it is (``running``) or was (``done``) copied from the
        registry ``source_id`` (its ``info.registry_id``)."""
        with self._db.write("copy"):
            set_info(self._db, "copy_of", source_id)
            set_info(self._db, "copy_state", state)

    def table_digest(self, table: str) -> tuple[int, str]:
        """(rows, SHA-256) of ``table``'s content, independent of row order and of the
        database (integers, floats to the bit, text, bytes): two registries hold the same
        rows when their digests agree. Drafts' parts are left out."""
        where = " WHERE print_id >= 0" if table == "print_array_parts" else ""
        digests = []
        for row in self._db.execute(f"SELECT * FROM {table}{where}"):
            h = hashlib.sha256()
            for value in row:
                h.update(_canonical(value))
            digests.append(h.digest())
        digests.sort()
        whole = hashlib.sha256(b"".join(digests)).hexdigest()
        return len(digests), whole


#: the tables whose rows belong to one print (copied with it, in its transaction)
_PRINT_SCOPED = {"prints", "print_versions", *PRINT_TABLES, *VERSION_TABLES}


class _MachineLoad:
    """The rows of one machine going into a registry (:meth:`Registry.load_machine`): each
    row's ids renumbered (import) or kept (copy), inserted, counted."""

    def __init__(self, db, new_name: str, keep_ids: bool):
        self.db, self.new_name, self.keep_ids = db, new_name, keep_ids
        self.ids: dict[str, dict] = {"machines": {}, "prints": {}, "print_versions": {},
                                     "live_sessions": {}}  # fmt: skip
        self.counts = {"prints": 0, "live_sessions": 0, "open_live_sessions": 0}
        self.columns = {t: db.columns(t) for t in db.tables()}
        self.skipping = False  # the print whose rows come is here already (a resumed copy)
        self.known_prints: set = set()
        if keep_ids:
            self.known_prints = {
                r[0]
                for r in db.execute(
                    "SELECT p.id FROM prints p JOIN machines m ON m.id = p.machine_id "
                    "WHERE m.name = ?",
                    (new_name,),
                ).fetchall()
            }

    def add(self, table: str, row: dict) -> None:
        """One row of the source machine (in :meth:`Registry.machine_rows` order)."""
        if table == "machines":
            self._machine(row)
            return
        if table not in _PRINT_SCOPED:
            self.skipping = False  # the machine's other rows: copied (or already here)
        if self.skipping:
            self.counts["prints"] += table == "prints"
            return
        if not self.keep_ids and table in ("print_versions", *VERSION_TABLES):
            return  # an export carries the prints as stored (the archive's docstring)
        self._renumber(table, row)
        new_id = self._insert(table, row)
        if table in self.ids:
            self.ids[table][row["id"]] = new_id
        self.counts["prints"] += table == "prints"

    def _machine(self, row: dict) -> None:
        old = row["id"]
        here = self.db.execute(
            "SELECT id, created_at FROM machines WHERE name = ?", (self.new_name,)
        ).fetchone()
        same = here is not None and here["id"] == old and here["created_at"] == row["created_at"]
        if here is not None and not (self.keep_ids and same):
            raise RegistryError(
                f"machine {printable(self.new_name)!r} already exists; import it under "
                "another name with --as NAME"
            )
        open_here = self.db.execute(
            "SELECT 1 FROM live_sessions WHERE machine = ? AND status = 'open'", (self.new_name,)
        ).fetchone()
        if open_here is not None and not self.keep_ids:
            raise RegistryError(
                f"an open live session of {printable(self.new_name)!r} is in this registry; "
                "import the machine under another name with --as NAME"
            )
        row["name"] = self.new_name
        self.ids["machines"][old] = self._insert("machines", row)

    def _renumber(self, table: str, row: dict) -> None:
        """The row's references to the machine, its print, result or live session, as here."""
        ids = self.ids
        if "machine_id" in row and table != "live_sessions":
            row["machine_id"] = ids["machines"][row["machine_id"]]
        if table in PRINT_TABLES or table == "print_versions":
            row["print_id"] = ids["prints"].get(row["print_id"], row["print_id"])
        if table in VERSION_TABLES:
            old = row["print_version_id"]
            row["print_version_id"] = ids["print_versions"].get(old, old)
        if table in LIVE_SESSION_TABLES:
            row["session_id"] = ids["live_sessions"][row["session_id"]]
        if table == "live_sessions":
            row["machine"] = self.new_name
            if row.get("print_id") is not None:
                old = row["print_id"]
                row["print_id"] = ids["prints"].get(old, old if self.keep_ids else None)
            self.counts["live_sessions"] += 1
            self.counts["open_live_sessions"] += row["status"] == "open"

    def _insert(self, table: str, row: dict):
        keys = [c for c in self.columns[table] if c in row]
        if not self.keep_ids:
            return self.db.insert(table, {k: row[k] for k in keys if k != "id"},
                                  returning_id="id" in self.columns[table])  # fmt: skip
        self.db.execute(
            f"INSERT INTO {table} ({', '.join(keys)}) VALUES ({', '.join('?' * len(keys))}) "
            "ON CONFLICT DO NOTHING",
            [row[k] for k in keys],
        )
        return row.get("id")


def _anomaly_values(ev) -> tuple:
    """An anomaly event's columns after the print's (or version's) id."""
    return (
        ev.detected_s,
        ev.onset_s,
        ev.cause,
        ev.description,
        ", ".join(ev.detectors),
        json.dumps(ev.evidence),
    )


def _canonical(value) -> bytes:
    """Bytes of one stored value, the same from SQLite and PostgreSQL (table digests)."""
    if value is None:
        return b"N;"
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, int):
        return b"I" + str(value).encode() + b";"
    if isinstance(value, float):
        return b"F" + float(value).hex().encode() + b";"
    if isinstance(value, bytes | bytearray | memoryview):
        raw = bytes(value)
        return b"B" + str(len(raw)).encode() + b":" + raw
    text = str(value).encode()
    return b"T" + str(len(text)).encode() + b":" + text


def _iso(unix: float) -> str:
    return _dt.datetime.fromtimestamp(unix, _dt.UTC).isoformat(timespec="seconds")
