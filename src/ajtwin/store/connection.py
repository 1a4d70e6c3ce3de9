"""The registry's SQLite connection: failures said in words, writability and integrity checked.

Every connection to a registry file (:class:`ajtwin.store.registry.Registry`, the live log)
is made by :func:`connect`. Its statements and cursors turn the SQLite failures that come
from the file or the disk — full, read-only, damaged, locked, an I/O error — into a
:class:`StoreError` (a :class:`RegistryError`) that names the file and says what to do,
instead of a traceback; constraint violations and programming errors pass unchanged.

Before a command writes, :func:`check_writable` says whether it can (the file, its WAL
journal ``-wal``/``-shm`` and its folder), so a read-only registry is refused before the
twin runs rather than after. :func:`check_integrity` runs SQLite's integrity check (0.1 s
for a 190 MB registry) once per process and file version, so a damaged file is refused on
open, never read in silence.
:func:`repair_journal_modes` gives the owner write permission back on a ``-shm``/``-wal``
that SQLite created read-only (it copies the database file's mode: a read-only registry
left a read-only ``-shm`` that kept failing after the registry was made writable again).

Example
-------
>>> import os, tempfile
>>> path = os.path.join(tempfile.mkdtemp(), "r.sqlite")
>>> conn = connect(path)
>>> check_integrity(conn, path)
>>> conn.close()
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import stat
import tempfile
from pathlib import Path


class RegistryError(RuntimeError):
    """A registry operation that cannot be done (unknown machine, duplicate, ...)."""


class StoreError(RegistryError):
    """The registry's file or disk failed (full, read-only, damaged, locked, I/O): the
    message names the file and what to do."""

    #: the command line ends with this sentence, never a traceback (``ajtwin.cli.LazyGroup``)
    shown_as_sentence = True


#: SQLite's result-code names (``sqlite3.Error.sqlite_errorname``, before any '_' detail)
#: → what the user should do; the sentence is completed with the file and SQLite's words
_ADVICE = {
    "SQLITE_FULL": (
        "the disk holding it is full",
        "nothing of this command was stored (SQLite rolled the transaction back); free space "
        "on that disk or give another --store",
    ),
    "SQLITE_READONLY": (
        "it cannot be written by this user",
        "make the file, its -wal and -shm journal files and its folder writable (ls -l, "
        "chmod u+w), or give another --store",
    ),
    "SQLITE_PERM": (
        "permission denied",
        "make the file and its folder accessible to this user, or give another --store",
    ),
    "SQLITE_CORRUPT": (
        "registry damaged",
        "nothing was read from it; restore it from a backup (an `ajtwin machine export` "
        "archive with `ajtwin machine import`), or recover what is readable with "
        "`sqlite3 FILE .recover`",
    ),
    "SQLITE_NOTADB": (
        "not a usable ajtwin registry: not an SQLite database (another kind of file, or a "
        "registry damaged beyond repair)",
        "give the registry's path with --store, or restore it from a backup "
        "(`ajtwin machine import`)",
    ),
    "SQLITE_IOERR": (
        "an input/output error reading or writing it (a failing disk, a network share gone?)",
        "check the disk and retry; nothing of this command was stored",
    ),
    "SQLITE_CANTOPEN": (
        "it cannot be opened",
        "check that the file and its folder exist and are accessible",
    ),
    "SQLITE_BUSY": (
        "another process holds it locked longer than this command waits",
        "retry when that process (an ingest, a compaction) is done",
    ),
    "SQLITE_LOCKED": (
        "it is locked by another connection",
        "retry when the other command is done",
    ),
}


def _kind(exc: sqlite3.Error) -> str | None:
    """The :data:`_ADVICE` key of a SQLite failure, or None (not the file's or disk's fault)."""
    if "Could not decode to UTF-8" in str(exc):  # a text column whose bytes were flipped
        return "SQLITE_CORRUPT"
    name = str(getattr(exc, "sqlite_errorname", "") or "")
    for key in _ADVICE:
        if name == key or name.startswith(key + "_"):
            return key
    text = str(exc).lower()
    if "malformed" in text:  # "malformed database schema (...)" comes without a code
        return "SQLITE_CORRUPT"
    return None


def describe(path, exc: sqlite3.Error) -> str | None:
    """The sentence for a SQLite failure on ``path`` (None: not a failure of the file or disk).

    >>> e = sqlite3.OperationalError("database or disk is full")
    >>> describe("r.sqlite", e) is None     # no result code: the words alone do not say
    True
    """
    kind = _kind(exc)
    if kind is None:
        return None
    what, todo = _ADVICE[kind]
    words = str(exc)
    if len(words) > 160:
        words = words[:160] + "…"
    return f"{path}: {what} ({words}); {todo.replace('FILE', str(path))}"


@contextlib.contextmanager
def _translated(path):
    try:
        yield
    except sqlite3.Error as exc:
        message = describe(path, exc)
        if message is None:
            raise
        raise StoreError(message) from None


class _Cursor(sqlite3.Cursor):
    """A cursor whose file and disk failures are :class:`StoreError` (module docstring)."""

    def execute(self, *args):
        with _translated(self.connection.path):
            return super().execute(*args)

    def executemany(self, *args):
        with _translated(self.connection.path):
            return super().executemany(*args)

    def executescript(self, *args):
        with _translated(self.connection.path):
            return super().executescript(*args)

    def fetchone(self):
        with _translated(self.connection.path):
            return super().fetchone()

    def fetchmany(self, *args):
        with _translated(self.connection.path):
            return super().fetchmany(*args)

    def fetchall(self):
        with _translated(self.connection.path):
            return super().fetchall()

    def __next__(self):
        with _translated(self.connection.path):
            return super().__next__()


class Connection(sqlite3.Connection):
    """A registry connection (:func:`connect`): every statement through :class:`_Cursor`."""

    path: str = ""

    def cursor(self, factory=None):
        """A cursor of this connection (:class:`_Cursor` unless ``factory`` says)."""
        return super().cursor(factory or _Cursor)

    def execute(self, sql, parameters=()):
        """Run one statement (failures of the file or disk: :class:`StoreError`)."""
        return self.cursor().execute(sql, parameters)

    def executemany(self, sql, parameters):
        """Run one statement for every row of ``parameters``."""
        return self.cursor().executemany(sql, parameters)

    def executescript(self, script):
        """Run a script of statements (commits first, as sqlite3 does)."""
        return self.cursor().executescript(script)

    def commit(self):
        """Commit (failures of the file or disk: :class:`StoreError`)."""
        with _translated(self.path):
            super().commit()


def connect(path, timeout_s: float = 30.0) -> Connection:
    """A :class:`Connection` to ``path`` (autocommit mode, rows as :class:`sqlite3.Row`,
    usable from several threads: the callers serialise their use)."""
    with _translated(path):
        conn = sqlite3.connect(
            str(path),
            timeout=timeout_s,
            isolation_level=None,
            check_same_thread=False,
            factory=Connection,
        )
    conn.path = str(path)
    conn.row_factory = sqlite3.Row
    return conn


def rollback_if_open(conn) -> None:
    """ROLLBACK the open transaction, if one is open: after a full disk SQLite has already
    rolled back, and a second ROLLBACK would hide the real failure behind 'no transaction'."""
    if conn.in_transaction:
        with contextlib.suppress(sqlite3.Error, StoreError):
            conn.execute("ROLLBACK")


def _journal_files(path: Path) -> list[Path]:
    return [Path(f"{path}-wal"), Path(f"{path}-shm"), Path(f"{path}-journal")]


def check_writable(path) -> None:
    """Refuse (:class:`StoreError`) unless this process can write the registry at ``path``:
    the file and its existing journal files opened for writing, and a file made in its
    folder (where SQLite puts the ``-wal``/``-shm`` journal). A missing file: its folder
    (or the nearest existing parent, which the registry's creation makes folders in)."""
    path = Path(path)
    todo = (
        "make it writable for this user (ls -l; chmod u+w), or give another --store; "
        "nothing was run"
    )
    for p in [path, *_journal_files(path)]:
        if not p.exists():
            continue
        try:
            os.close(os.open(p, os.O_RDWR))
        except OSError as exc:
            raise StoreError(
                f"{p}: the registry cannot be written ({exc.strerror}); {todo}"
            ) from None
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".ajtwin-write-check-")
    except OSError as exc:
        raise StoreError(
            f"{os.path.abspath(folder)}: the registry's folder cannot be written "
            f"({exc.strerror}); SQLite keeps the registry's journal beside it; {todo}"
        ) from None
    os.close(fd)
    os.unlink(probe)


