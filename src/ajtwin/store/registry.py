"""The machine registry: one twin per physical printer, kept in SQLite.

Each machine has a history of ingested prints. A print row keeps the print's metadata,
its content hash (idempotency), the twin's start and end state (mean, covariance), θ
before and after, a summary and a chain status; the per-second estimates (states, σ,
predicted outputs, NIS, θ history, covariance key frames) are stored as compressed
array blobs (:mod:`ajtwin.store.arrays`); anomalies as rows. The next print of a machine
starts from the end state and θ of the last print *in the chain* (``status = 'ok'``): a
print whose states left the physical range is kept for history but marked
``excluded`` and never becomes a start (:mod:`ajtwin.engine.chain`).

Guarantees
----------
* **Crash-safe**: one transaction per ingest (``BEGIN IMMEDIATE`` … ``COMMIT``); a process
  killed inside it leaves the store as it was (SQLite rolls back on the next open).
* **Idempotent**: ``UNIQUE(machine, content_hash)``; ingesting the same print again is
  detected before the twin runs.
* **Readable while written**: WAL journal mode; readers see the last committed state and
  never wait for a writer.
* **Never takes over another database**: a file that is not an ajtwin registry (an
  unrelated SQLite database, a FIFO, a directory) is refused with a message and left
  untouched (no table added, journal mode unchanged). Read-only commands never create a
  file or folder (``create=False``).
* **Versioned**: ``info.schema_version``; an older registry is migrated in one
  transaction on open (with a message in :attr:`Registry.migrated`), a newer one refused.

Adding a migration (how to change the schema)
---------------------------------------------
The schema is the version-1 statements (:data:`_SCHEMA_V1`, what ajtwin 0.x wrote) plus
every entry of :data:`MIGRATIONS` in order; a new registry runs them all, an old one the
missing ones, so a table you add exists in both. To add one:

1. Write ``def _migrate_to_N(conn): ...`` using ``CREATE TABLE IF NOT EXISTS`` /
   ``ALTER TABLE ... ADD COLUMN`` (with a ``DEFAULT`` so old rows stay valid). It runs
   inside the migration's transaction: never ``COMMIT``, never ``executescript``.
2. Append ``(N, "one line saying what it adds", _migrate_to_N)`` to :data:`MIGRATIONS`,
   N = last version + 1 (if two branches both added N, the merge renumbers one of them).
   :data:`SCHEMA_VERSION` follows automatically.
3. A machine-scoped table (a ``machine_id`` column) must be added to
   :data:`MACHINE_TABLES` (a print-scoped one, ``print_id``, to :data:`PRINT_TABLES`; one
   scoped to a live session, ``session_id``, to :data:`LIVE_SESSION_TABLES`) so that
   ``machine export/import`` carry it.
4. Test it in tests/test_store_reliability.py: a registry of the previous version opens,
   migrates and keeps its prints.

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
import socket
import sqlite3
import stat
import time
import unicodedata
import zlib
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.model.limits import DEFAULT_LIMITS
from ajtwin.model.names import STATE_NAMES
from ajtwin.store import arrays as _arrays
from ajtwin.store.connection import (
    RegistryError,
    check_integrity,
    check_writable,
    connect,
    repair_journal_modes,
    rollback_if_open,
)

#: environment variable: seconds to sleep inside the ingest transaction (crash tests only)
TEST_SLEEP_ENV = "AJTWIN_STORE_TEST_SLEEP_IN_TRANSACTION"
#: ``info.application`` of an ajtwin registry (schema ≥ 2)
APPLICATION = "ajtwin-registry"

#: Version 1 (ajtwin before the reliability work): never edit, add a migration instead.
_SCHEMA_V1 = """
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
_V1_TABLES = {"info", "machines", "prints", "print_arrays", "anomalies"}

#: Chain status of a print: in the chain, or kept for history only.
STATUS_OK = "ok"
STATUS_EXCLUDED = "excluded"  # its states left the physical range (set at ingest)
STATUS_DROPPED = "dropped"  # taken out by `ajtwin machine drop`


def _execute_all(conn, script: str):
    # executescript would COMMIT: run each statement inside the caller's transaction
    for statement in script.split(";"):
        if statement.strip():
            conn.execute(statement)


def _migrate_to_2(conn):
    """Print chain status, array codecs, the anomaly index, the application marker."""
    conn.execute(f"ALTER TABLE prints ADD COLUMN status TEXT NOT NULL DEFAULT '{STATUS_OK}'")
    conn.execute("ALTER TABLE prints ADD COLUMN status_reason TEXT NOT NULL DEFAULT ''")
    conn.execute(f"ALTER TABLE print_arrays ADD COLUMN codec TEXT NOT NULL DEFAULT '{_arrays.NPY}'")
    conn.execute("CREATE INDEX IF NOT EXISTS anomalies_by_print ON anomalies(print_id)")
    conn.execute("INSERT OR REPLACE INTO info VALUES ('application', ?)", (APPLICATION,))


