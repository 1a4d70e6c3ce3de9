"""``ajtwin machine add|show|history|list|drop|restore|compact|export|import`` and
``ajtwin ingest`` (docs/registry.md)."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ajtwin.io.cli_options import BoundedFloat, record_options

STATE_LABELS = (
    ("droplet_diameter_um", "d_a", "µm"),
    ("vial_volume_mL", "V_l", "mL"),
    ("tube_deposition_um", "ΔR_T", "µm"),
    ("nozzle_deposition_um", "ΔR_N", "µm"),
    ("aerosol_fraction", "φ_A", "–"),
)


def store_option(func):
    return click.option(
        "--store",
        "store",
        type=click.Path(dir_okay=False, path_type=Path),
        default=None,
        envvar="AJTWIN_STORE",
        help="Registry file (default: $AJTWIN_STORE or ~/.local/share/ajtwin/registry.sqlite).",
    )(func)


def open_registry(store, create: bool = False):
    """The registry at ``store``; read-only commands (the default) never create it."""
    from ajtwin.store.registry import Registry, RegistryError

    try:
        reg = Registry(store, create=create)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    for message in reg.migrated:
        click.echo(message, err=True)
    return reg


def _safe(text) -> str:
    from ajtwin.store.registry import printable

    return printable(text)


def _range(text):
    if text is None:
        return None
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        raise click.BadParameter(f"expected LOW,HIGH, got {text!r}") from None
    return [low, high]


@click.group()
def machine():
    """Machine registry: one twin per printer, carried from print to print."""


@machine.command("add")
@click.argument("name")
@click.option("--current", "current_range", default=None, help="I_A limits LOW,HIGH [mA].")
@click.option("--carrier", "carrier_range", default=None, help="Q_c limits LOW,HIGH [sccm].")
@click.option("--sheath", "sheath_range", default=None, help="Q_s limits LOW,HIGH [sccm].")
@click.option("--notes", default="", help="Free text (location, nozzle, ink...).")
@store_option
def add(name, current_range, carrier_range, sheath_range, notes, store):
    """Register machine NAME (default limits: I_A 300–440 mA, Q_c 15–35, Q_s 30–80 sccm)."""
    from ajtwin.store.registry import RegistryError

    limits = {}
    for key, text in (
        ("atomizer_current_mA", current_range),
        ("carrier_flow_sccm", carrier_range),
        ("sheath_flow_sccm", sheath_range),
    ):
        value = _range(text)
        if value is not None:
            limits[key] = value
    reg = open_registry(store, create=True)
    try:
        m = reg.add_machine(name, limits, notes)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"added machine {_safe(m['name'])!r} to {reg.path}")
    for key, (low, high) in m["limits"].items():
        click.echo(f"  {key}: {low:g} – {high:g}")


@machine.command("list")
@store_option
def list_machines(store):
    """List the registered machines."""
    reg = open_registry(store)
    rows = reg.machines()
    if not rows:
        click.echo(f"no machines in {reg.path}")
    for row in rows:
        m = reg.machine(row["name"])
        click.echo(f"{_safe(m['name'])}  ({m['n_prints']} prints, added {m['created_at']})")


@machine.command("show")
@click.argument("name")
@store_option
def show(name, store):
    """The machine's current twin: last state ± σ, θ, limits, recent anomalies."""
    from ajtwin.store.registry import RegistryError

    reg = open_registry(store)
    try:
        m = reg.machine(name)
        last = reg.last_print(name)
        newest = reg.last_print(name, in_chain=False)
        anomalies = reg.anomalies(name)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"machine {_safe(m['name'])}  (registry {reg.path})")
    click.echo(f"  added {m['created_at']}, {m['n_prints']} print(s)")
    for key, (low, high) in m["limits"].items():
        click.echo(f"  limit {key}: {low:g} – {high:g}")
    from ajtwin.store.calibration_cli import describe_calibration

    for line in describe_calibration(reg, name):
        click.echo(line)
    if newest is not None and (last is None or newest["seq"] != last["seq"]):
        click.echo(
            f"  newest print #{newest['seq']} is {newest['status']} (not in the chain): "
            f"{_safe(newest['status_reason'])}"
        )
    if last is None:
        click.echo("  no print in the chain: the next ingest starts from the initial-state fit")
        return
    click.echo(
        f"  last print: #{last['seq']} from {_safe(last['source'])} "
        f"({last['ingested_at']}), the twin's current state:"
    )
    std = np.sqrt(np.diag(last["end_cov"]))
    # which bands that print's data set (apps.mismatch.data_share; prints before it: none)
    shares = (last.get("summary") or {}).get("data_share") or {}
    for i, (name_i, short, unit) in enumerate(STATE_LABELS):
        line = f"    {short:5s} = {last['end_mean'][i]:.4g} ± {std[i]:.2g} {unit}"
        share = shares.get(name_i)
        if share is not None and not share["determined"]:
            line += (
                f"   (not determined by this print's data: data share {share['data_share']:.2f};"
                " the band is the prior's)"
            )
        click.echo(line)
    theta = ", ".join(f"{v:.3g}" for v in last["theta_after"])
    click.echo(f"    θ [1/s] = [{theta}]")
    if len(anomalies):
        click.echo(f"  anomalies ({len(anomalies)}), latest:")
        for _, row in anomalies.tail(5).iterrows():
            click.echo(
                f"    print #{row['seq']} at {row['detected_s']:.0f} s "
                f"(onset ≈ {row['onset_s']:.0f} s): {_safe(row['description'])}"
            )


