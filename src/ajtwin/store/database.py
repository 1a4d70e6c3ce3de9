"""The registry's two databases behind one small interface: SQLite and PostgreSQL.

:class:`~ajtwin.store.registry.Registry` writes its statements once, in the SQL both
databases understand (``?`` parameters, ``INSERT … ON CONFLICT``, ``RETURNING id``), and
runs them through a :class:`Database`: :class:`SqliteDatabase` (a file, the embedded
default: :mod:`ajtwin.store.connection` opens and checks it) or :class:`PostgresDatabase`
(a server, psycopg 3). What differs between the two lives here and only here:

==========================  ==============================  ==================================
                            SQLite                          PostgreSQL
==========================  ==============================  ==================================
parameters                  ``?``                           ``%s`` (translated)
types in the schema         INTEGER, REAL, BLOB             BIGINT (ids: identity), DOUBLE
                                                            PRECISION, BYTEA
a write transaction         ``BEGIN IMMEDIATE`` (the file's ``BEGIN`` + a transaction-scoped
                            one writer)                     advisory lock per ``key``
a read snapshot             ``BEGIN`` (deferred)            ``REPEATABLE READ READ ONLY``
tables, columns             ``sqlite_master``, ``PRAGMA``   ``information_schema`` (the
                                                            current schema only)
"something changed"         ``PRAGMA data_version``         the newest transaction id
freeing space               incremental vacuum, VACUUM      autovacuum; VACUUM on compact
failures                    :class:`StoreError` naming the file or the server and what to do;
                            a duplicate key: :class:`ConstraintError`; a server gone:
                            :class:`ConnectionLost` (the next statement reconnects)
==========================  ==============================  ==================================

Arrays are the same bytes on both (``.npy``/``zs1`` blobs as BLOB or BYTEA), so a print
reads back bit for bit whichever database holds it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import sqlite3
import stat
import threading
import zlib
from pathlib import Path

from ajtwin.store.connection import (
    RegistryError,
    StoreError,
    check_integrity,
    check_writable,
    connect,
    repair_journal_modes,
    rollback_if_open,
)
from ajtwin.store.location import StoreLocation, parse_store

log = logging.getLogger("ajtwin.store")


class ConstraintError(RegistryError):
    """A row that breaks a uniqueness rule (a machine name taken, a print stored twice)."""


class ConnectionLost(StoreError):
    """The database server could not be reached or went away; nothing of the statement
    that failed was stored unless it had committed. The next statement reconnects."""


def open_database(location, *, timeout_s: float = 30.0, create: bool = True, write: bool = False):
    """The :class:`Database` of ``location`` (a :class:`StoreLocation`, a path or a URL)."""
    location = parse_store(location)
    if location.is_sqlite:
        return SqliteDatabase(location, timeout_s=timeout_s, create=create, write=write)
    return PostgresDatabase(location, timeout_s=timeout_s)


class Database:
    """What :class:`~ajtwin.store.registry.Registry` needs of a database (module docstring).

    Statements use ``?`` parameters; rows read back index by position and by column name
    (``row[0]``, ``row["seq"]``, ``dict(row)``).
    """

    kind = ""
    location: StoreLocation

    def __str__(self) -> str:
        return str(self.location)

    # -- statements
    def execute(self, sql: str, params=()):
        """Run one statement; the cursor (``fetchone``, ``fetchall``, iteration, ``rowcount``)."""
        raise NotImplementedError

    def executemany(self, sql: str, rows) -> None:
        """Run one statement for each parameter row of ``rows``."""
        raise NotImplementedError

    def insert(self, table: str, row: dict, *, returning_id: bool = True) -> int | None:
        """Insert ``row`` (column → value) into ``table``; the new row's ``id``."""
        keys = list(row)
        sql = f"INSERT INTO {table} ({', '.join(keys)}) VALUES ({', '.join('?' * len(keys))})"
        if not returning_id:
            self.execute(sql, [row[k] for k in keys])
            return None
        return int(self.execute(sql + " RETURNING id", [row[k] for k in keys]).fetchone()[0])

    # -- transactions
    @contextlib.contextmanager
    def write(self, key: str | None = "registry"):
        """One write transaction: committed at the end, rolled back on any exception.

        Writers of the same ``key`` run one after the other (SQLite: every writer, the file
        has one write lock); ``key`` None takes no lock of its own (PostgreSQL: rows of
        their own, made unique by the schema)."""
        raise NotImplementedError
        yield  # pragma: no cover

    @contextlib.contextmanager
    def snapshot(self):
        """Reads that see one committed state of the database (nothing written)."""
        raise NotImplementedError
        yield  # pragma: no cover

    @property
    def in_transaction(self) -> bool:
        """Whether a transaction is open on this connection."""
        raise NotImplementedError

    # -- schema
    def tables(self) -> set[str]:
        """The names of the tables of the registry's schema."""
        raise NotImplementedError

    def columns(self, table: str) -> list[str]:
        """The column names of ``table``, in order."""
        raise NotImplementedError

    def prepare(self, empty: bool) -> None:
        """Settings of an opened registry (or an empty database about to become one)."""

    def check_write(self) -> None:
        """Refuse (:class:`StoreError`) now when this connection cannot write the registry."""

    def ddl(self, script: str) -> list[str]:
        """The statements of a schema script (SQLite's words) in this database's words."""
        return [s.strip() for s in script.split(";") if s.strip()]

    def identity_set(self, table: str) -> None:
        """After rows were inserted into ``table`` with their ``id`` given: the next id the
        database makes follows them (nothing to do on SQLite)."""

    # -- upkeep
    def change_token(self) -> int:
        """A number that changes whenever any connection commits a write."""
        raise NotImplementedError

    def release_free_pages(self) -> None:
        """Give freed space back (after many rows were deleted)."""

    def size_bytes(self, tables) -> int:
        """Bytes the registry takes on disk (the file, or the tables on the server)."""
        raise NotImplementedError

    def compact_storage(self) -> None:
        """Rewrite the storage so that freed space is returned (``machine compact``)."""
        raise NotImplementedError

    def free_bytes(self) -> int:
        """Bytes kept free for later rows (SQLite's free pages; 0 where not known)."""
        return 0

    def close(self) -> None:
        """Close the connection."""
        raise NotImplementedError


