"""``ajtwin machine add|list|show|history|drop|restore|compact|export|import|commission|maintain|
calibrations``: the machine registry (docs/reference/registry.md,
docs/howto/commission-a-machine.md)."""

from __future__ import annotations

import datetime as _dt
import sqlite3
import time
from pathlib import Path

import click
import numpy as np
import pandas as pd

from ajtwin.cli.options import (
    STATE_DISPLAY_SCALE,
    STATE_LABELS,
    open_registry,
    record_options,
    store_option,
    theta_text,
)
from ajtwin.engine.chain import chain_start, state_violations
from ajtwin.io.records import RecordError, read_record
from ajtwin.store.archive import export_machine, import_machine
from ajtwin.store.compaction import compact
from ajtwin.store.live_log import live_session_now
from ajtwin.store.queries import reported_end_std
from ajtwin.store.registry import STATUS_DROPPED, STATUS_OK, RegistryError, printable


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
    click.echo(f"added machine {printable(m['name'])!r} to {reg.path}")
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
        click.echo(f"{printable(m['name'])}  ({m['n_prints']} prints, added {m['created_at']})")


@machine.command("show")
@click.argument("name")
@store_option
def show(name, store):
    """The machine's current twin: the live print if one runs (since when, samples, the
    state now, its alarms so far), the last stored state ± σ, θ, limits, recent anomalies."""

    reg = open_registry(store)
    try:
        m = reg.machine(name)
        last = reg.last_print(name)
        newest = reg.last_print(name, in_chain=False)
        anomalies = reg.anomalies(name)
        live = live_session_now(reg, m["name"])
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"machine {printable(m['name'])}  (registry {reg.path})")
    click.echo(f"  added {m['created_at']}, {m['n_prints']} print(s)")
    for key, (low, high) in m["limits"].items():
        click.echo(f"  limit {key}: {low:g} – {high:g}")
    for line in describe_calibration(reg, name):
        click.echo(line)
    for line in describe_live(live):
        click.echo(line)
    if newest is not None and (last is None or newest["seq"] != last["seq"]):
        click.echo(
            f"  newest print #{newest['seq']} is {newest['status']} (not in the chain): "
            f"{printable(newest['status_reason'])}"
        )
    if last is None:
        click.echo("  no print in the chain: the next ingest starts from the initial-state fit")
        return
    click.echo(
        f"  last stored print: #{last['seq']} from {printable(last['source'])} "
        f"({last['ingested_at']}), the twin's state at its end:"
    )
    std = reported_end_std(reg, last)  # the band as reported (calibration, φ_A's level)
    # which bands that print's data set (apps.mismatch.data_share; prints before it: none)
    shares = (last.get("summary") or {}).get("data_share") or {}
    for i, (name_i, short, unit) in enumerate(STATE_LABELS):
        scale = STATE_DISPLAY_SCALE[i]
        line = f"    {short:5s} = {_band(last['end_mean'][i] * scale, std[i] * scale)} {unit}"
        share = shares.get(name_i)
        if share is not None and not share["determined"]:
            line += (
                f"   (not determined by this print's data: data share {share['data_share']:.2f};"
                " the band is the prior's)"
            )
        click.echo(line)
    click.echo(f"    {theta_text(last['theta_after'])}")
    if len(anomalies):
        for line in _anomaly_lines(reg, name, anomalies.tail(5)):
            click.echo(line)