#: (real path, device, inode, size, mtime) of the files checked by this process
_CHECKED: set = set()

#: registries up to this size get SQLite's full ``integrity_check`` (which also finds an
#: index that lost a row: a lookup would then miss a print's arrays in silence); larger ones
#: the ``quick_check`` of the page structure. Measured on a 2-core machine (warm cache):
#: 190 MB: quick 0.08 s, full 0.09 s; 1.96 GB (a 1,000,000-step live log kept): quick
#: 2.2 s, full 3.6-4.2 s.
FULL_CHECK_MAX_BYTES = 256 * 2**20


def check_integrity(conn, path) -> None:
    """SQLite's integrity check on a registry (once per process and version of the file;
    ``integrity_check`` up to :data:`FULL_CHECK_MAX_BYTES`, else ``quick_check``):
    :class:`StoreError` saying where it is damaged, so nothing is read from a damaged file."""
    try:
        st = os.stat(path)
        key = (os.path.realpath(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    except OSError:
        st, key = None, None
    if key is not None and key in _CHECKED:
        return
    full = st is not None and st.st_size <= FULL_CHECK_MAX_BYTES
    pragma = "integrity_check" if full else "quick_check"
    rows = [r[0] for r in conn.execute(f"PRAGMA {pragma}").fetchall()]
    if rows != ["ok"]:
        found = "; ".join(str(r).replace("\n", " ") for r in rows[:3])
        if len(found) > 200:
            found = found[:200] + "…"
        raise StoreError(
            f"{path}: registry damaged (SQLite's integrity check: {found}); nothing was read "
            "from it; restore it from a backup (an `ajtwin machine export` archive with "
            f"`ajtwin machine import`), or recover what is readable with `sqlite3 {path} "
            ".recover`"
        )
    if key is not None:
        _CHECKED.add(key)


def repair_journal_modes(path) -> None:
    """Give the owner write permission on this process's ``-wal``/``-shm`` files that lack it
    (SQLite creates them with the database file's mode: a read-only registry left read-only
    journal files that broke every later write, even after ``chmod u+w`` of the registry).
    The database file's own mode is left as it is."""
    for p in _journal_files(Path(path)):
        try:
            st = os.stat(p)
        except OSError:
            continue
        if st.st_uid == os.geteuid() and not st.st_mode & stat.S_IWUSR:
            with contextlib.suppress(OSError):
                os.chmod(p, stat.S_IMODE(st.st_mode) | stat.S_IWUSR)
