"""``ajtwin store copy|info|versions``: the registry as a whole — move a lab's registry
between SQLite and PostgreSQL, say what and where it is, list its versions of results
(docs/howto/lab-with-several-printers.md)."""

from __future__ import annotations

from pathlib import Path

import click

from ajtwin.cli.options import open_registry, store_location, store_option
from ajtwin.store.copy import copy_registry
from ajtwin.store.registry import RegistryError


@click.group()
def store():
    """The registry as a whole: copy it (SQLite ⇄ PostgreSQL), what it holds, its versions."""


def _password_option(name: str, which: str):
    return click.option(
        f"--{name}",
        type=click.Path(dir_okay=False, path_type=Path),
        default=None,
        help=f"PostgreSQL {which}: a file whose first line is the password (or $PGPASSWORD, "
        "~/.pgpass).",
    )


@store.command("copy")
@click.argument("source", metavar="SRC")
@click.argument("destination", metavar="DST")
@_password_option("src-password-file", "SRC")
@_password_option("dst-password-file", "DST")
@click.option("--progress/--no-progress", default=True, show_default=True)
def copy_command(source, destination, src_password_file, dst_password_file, progress):
    """Copy the whole registry SRC into DST (each an SQLite file's path or a PostgreSQL
    URL): every machine, print, array, calibration, live session and reprocessed version,
    ids kept. Run it again after an interruption: it goes on where it stopped. Checked at
    the end (row counts and content digests of every table on both sides)."""
    # lazy CLI loading: imported when the command runs, not for --help
    from tqdm import tqdm

    src = open_registry(store_location(source, src_password_file))
    dst = open_registry(store_location(destination, dst_password_file), create=True)
    total = sum(src.machine(m["name"])["n_prints"] for m in src.machines())
    bar = tqdm(total=total, unit="print", disable=not progress, desc="copying")
    try:
        done = copy_registry(src, dst, progress=lambda table: bar.update(table == "prints"))
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    finally:
        bar.close()
    resumed = " (taken up where an earlier copy stopped)" if done["resumed"] else ""
    click.echo(
        f"copied {done['machines']} machine(s), {done['prints']} print(s) and "
        f"{done['live_sessions']} live session(s) from {src.path} to {dst.path}{resumed}"
    )
    rows = sum(done["tables"].values())
    click.echo(f"checked: {len(done['tables'])} tables, {rows} rows, the same on both sides")


@store.command("info")
@store_option
def info_command(store):
    """Where the registry is, which database, its schema version, size and machines."""
    reg = open_registry(store)
    click.echo(f"registry {reg.path}")
    click.echo(f"  database: {reg.kind}, schema version {reg.info('schema_version')}")
    click.echo(f"  identity: {reg.info('registry_id')}")
    copied = reg.info("copy_of")
    if copied:
        click.echo(f"  a copy of registry {copied} ({reg.info('copy_state')})")
    click.echo(f"  size: {reg.size_bytes() / 1e6:.1f} MB")
    click.echo(f"  machines: {len(reg.machines())}")


@store.command("versions")
@store_option
def versions_command(store):
    """The versions of results: 1 the prints as stored, then each `ajtwin reprocess` run."""
    reg = open_registry(store)
    for v in reg.versions():
        when = f", {v['created_at']}" if v["created_at"] else ""
        click.echo(
            f"version {v['id']}: {v['reason']} ({v['n_prints']} print(s), {v['status']}{when})"
        )