def _exclude_impossible_ends(conn, end_state_check) -> None:
    """Prints of a version-1 registry (stored before the chain's range check) whose end state
    ``end_state_check`` rejects leave the chain, the reason kept; inside the migration's
    transaction. The judgement is the caller's: the store holds no physics."""
    rows = conn.execute("SELECT id, end_mean FROM prints").fetchall()
    for print_id, blob in rows:
        try:
            problems = end_state_check(_arrays.decode(blob, _arrays.NPY))
        except ValueError as exc:
            problems = [f"unreadable end state ({exc})"]
        if problems:
            conn.execute(
                "UPDATE prints SET status = ?, status_reason = ? WHERE id = ?",
                (STATUS_EXCLUDED, "migration: end state " + "; ".join(problems), print_id),
            )


#: The live twin's log (:mod:`ajtwin.store.live_log`): a session per live print of a
#: machine (keyed by the machine's *name*, as the live link knows it), its samples, the
#: published state of every committed step and its alarms. Never edit: add a migration.
_LIVE_SCHEMA = """
CREATE TABLE IF NOT EXISTS live_sessions (
    id INTEGER PRIMARY KEY,
    machine TEXT NOT NULL,
    started_at REAL NOT NULL,
    source TEXT NOT NULL,
    status TEXT NOT NULL,
    start_mean BLOB,
    start_cov BLOB,
    theta_before BLOB NOT NULL,
    expected_last_seq INTEGER,
    print_id INTEGER,
    closed_at REAL
);
CREATE TABLE IF NOT EXISTS live_samples (
    session_id INTEGER NOT NULL REFERENCES live_sessions(id),
    step INTEGER NOT NULL,
    time_s REAL NOT NULL,
    inputs BLOB NOT NULL,
    outputs BLOB NOT NULL,
    PRIMARY KEY (session_id, step)
);
CREATE TABLE IF NOT EXISTS live_states (
    session_id INTEGER NOT NULL REFERENCES live_sessions(id),
    step INTEGER NOT NULL,
    message_json TEXT NOT NULL,
    PRIMARY KEY (session_id, step)
);
CREATE TABLE IF NOT EXISTS live_events (
    session_id INTEGER NOT NULL REFERENCES live_sessions(id),
    detected_s REAL NOT NULL,
    state TEXT NOT NULL,
    event_json TEXT NOT NULL,
    PRIMARY KEY (session_id, detected_s, state)
);
CREATE INDEX IF NOT EXISTS live_sessions_by_machine ON live_sessions(machine, status)
"""


def _migrate_to_3(conn):
    """The live twin's session tables (a registry the live twin already wrote keeps them)."""
    _execute_all(conn, _LIVE_SCHEMA)


#: A machine's calibrations (one row per commissioning, the newest active) and its
#: maintenance events (:mod:`ajtwin.store.calibration`, model reference §11). Never edit: add a
#: migration.
_CALIBRATION_SCHEMA = """
CREATE TABLE IF NOT EXISTS calibrations (
    id INTEGER PRIMARY KEY,
    machine_id INTEGER NOT NULL REFERENCES machines(id),
    created_at TEXT NOT NULL,
    created_unix REAL NOT NULL,
    source TEXT NOT NULL,
    after_print_seq INTEGER NOT NULL,
    calibration_json TEXT NOT NULL,
    std_json TEXT NOT NULL,
    prior_std_json TEXT NOT NULL,
    determined_json TEXT NOT NULL,
    priors_json TEXT NOT NULL,
    notes_json TEXT NOT NULL,
    end_mean_json TEXT NOT NULL,
    end_cov_json TEXT NOT NULL,
    calibration_cov_json TEXT NOT NULL,
    noise_factors_json TEXT NOT NULL DEFAULT 'null'
);
CREATE TABLE IF NOT EXISTS maintenance_events (
    id INTEGER PRIMARY KEY,
    machine_id INTEGER NOT NULL REFERENCES machines(id),
    created_at TEXT NOT NULL,
    created_unix REAL NOT NULL,
    after_print_seq INTEGER NOT NULL,
    event_json TEXT NOT NULL
)
"""


