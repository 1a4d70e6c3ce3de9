"""``ajtwin simulate`` and ``ajtwin plot`` (registered in :mod:`ajtwin.cli`)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from ajtwin.io.cli_options import BoundedFloat


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
    "machine_profile",
    default=None,
    help="A machine profile instead: 'paper' (L_w ≈ 43, L_o ≈ 29 µm at 23/50 sccm) or 'nominal'.",
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
    machine_profile,
    truth_generator,
    list_only,
):
    """Virtual printer: simulate one print with known truth into a record file.

    Example: ajtwin simulate --scenario exp3 --seed 1 --out print.parquet
    """
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
    from ajtwin.io.records import write_record
    from ajtwin.simulation.printer import simulate as run

    previous = None
    if continue_from is not None:
        from ajtwin.io.records import RecordError, read_record

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
            machine=machine_profile,
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
def plot(record_path, output, aliases, nominal):
    """Plot a print record: inputs, outputs and (when present) truth in one figure.

    Example: ajtwin plot print.parquet -o print.png
    """
    from ajtwin.io.records import RecordError, read_record
    from ajtwin.simulation.plotting import plot_record

    try:
        record = read_record(record_path, aliases=aliases)
    except RecordError as exc:
        raise click.ClickException(str(exc)) from None
    plot_record(record, output, nominal=nominal)
    click.echo(f"{output}: {record.meta.get('scenario')} ({len(record)} samples)")


@click.command("openloop")
@click.option("--minutes", default=90.0, show_default=True, help="Length of the run.")
@click.option("--current-ma", default=EXP1_INPUTS[0], show_default=True)
@click.option("--carrier-sccm", default=EXP1_INPUTS[1], show_default=True)
@click.option("--sheath-sccm", default=EXP1_INPUTS[2], show_default=True)
@click.option("--droplet-um", default=3.5, show_default=True, help="Initial d_a.")
@click.option("--vial-ml", default=1.0, show_default=True, help="Initial V_l.")
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write a PNG of states and outputs.",
)
@click.option(
    "--out", type=click.Path(dir_okay=False), default=None, help="Write the trajectory as CSV."
)
def openloop(minutes, current_ma, carrier_sccm, sheath_sccm, droplet_um, vial_ml, plot_path, out):
    """Open-loop run of the digital model at constant inputs (default: Exp 1).

    Prints the states at 30/60/90 min (or the run's thirds).
    """
    model = DigitalModel.default()
    u = np.array([current_ma, carrier_sccm, sheath_sccm], dtype=float)
    steps = int(round(minutes * 60))
    if steps < 1:
        raise click.BadParameter("must be at least 1/60 min", param_hint="--minutes")
    try:
        phi0 = float(model.steady_aerosol_fraction(u, vial_ml))
        x0 = np.array([droplet_um, vial_ml, 0.0, 0.0, phi0])
        states, outputs = run_open_loop(model, x0, np.tile(u, (steps, 1)))
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    marks = [30, 60, 90] if minutes >= 90 else [minutes / 3, 2 * minutes / 3, minutes]
    header = "time_min  " + "  ".join(f"{n:>22s}" for n in STATE_NAMES)
    click.echo(
        f"open loop: I_A {current_ma:g} mA, Q_c {carrier_sccm:g} sccm, "
        f"Q_s {sheath_sccm:g} sccm, x0 = {np.array2string(x0, precision=4)}"
    )
    click.echo(header)
    for m in marks:
        k = min(int(round(m * 60)), steps)
        click.echo(f"{m:8.1f}  " + "  ".join(f"{v:22.6g}" for v in states[k]))
    if out:
        import pandas as pd

        frame = pd.DataFrame(states, columns=STATE_NAMES)
        frame.insert(0, "time_s", np.arange(steps + 1, dtype=float))
        for i, name in enumerate(OUTPUT_NAMES):
            frame["pred_" + name] = outputs[:, i]
        frame.to_csv(out, index=False)
        click.echo(f"wrote {out}")
    if plot_path:
        plot_open_loop(
            np.arange(steps + 1),
            states,
            outputs,
            plot_path,
            title=f"Open-loop digital model, Q_c {carrier_sccm:g} / Q_s {sheath_sccm:g}"
            f" sccm, I_A {current_ma:g} mA",
        )
        click.echo(f"wrote {plot_path}")