@machine.command("history")
@click.argument("name")
@click.option(
    "--csv",
    "csv_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write the table as CSV.",
)
@store_option
def history(name, csv_path, store):
    """One row per print: end states, θ and anomaly count."""
    import pandas as pd

    from ajtwin.store.registry import RegistryError

    reg = open_registry(store)
    try:
        table = reg.history(name)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    if table.empty:
        click.echo(f"machine {_safe(name)!r} has no prints yet")
        return
    show_cols = ["seq", "ingested_at", "duration_min", "anomalies", "status"] + [
        "end_" + key for key, _, _ in STATE_LABELS
    ]
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        click.echo(table[show_cols].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    for _, row in table[table["status"] != "ok"].iterrows():
        click.echo(f"  #{row['seq']} {row['status']}: {_safe(row['status_reason'])}")
    if csv_path:
        table.to_csv(csv_path, index=False)
        click.echo(f"wrote {csv_path}")


@machine.command("drop")
@click.argument("name")
@click.option("--print", "seq", type=click.IntRange(min=1), required=True, help="Print number.")
@click.option("--reason", default="dropped by hand", show_default=True, help="Why (kept).")
@store_option
def drop(name, seq, reason, store):
    """Take print SEQ out of NAME's chain (kept for history; the next ingest starts from
    the newest print still in the chain)."""
    from ajtwin.store.chain import chain_start
    from ajtwin.store.registry import STATUS_DROPPED, RegistryError

    reg = open_registry(store)
    try:
        p = reg.set_status(name, seq, STATUS_DROPPED, reason)
        chain = chain_start(reg, name)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"print #{p['seq']} of {_safe(name)!r} dropped from the chain ({_safe(reason)})")
    start = "the initial-state fit" if chain.from_seq is None else f"print #{chain.from_seq}'s end"
    click.echo(f"  the next ingest starts from {start} state")


@machine.command("restore")
@click.argument("name")
@click.option("--print", "seq", type=click.IntRange(min=1), required=True, help="Print number.")
@store_option
def restore(name, seq, store):
    """Put a dropped or excluded print SEQ back into NAME's chain."""
    from ajtwin.store.chain import state_violations
    from ajtwin.store.registry import STATUS_OK, RegistryError

    reg = open_registry(store)
    try:
        p = reg.print_by_seq(name, seq)
        problems = state_violations(p["end_mean"])
        if problems:
            raise click.ClickException(
                f"print #{seq} ends in an impossible state ({'; '.join(problems)}); "
                "it cannot start the next print"
            )
        reg.set_status(name, seq, STATUS_OK, "")
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"print #{seq} of {_safe(name)!r} is back in the chain")


@machine.command("compact")
@click.argument("name")
@click.option(
    "--keep-covariances-days",
    type=click.FloatRange(min=0),
    default=30.0,
    show_default=True,
    help="Older prints keep covariances only at their end and alarms.",
)
@store_option
def compact_command(name, keep_covariances_days, store):
    """Apply the storage policy and covariance retention to NAME, then VACUUM."""
    import sqlite3

    from ajtwin.store.maintenance import compact
    from ajtwin.store.registry import RegistryError

    reg = open_registry(store)
    try:
        stats = compact(reg, name, keep_covariances_days)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    except sqlite3.Error as exc:  # e.g. VACUUM while another process holds a lock
        raise click.ClickException(f"{reg.path}: compaction stopped ({exc}); retry") from None
    click.echo(
        f"compacted {_safe(name)!r}: {stats['prints']} print(s), {stats['reencoded']} "
        f"re-encoded, {stats['thinned']} with covariance key frames dropped, "
        f"{stats['live_steps_dropped']} steps of finished live sessions dropped; registry "
        f"{stats['bytes_before'] / 1e6:.2f} MB → {stats['bytes_after'] / 1e6:.2f} MB"
    )


