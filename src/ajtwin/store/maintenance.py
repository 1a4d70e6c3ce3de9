"""Registry upkeep: compaction/retention, and a machine's export to and import from a tar.

``compact`` re-encodes a machine's arrays with the storage policy
(:mod:`ajtwin.store.arrays`; version-1 prints hold raw ``.npy`` and the whole covariance
sequence), drops the periodic covariance key frames of prints older than
``keep_covariances_days`` (the end covariance, the alarms' covariances, every σ and mean
stay) and VACUUMs the file (switching it to ``auto_vacuum=INCREMENTAL``, as new
registries are, so that later closed live sessions give their pages back). A live
session that ends with its print stored drops its own per-step rows
(``Registry.save_print``); of the machine's *closed* sessions that still hold them
(written by older code, or kept with ``keep_live_steps``) compact drops the per-step
samples and published states (``live_samples``, ``live_states``: the stored print holds
the same samples and states, compressed) and keeps the session row and its alarms; an
open session is left whole, since a restarted ``ajtwin live`` replays it.
``export_machine`` writes ``manifest.json`` (format and schema version, machine, print
count, SHA-256 of the database) and ``machine.sqlite`` (a registry holding that machine
only) into an uncompressed tar; ``import_machine`` checks the archive strictly (exactly
those two regular files, sizes, checksum, versions), reads
the members into a private temporary folder under its own file names (never
``extract``: no path traversal, no links) and copies the machine in one transaction.
Export and import carry the machine's calibration history (provenance, standard errors)
and maintenance events (:mod:`ajtwin.store.calibration`; compact leaves them as they are),
so the importing registry starts the machine's next print exactly as the exporting one
would. They carry the machine's live-twin sessions too (:mod:`ajtwin.store.live_log`):
closed ones as history, and an open one (a print still running, or a client that was
stopped mid-print) whole, so ``ajtwin live`` on the importing registry resumes it.

Example
-------
>>> import tempfile, os
>>> from ajtwin.store.registry import Registry
>>> folder = tempfile.mkdtemp()
>>> reg = Registry(os.path.join(folder, "a.sqlite")); _ = reg.add_machine("m1")
>>> export_machine(reg, "m1", os.path.join(folder, "m1.tar"))["n_prints"]
0
>>> other = Registry(os.path.join(folder, "b.sqlite"))
>>> import_machine(other, os.path.join(folder, "m1.tar"), as_name="m1-copy")["machine"]
'm1-copy'
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import io
import json
import os
import sqlite3
import tarfile
import tempfile
from pathlib import Path

import numpy as np

from ajtwin.store import arrays as _arrays
from ajtwin.store.registry import (
    LIVE_SESSION_TABLES,
    MACHINE_TABLES,
    PRINT_TABLES,
    SCHEMA_VERSION,
    Registry,
    RegistryError,
    clean_name,
    printable,
)

EXPORT_FORMAT = "ajtwin-machine-export"
EXPORT_FORMAT_VERSION = 1
_MEMBERS = ("manifest.json", "machine.sqlite")
_MAX_MANIFEST = 1 << 20
_MAX_DATABASE = 1 << 36  # 64 GiB


def file_bytes(path) -> int:
    """Size of a registry on disk: the file and its WAL."""
    total = 0
    for suffix in ("", "-wal"):
        p = Path(str(path) + suffix)
        if p.exists():
            total += p.stat().st_size
    return total


def _checkpoint(conn):
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")


def compact(
    registry: Registry,
    name: str,
    keep_covariances_days: float = 30.0,
    *,
    now: _dt.datetime | None = None,
    vacuum: bool = True,
) -> dict:
    """Apply the storage policy and the covariance retention to machine ``name``.

    Parameters
    ----------
    keep_covariances_days : float
        Prints ingested longer ago than this keep covariances only at their end and
        alarms; younger ones keep the policy's periodic key frames too.
    now : datetime, optional
        "Now" for the retention (tests); default the current UTC time.

    Returns
    -------
    dict: ``bytes_before``, ``bytes_after`` (file + WAL), ``prints``, ``reencoded``
    (version-1 prints converted), ``thinned`` (prints whose key frames were dropped),
    ``live_steps_dropped`` (per-step rows of closed live sessions, module docstring).
    """
    if not keep_covariances_days >= 0:
        raise RegistryError(f"--keep-covariances-days must be ≥ 0, got {keep_covariances_days}")
    machine = registry.machine(name)
    conn = registry._conn
    now = now or _dt.datetime.now(_dt.UTC)
    cutoff = now - _dt.timedelta(days=float(keep_covariances_days))
    _checkpoint(conn)
    before = file_bytes(registry.path)
    prints = conn.execute(
        "SELECT id, seq, ingested_at FROM prints WHERE machine_id = ? ORDER BY seq",
        (machine["id"],),
    ).fetchall()
    reencoded = thinned = 0
    for row in prints:
        stored = conn.execute(
            "SELECT name, npy, codec FROM print_arrays WHERE print_id = ?", (row["id"],)
        ).fetchall()
        try:
            ingested = _dt.datetime.fromisoformat(row["ingested_at"])
        except ValueError:
            ingested = now  # unreadable time: keep its key frames
        if ingested.tzinfo is None:
            ingested = ingested.replace(tzinfo=_dt.UTC)
        old = ingested < cutoff
        alarm_times = [
            t
            for r in conn.execute(
                "SELECT detected_s, onset_s FROM anomalies WHERE print_id = ?", (row["id"],)
            )
            for t in (r[0], r[1])
        ]
        decoded = {}
        for r in stored:
            try:
                decoded[r["name"]] = _arrays.decode(r["npy"], r["codec"])
            except ValueError as exc:
                raise RegistryError(
                    f"{registry.path}: registry damaged at print {row['seq']}, array "
                    f"{printable(r['name'])}: {exc}; nothing compacted from there on"
                ) from None
        legacy = any(r["codec"] == _arrays.NPY for r in stored)
        if legacy:
            every = -1.0 if old else None
            encoded = _arrays.encode_all(decoded, registry.policy, alarm_times, every_s=every)
            reencoded += 1
        elif old and "covariance_steps" in decoded:
            steps = decoded["covariance_steps"]
            n = int(decoded["time_s"].shape[0]) if "time_s" in decoded else int(steps.max()) + 1
            keep = _arrays.keyframe_steps(n, decoded.get("time_s"), -1.0, alarm_times)
            mask = np.isin(steps, keep)
            if mask.all():
                continue
            encoded = {
                "covariance_steps": _arrays.encode(steps[mask]),
                "covariance_keyframes": _arrays.encode(decoded["covariance_keyframes"][mask]),
            }
            thinned += 1
        else:
            continue
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.execute("DELETE FROM print_arrays WHERE print_id = ?", (row["id"],))
            for key in decoded:
                if key not in encoded and key not in ("covariances", "predicted_means"):
                    encoded[key] = (
                        next(r["codec"] for r in stored if r["name"] == key),
                        next(r["npy"] for r in stored if r["name"] == key),
                    )
            conn.executemany(
                "INSERT INTO print_arrays (print_id, name, npy, codec) VALUES (?, ?, ?, ?)",
                [(row["id"], key, blob, codec) for key, (codec, blob) in encoded.items()],
            )
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        if old and legacy:
            thinned += 1
    live_steps_dropped = _drop_closed_live_steps(conn, machine["name"], machine["id"])
    if vacuum:
        _checkpoint(conn)
        # from now on the file also shrinks when a live session closes (release_free_pages)
        conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
        conn.execute("VACUUM")
        _checkpoint(conn)
    return {
        "bytes_before": before,
        "bytes_after": file_bytes(registry.path),
        "prints": len(prints),
        "reencoded": reencoded,
        "thinned": thinned,
        "live_steps_dropped": live_steps_dropped,
    }


def _drop_closed_live_steps(conn, name: str, machine_id: int) -> int:
    """Per-step rows of the machine's closed live sessions whose print is stored (module
    docstring); returns how many steps were dropped. One transaction."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        sessions = [
            r[0]
            for r in conn.execute(
                "SELECT s.id FROM live_sessions s JOIN prints p ON p.id = s.print_id "
                "WHERE s.machine = ? AND s.status = 'closed' AND p.machine_id = ?",
                (name, machine_id),
            )
        ]
        dropped = 0
        for session_id in sessions:
            dropped += conn.execute(
                "DELETE FROM live_samples WHERE session_id = ?", (session_id,)
            ).rowcount
            conn.execute("DELETE FROM live_states WHERE session_id = ?", (session_id,))
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise
    return dropped