def _anomaly_lines(reg, name: str, anomalies) -> list[str]:
    """The latest anomalies, each with what to do — or the maintenance recorded after its
    print that closed its fault."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.detection.causes import alarm_lines, closing_maintenance, maintenance_words

    maintenance = reg.maintenance(name)
    lines = [f"  anomalies ({len(reg.anomalies(name))}), latest:"]
    for _, row in anomalies.iterrows():
        after = [m for m in maintenance if m["after_print_seq"] >= row["seq"]]
        k = closing_maintenance(row["cause"], [m["event"] for m in after])
        closed = None
        if k is not None:
            m = after[k]
            closed = (
                f"{maintenance_words(m['event'])} after print #{m['after_print_seq']} "
                f"({m['created_at']})"
            )
        alarm = {**row.to_dict(), "description": printable(row["description"])}
        first, *rest = alarm_lines(alarm, name, closed_by=closed)
        lines.append(f"    print #{row['seq']}: {first}")
        lines.extend(f"    {line}" for line in rest)
    return lines


@machine.command("history")
@click.argument("name")
@click.option(
    "--csv",
    "csv_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write the table as CSV.",
)
@click.option(
    "--version",
    "version",
    type=click.IntRange(min=1),
    default=None,
    help="The results of an `ajtwin reprocess` run (`ajtwin store versions`); 1 or none: "
    "the prints as stored.",
)
@store_option
def history(name, csv_path, version, store):
    """One row per print: the program it ran, its status (what its alarms were: clog,
    carrier leak, …, or mismatch; ok only without either) and its end states; what to do
    about an open fault of the newest print. --csv: every column, θ included."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.detection.causes import print_status

    reg = open_registry(store)
    try:
        table = reg.history(name, version=version)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    if table.empty:
        held = "" if version in (None, 1) else f" in version {version}"
        click.echo(f"machine {printable(name)!r} has no prints yet{held}")
        return
    status = [
        print_status(row.status, [c for c in row.causes.split(",") if c], row.mismatch)
        for row in table.itertuples(index=False)
    ]
    for line in history_lines(table, status):
        click.echo(line)
    for _, row in table[table["status"] != "ok"].iterrows():
        for line in _wrapped(f"#{row['seq']} {row['status']}: {printable(row['status_reason'])}"):
            click.echo(line)
    if version in (None, 1):
        # lazy CLI loading: the engine loads JAX, `machine --help` must not
        from ajtwin.engine.start import machine_open_faults

        seq, faults = machine_open_faults(reg, name)
        for fault in faults:
            for line in _wrapped(f"#{seq} open fault: {fault['sentence']}"):
                click.echo(line)
    if csv_path:
        table.to_csv(csv_path, index=False)
        click.echo(f"wrote {csv_path}")


#: the widest line `machine history` prints (a terminal of 110 columns)
HISTORY_WIDTH = 110
#: the end states `machine history` shows (all of them, θ too, in --csv)
HISTORY_STATES = (
    "droplet_diameter_um",
    "vial_volume_mL",
    "nozzle_deposition_um",
    "aerosol_fraction",
)


def _wrapped(text: str) -> list[str]:
    """``text`` as lines of at most :data:`HISTORY_WIDTH` columns, indented by two."""
    # lazy CLI loading: textwrap is only needed here
    import textwrap

    return textwrap.wrap(
        text, HISTORY_WIDTH, initial_indent="  ", subsequent_indent="    ", break_on_hyphens=False
    )


