"""``ajtwin simulate`` and ``ajtwin plot`` (registered in :mod:`ajtwin.cli`)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from ajtwin.cli.options import BoundedFloat, csv_dialect_option
from ajtwin.io.records import RecordError, read_record, write_record


@click.command()
@click.option(
    "--scenario",
    "-s",
    default="exp1",
    show_default=True,
    help="Packaged scenario name (see --list) or a path to your own scenario .toml.",
)
@click.option(
    "--seed",
    "-n",
    default=0,
    show_default=True,
    type=click.IntRange(min=0),
    help="Seed of every random process; same seed, same record.",
)
@click.option(
    "--out",
    "-o",
    "out",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Output record (.parquet or .csv).",
)
@click.option(
    "--duration-min",
    type=BoundedFloat(0.0, None),  # click's FloatRange lets NaN through
    default=None,
    help="Override the scenario's duration [min].",
)
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also draw the record to this PNG.",
)
@click.option(
    "--continue-from",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="A previous virtual print of the same machine: start from its final vial level "
    "and deposits.",
)
@click.option(
    "--machine-seed",
    type=click.IntRange(min=0),
    default=None,
    help="Draw a virtual machine that differs from the nominal model (line resistances, "
    "gauges, line model, camera, Q_m gain; data/machine_variation.toml). Default: nominal.",
)
@click.option(
    "--machine",
    "machine_name",
    default=None,
    help="A named machine instead: 'paper' (L_w ≈ 43, L_o ≈ 29 µm at 23/50 sccm) or 'nominal'.",
)
@click.option(
    "--truth",
    "truth_generator",
    type=click.Choice(["model", "alt"]),
    default="model",
    show_default=True,
    help="Truth generator: 'alt' is the second, structurally different one (evaluation only; "
    "ajtwin.simulation.truth_alt).",
)
@click.option("--list", "list_only", is_flag=True, help="List the packaged scenarios and exit.")
def simulate(
    scenario,
    seed,
    out,
    duration_min,
    plot_path,
    continue_from,
    machine_seed,
    machine_name,
    truth_generator,
    list_only,
):
    """Virtual printer: simulate one print with known truth into a record file.

    Example: ajtwin simulate --scenario exp3 --seed 1 --out print.parquet
    """
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.simulation.scenarios import list_scenarios, load_scenario

    if list_only:
        for name in list_scenarios():
            s = load_scenario(name)
            click.echo(f"{name:24s} {s.config['scenario']['description']}")
        return
    if out is None:
        raise click.UsageError("--out is required (a .parquet or .csv path)")
    if out.suffix.lower() not in (".parquet", ".pq", ".csv"):
        raise click.BadParameter(f"{out}: use a .parquet or .csv suffix", param_hint="--out")
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.simulation.printer import simulate as run

    previous = None
    if continue_from is not None:
        try:
            previous = read_record(continue_from)
        except RecordError as exc:
            raise click.ClickException(str(exc)) from None
    t0 = time.perf_counter()
    try:
        record = run(
            scenario,
            seed,
            duration_min,
            continue_from=previous,
            machine=machine_name,
            machine_seed=machine_seed,
            truth_generator=truth_generator,
        )
    except (ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    elapsed = time.perf_counter() - t0
    write_record(record, out)
    meta = record.meta
    onset = meta["fault_onset_s"]
    fault = meta["fault_kind"] + (f" from {onset / 60:.1f} min" if onset is not None else "")
    click.echo(
        f"{out}: {meta['scenario']} seed {seed}, {len(record)} s, fault {fault} "
        f"(simulated in {elapsed:.2f} s)"
    )
    if "machine" in meta:
        cal = meta["machine"]["equivalent_calibration"]
        click.echo(
            f"machine {meta['machine']['name']}: "
            + ", ".join(f"{k} {v:.4g}" for k, v in cal.items())
        )
    if plot_path is not None:
        # lazy CLI loading: imported when the command runs, not for --help
        from ajtwin.simulation.plotting import plot_record

        plot_record(record, plot_path)
        click.echo(f"{plot_path}: plot")


@click.command()
@click.argument("record_path", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--output",
    "-o",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Image file (.png, .pdf, .svg).",
)
@click.option(
    "--aliases",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Extra column-alias TOML file for a machine log.",
)
@click.option(
    "--nominal/--no-nominal",
    default=True,
    show_default=True,
    help="Overlay the nominal model's open-loop prediction when truth is present.",
)
@csv_dialect_option
def plot(record_path, output, aliases, nominal, csv_dialect):
    """Plot a print record: inputs, outputs and (when present) truth in one figure.

    Example: ajtwin plot print.parquet -o print.png
    """
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.simulation.plotting import plot_record

    try:
        record = read_record(record_path, aliases=aliases, dialect=csv_dialect)
    except RecordError as exc:
        raise click.ClickException(str(exc)) from None
    plot_record(record, output, nominal=nominal)
    click.echo(f"{output}: {record.meta.get('scenario')} ({len(record)} samples)")