# ---------------------------------------------------------------------- copy a machine
def _columns(conn, table) -> list[str]:
    return [r[1] for r in conn.execute(f"PRAGMA table_info({table})").fetchall()]


def _has_integer_id(conn, table) -> bool:
    return any(
        r[1] == "id" and r[5] == 1 and r[2].upper() == "INTEGER"
        for r in conn.execute(f"PRAGMA table_info({table})").fetchall()
    )


def _insert(dst, table, row: dict, columns) -> int:
    keys = [c for c in columns if c in row]
    cur = dst.execute(
        f"INSERT INTO {table} ({', '.join(keys)}) VALUES ({', '.join('?' * len(keys))})",
        [row[k] for k in keys],
    )
    return cur.lastrowid


def copy_machine(
    src: sqlite3.Connection, dst: sqlite3.Connection, name: str, new_name: str
) -> dict:
    """Copy machine ``name`` with every machine-, print- and live-session-scoped row from
    ``src`` into ``dst`` as ``new_name`` in one transaction of ``dst`` (ids renumbered).

    ``src`` is read in one snapshot (a live twin may be appending to an open session).

    Returns
    -------
    dict: ``prints``, ``live_sessions``, ``open_live_sessions`` (copied counts).
    """
    src.execute("BEGIN")  # deferred: one read snapshot of src for the whole copy
    try:
        return _copy_machine(src, dst, name, new_name)
    finally:
        src.execute("ROLLBACK")  # nothing was written to src