def _migrate_to_4(conn):
    """Calibrations and maintenance events. A schema-3 registry that already has them
    (ajtwin's calibration code created them on first write) keeps its rows; one written
    before ``noise_factors_json`` existed gets that column with its default."""
    _execute_all(conn, _CALIBRATION_SCHEMA)
    columns = {r[1] for r in conn.execute("PRAGMA table_info(calibrations)").fetchall()}
    if "noise_factors_json" not in columns:
        conn.execute(
            "ALTER TABLE calibrations ADD COLUMN noise_factors_json TEXT NOT NULL DEFAULT 'null'"
        )


def _migrate_to_5(conn):
    """The anomaly detectors' long-run statistics (``long_run_json``, JSON, 'null' for rows
    written before): per print, what it leaves the machine's next print; per calibration,
    what the commissioning print showed (:func:`ajtwin.engine.start.carried_long_run_history`)."""
    for table in ("prints", "calibrations"):
        columns = {r[1] for r in conn.execute(f"PRAGMA table_info({table})").fetchall()}
        if "long_run_json" not in columns:
            conn.execute(
                f"ALTER TABLE {table} ADD COLUMN long_run_json TEXT NOT NULL DEFAULT 'null'"
            )


#: The job a print ran (``ajtwin ingest --job``): the machine program's bytes (zlib), its
#: file name and SHA-256, and how the print ran it (speeds, looping, the part's tolerance) as
#: JSON. One row per print at most. Never edit: add a migration.
_PRINT_JOB_SCHEMA = """
CREATE TABLE IF NOT EXISTS print_jobs (
    print_id INTEGER PRIMARY KEY REFERENCES prints(id),
    program TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    program_blob BLOB NOT NULL,
    settings_json TEXT NOT NULL
)
"""


#: A print's per-second arrays written while the print runs (a long ingest, a live print):
#: parts of consecutive steps, each encoded as ``print_arrays`` are (ajtwin.store.arrays).
#: Until the print is stored they belong to a draft (``print_id`` = −draft id: no foreign
#: key), and the transaction that stores the print moves them to it. A draft whose process
#: died is removed by the next ingest, live start or ``machine compact``. Never edit: add
#: a migration.
_PARTS_SCHEMA = """
CREATE TABLE IF NOT EXISTS array_drafts (
    id INTEGER PRIMARY KEY,
    machine TEXT NOT NULL,
    label TEXT NOT NULL,
    created_unix REAL NOT NULL,
    pid INTEGER NOT NULL,
    host TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS print_array_parts (
    print_id INTEGER NOT NULL,
    name TEXT NOT NULL,
    part INTEGER NOT NULL,
    codec TEXT NOT NULL,
    blob BLOB NOT NULL,
    PRIMARY KEY (print_id, name, part)
)
"""


def _migrate_to_6(conn):
    """The job a print ran (``print_jobs``); older prints have none (no row)."""
    _execute_all(conn, _PRINT_JOB_SCHEMA)


def _migrate_to_7(conn):
    """Print arrays written in parts while a print runs (array_drafts, print_array_parts)."""
    _execute_all(conn, _PARTS_SCHEMA)


#: (version, what it adds, function(conn)); append only (see the module docstring).
MIGRATIONS: list[tuple[int, str, object]] = [
    (2, "print chain status, compressed arrays, anomaly index", _migrate_to_2),
    (3, "live twin sessions: live_sessions, live_samples, live_states, live_events", _migrate_to_3),
    (4, "per-machine calibrations and maintenance events", _migrate_to_4),
    (5, "the detectors' long-run noise statistics per print and calibration", _migrate_to_5),
    (6, "the job (machine program) each print ran: print_jobs", _migrate_to_6),
    (7, "print arrays written in parts while a print runs", _migrate_to_7),
]
SCHEMA_VERSION = MIGRATIONS[-1][0] if MIGRATIONS else 1

#: Tables with a ``machine_id`` column / a ``print_id`` column (export, import, delete).
#: Copied in this order, each in its ``id`` order (the newest calibration stays active).
MACHINE_TABLES = ["prints", "calibrations", "maintenance_events"]
PRINT_TABLES = ["print_arrays", "print_array_parts", "anomalies", "print_jobs"]
#: Tables with a ``session_id`` column (rows of one ``live_sessions`` row). The sessions
#: themselves are found by ``live_sessions.machine`` (a name) and copied, renamed and with
#: ``print_id`` renumbered, by :func:`ajtwin.store.archive.copy_machine`.
LIVE_SESSION_TABLES = ["live_samples", "live_states", "live_events"]


