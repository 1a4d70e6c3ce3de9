"""A machine's export to and import from a tar archive (``ajtwin machine export|import``).

``export_machine`` writes ``manifest.json`` (format and schema version, machine, print
count, SHA-256 of the database) and ``machine.sqlite`` (a registry holding that machine
only) into an uncompressed tar; ``import_machine`` checks the archive strictly (exactly
those two regular files, sizes, checksum, versions), reads
the members into a private temporary folder under its own file names (never
``extract``: no path traversal, no links) and copies the machine in one transaction.
Export and import carry the machine's calibration history (provenance, standard errors)
and maintenance events (:mod:`ajtwin.store.calibration`; compaction leaves them as they
are), so the importing registry starts the machine's next print exactly as the exporting
one would. They carry the machine's live-twin sessions too (:mod:`ajtwin.store.live_log`):
closed ones as history, and an open one (a print still running, or a client that was
stopped mid-print) whole, so ``ajtwin live`` on the importing registry resumes it.
An archive holds the prints as they were stored; results of ``ajtwin reprocess`` stay in
the registry (``ajtwin store copy`` carries them).
The registry may be an SQLite file or a PostgreSQL database; the archive's member is
always an SQLite file.

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

from ajtwin import __version__
from ajtwin.store.registry import (
    SCHEMA_VERSION,
    Registry,
    RegistryError,
    check_new_name,
    printable,
)

EXPORT_FORMAT = "ajtwin-machine-export"
EXPORT_FORMAT_VERSION = 1
_MEMBERS = ("manifest.json", "machine.sqlite")
_MAX_MANIFEST = 1 << 20
_MAX_DATABASE = 1 << 36  # 64 GiB


# ---------------------------------------------------------------------- copy a machine
def copy_machine(src: Registry, dst: Registry, name: str, new_name: str) -> dict:
    """Copy machine ``name`` with every machine-, print- and live-session-scoped row from
    registry ``src`` into registry ``dst`` as ``new_name`` in one transaction of ``dst``
    (ids renumbered; the prints as stored, not their reprocessed versions).

    ``src`` is read in one snapshot (a live twin may be appending to an open session).

    Returns
    -------
    dict: ``prints``, ``live_sessions``, ``open_live_sessions`` (copied counts).
    """
    return dst.load_machine(src.machine_rows(name), new_name)


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
    machine = registry.machine(name)
    out = Path(out)
    with tempfile.TemporaryDirectory(prefix="ajtwin-export-") as tmp:
        db_path = Path(tmp) / "machine.sqlite"
        part = Registry(db_path)
        copied = copy_machine(registry, part, machine["name"], machine["name"])
        part.self_contained()  # one file, no journal beside it
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


def import_machine(
    registry: Registry, archive, as_name: str | None = None, *, end_state_check=None
) -> dict:
    """Import the machine of an :func:`export_machine` tar into ``registry``.

    Refuses (RegistryError, registry unchanged) an archive that is not a tar, has any
    member but ``manifest.json`` and ``machine.sqlite`` as regular files, a wrong
    checksum, a newer format or schema version, or a machine name already in use.
    ``end_state_check``: as :class:`~ajtwin.store.registry.Registry`'s, for an archive of
    a version-1 registry.

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
        new_name = check_new_name(as_name if as_name is not None else source_name)
        try:
            part = Registry(db_path, create=False, end_state_check=end_state_check)
        except RegistryError as exc:
            raise _bad(archive, str(exc)) from None
        try:
            part.machine(source_name)
            # every print and array must decode before anything is copied
            for row in part.print_rows(source_name):
                part.get_print(row["id"])
                part.print_arrays(row["id"])
        except RegistryError as exc:
            part.close()
            raise _bad(archive, str(exc)) from None
        try:
            copied = copy_machine(part, registry, source_name, new_name)
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
