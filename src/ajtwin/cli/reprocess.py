"""``ajtwin reprocess``: the twin re-run over stored prints on Dask, stored as a new version
of results beside the old (docs/howto/lab-with-several-printers.md)."""

from __future__ import annotations

import datetime as _dt

import click

from ajtwin.cli.options import open_registry, store_option
from ajtwin.store.registry import RegistryError


def _since(value):
    if value is None:
        return None
    try:
        _dt.datetime.fromisoformat(value)
    except ValueError:
        raise click.BadParameter(
            f"{value!r} is not a date (YYYY-MM-DD, or YYYY-MM-DDTHH:MM:SS)", param_hint="--since"
        ) from None
    return value


@click.command()
@click.option(
    "--machines",
    default=None,
    metavar="NAME[,NAME...]",
    help="Only these machines (default: every machine of the registry).",
)
@click.option("--since", default=None, metavar="DATE", help="Only prints ingested from DATE on.")
@click.option(
    "--workers",
    type=click.IntRange(min=1, max=256),
    default=2,
    show_default=True,
    help="Worker processes of the local Dask cluster (one print at a time each).",
)
@click.option(
    "--scheduler",
    default=None,
    metavar="tcp://HOST:8786",
    help="A running Dask scheduler: its workers do the work (they must reach the same "
    "PostgreSQL registry).",
)
@click.option("--reason", default="", help="Why (kept with the version): 'new calibration'.")
@click.option("--progress/--no-progress", default=True, show_default=True)
@store_option
def reprocess(machines, since, workers, scheduler, reason, progress, store):
    """Re-run every machine's twin over its stored prints (after a model update or a new
    calibration), in each machine's order, from the new chain's starts; the results are
    stored as a new version (nothing is overwritten): `ajtwin machine history NAME
    --version N`, `ajtwin store versions`."""
    # lazy CLI loading: imported when the command runs, not for --help
    from tqdm import tqdm

    # lazy CLI loading: the engine loads JAX; --help must not
    from ajtwin.engine.reprocess import reprocess as run

    names = None if machines is None else [m.strip() for m in machines.split(",") if m.strip()]
    registry = open_registry(store, write=True)
    registry.close()
    bar = tqdm(unit="print", disable=not progress, desc="reprocessing")

    def advance(done, total):
        bar.total = total
        bar.n = done
        bar.refresh()

    try:
        done = run(store, machines=names, since=_since(since), workers=workers,
                   scheduler=scheduler, reason=reason, progress=advance)  # fmt: skip
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    finally:
        bar.close()
    click.echo(
        f"version {done['version']}: {done['prints']} print(s) of {done['machines']} "
        f"machine(s) re-run on {done['workers']} worker(s) in {done['seconds']:.0f} s "
        f"({done['prints_per_min']:.1f} prints/min)"
    )
    click.echo(f"see: ajtwin machine history NAME --version {done['version']} --store {store}")
