"""Moving a lab: a whole registry copied into another, SQLite ⇄ PostgreSQL (``ajtwin store copy``).

:func:`copy_registry` copies every machine with all its rows — prints, arrays, parts,
anomalies, jobs, calibrations, maintenance, live sessions and the reprocessed versions
— keeping every id, so that ``machine history`` and ``machine show`` print the same on
both. Each print (with its rows) is one transaction of the destination: a copy stopped
midway (a kill, a lost network) is taken up again by running the same command; what is
already there is skipped, what was half-written was rolled back. The destination must be
empty or hold an unfinished copy of the same source (``info.copy_of``, the source's
``registry_id``); anything else is refused.

When every machine is in, the copy is checked: each copied table's row count and content
digest (:meth:`~ajtwin.store.registry.Registry.table_digest`: integers, floats to the bit,
text and bytes, whatever the database) must agree on both sides; the destination is
marked done only then. Drafts of running prints and live writers' claims are not copied
(they belong to processes of the old place); a live print still running is copied as its
open session, which ``ajtwin live`` resumes on the new registry.

Example
-------
>>> import os, tempfile
>>> from ajtwin.store.registry import Registry
>>> folder = tempfile.mkdtemp()
>>> src = Registry(os.path.join(folder, "a.sqlite")); _ = src.add_machine("lab1")
>>> dst = Registry(os.path.join(folder, "b.sqlite"))
>>> copy_registry(src, dst)["machines"]
1
"""

from __future__ import annotations

from ajtwin.store.registry import Registry, RegistryError, printable

#: tables whose rows a copy carries and checks (not: info, drafts, writers' claims)
COPIED_TABLES = (
    "machines",
    "prints",
    "print_arrays",
    "print_array_parts",
    "anomalies",
    "print_jobs",
    "calibrations",
    "maintenance_events",
    "live_sessions",
    "live_samples",
    "live_states",
    "live_events",
    "versions",
    "print_versions",
    "print_version_arrays",
    "print_version_anomalies",
)


def copy_registry(src: Registry, dst: Registry, progress=None) -> dict:
    """Copy registry ``src`` into ``dst`` (module docstring).

    Parameters
    ----------
    progress : callable(str), optional
        Called after each print and live session copied, with the table's name.

    Returns
    -------
    dict: ``machines``, ``prints``, ``live_sessions`` (in the source), ``resumed`` (the
    destination held an unfinished copy), ``tables`` (table → rows, as checked).
    """
    source_id = src.info("registry_id")
    if dst.info("registry_id") == source_id:
        raise RegistryError(f"{dst.path} is {src.path} itself; give another destination")
    resumed = dst.info("copy_of") == source_id and dst.info("copy_state") == "running"
    if dst.info("copy_of") == source_id and dst.info("copy_state") == "done":
        resumed = True  # copied before: the check below says whether it still agrees
    elif not resumed and dst.machines():
        shown = ", ".join(printable(m["name"]) for m in dst.machines()[:5])
        raise RegistryError(
            f"{dst.path} already holds machines ({shown}) that are not a copy of {src.path}; "
            "copy into an empty registry (a new SQLite file, or an empty PostgreSQL "
            "database or schema)"
        )
    dst.mark_copy(source_id, "running")
    dst.load_versions(src.version_rows())
    machines = [m["name"] for m in src.machines()]
    counts = {"prints": 0, "live_sessions": 0}
    for name in machines:
        copied = dst.load_machine(src.machine_rows(name, versions=True), name, keep_ids=True,
                                  progress=progress)  # fmt: skip
        counts["prints"] += copied["prints"]
        counts["live_sessions"] += copied["live_sessions"]
    tables = check_copy(src, dst)
    dst.mark_copy(source_id, "done")
    return {"machines": len(machines), **counts, "resumed": resumed, "tables": tables}


def check_copy(src: Registry, dst: Registry) -> dict:
    """Compare every copied table of ``src`` and ``dst`` (rows and content digest);
    :class:`RegistryError` naming the tables that differ. Returns table → rows."""
    out, differ = {}, []
    for table in COPIED_TABLES:
        a, b = src.table_digest(table), dst.table_digest(table)
        if a != b:
            differ.append(f"{table} ({a[0]} rows there, {b[0]} here)")
        out[table] = a[0]
    if differ:
        raise RegistryError(
            f"{dst.path}: the copy of {src.path} differs in {', '.join(differ)}; run the copy "
            "again (it goes on where it stopped), and if it still differs, copy into an empty "
            "registry"
        )
    return out