def _copy_machine(src, dst, name, new_name) -> dict:
    src_tables = {r[0] for r in src.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    machine = src.execute("SELECT * FROM machines WHERE name = ?", (name,)).fetchone()
    if machine is None:
        raise RegistryError(f"no machine {printable(name)!r} to copy")
    dst.execute("BEGIN IMMEDIATE")
    try:
        if dst.execute("SELECT 1 FROM machines WHERE name = ?", (new_name,)).fetchone():
            raise RegistryError(
                f"machine {printable(new_name)!r} already exists; import it under another "
                "name with --as NAME"
            )
        if dst.execute(
            "SELECT 1 FROM live_sessions WHERE machine = ? AND status = 'open'", (new_name,)
        ).fetchone():
            raise RegistryError(
                f"an open live session of {printable(new_name)!r} is in this registry; "
                "import the machine under another name with --as NAME"
            )
        row = dict(zip(machine.keys(), machine))
        row.pop("id")
        row["name"] = new_name
        new_machine = _insert(dst, "machines", row, _columns(dst, "machines"))
        print_ids = {}
        for table in MACHINE_TABLES:
            if table not in src_tables:
                continue
            columns = _columns(dst, table)
            drop_id = _has_integer_id(dst, table)
            cursor = src.execute(
                f"SELECT * FROM {table} WHERE machine_id = ? ORDER BY rowid", (machine["id"],)
            )
            for r in cursor:
                row = dict(zip(r.keys(), r))
                old_id = row.get("id")
                if drop_id:
                    row.pop("id", None)
                row["machine_id"] = new_machine
                new_id = _insert(dst, table, row, columns)
                if table == "prints":
                    print_ids[old_id] = new_id
        for table in PRINT_TABLES:
            if table not in src_tables:
                continue
            columns = _columns(dst, table)
            drop_id = _has_integer_id(dst, table)
            for old_print, new_print in print_ids.items():
                for r in src.execute(f"SELECT * FROM {table} WHERE print_id = ?", (old_print,)):
                    row = dict(zip(r.keys(), r))
                    if drop_id:
                        row.pop("id", None)
                    row["print_id"] = new_print
                    _insert(dst, table, row, columns)
        n_sessions = n_open = 0
        if "live_sessions" in src_tables:
            columns = _columns(dst, "live_sessions")
            sessions = src.execute(
                "SELECT * FROM live_sessions WHERE machine = ? ORDER BY id", (name,)
            ).fetchall()
            for r in sessions:
                row = dict(zip(r.keys(), r))
                old_session = row.pop("id")
                row["machine"] = new_name
                if row.get("print_id") is not None:
                    row["print_id"] = print_ids.get(row["print_id"])
                new_session = _insert(dst, "live_sessions", row, columns)
                n_sessions += 1
                n_open += row["status"] == "open"
                for table in LIVE_SESSION_TABLES:
                    if table not in src_tables:
                        continue
                    table_columns = _columns(dst, table)
                    for s_row in src.execute(
                        f"SELECT * FROM {table} WHERE session_id = ?", (old_session,)
                    ):
                        s_row = dict(zip(s_row.keys(), s_row))
                        s_row["session_id"] = new_session
                        _insert(dst, table, s_row, table_columns)
        dst.execute("COMMIT")
    except BaseException:
        dst.execute("ROLLBACK")
        raise
    return {"prints": len(print_ids), "live_sessions": n_sessions, "open_live_sessions": n_open}


def _sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def export_machine(registry: Registry, name: str, out) -> dict:
    """Write machine ``name`` (every print, array, anomaly, calibration, maintenance event
    and live session) to the tar ``out``.

    Returns the manifest. The tar is written to a temporary name and renamed, so a killed
    export never leaves a half archive under ``out``.
    """
    from ajtwin import __version__

    machine = registry.machine(name)
    out = Path(out)
    with tempfile.TemporaryDirectory(prefix="ajtwin-export-") as tmp:
        db_path = Path(tmp) / "machine.sqlite"
        part = Registry(db_path)
        copied = copy_machine(registry._conn, part._conn, machine["name"], machine["name"])
        part._conn.execute("PRAGMA journal_mode=DELETE")  # one self-contained file
        part.close()
        manifest = {
            "format": EXPORT_FORMAT,
            "format_version": EXPORT_FORMAT_VERSION,
            "schema_version": SCHEMA_VERSION,
            "machine": machine["name"],
            "n_prints": copied["prints"],
            "live_sessions": copied["live_sessions"],
            "open_live_sessions": copied["open_live_sessions"],
            "exported_at": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "ajtwin_version": __version__,
            "database_sha256": _sha256(db_path),
            "database_bytes": db_path.stat().st_size,
        }
        partial = out.with_name(out.name + ".partial")
        with tarfile.open(partial, "w") as tar:
            data = json.dumps(manifest, indent=2).encode()
            info = tarfile.TarInfo("manifest.json")
            info.size = len(data)
            info.mtime = int(_dt.datetime.now(_dt.UTC).timestamp())
            tar.addfile(info, io.BytesIO(data))
            tar.add(db_path, arcname="machine.sqlite", recursive=False)
        os.replace(partial, out)
    return manifest


def _bad(archive, why) -> RegistryError:
    return RegistryError(f"{archive}: not an ajtwin machine export ({why}); nothing imported")


def import_machine(registry: Registry, archive, as_name: str | None = None) -> dict:
    """Import the machine of an :func:`export_machine` tar into ``registry``.

    Refuses (RegistryError, registry unchanged) an archive that is not a tar, has any
    member but ``manifest.json`` and ``machine.sqlite`` as regular files, a wrong
    checksum, a newer format or schema version, or a machine name already in use.

    Returns
    -------
    dict: ``machine`` (its name here), ``n_prints``, ``live_sessions``,
    ``open_live_sessions``, ``manifest``, ``migrated`` (messages).
    """
    archive = Path(archive)
    if not archive.is_file():
        raise _bad(archive, "not a regular file")
    try:
        tar = tarfile.open(archive, "r:*")
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise _bad(archive, f"not a tar archive: {exc}") from None
    with tar, tempfile.TemporaryDirectory(prefix="ajtwin-import-") as tmp:
        try:
            members = tar.getmembers()
        except (tarfile.TarError, OSError, EOFError) as exc:
            raise _bad(archive, f"damaged tar: {exc}") from None
        names = [m.name for m in members]
        if sorted(names) != sorted(_MEMBERS):
            shown = ", ".join(printable(n) for n in names[:6])
            raise _bad(archive, f"expected exactly {list(_MEMBERS)}, found [{shown}]")
        by_name = {m.name: m for m in members}
        for m in members:
            if not m.isreg():
                raise _bad(archive, f"{m.name} is not a regular file (link or device?)")
        if by_name["manifest.json"].size > _MAX_MANIFEST:
            raise _bad(archive, "manifest.json is too large")
        if by_name["machine.sqlite"].size > _MAX_DATABASE:
            raise _bad(archive, "machine.sqlite is too large")
        try:
            manifest = json.loads(tar.extractfile(by_name["manifest.json"]).read())
        except (ValueError, tarfile.TarError, OSError, EOFError) as exc:
            raise _bad(archive, f"unreadable manifest.json: {exc}") from None
        if not isinstance(manifest, dict) or manifest.get("format") != EXPORT_FORMAT:
            raise _bad(archive, "manifest.json is not an ajtwin machine manifest")
        for key, known in (
            ("format_version", EXPORT_FORMAT_VERSION),
            ("schema_version", SCHEMA_VERSION),
        ):
            value = manifest.get(key)
            if not isinstance(value, int) or value < 1:
                raise _bad(archive, f"manifest {key} {value!r} is not a version number")
            if value > known:
                raise RegistryError(
                    f"{archive}: written by a newer ajtwin ({key} {value}, this one knows up "
                    f"to {known}); upgrade ajtwin to import it"
                )
        # our own file name in our own folder: the member's name is never used as a path
        db_path = Path(tmp) / "machine.sqlite"
        h = hashlib.sha256()
        try:
            source = tar.extractfile(by_name["machine.sqlite"])
            with open(db_path, "wb") as fh:
                for block in iter(lambda: source.read(1 << 20), b""):
                    h.update(block)
                    fh.write(block)
        except (tarfile.TarError, OSError, EOFError) as exc:
            raise _bad(archive, f"damaged machine.sqlite: {exc}") from None
        if h.hexdigest() != manifest.get("database_sha256"):
            raise _bad(archive, "machine.sqlite does not match the manifest's SHA-256")
        source_name = manifest.get("machine")
        if not isinstance(source_name, str):
            raise _bad(archive, "manifest has no machine name")
        new_name = clean_name(as_name if as_name is not None else source_name)
        try:
            part = Registry(db_path, create=False)
        except RegistryError as exc:
            raise _bad(archive, str(exc)) from None
        try:
            part.machine(source_name)
            # every print and array must decode before anything is copied
            for (print_id,) in part._conn.execute("SELECT id FROM prints").fetchall():
                part.get_print(print_id)
                part.print_arrays(print_id)
        except RegistryError as exc:
            part.close()
            raise _bad(archive, str(exc)) from None
        try:
            copied = copy_machine(part._conn, registry._conn, source_name, new_name)
        except sqlite3.Error as exc:
            raise _bad(archive, f"machine.sqlite: {exc}") from None
        finally:
            migrated = list(part.migrated)
            part.close()
    return {
        "machine": new_name,
        "n_prints": copied["prints"],
        "live_sessions": copied["live_sessions"],
        "open_live_sessions": copied["open_live_sessions"],
        "manifest": manifest,
        "migrated": migrated,
    }
