"""The registry's schema: the version-1 tables and every migration since, for both databases.

The schema is the version-1 statements (:data:`SCHEMA_V1`, what ajtwin 0.x wrote) plus
every entry of :data:`MIGRATIONS` in order; a new registry runs them all, an old one the
missing ones, so a table you add exists in both. The statements are written in SQLite's
words and run on PostgreSQL through :meth:`ajtwin.store.database.Database.ddl` (INTEGER
→ BIGINT, an ``id INTEGER PRIMARY KEY`` → an identity column, REAL → DOUBLE PRECISION,
BLOB → BYTEA): the same tables, columns and constraints on both.

Adding a migration (how to change the schema)
---------------------------------------------
1. Write ``def _migrate_to_N(db): ...`` using ``CREATE TABLE IF NOT EXISTS`` /
   ``ALTER TABLE ... ADD COLUMN`` (with a ``DEFAULT`` so old rows stay valid), through
   ``db.execute`` (or ``_execute_all`` for a script) and ``db.columns(table)`` to look
   at a table. It runs inside the migration's transaction: never ``COMMIT``. Use only
   types the translation knows (TEXT, INTEGER, REAL, BLOB).
2. Append ``(N, "one line saying what it adds", _migrate_to_N)`` to :data:`MIGRATIONS`,
   N = last version + 1 (if two branches both added N, the merge renumbers one of them).
   :data:`SCHEMA_VERSION` follows automatically.
3. A machine-scoped table (a ``machine_id`` column) must be added to
   :data:`MACHINE_TABLES` (a print-scoped one, ``print_id``, to :data:`PRINT_TABLES`; one
   scoped to a live session, ``session_id``, to :data:`LIVE_SESSION_TABLES`) so that
   ``machine export/import`` and ``store copy`` carry it.
4. Test it in tests/test_store_reliability.py: a registry of the previous version opens,
   migrates and keeps its prints (on both databases: the ``store`` fixture).
"""

from __future__ import annotations

import uuid

from ajtwin.store import arrays as _arrays

#: ``info.application`` of an ajtwin registry (schema ≥ 2)
APPLICATION = "ajtwin-registry"


def get_info(db, key: str):
    """The registry's ``info`` value of ``key`` (None: not set)."""
    row = db.execute("SELECT value FROM info WHERE key = ?", (key,)).fetchone()
    return None if row is None else row[0]


def set_info(db, key: str, value) -> None:
    """Set the registry's ``info`` value of ``key``."""
    db.execute(
        "INSERT INTO info (key, value) VALUES (?, ?) "
        "ON CONFLICT (key) DO UPDATE SET value = excluded.value",
        (key, str(value)),
    )


