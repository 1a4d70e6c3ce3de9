"""``ajtwin machine commission|maintain|calibrations`` (docs/calibration.md, SPEC §11)."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ajtwin.io.cli_options import record_options
from ajtwin.store.cli import open_registry, store_option


@click.command("commission")
@click.argument("name")
@click.argument("record", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option(
    "--known",
    "known_items",
    multiple=True,
    help="A state known at the start, NAME=VALUE±STD (e.g. droplet_diameter_um=3.5±0.2); "
    "repeatable. Pins what the print confounds (d_a with the line offsets, φ_A with the "
    "Q_m gain).",
)
@click.option("--vial-ml", default=1.0, show_default=True, help="The weighed fill [mL].")
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write the calibration as a TOML file (for `ajtwin estimate --calibration`).",
)
@click.option(
    "--no-registry",
    is_flag=True,
    help="Only fit (and write --out); do not store it in the registry.",
)
@record_options
@store_option
def commission(
    name, record, known_items, vial_ml, out_path, no_registry, csv_dialect, aliases, store
):
    """Fit machine NAME's calibration from a commissioning print RECORD.

    The print must start from a cleaned nozzle and a known fill and step Q_c, Q_s (and
    I_A) across the operating window (`ajtwin simulate --scenario commissioning`).
    Prints each calibration parameter with its standard error and whether the print
    determined it; stores it in the registry (the history is kept).
    """
    from ajtwin.estimation.commission import CommissioningError, commission, parse_known
    from ajtwin.io.records import RecordError, read_record
    from ajtwin.model.calibration import write_calibration_file
    from ajtwin.store.calibration import save_calibration
    from ajtwin.store.registry import RegistryError

    try:
        known = parse_known(known_items)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--known") from None
    reg = None
    if not no_registry:
        reg = open_registry(store)
        try:
            reg.machine(name)
        except RegistryError as exc:
            raise click.ClickException(str(exc)) from None
    try:
        rec = read_record(record, aliases=aliases, dialect=csv_dialect)
        result = commission(rec, known=known, vial_fill_ml=vial_ml, where=str(record))
    except (RecordError, CommissioningError, ValueError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"commissioning of {name} from {record} ({result.n_samples} s):")
    click.echo(f"  {'parameter':26s} {'value':>11s} {'std error':>10s} {'prior σ':>9s}  print")
    for row in result.table():
        status = "determined" if row["determined"] else "NOT determined (prior)"
        click.echo(
            f"  {row['parameter']:26s} {row['value']:11.5g} {row['std_error']:10.3g} "
            f"{row['prior_std']:9.3g}  {status}"
        )
    for note in result.notes:
        click.echo(f"  note: {note}")
    click.echo(f"  mean NIS per output {result.mean_nis:.2f} (1 = the calibrated model fits)")
    factors = ", ".join(f"{v:.2f}" for v in np.asarray(result.noise_factors))
    click.echo(f"  output noise of this machine / tuned σ (L_w, L_o, P_c, P_s, Q_m): {factors}")
    provenance = {
        "machine": name,
        "print": str(record),
        "samples": result.n_samples,
        "vial_fill_mL": vial_ml,
        "priors": {k: f"{v[0]:.6g}±{v[1]:.3g}" for k, v in result.priors.items()},
    }
    if out_path is not None:
        from ajtwin.model import OUTPUT_NAMES

        write_calibration_file(
            out_path,
            result.calibration,
            result.std,
            provenance,
            covariance=result.calibration_cov,
            noise_factors=dict(zip(OUTPUT_NAMES, np.asarray(result.noise_factors).tolist())),
        )
        click.echo(f"wrote {out_path}")
    if reg is not None:
        from ajtwin.apps.anomaly import commissioning_long_run_history

        # the detectors of the next print start with this machine's noise scale
        history = commissioning_long_run_history(rec, result)
        cal_id = save_calibration(reg, name, result, str(record), long_run_history=history)
        click.echo(f"stored as calibration {cal_id} of {name!r} in {reg.path}")


@click.command("maintain")
@click.argument("name")
@click.option("--nozzle-cleaned", is_flag=True, help="Nozzle deposit → 0 (and θ_RN → 0).")
@click.option(
    "--vial-refilled", "vial_refilled", type=float, default=None, help="New vial fill [mL]."
)
@click.option("--reset-theta", is_flag=True, help="Forget the learned drift parameters θ.")
@click.option("--note", default="", help="Free text.")
@store_option
def maintain(name, nozzle_cleaned, vial_refilled, reset_theta, note, store):
    """Record a maintenance event on machine NAME; the next print starts from it."""
    from ajtwin.store.calibration import record_maintenance
    from ajtwin.store.registry import RegistryError

    reg = open_registry(store)
    try:
        event = record_maintenance(
            reg,
            name,
            nozzle_cleaned=nozzle_cleaned,
            vial_refilled_ml=vial_refilled,
            reset_theta=reset_theta,
            note=note,
        )
    except (RegistryError, ValueError) as exc:
        raise click.ClickException(str(exc)) from None
    done = [
        "nozzle cleaned" if event["nozzle_cleaned"] else "",
        f"vial refilled to {event['vial_refilled_ml']} mL" if event["vial_refilled_ml"] else "",
        "θ reset" if event["reset_theta"] else "",
    ]
    click.echo(f"{name}: {', '.join(d for d in done if d)} ({event['created_at']})")


@click.command("calibrations")
@click.argument("name")
@store_option
def calibrations(name, store):
    """Every commissioning of machine NAME (oldest first) and its maintenance events."""
    import pandas as pd

    from ajtwin.store.calibration import calibration_history, maintenance_history
    from ajtwin.store.registry import RegistryError

    reg = open_registry(store)
    try:
        table = calibration_history(reg, name)
        events = maintenance_history(reg, name)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    if table.empty:
        click.echo(f"{name}: never commissioned (the nominal model is used)")
    else:
        with pd.option_context("display.width", 200, "display.max_columns", 40):
            click.echo(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if not events.empty:
        click.echo("maintenance:")
        click.echo(events.to_string(index=False))


def describe_calibration(reg, name) -> list[str]:
    """Lines for `machine show`: the active calibration and the last mismatch status."""
    from ajtwin.store.calibration import active_calibration

    active = active_calibration(reg, name)
    if active is None:
        lines = ["  calibration: none — never commissioned, the nominal model is used"]
    else:
        cal = active["calibration"]
        lines = [
            f"  calibration {active['id']} from {active['source']} ({active['created_at']}):",
            f"    L_w = {cal.linewidth_gain:.3g}·L_w⁰ {cal.linewidth_offset_um:+.3g} µm, "
            f"L_o = {cal.overspray_gain:.3g}·L_o⁰ {cal.overspray_offset_um:+.3g} µm, "
            f"P_c gain {cal.carrier_gauge_gain:.4g} offset {cal.carrier_gauge_offset_Pa:+.3g} Pa, "
            f"P_s gain {cal.sheath_gauge_gain:.4g} offset {cal.sheath_gauge_offset_Pa:+.3g} Pa, "
            f"Q_m gain {cal.material_flow_gain:.3g}",
        ]
    last = reg.last_print(name)
    if last is not None and "mismatch" in last["summary"]:
        status = last["summary"]["mismatch"]
        if status.get("mismatch"):
            lines.append(f"  MODEL–MACHINE MISMATCH on print #{last['seq']}: {status['message']}")
        else:
            lines.append(f"  model–machine fit on print #{last['seq']}: ok")
    return lines