def history_lines(table: pd.DataFrame, status: list[str]) -> list[str]:
    """The history table as fixed-width lines (≤ :data:`HISTORY_WIDTH` columns): print,
    when (UTC, to the minute), minutes, program, status, the end states of
    :data:`HISTORY_STATES` in their display units (:data:`ajtwin.units.DISPLAY_UNITS`)."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.units import display, readable

    def cut(text, width):
        text = str(text)
        return text if len(text) <= width else text[: width - 1] + "…"

    def number(value, width):
        text = readable(value)
        return text if len(text) <= width else readable(value, 1)[:width]

    columns = [
        ("#", 3, ">", [str(v) for v in table["seq"]]),
        ("ingested (UTC)", 16, "<", [str(v)[:16].replace("T", " ") for v in table["ingested_at"]]),
        ("min", 5, ">", [f"{v:.0f}" if v >= 100 else f"{v:.1f}" for v in table["duration_min"]]),
        ("program", 16, "<", [cut(v or "–", 16) for v in table["program"]]),
        ("status", 18, "<", [cut(v, 18) for v in status]),
    ]
    # ΔR_T is left to --csv: no output sees the tube's deposit (it is rarely determined)
    for key in HISTORY_STATES:
        unit = display(key)
        values = unit.shown(table["end_" + key].to_numpy(dtype=float))
        columns.append((f"{unit.symbol} {unit.unit}", 8, ">", [number(v, 8) for v in values]))
    rows = [[head for head, *_ in columns]]
    rows += [[values[i] for *_, values in columns] for i in range(len(table))]
    return [
        "  ".join(
            f"{cell:{align}{width}}" for cell, (_, width, align, _) in zip(row, columns)
        ).rstrip()
        for row in rows
    ]


@machine.command("drop")
@click.argument("name")
@click.option("--print", "seq", type=click.IntRange(min=1), required=True, help="Print number.")
@click.option("--reason", default="dropped by hand", show_default=True, help="Why (kept).")
@store_option
def drop(name, seq, reason, store):
    """Take print SEQ out of NAME's chain (kept for history; the next ingest starts from
    the newest print still in the chain)."""

    reg = open_registry(store, write=True)
    try:
        p = reg.set_status(name, seq, STATUS_DROPPED, reason)
        chain = chain_start(reg, name)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(
        f"print #{p['seq']} of {printable(name)!r} dropped from the chain ({printable(reason)})"
    )
    start = "the initial-state fit" if chain.from_seq is None else f"print #{chain.from_seq}'s end"
    click.echo(f"  the next ingest starts from {start} state")


@machine.command("restore")
@click.argument("name")
@click.option("--print", "seq", type=click.IntRange(min=1), required=True, help="Print number.")
@store_option
def restore(name, seq, store):
    """Put a dropped or excluded print SEQ back into NAME's chain."""

    reg = open_registry(store, write=True)
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
    click.echo(f"print #{seq} of {printable(name)!r} is back in the chain")


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

    reg = open_registry(store, write=True)
    try:
        stats = compact(reg, name, keep_covariances_days)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    except sqlite3.Error as exc:  # e.g. VACUUM while another process holds a lock
        raise click.ClickException(f"{reg.path}: compaction stopped ({exc}); retry") from None
    click.echo(
        f"compacted {printable(name)!r}: {stats['prints']} print(s), {stats['reencoded']} "
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

    reg = open_registry(store)
    try:
        manifest = export_machine(reg, name, out)
    except (RegistryError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(
        f"exported {printable(name)!r} ({manifest['n_prints']} prints, "
        f"{manifest['live_sessions']} live sessions of which {manifest['open_live_sessions']} "
        f"open, schema {manifest['schema_version']}) to {out}"
    )


@machine.command("import")
@click.argument("archive", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--as", "as_name", default=None, help="Name in this registry (default: as exported).")
@store_option
def import_command(archive, as_name, store):
    """Add the machine of an `ajtwin machine export` ARCHIVE to the registry."""

    reg = open_registry(store, create=True)
    try:
        result = import_machine(reg, archive, as_name=as_name)
    except (RegistryError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    for message in result["migrated"]:
        click.echo(f"archive: {message}", err=True)
    click.echo(
        f"imported {printable(result['machine'])!r} ({result['n_prints']} prints, "
        f"{result['live_sessions']} live sessions of which {result['open_live_sessions']} "
        f"open) into {reg.path}"
    )


@machine.command("commission")
@click.argument("name")
@click.argument("record", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option(
    "--known",
    "known_items",
    multiple=True,
    help="A state known at the start or a calibration parameter known from elsewhere, "
    "NAME=VALUE±STD (e.g. droplet_diameter_um=3.5±0.2 from a droplet sizer, "
    "material_flow_gain=1.00±0.03 from a profilometer-calibrated CNN); repeatable. Pins "
    "what the print confounds (d_a with the line offsets, φ_A with the Q_m gain).",
)
@click.option("--vial-ml", default=1.0, show_default=True, help="The weighed fill [mL].")
@click.option(
    "--vial-used-ml",
    "vial_used",
    default=None,
    help="The ink the print drew, VALUE±STD [mL]: the vial weighed before and after it "
    "(an evaporation blank subtracted). Pins φ_A's level through dV_l/dt = −φ_A Q_c.",
)
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
    name,
    record,
    known_items,
    vial_ml,
    vial_used,
    out_path,
    no_registry,
    csv_dialect,
    aliases,
    store,
):
    """Fit machine NAME's calibration from a commissioning print RECORD.

    The print must start from a cleaned nozzle and a known fill and step Q_c, Q_s (and
    I_A) across the operating window (`ajtwin simulate --scenario commissioning`).
    Prints each calibration parameter with its standard error and whether the print
    determined it; stores it in the registry (the history is kept).
    """
    # lazy CLI loading: the fit loads JAX, `machine --help` must not
    from ajtwin.engine.commissioning import commission_machine, save_commissioning
    from ajtwin.engine.commissioning import write_calibration as write_calibration_toml
    from ajtwin.estimation.commission import CommissioningError, parse_amount, parse_known

    try:
        known = parse_known(known_items)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--known") from None
    vial_used_ml = None
    if vial_used is not None:
        try:
            vial_used_ml = parse_amount(vial_used, "--vial-used-ml")
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--vial-used-ml") from None
        if not vial_used_ml[0] > 0:
            raise click.BadParameter(
                f"{vial_used!r}: the ink used must be positive [mL]", param_hint="--vial-used-ml"
            )
    reg = None
    if not no_registry:
        reg = open_registry(store, write=True)
        try:
            reg.machine(name)
        except RegistryError as exc:
            raise click.ClickException(str(exc)) from None
    try:
        rec = read_record(record, aliases=aliases, dialect=csv_dialect)
        done = commission_machine(
            rec,
            known=known,
            vial_fill_ml=vial_ml,
            vial_used_ml=vial_used_ml,
            where=str(record),
            learn_noise_scale=reg is not None,
        )
    except (RecordError, CommissioningError, ValueError) as exc:
        raise click.ClickException(str(exc)) from None
    result = done.result
    _echo_commissioning(name, record, result)
    if out_path is not None:
        provenance = {
            "machine": name,
            "print": str(record),
            "samples": result.n_samples,
            "vial_fill_mL": vial_ml,
            "priors": {k: f"{v[0]:.6g}±{v[1]:.3g}" for k, v in result.priors.items()},
            "known": {k: f"{v[0]:.6g}±{v[1]:.3g}" for k, v in known.items()},
        }
        if vial_used_ml is not None:
            provenance["vial_used_mL"] = f"{vial_used_ml[0]:.6g}±{vial_used_ml[1]:.3g}"
        write_calibration_toml(out_path, result, provenance)
        click.echo(f"wrote {out_path}")
    if reg is not None:
        # the detectors of the next print start with this machine's noise scale
        cal_id = save_commissioning(reg, name, done, str(record))
        click.echo(f"stored as calibration {cal_id} of {name!r} in {reg.path}")


def _echo_commissioning(name, record, result) -> None:
    """The fitted calibration, one parameter a line, with its standard error and prior."""
    click.echo(f"commissioning of {name} from {record} ({result.n_samples} s):")
    click.echo(f"  {'parameter':26s} {'value':>11s} {'std error':>10s} {'prior σ':>9s}  print")
    unpinned = not result.aerosol_level.get("pinned_by")
    for row in result.table():
        status = "determined" if row["determined"] else "NOT determined (prior)"
        if row["parameter"] == "material_flow_gain" and unpinned:
            status = "rests on φ_A's prior (see note)"
        click.echo(
            f"  {row['parameter']:26s} {row['value']:11.5g} {row['std_error']:10.3g} "
            f"{row['prior_std']:9.3g}  {status}"
        )
    for note in result.notes:
        click.echo(f"  note: {note}")
    click.echo(
        "  how well the calibrated model explains the print — mean normalised innovation "
        f"squared (NIS) per output: {result.mean_nis:.2f} (1 = it fits)"
    )
    factors = ", ".join(f"{v:.2f}" for v in np.asarray(result.noise_factors))
    click.echo(f"  output noise of this machine / tuned σ (L_w, L_o, P_c, P_s, Q_m): {factors}")


@machine.command("maintain")
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
    # lazy CLI loading: calibrations load JAX (model.calibration), `machine --help` must not
    from ajtwin.apps.detection.causes import maintenance_words
    from ajtwin.store.calibration import record_maintenance

    reg = open_registry(store, write=True)
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
    click.echo(f"{name}: {maintenance_words(event)} ({event['created_at']})")


@machine.command("calibrations")
@click.argument("name")
@store_option
def calibrations(name, store):
    """Every commissioning of machine NAME (oldest first) and its maintenance events."""
    # lazy CLI loading: calibrations load JAX (model.calibration), `machine --help` must not
    from ajtwin.store.calibration import calibration_history, maintenance_history

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


def _band(mean, std) -> str:
    """``mean ± σ`` as a person reads it (4 and 2 significant figures, no e-notation)."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.units import readable

    return f"{readable(mean, 4)} ± {readable(std, 2)}"


def describe_live(live: dict | None, now: float | None = None) -> list[str]:
    """Lines for `machine show` on the machine's live print (:func:`live_session_now`): since
    when, how many samples, the twin's state now with its ±1σ, the alarms so far."""
    if live is None:
        return []
    now = time.time() if now is None else now
    started = _dt.datetime.fromtimestamp(live["started_at"], _dt.UTC)
    lines = [
        f"  LIVE print since {started:%Y-%m-%d %H:%M:%S} UTC "
        f"({(now - live['started_at']) / 60:.1f} min ago) from {printable(live['source'])}: "
        f"{live['n_samples']} samples"
    ]
    latest = live["latest"]
    if latest is None:
        lines.append("    the twin has not committed a step yet")
    else:
        lines.append(
            f"    the twin now ({latest['time_s'] / 60:.1f} min into the print, "
            f"{latest['status']}):"
        )
        for (key, short, unit), scale in zip(STATE_LABELS, STATE_DISPLAY_SCALE, strict=True):
            mean, std = latest["states"][key] * scale, latest["stds"][key] * scale
            lines.append(f"      {short:5s} = {_band(mean, std)} {unit}")
    alarms = live["alarms"]
    lines.append(f"    alarms so far: {len(alarms) if alarms else 'none'}")
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.detection.causes import alarm_lines

    for event in alarms:
        alarm = {**event, "description": printable(event["description"])}
        lines += [f"      {line}" for line in alarm_lines(alarm)]
    return lines


def describe_calibration(reg, name) -> list[str]:
    """Lines for `machine show`: the active calibration and the last mismatch status."""
    # lazy CLI loading: calibrations load JAX (model.calibration), `machine --help` must not
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
    # lazy CLI loading: calibrations load JAX (model.calibration), `machine --help` must not
    from ajtwin.engine.commissioning import aerosol_level
    from ajtwin.estimation.commission import aerosol_level_note

    level = None if active is None else aerosol_level(active)
    lines.append(f"  {aerosol_level_note(level)}")
    last = reg.last_print(name)
    if last is not None and "mismatch" in last["summary"]:
        status = last["summary"]["mismatch"]
        if status.get("mismatch"):
            lines.append(f"  MODEL–MACHINE MISMATCH on print #{last['seq']}: {status['message']}")
        else:
            lines.append(f"  model–machine fit on print #{last['seq']}: ok")
    return lines