@machine.command("export")
@click.argument("name")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True)
@store_option
def export_command(name, out, store):
    """Write machine NAME (all prints, arrays, anomalies, live sessions) to a tar archive."""
    from ajtwin.store.maintenance import export_machine
    from ajtwin.store.registry import RegistryError

    reg = open_registry(store)
    try:
        manifest = export_machine(reg, name, out)
    except (RegistryError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(
        f"exported {_safe(name)!r} ({manifest['n_prints']} prints, "
        f"{manifest['live_sessions']} live sessions of which {manifest['open_live_sessions']} "
        f"open, schema {manifest['schema_version']}) to {out}"
    )


@machine.command("import")
@click.argument("archive", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--as", "as_name", default=None, help="Name in this registry (default: as exported).")
@store_option
def import_command(archive, as_name, store):
    """Add the machine of an `ajtwin machine export` ARCHIVE to the registry."""
    from ajtwin.store.maintenance import import_machine
    from ajtwin.store.registry import RegistryError

    reg = open_registry(store, create=True)
    try:
        result = import_machine(reg, archive, as_name=as_name)
    except (RegistryError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    for message in result["migrated"]:
        click.echo(f"archive: {message}", err=True)
    click.echo(
        f"imported {_safe(result['machine'])!r} ({result['n_prints']} prints, "
        f"{result['live_sessions']} live sessions of which {result['open_live_sessions']} "
        f"open) into {reg.path}"
    )


@click.command()
@click.option("--machine", "machine_name", required=True, help="Registered machine name.")
@click.argument("record", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option(
    "--video",
    type=click.Path(exists=True, path_type=Path),
    default=None,
    help="Alignment-camera video: fills linewidth/overspray (ajtwin.vision).",
)
@click.option(
    "--um-per-px",
    type=BoundedFloat(0.0, None),
    default=None,
    help="Camera pixel size, µm (with --video).",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
@record_options
@store_option
def ingest(machine_name, record, video, um_per_px, progress, csv_dialect, aliases, store):
    """Run the machine's twin over RECORD (from its last state and θ) and store it."""
    from tqdm import tqdm

    from ajtwin.io.records import RecordError
    from ajtwin.live.engine import ingest_file
    from ajtwin.store.registry import RegistryError

    if video is not None and um_per_px is None:
        raise click.BadParameter("--video needs --um-per-px", param_hint="--um-per-px")
    reg = open_registry(store)
    bar = None
    state = {"done": 0}

    def step(done):
        nonlocal bar
        if bar is None:
            bar = tqdm(unit="s", desc="twin", disable=not progress)
        bar.update(done - state["done"])
        state["done"] = done

    try:
        reg.machine(machine_name)
        result = ingest_file(
            reg,
            machine_name,
            record,
            video=video,
            um_per_px=um_per_px,
            progress=step,
            video_progress=progress,
            aliases=aliases,
            dialect=csv_dialect,
        )
    except (RegistryError, RecordError, ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    finally:
        if bar is not None:
            bar.close()
    if result.duplicate:
        click.echo(
            f"{record}: already ingested as print #{result.seq} of {machine_name!r} "
            "(same content hash); nothing changed"
        )
        return
    click.echo(
        f"ingested {record} as print #{result.seq} of {_safe(machine_name)!r} "
        f"({result.n_samples} s, {result.seconds:.1f} s wall, "
        f"started from {result.summary['started_from']})"
    )
    status = result.summary.get("mismatch", {})
    if status.get("mismatch"):
        click.echo(f"  WARNING {status['message']}", err=True)
    if result.summary.get("status", "ok") != "ok":
        click.echo(
            f"  WARNING: stored but EXCLUDED from the machine's chain (the next print will not "
            f"start from it): {result.summary['status_reason']}",
            err=True,
        )
    end = result.summary["end_state"]
    for key, short, unit in STATE_LABELS:
        click.echo(f"  end {short:5s} = {end[key]:.4g} {unit}")
    for note in result.run.visibility_notes() if result.run is not None else ():
        click.echo(note, err=True)  # e.g. no camera: which states the data cannot see
    if result.events:
        click.echo(f"  {len(result.events)} anomaly event(s):")
        for ev in result.events:
            click.echo(
                f"    detected {ev.detected_s:.0f} s (onset ≈ {ev.onset_s:.0f} s): "
                f"{ev.description} [{', '.join(ev.detectors)}]"
            )
    else:
        click.echo("  no anomalies")


# commissioning, maintenance and calibration history (SPEC §11; ajtwin.store.calibration_cli)
from ajtwin.store.calibration_cli import calibrations, commission, maintain  # noqa: E402

machine.add_command(commission)
machine.add_command(maintain)
machine.add_command(calibrations)