#: Version 1 (ajtwin before the reliability work): never edit, add a migration instead.
SCHEMA_V1 = """
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
V1_TABLES = {"info", "machines", "prints", "print_arrays", "anomalies"}

#: Chain status of a print: in the chain, or kept for history only.
STATUS_OK = "ok"
STATUS_EXCLUDED = "excluded"  # its states left the physical range (set at ingest)
STATUS_DROPPED = "dropped"  # taken out by `ajtwin machine drop`


def _execute_all(db, script: str):
    # each statement inside the caller's transaction, in the database's own words
    for statement in db.ddl(script):
        db.execute(statement)


def _migrate_to_2(db):
    """Print chain status, array codecs, the anomaly index, the application marker."""
    db.execute(f"ALTER TABLE prints ADD COLUMN status TEXT NOT NULL DEFAULT '{STATUS_OK}'")
    db.execute("ALTER TABLE prints ADD COLUMN status_reason TEXT NOT NULL DEFAULT ''")
    db.execute(f"ALTER TABLE print_arrays ADD COLUMN codec TEXT NOT NULL DEFAULT '{_arrays.NPY}'")
    db.execute("CREATE INDEX IF NOT EXISTS anomalies_by_print ON anomalies(print_id)")
    set_info(db, "application", APPLICATION)


def exclude_impossible_ends(db, end_state_check) -> None:
    """Prints of a version-1 registry (stored before the chain's range check) whose end state
    ``end_state_check`` rejects leave the chain, the reason kept; inside the migration's
    transaction. The judgement is the caller's: the store holds no physics."""
    rows = db.execute("SELECT id, end_mean FROM prints").fetchall()
    for print_id, blob in rows:
        try:
            problems = end_state_check(_arrays.decode(blob, _arrays.NPY))
        except ValueError as exc:
            problems = [f"unreadable end state ({exc})"]
        if problems:
            db.execute(
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


def _migrate_to_3(db):
    """The live twin's session tables (a registry the live twin already wrote keeps them)."""
    _execute_all(db, _LIVE_SCHEMA)


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


def _migrate_to_4(db):
    """Calibrations and maintenance events. A schema-3 registry that already has them
    (ajtwin's calibration code created them on first write) keeps its rows; one written
    before ``noise_factors_json`` existed gets that column with its default."""
    _execute_all(db, _CALIBRATION_SCHEMA)
    if "noise_factors_json" not in db.columns("calibrations"):
        db.execute(
            "ALTER TABLE calibrations ADD COLUMN noise_factors_json TEXT NOT NULL DEFAULT 'null'"
        )


def _migrate_to_5(db):
    """The anomaly detectors' long-run statistics (``long_run_json``, JSON, 'null' for rows
    written before): per print, what it leaves the machine's next print; per calibration,
    what the commissioning print showed (:func:`ajtwin.engine.start.carried_long_run_history`)."""
    for table in ("prints", "calibrations"):
        if "long_run_json" not in db.columns(table):
            db.execute(f"ALTER TABLE {table} ADD COLUMN long_run_json TEXT NOT NULL DEFAULT 'null'")


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


def _migrate_to_6(db):
    """The job a print ran (``print_jobs``); older prints have none (no row)."""
    _execute_all(db, _PRINT_JOB_SCHEMA)


def _migrate_to_7(db):
    """Print arrays written in parts while a print runs (array_drafts, print_array_parts)."""
    _execute_all(db, _PARTS_SCHEMA)


#: Who writes a machine's live print now (:meth:`ajtwin.store.registry.Registry.claim_machine`):
#: one row per machine being written, its host, process and when it was last heard from,
#: so that a second twin on another PC given the same machine name is refused instead of
#: interleaving its samples with the first one's. Never edit: add a migration.
_WRITERS_SCHEMA = """
CREATE TABLE IF NOT EXISTS machine_writers (
    machine TEXT PRIMARY KEY,
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    what TEXT NOT NULL,
    started_unix REAL NOT NULL,
    heard_unix REAL NOT NULL
)
"""

#: Results of the twin re-run over stored prints (``ajtwin reprocess``): each run is a
#: version (2, 3, ...; version 1 is the prints as they were stored), each print's result in
#: it a row of ``print_versions`` with its own per-second arrays and anomalies. The prints
#: and their samples are never changed. Never edit: add a migration.
_VERSIONS_SCHEMA = """
CREATE TABLE IF NOT EXISTS versions (
    id INTEGER PRIMARY KEY,
    created_at TEXT NOT NULL,
    reason TEXT NOT NULL,
    settings_json TEXT NOT NULL,
    status TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS print_versions (
    id INTEGER PRIMARY KEY,
    version_id INTEGER NOT NULL REFERENCES versions(id),
    print_id INTEGER NOT NULL REFERENCES prints(id),
    computed_at TEXT NOT NULL,
    summary_json TEXT NOT NULL,
    start_mean BLOB NOT NULL,
    start_cov BLOB NOT NULL,
    end_mean BLOB NOT NULL,
    end_cov BLOB NOT NULL,
    theta_before BLOB NOT NULL,
    theta_after BLOB NOT NULL,
    status TEXT NOT NULL,
    status_reason TEXT NOT NULL,
    long_run_json TEXT NOT NULL,
    UNIQUE (version_id, print_id)
);
CREATE TABLE IF NOT EXISTS print_version_arrays (
    print_version_id INTEGER NOT NULL REFERENCES print_versions(id),
    name TEXT NOT NULL,
    codec TEXT NOT NULL,
    blob BLOB NOT NULL,
    PRIMARY KEY (print_version_id, name)
);
CREATE TABLE IF NOT EXISTS print_version_anomalies (
    id INTEGER PRIMARY KEY,
    print_version_id INTEGER NOT NULL REFERENCES print_versions(id),
    detected_s REAL NOT NULL,
    onset_s REAL NOT NULL,
    cause TEXT NOT NULL,
    description TEXT NOT NULL,
    detectors TEXT NOT NULL,
    evidence_json TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS print_versions_by_print ON print_versions(print_id);
CREATE INDEX IF NOT EXISTS version_anomalies_by_print ON print_version_anomalies(print_version_id)
"""


def _migrate_to_8(db):
    """The registry's own identity (``info.registry_id``, what ``store copy`` resumes by),
    the live writers' claims and the reprocessed versions."""
    if get_info(db, "registry_id") is None:
        set_info(db, "registry_id", uuid.uuid4().hex)
    _execute_all(db, _WRITERS_SCHEMA)
    _execute_all(db, _VERSIONS_SCHEMA)


#: (version, what it adds, function(db)); append only (see the module docstring).
MIGRATIONS: list[tuple[int, str, object]] = [
    (2, "print chain status, compressed arrays, anomaly index", _migrate_to_2),
    (3, "live twin sessions: live_sessions, live_samples, live_states, live_events", _migrate_to_3),
    (4, "per-machine calibrations and maintenance events", _migrate_to_4),
    (5, "the detectors' long-run noise statistics per print and calibration", _migrate_to_5),
    (6, "the job (machine program) each print ran: print_jobs", _migrate_to_6),
    (7, "print arrays written in parts while a print runs", _migrate_to_7),
    (8, "registry identity, live writers' claims, reprocessed versions", _migrate_to_8),
]
SCHEMA_VERSION = MIGRATIONS[-1][0] if MIGRATIONS else 1

#: Tables with a ``machine_id`` column / a ``print_id`` column (export, import, delete).
#: Copied in this order, each in its ``id`` order (the newest calibration stays active).
MACHINE_TABLES = ["prints", "calibrations", "maintenance_events"]
PRINT_TABLES = ["print_arrays", "print_array_parts", "anomalies", "print_jobs"]
#: A print's reprocessed results (``print_id``) and their rows (``print_version_id``):
#: carried by ``store copy``; a machine export carries the prints as stored (version 1).
VERSION_TABLES = ["print_version_arrays", "print_version_anomalies"]
#: Tables with a ``session_id`` column (rows of one ``live_sessions`` row). The sessions
#: themselves are found by ``live_sessions.machine`` (a name) and copied, renamed and with
#: ``print_id`` renumbered, by :meth:`ajtwin.store.registry.Registry.load_machine`.
LIVE_SESSION_TABLES = ["live_samples", "live_states", "live_events"]