# ====================================================================== SQLite
class SqliteDatabase(Database):
    """An SQLite registry file (:mod:`ajtwin.store.connection`: failures said in words,
    writability and integrity checked; WAL journal, readers never wait for the writer).

    Parameters
    ----------
    location : StoreLocation
    timeout_s : float
        How long a writer waits for another writer's transaction.
    create : bool
        Make the file (and its folder) when missing; else :class:`RegistryError`.
    write : bool
        Refuse at once when this process cannot write the file, its journal or folder.
    """

    kind = "sqlite"

    def __init__(self, location, *, timeout_s: float = 30.0, create=True, write=False):
        self.location = parse_store(location)
        self.path = Path(self.location.path)
        self._conn = None
        path = self.path
        exists = os.path.lexists(path)
        if exists:
            try:
                mode = os.stat(path).st_mode
            except OSError as exc:
                raise RegistryError(f"{path}: cannot open the registry ({exc})") from None
            if not stat.S_ISREG(mode):
                kind = "a directory" if stat.S_ISDIR(mode) else "not a regular file"
                raise RegistryError(
                    f"{path}: is {kind} (a FIFO, device or socket?); "
                    "a registry must be an ordinary file"
                )
        elif not create:
            raise RegistryError(
                f"no registry at {path}; create one with `ajtwin machine add NAME "
                f"--store {path}` (read-only commands never create it)"
            )
        if write or (create and not exists):
            check_writable(path)
        if not exists:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise RegistryError(f"{path}: cannot create its folder ({exc})") from None
        self.new_file = not exists
        try:
            self._conn = connect(path, timeout_s)
            check_integrity(self._conn, path)
        except BaseException:
            self.close()
            raise

    def prepare(self, empty: bool) -> None:
        """Journal mode and pragmas, on a file known to be ours (or empty)."""
        if empty:
            # a new registry returns the pages it frees (a closed live session's per-step
            # rows) to the file system: release_free_pages(); must precede the first table
            # and the journal mode (an existing registry gets it from `machine compact`)
            self._conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
        self._conn.execute("PRAGMA journal_mode=WAL")
        self._conn.execute("PRAGMA foreign_keys=ON")
        self._conn.execute("PRAGMA synchronous=NORMAL")
        repair_journal_modes(self.path)

    def check_write(self) -> None:
        """Take the write lock once: a read-only mount or another writer's hold is said
        now, before any work."""
        self._conn.execute("BEGIN IMMEDIATE")
        self._conn.execute("ROLLBACK")

    def execute(self, sql: str, params=()):
        """Run one statement (``?`` parameters); its cursor."""
        try:
            return self._conn.execute(sql, params)
        except sqlite3.IntegrityError as exc:
            raise ConstraintError(str(exc)) from None

    def executemany(self, sql: str, rows) -> None:
        """Run one statement for each parameter row of ``rows``."""
        try:
            self._conn.executemany(sql, rows)
        except sqlite3.IntegrityError as exc:
            raise ConstraintError(str(exc)) from None

    @contextlib.contextmanager
    def write(self, key: str | None = "registry"):
        """One write transaction (:meth:`Database.write`)."""
        self._conn.execute("BEGIN IMMEDIATE")
        try:
            yield self
            self._conn.execute("COMMIT")
        except BaseException:
            rollback_if_open(self._conn)
            raise

    @contextlib.contextmanager
    def snapshot(self):
        """Reads that see one committed state (:meth:`Database.snapshot`)."""
        if self._conn.in_transaction:  # inside a caller's transaction: its view already
            yield self
            return
        self._conn.execute("BEGIN")
        try:
            yield self
        finally:
            if self._conn is not None:  # not closed under a reader left open
                rollback_if_open(self._conn)

    @property
    def in_transaction(self) -> bool:
        """Whether a transaction is open on this connection."""
        return self._conn.in_transaction

    def tables(self) -> set[str]:
        """The names of the registry's tables."""
        rows = self._conn.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'"
        ).fetchall()
        return {r[0] for r in rows}

    def columns(self, table: str) -> list[str]:
        """The column names of ``table``, in order."""
        return [r[1] for r in self._conn.execute(f"PRAGMA table_info({table})").fetchall()]

    def change_token(self) -> int:
        """A number that changes whenever any connection commits a write."""
        return int(self._conn.execute("PRAGMA data_version").fetchone()[0])

    def release_free_pages(self) -> None:
        """Give the file's free pages back to the file system (registries made with
        ``auto_vacuum=INCREMENTAL``: every new one, and any after ``machine compact``);
        others keep them for reuse by later rows (the next live session)."""
        if self._conn.execute("PRAGMA auto_vacuum").fetchone()[0] == 2:
            # executescript steps the pragma to its end (execute would free one page)
            self._conn.executescript("PRAGMA incremental_vacuum")

    def checkpoint(self) -> None:
        """Move the write-ahead log into the file (its size then is the registry's)."""
        self._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")

    def size_bytes(self, tables=()) -> int:
        """The file and its write-ahead log [bytes]."""
        total = 0
        for suffix in ("", "-wal"):
            p = Path(str(self.path) + suffix)
            if p.exists():
                total += p.stat().st_size
        return total

    def compact_storage(self) -> None:
        """VACUUM the file (switching it to ``auto_vacuum=INCREMENTAL`` as new registries
        are, so that later closed live sessions give their pages back)."""
        self.checkpoint()
        self._conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
        self._conn.execute("VACUUM")
        self.checkpoint()

    def free_bytes(self) -> int:
        """Bytes of the file's free pages."""
        free = self._conn.execute("PRAGMA freelist_count").fetchone()[0]
        return int(free) * int(self._conn.execute("PRAGMA page_size").fetchone()[0])

    def self_contained(self) -> None:
        """One file without a journal beside it (an export's member)."""
        self._conn.execute("PRAGMA journal_mode=DELETE")

    def close(self) -> None:
        """Close the connection."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
            repair_journal_modes(self.path)


# ====================================================================== PostgreSQL
#: SQLite's words in the schema scripts → PostgreSQL's (whole words, in this order)
_PG_TYPES = [
    (re.compile(r"\bid INTEGER PRIMARY KEY\b"),
     "id BIGINT GENERATED BY DEFAULT AS IDENTITY PRIMARY KEY"),
    (re.compile(r"\bINTEGER\b"), "BIGINT"),
    (re.compile(r"\bREAL\b"), "DOUBLE PRECISION"),
    (re.compile(r"\bBLOB\b"), "BYTEA"),
]  # fmt: skip


class Row(tuple):
    """A row read from PostgreSQL, indexed by position or by column name (as
    :class:`sqlite3.Row`)."""

    __slots__ = ()
    _index: dict = {}

    def __getitem__(self, key):
        if isinstance(key, str):
            return tuple.__getitem__(self, self._index[key])
        return tuple.__getitem__(self, key)

    def keys(self) -> list[str]:
        """The column names, in order."""
        return list(self._index)


def _row_factory(cursor):
    names = [c.name for c in cursor.description or ()]
    index = {name: i for i, name in enumerate(names)}
    cls = type("Row", (Row,), {"__slots__": (), "_index": index})
    return lambda values: tuple.__new__(cls, values)


#: libpq connection settings ajtwin adds unless the URL gives them: fail fast when the
#: server is gone (a lost network is noticed in ~10 s, not after TCP's 15 min)
_CONNECT_DEFAULTS = {
    "connect_timeout": "10",
    "keepalives": "1",
    "keepalives_idle": "5",
    "keepalives_interval": "2",
    "keepalives_count": "3",
    "tcp_user_timeout": "10000",
    "application_name": "ajtwin",
}


def _pg_key(text: str) -> int:
    """A 64-bit advisory-lock key for ``text`` (CRC-32 in the low half: stable across runs)."""
    return 0x616A0000_00000000 | zlib.crc32(text.encode())


class PostgresDatabase(Database):
    """A registry in a PostgreSQL database (psycopg 3), in the schema first on the role's
    ``search_path`` (``public`` unless the URL's ``options=-csearch_path=…`` says).

    One connection, autocommit between explicit transactions, used by one thread at a time
    (psycopg serialises it). A connection found broken is made again on the next statement
    outside a transaction (:class:`ConnectionLost` for the one that failed).
    """

    kind = "postgresql"

    def __init__(self, location, *, timeout_s: float = 30.0):
        self.location = parse_store(location)
        self.path = self.location  # what messages name
        self.timeout_s = float(timeout_s)
        self._conn = None
        self._sql: dict[str, str] = {}
        self._lock = threading.RLock()
        self.new_file = False
        self._connect()

    # -- connecting
    def _connect(self) -> None:
        import psycopg
        from psycopg.conninfo import conninfo_to_dict

        try:
            given = conninfo_to_dict(self.location.url)
        except psycopg.ProgrammingError as exc:
            raise RegistryError(
                f"--store {self.location.url}: not a PostgreSQL URL ({exc})"
            ) from None
        extra = {k: v for k, v in _CONNECT_DEFAULTS.items() if k not in given}
        password = self.location.password()
        if password is not None:
            extra["password"] = password
        lock_ms = max(1, int(self.timeout_s * 1000))  # 0 would be "wait for ever"
        options = f"-c lock_timeout={lock_ms} -c idle_in_transaction_session_timeout=600000"
        extra["options"] = (given.get("options", "") + " " + options).strip()
        try:
            self._conn = psycopg.connect(
                self.location.url, autocommit=True, row_factory=_row_factory, **extra
            )
        except psycopg.Error as exc:
            raise self._failure(exc, connecting=True) from None

    def _ensure_connected(self) -> None:
        if self._conn is None or self._conn.closed or self._conn.broken:
            if self._conn is not None and not self._conn.closed:
                with contextlib.suppress(Exception):
                    self._conn.close()
            self._connect()
            log.info("%s: connected again", self.location)

    def _failure(self, exc, connecting: bool = False) -> RegistryError:
        """The registry error for a psycopg failure (None: not the database's fault)."""
        import psycopg
        from psycopg import errors

        words = " ".join(str(exc).split())
        if len(words) > 200:
            words = words[:200] + "…"
        where = str(self.location)
        if isinstance(exc, psycopg.IntegrityError):
            return ConstraintError(words)
        if isinstance(exc, errors.InsufficientPrivilege | errors.ReadOnlySqlTransaction):
            return StoreError(
                f"{where}: this role may not do that ({words}); a read-only role serves the "
                "dashboard and read commands only: write with the registry's owner role"
            )
        if isinstance(exc, errors.LockNotAvailable):
            return StoreError(
                f"{where}: another writer held the lock longer than this command waits "
                f"({self.timeout_s:g} s: {words}); retry when it is done"
            )
        if isinstance(exc, errors.InvalidCatalogName | errors.InvalidAuthorizationSpecification):
            return StoreError(f"{where}: {words}; check the URL's database and user")
        if isinstance(exc, psycopg.OperationalError) or connecting:
            if "password" in words.lower():
                return StoreError(
                    f"{where}: the server refused the login ({words}); give the password with "
                    "--store-password-file, $PGPASSWORD or ~/.pgpass (never in the URL)"
                )
            return ConnectionLost(
                f"{where}: the database server cannot be reached ({words}); check that the "
                "server runs and is reachable; nothing of this was stored"
            )
        return None

    def _translate(self, sql: str) -> str:
        out = self._sql.get(sql)
        if out is None:
            out = sql.replace("%", "%%").replace("?", "%s")
            self._sql[sql] = out
        return out

    def _run(self, method: str, sql: str, params):
        import psycopg

        with self._lock:
            if not self.in_transaction:
                self._ensure_connected()
            cursor = self._conn.cursor()
            try:
                getattr(cursor, method)(self._translate(sql), params)
            except psycopg.Error as exc:
                failure = self._failure(exc)
                if failure is None:
                    raise
                raise failure from None
            return cursor

    # -- statements
    def execute(self, sql: str, params=()):
        """Run one statement (``?`` parameters); its cursor."""
        return self._run("execute", sql, tuple(params))

    def executemany(self, sql: str, rows) -> None:
        """Run one statement for each parameter row of ``rows``."""
        rows = [tuple(r) for r in rows]
        if rows:
            self._run("executemany", sql, rows)

    @contextlib.contextmanager
    def write(self, key: str | None = "registry"):
        """One write transaction (:meth:`Database.write`)."""
        with self._lock:
            self.execute("BEGIN")
            try:
                if key is not None:
                    self.execute("SELECT pg_advisory_xact_lock(?)", (self._key(key),))
                yield self
                self.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise

    def _key(self, key: str) -> int:
        # the schema is part of the key: two registries in one database never wait on
        # each other
        return _pg_key(f"{self._schema()}/{key}") - (1 << 63)

    def _schema(self) -> str:
        if not hasattr(self, "_schema_name"):
            self._schema_name = self.execute("SELECT current_schema()").fetchone()[0]
        return self._schema_name

    def _rollback(self) -> None:
        if self._conn is None or self._conn.closed or self._conn.broken:
            return
        with contextlib.suppress(Exception):
            self._conn.execute("ROLLBACK")

    @contextlib.contextmanager
    def snapshot(self):
        """Reads that see one committed state (:meth:`Database.snapshot`)."""
        with self._lock:
            if self.in_transaction:
                yield self
                return
            self.execute("BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY")
            try:
                yield self
            finally:
                self._rollback()

    @property
    def in_transaction(self) -> bool:
        """Whether a transaction is open on this connection."""
        from psycopg.pq import TransactionStatus

        if self._conn is None or self._conn.closed:
            return False
        return self._conn.info.transaction_status != TransactionStatus.IDLE

    # -- schema
    def tables(self) -> set[str]:
        """The names of the registry's tables."""
        rows = self.execute(
            "SELECT table_name FROM information_schema.tables "
            "WHERE table_schema = current_schema() AND table_type = 'BASE TABLE'"
        ).fetchall()
        return {r[0] for r in rows}

    def columns(self, table: str) -> list[str]:
        """The column names of ``table``, in order."""
        rows = self.execute(
            "SELECT column_name FROM information_schema.columns WHERE table_schema = "
            "current_schema() AND table_name = ? ORDER BY ordinal_position",
            (table,),
        ).fetchall()
        return [r[0] for r in rows]

    def ddl(self, script: str) -> list[str]:
        """The statements of a schema script in PostgreSQL's words."""
        out = []
        for statement in super().ddl(script):
            for pattern, words in _PG_TYPES:
                statement = pattern.sub(words, statement)
            out.append(statement)
        return out

    def identity_set(self, table: str) -> None:
        """The next identity of ``table`` follows its explicit ids."""
        self.execute(
            f"SELECT setval(pg_get_serial_sequence('{table}', 'id'), "
            f"GREATEST((SELECT COALESCE(MAX(id), 0) FROM {table}), 1), "
            f"(SELECT COUNT(*) > 0 FROM {table}))"
        )

    # -- upkeep
    def change_token(self) -> int:
        """A number that changes whenever any connection commits a write."""
        # any committed write took a transaction id below the snapshot's xmax
        return int(
            self.execute("SELECT pg_snapshot_xmax(pg_current_snapshot())::text").fetchone()[0]
        )

    def size_bytes(self, tables=()) -> int:
        """Bytes of the registry's tables on the server (rows, TOAST, indexes)."""
        total = 0
        for table in tables:
            total += int(
                self.execute("SELECT pg_total_relation_size(to_regclass(?))", (table,)).fetchone()[
                    0
                ]
                or 0
            )
        return total

    def compact_storage(self) -> None:
        """VACUUM the registry's tables (autovacuum does it over time anyway)."""
        for table in sorted(self.tables()):
            self.execute(f"VACUUM {table}")

    def check_write(self) -> None:
        """Refuse a role that may not write the registry's tables (a read-only role)."""
        row = self.execute(
            "SELECT has_table_privilege(current_user, to_regclass('prints'), 'INSERT') "
            "AND has_table_privilege(current_user, to_regclass('live_samples'), 'INSERT')"
        ).fetchone()
        if not row[0]:
            user = self.execute("SELECT current_user").fetchone()[0]
            raise StoreError(
                f"{self.location}: role {user!r} may not write the registry (a read-only role "
                "serves the dashboard and read commands); nothing was run: write with a role "
                "granted INSERT, UPDATE and DELETE on its tables"
            )

    def server_version(self) -> int:
        """The server's version number (150018 for 15.18)."""
        return int(self._conn.info.server_version)

    def close(self) -> None:
        """Close the connection."""
        with self._lock:
            if self._conn is not None:
                with contextlib.suppress(Exception):
                    self._conn.close()
                self._conn = None


__all__ = [
    "ConnectionLost",
    "ConstraintError",
    "Database",
    "PostgresDatabase",
    "SqliteDatabase",
    "open_database",
]