def default_store_path() -> Path:
    """``$AJTWIN_STORE``, else ``$XDG_DATA_HOME/ajtwin/registry.sqlite``, else
    ``~/.local/share/ajtwin/registry.sqlite``."""
    env = os.environ.get("AJTWIN_STORE")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base).expanduser() / "ajtwin" / "registry.sqlite"


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
    """A SQLite machine registry (see module docstring).

    Parameters
    ----------
    path : str or Path, optional
        Database file; default :func:`default_store_path`.
    timeout_s : float
        How long a writer waits for another writer's transaction.
    create : bool
        Create the file (and its folder) when it does not exist; read-only commands pass
        False and get a :class:`RegistryError` instead.
    policy : arrays.StoragePolicy, optional
        How per-second arrays are stored (default :class:`ajtwin.store.arrays.StoragePolicy`).
    write : bool
        The caller will write: refuse at once (:class:`~ajtwin.store.connection.StoreError`)
        when this process cannot write the file, its journal or its folder
        (:func:`~ajtwin.store.connection.check_writable`), before any work is done.
    end_state_check : callable, optional
        ``end_state_check(end_mean (5,)) -> list of problems``: when a version-1 registry is
        migrated, its prints whose end state this rejects are excluded from the chain
        (:func:`ajtwin.engine.chain.open_registry` passes the physical range check).
        Without it they keep their status (the engine's chain start refuses such a start
        anyway).

    Attributes
    ----------
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
        self.path = Path(path) if path is not None else default_store_path()
        self.policy = policy or _arrays.StoragePolicy()
        self.end_state_check = end_state_check
        self.migrated: list[str] = []
        self._conn = None
        exists = os.path.lexists(self.path)
        if exists:
            try:
                mode = os.stat(self.path).st_mode
            except OSError as exc:
                raise RegistryError(f"{self.path}: cannot open the registry ({exc})") from None
            if not stat.S_ISREG(mode):
                kind = "a directory" if stat.S_ISDIR(mode) else "not a regular file"
                raise RegistryError(
                    f"{self.path}: is {kind} (a FIFO, device or socket?); "
                    "a registry must be an ordinary file"
                )
        elif not create:
            raise RegistryError(
                f"no registry at {self.path}; create one with `ajtwin machine add NAME "
                f"--store {self.path}` (read-only commands never create it)"
            )
        if write or (create and not exists):
            check_writable(self.path)
        if not exists:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise RegistryError(f"{self.path}: cannot create its folder ({exc})") from None
        try:
            self._conn = connect(self.path, timeout_s)
            check_integrity(self._conn, self.path)
            self._open(create)
            if write:  # the lock a write takes (a read-only mount, another writer's hold)
                self._conn.execute("BEGIN IMMEDIATE")
                self._conn.execute("ROLLBACK")
        except RegistryError:
            self.close()
            raise
        except sqlite3.Error as exc:
            self.close()
            raise RegistryError(f"{self.path}: not a usable ajtwin registry ({exc})") from None
        finally:
            repair_journal_modes(self.path)

    # ------------------------------------------------------------------ opening
    def _tables(self) -> set[str]:
        rows = self._conn.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'"
        ).fetchall()
        return {r[0] for r in rows}

    def _info(self, key: str):
        row = self._conn.execute("SELECT value FROM info WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]

    def _recognise(self, tables: set[str]) -> int | None:
        """Schema version of an ajtwin registry, None for an empty database; refuse others."""
        if not tables:
            return None
        if "info" not in tables:
            raise RegistryError(self._foreign(tables))
        try:
            version_text = self._info("schema_version")
            application = self._info("application")
        except sqlite3.Error:
            raise RegistryError(self._foreign(tables)) from None
        if application is None and not (_V1_TABLES <= tables and version_text == "1"):
            # version 1 had no application marker: recognise it by its exact tables
            raise RegistryError(self._foreign(tables))
        if application is not None and application != APPLICATION:
            raise RegistryError(self._foreign(tables))
        if not _V1_TABLES <= tables:
            raise RegistryError(
                f"{self.path}: registry damaged: tables {sorted(_V1_TABLES - tables)} are "
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
        return (
            f"{self.path}: an SQLite database but not an ajtwin registry (tables: {shown}); "
            "refusing to change it; give another --store path"
        )

    def _open(self, create: bool):
        version = self._recognise(self._tables())
        if version is None and not create:
            raise RegistryError(
                f"no registry in {self.path} (an empty file); create one with "
                f"`ajtwin machine add NAME --store {self.path}`"
            )
        if version is None:
            # a new registry returns the pages it frees (a closed live session's per-step
            # rows) to the file system: release_free_pages(); must precede the first table
            # and the journal mode (an existing registry gets it from `machine compact`)
            self._conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
        # only now, on our own file, change its journal mode
        self._conn.execute("PRAGMA journal_mode=WAL")
        self._conn.execute("PRAGMA foreign_keys=ON")
        self._conn.execute("PRAGMA synchronous=NORMAL")
        if version == SCHEMA_VERSION:
            return
        self._conn.execute("BEGIN IMMEDIATE")
        try:
            # another process may have created or migrated it while we waited
            version = self._recognise(self._tables())
            fresh = version is None
            if fresh:
                _execute_all(self._conn, _SCHEMA_V1)
                self._conn.execute("INSERT INTO info VALUES ('schema_version', '1')")
                version = 1
            for target, what, function in MIGRATIONS:
                if target <= version:
                    continue
                function(self._conn)
                self._conn.execute(
                    "UPDATE info SET value = ? WHERE key = 'schema_version'", (str(target),)
                )
                if not fresh:
                    self.migrated.append(
                        f"{self.path}: migrated registry schema {version} → {target} ({what})"
                    )
                if target == 2 and not fresh and self.end_state_check is not None:
                    _exclude_impossible_ends(self._conn, self.end_state_check)
                version = target
            if not fresh:
                missing = _V1_TABLES - self._tables()
                if missing:
                    raise RegistryError(
                        f"{self.path}: registry damaged: tables {sorted(missing)} are missing"
                    )
            self._conn.execute("COMMIT")
        except BaseException:
            rollback_if_open(self._conn)
            self.migrated = []
            raise

    def close(self):
        """Close the connection (a closed registry cannot be used again)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
            repair_journal_modes(self.path)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

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
            self._conn.execute(
                "INSERT INTO machines (name, created_at, limits_json, notes) VALUES (?, ?, ?, ?)",
                (name, _now(), json.dumps(merged), notes),
            )
        except sqlite3.IntegrityError:
            raise RegistryError(
                f"machine {printable(name)!r} already exists in {self.path}"
            ) from None
        return self.machine(name)

    def machine(self, name: str) -> dict:
        """The machine's row with its limits and print count (RegistryError: unknown)."""
        name = str(name).strip()
        row = self._conn.execute("SELECT * FROM machines WHERE name = ?", (name,)).fetchone()
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
        count = self._conn.execute(
            "SELECT COUNT(*) FROM prints WHERE machine_id = ?", (out["id"],)
        ).fetchone()[0]
        out["n_prints"] = int(count)
        return out

    def machines(self) -> list[dict]:
        """Every machine's name and creation time, by name."""
        rows = self._conn.execute("SELECT name, created_at FROM machines ORDER BY name").fetchall()
        return [dict(r) for r in rows]

    # ------------------------------------------------------------------ prints
    def _damaged(self, row, column, exc) -> RegistryError:
        return RegistryError(
            f"{self.path}: registry damaged at print {row['seq']} (id {row['id']}), "
            f"column {column}: {exc}; drop it with `ajtwin machine drop` or restore a backup"
        )

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
            if key not in out:  # a query that selected only some columns
                continue
            try:
                value = _arrays.decode(out[key], _arrays.NPY)
                expected = (5, 5) if key.endswith("_cov") else (5,)
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
        row = self._conn.execute(
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
        for row in self._conn.execute(query + " ORDER BY seq DESC", args).fetchall():
            yield self._print_row(row)

    def find_print(self, name: str, content_hash: str) -> dict | None:
        """The machine's print with this content hash (None: not ingested)."""
        machine = self.machine(name)
        row = self._conn.execute(
            "SELECT * FROM prints WHERE machine_id = ? AND content_hash = ?",
            (machine["id"], content_hash),
        ).fetchone()
        return None if row is None else self._print_row(row)

    def get_print(self, print_id: int) -> dict:
        """The print with this id (RegistryError when there is none)."""
        row = self._conn.execute("SELECT * FROM prints WHERE id = ?", (print_id,)).fetchone()
        if row is None:
            raise RegistryError(f"no print with id {print_id}")
        return self._print_row(row)

    def print_by_seq(self, name: str, seq: int) -> dict:
        """The machine's print number ``seq`` (RegistryError saying how many it has)."""
        machine = self.machine(name)
        row = None
        if -(2**63) <= int(seq) < 2**63:  # beyond SQLite's integers there is no print
            row = self._conn.execute(
                "SELECT * FROM prints WHERE machine_id = ? AND seq = ?", (machine["id"], int(seq))
            ).fetchone()
        if row is None:
            raise RegistryError(
                f"machine {printable(machine['name'])!r} has no print #{seq} "
                f"(it has {machine['n_prints']})"
            )
        return self._print_row(row)

    def print_arrays(self, print_id: int) -> dict[str, np.ndarray]:
        """The print's per-second arrays, decoded (see :mod:`ajtwin.store.arrays`).

        ``predicted_means`` is rebuilt from the stored means and corrections; covariances
        are ``covariance_keyframes`` (K, 5, 5) at ``covariance_steps`` (K,) unless the
        print was stored with the whole sequence (``covariances``, T × 5 × 5).
        """
        rows = self._conn.execute(
            "SELECT name, npy, codec FROM print_arrays WHERE print_id = ?", (print_id,)
        ).fetchall()
        out = {r["name"]: self._decoded(print_id, r["name"], r["npy"], r["codec"]) for r in rows}
        parts: dict[str, list] = {}
        for r in self._conn.execute(
            "SELECT name, codec, blob FROM print_array_parts WHERE print_id = ? "
            "ORDER BY name, part",
            (print_id,),
        ).fetchall():
            decoded = self._decoded(print_id, r["name"], r["blob"], r["codec"])
            parts.setdefault(r["name"], []).append(decoded)
        out.update(_arrays.join_parts(parts))
        return _arrays.expand(out)

    def print_array(self, print_id: int, name: str) -> np.ndarray | None:
        """One stored array of a print, decoded without loading the others, whether it was
        written whole or in parts (None: not stored)."""
        row = self._conn.execute(
            "SELECT npy, codec FROM print_arrays WHERE print_id = ? AND name = ?",
            (print_id, name),
        ).fetchone()
        if row is not None:
            return self._decoded(print_id, name, row["npy"], row["codec"])
        parts = [
            self._decoded(print_id, name, r["blob"], r["codec"])
            for r in self._conn.execute(
                "SELECT codec, blob FROM print_array_parts WHERE print_id = ? AND name = ? "
                "ORDER BY part",
                (print_id, name),
            ).fetchall()
        ]
        return _arrays.join_parts({name: parts})[name] if parts else None

    def _decoded(self, print_id: int, name: str, blob, codec: str) -> np.ndarray:
        """A stored array decoded (RegistryError naming the print and array if damaged)."""
        try:
            return _arrays.decode(blob, codec)
        except ValueError as exc:
            seq = self._conn.execute("SELECT seq FROM prints WHERE id = ?", (print_id,)).fetchone()
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
        cur = self._conn.execute(
            "INSERT INTO array_drafts (machine, label, created_unix, pid, host) "
            "VALUES (?, ?, ?, ?, ?)",
            (str(machine), str(label), time.time(), os.getpid(), socket.gethostname()),
        )
        return int(cur.lastrowid)

    def append_draft(self, draft: int, arrays: dict, part: dict, alarm_times=()) -> int:
        """Write one part of a running print's arrays (consecutive steps) to ``draft``, in
        its own short transaction; the bytes written.

        ``part``: ``first_step``, ``origin_s``, ``after_s``, ``last`` as
        :func:`ajtwin.store.arrays.encode_all` takes them; the arrays are stored by
        :attr:`policy` (key frames of the covariances as the whole print would have them).
        """
        encoded = _arrays.encode_all(arrays, self.policy, alarm_times, part=part)
        conn = self._conn
        conn.execute("BEGIN IMMEDIATE")
        try:
            if conn.execute("SELECT 1 FROM array_drafts WHERE id = ?", (draft,)).fetchone() is None:
                raise RegistryError(f"draft {draft} is not open (stored or discarded)")
            row = conn.execute(
                "SELECT COALESCE(MAX(part), -1) + 1 FROM print_array_parts WHERE print_id = ?",
                (-int(draft),),
            ).fetchone()
            conn.executemany(
                "INSERT INTO print_array_parts (print_id, name, part, codec, blob) "
                "VALUES (?, ?, ?, ?, ?)",
                [(-int(draft), key, row[0], c, b) for key, (c, b) in encoded.items()],
            )
            conn.execute("COMMIT")
        except BaseException:
            rollback_if_open(conn)
            raise
        return sum(len(b) for _, b in encoded.values())

    def discard_draft(self, draft: int) -> None:
        """Remove a draft and its parts (a print that failed or was refused)."""
        conn = self._conn
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.execute("DELETE FROM print_array_parts WHERE print_id = ?", (-int(draft),))
            conn.execute("DELETE FROM array_drafts WHERE id = ?", (int(draft),))
            conn.execute("COMMIT")
        except BaseException:
            rollback_if_open(conn)
            raise

    def discard_drafts(self, machine: str, label: str) -> int:
        """Remove the drafts of ``machine`` with ``label`` (a live session replayed from its
        samples writes its parts again); how many."""
        rows = self._conn.execute(
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
            for r in self._conn.execute("SELECT id, pid, host FROM array_drafts").fetchall()
            if r["host"] == host and not _process_alive(r["pid"])
        ]
        for draft in stale:
            self.discard_draft(draft)
        return len(stale)

    def long_run_history(self, name: str) -> tuple[int, dict] | None:
        """(seq, statistics) of the detectors' long-run statistics stored with the newest
        print in the chain that has them (None: no such print)."""
        machine = self.machine(name)
        row = self._conn.execute(
            "SELECT id, seq, long_run_json FROM prints WHERE machine_id = ? AND status = ? "
            "AND long_run_json != 'null' ORDER BY seq DESC LIMIT 1",
            (machine["id"], STATUS_OK),
        ).fetchone()
        if row is None:
            return None
        try:
            return int(row["seq"]), json.loads(row["long_run_json"])
        except ValueError as exc:
            raise self._damaged(row, "long_run_json", exc) from None

    def history(self, name: str) -> pd.DataFrame:
        """One row per print: seq, id, time, duration, source, the program it ran ("" when
        stored without a job), status, end states, θ, anomaly count."""
        machine = self.machine(name)
        rows = self._conn.execute(
            "SELECT p.id, p.seq, p.ingested_at, p.source, p.duration_s, p.meta_json, p.status,"
            " p.status_reason, p.end_mean, p.theta_after, j.program,"
            " (SELECT COUNT(*) FROM anomalies a WHERE a.print_id = p.id) AS n_anomalies"
            " FROM prints p LEFT JOIN print_jobs j ON j.print_id = p.id"
            " WHERE machine_id = ? ORDER BY seq",
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
                "scenario": p["meta"].get("scenario") if isinstance(p["meta"], dict) else None,
                "program": row["program"] or "",
                "anomalies": int(row["n_anomalies"]),
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

    def set_status(self, name: str, seq: int, status: str, reason: str = "") -> dict:
        """Put print ``seq`` in (``ok``) or out of (``dropped``/``excluded``) the chain.

        The print and its arrays stay (history); only the next ingest's start changes.
        """
        if status not in (STATUS_OK, STATUS_EXCLUDED, STATUS_DROPPED):
            raise RegistryError(f"unknown print status {status!r}")
        p = self.print_by_seq(name, seq)
        self._conn.execute(
            "UPDATE prints SET status = ?, status_reason = ? WHERE id = ?",
            (status, reason, p["id"]),
        )
        return self.get_print(p["id"])

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
        status: str = STATUS_OK,
        status_reason: str = "",
        live_session: int | None = None,
        keep_live_steps: bool = False,
        long_run_history: dict | None = None,
        draft: int | None = None,
        job: dict | None = None,
    ) -> int:
        """Write one print, its arrays and anomalies in ONE transaction; returns its id.

        ``draft``: the print's per-step arrays written in parts as it ran (:meth:`open_draft`,
        :meth:`append_draft`), made this print's in the same transaction (``arrays``: the
        rest, the θ history). ``job``: the machine program the print ran (``print_jobs``):
        ``program`` (file name), ``program_bytes`` (the file's bytes) and ``settings`` (a
        JSON-ready dict: speeds used, looping, tolerance); read back by :meth:`print_job`.

        ``long_run_history``: the detectors' long-run statistics at the print's end
        (:meth:`ajtwin.apps.detection.streaming.AnomalyDetector.long_run_history`), read back by
        :meth:`long_run_history` for the machine's next print.

        ``live_session``: the live session (:mod:`ajtwin.store.live_log`) this print ends;
        in the same transaction it is closed with this print's id and, unless
        ``keep_live_steps``, its per-step rows (``live_samples``, ``live_states``) are
        deleted: the print now holds its samples exactly and its states by the storage
        policy, and a session is only replayed while open. Its session row and alarms
        stay. A kill before the COMMIT leaves the session open and whole (resumable).

        ``expected_last_seq`` is the seq of the machine's latest print (in the chain or
        not) when the twin started (None: none); if another ingest of the same machine
        committed in between, nothing is written and :class:`RegistryError` says so (the
        run started from a stale state). ``arrays`` are stored by :attr:`policy`
        (full covariances only at key frames, alarms and the end; see
        :mod:`ajtwin.store.arrays`).
        """
        machine = self.machine(name)
        if status not in (STATUS_OK, STATUS_EXCLUDED, STATUS_DROPPED):
            raise RegistryError(f"unknown print status {status!r}")
        alarm_times = [t for ev in anomalies for t in (ev.detected_s, ev.onset_s)]
        encoded = _arrays.encode_all(arrays, self.policy, alarm_times)
        conn = self._conn
        conn.execute("BEGIN IMMEDIATE")
        try:
            row = conn.execute(
                "SELECT MAX(seq) FROM prints WHERE machine_id = ?", (machine["id"],)
            ).fetchone()
            last = row[0]
            if last != expected_last_seq:
                raise RegistryError(
                    f"machine {printable(name)!r} got print {last} while this ingest ran from "
                    f"print {expected_last_seq}; ingest again"
                )
            dup = conn.execute(
                "SELECT seq FROM prints WHERE machine_id = ? AND content_hash = ?",
                (machine["id"], content_hash),
            ).fetchone()
            if dup is not None:
                raise RegistryError(f"this print is already print {dup[0]} of {printable(name)!r}")
            seq = 1 if last is None else last + 1
            row = {
                "machine_id": machine["id"],
                "seq": seq,
                "content_hash": content_hash,
                "ingested_at": _now(),
                "source": source,
                "n_samples": int(n_samples),
                "duration_s": float(duration_s),
                "meta_json": json.dumps(meta, default=str),
                "summary_json": json.dumps(summary, default=str),
                **{
                    key: to_npy(np.asarray(value, dtype=float))
                    for key, value in (
                        ("start_mean", start_mean),
                        ("start_cov", start_cov),
                        ("end_mean", end_mean),
                        ("end_cov", end_cov),
                        ("theta_before", theta_before),
                        ("theta_after", theta_after),
                    )
                },
                "status": status,
                "status_reason": status_reason,
                "long_run_json": json.dumps(long_run_history),
            }
            print_id = self._insert_print(row, encoded, anomalies)
            if draft is not None:
                self._adopt_draft(draft, print_id)
            if job is not None:
                self._insert_job(print_id, job)
            dropped = 0
            if live_session is not None:
                dropped = self._end_live_session(live_session, print_id, keep_live_steps)
            delay = float(os.environ.get(TEST_SLEEP_ENV, "0") or 0)
            if delay > 0:  # crash-safety tests kill the process here
                time.sleep(delay)
            conn.execute("COMMIT")
        except BaseException:
            rollback_if_open(conn)
            raise
        if dropped or draft is not None:  # the draft's parts were moved: their old pages
            self.release_free_pages()
        return int(print_id)

    def _insert_print(self, row: dict, encoded: dict, anomalies: list) -> int:
        """Inside save_print's transaction: the print's row, its encoded arrays and its
        anomalies; the new print's id."""
        columns = ", ".join(row)
        cur = self._conn.execute(
            f"INSERT INTO prints ({columns}) VALUES ({', '.join('?' * len(row))})",
            tuple(row.values()),
        )
        print_id = cur.lastrowid
        self._conn.executemany(
            "INSERT INTO print_arrays (print_id, name, npy, codec) VALUES (?, ?, ?, ?)",
            [(print_id, key, blob, codec) for key, (codec, blob) in encoded.items()],
        )
        self._conn.executemany(
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
        return int(print_id)

    def _adopt_draft(self, draft: int, print_id: int) -> None:
        """Inside save_print's transaction: the draft's parts become the print's."""
        gone = self._conn.execute("DELETE FROM array_drafts WHERE id = ?", (int(draft),))
        if gone.rowcount != 1:
            raise RegistryError(f"draft {draft} is not open (stored or discarded); nothing stored")
        self._conn.execute(
            "UPDATE print_array_parts SET print_id = ? WHERE print_id = ?", (print_id, -int(draft))
        )

    def _insert_job(self, print_id: int, job: dict) -> None:
        """Inside save_print's transaction: the job the print ran (compressed program)."""
        raw = bytes(job["program_bytes"])
        self._conn.execute(
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
        row = self._conn.execute(
            "SELECT p.seq, j.* FROM print_jobs j JOIN prints p ON p.id = j.print_id "
            "WHERE j.print_id = ?",
            (int(print_id),),
        ).fetchone()
        if row is None:
            return None
        try:
            raw = zlib.decompress(row["program_blob"])
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
        """Inside save_print's transaction: close the open live session with its print;
        drop its per-step rows unless ``keep_steps``. Returns the number of steps dropped."""
        closed = self._conn.execute(
            "UPDATE live_sessions SET status = 'closed', print_id = ?, closed_at = ? "
            "WHERE id = ? AND status = 'open'",
            (print_id, time.time(), session_id),
        ).rowcount
        if closed != 1:
            raise RegistryError(f"live session {session_id} is not open; nothing stored")
        if keep_steps:
            return 0
        dropped = self._conn.execute(
            "DELETE FROM live_samples WHERE session_id = ?", (session_id,)
        ).rowcount
        self._conn.execute("DELETE FROM live_states WHERE session_id = ?", (session_id,))
        return dropped

    def release_free_pages(self) -> None:
        """Give the file's free pages back to the file system (registries made with
        ``auto_vacuum=INCREMENTAL``: every new one, and any after ``machine compact``);
        others keep them for reuse by later rows (the next live session)."""
        if self._conn.execute("PRAGMA auto_vacuum").fetchone()[0] == 2:
            # executescript steps the pragma to its end (execute would free one page)
            self._conn.executescript("PRAGMA incremental_vacuum")
