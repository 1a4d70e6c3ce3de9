"""``ajtwin ingest``: run a machine's twin over a finished print and store it
(docs/reference/registry.md)."""

from __future__ import annotations

from pathlib import Path

import click
from tqdm import tqdm

from ajtwin.cli.options import (
    STATE_DISPLAY_SCALE,
    STATE_LABELS,
    BoundedFloat,
    ToleranceType,
    open_registry,
    record_options,
    store_option,
    switched_on_option,
)
from ajtwin.io.records import RecordError
from ajtwin.store.registry import RegistryError, printable


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
@click.option(
    "--job",
    "program",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="The machine program the print ran (.prg): kept with the print (its text, SHA-256 "
    "and the speeds used) for `ajtwin job report --machine` and the dashboard's part map.",
)
@click.option("--process-speed", "process_speed", type=BoundedFloat(0.0, 10_000.0),
              default=None, help="With --job: the GUI's process speed [mm/s] (default: the "
              "record's, else stage.toml).")  # fmt: skip
@click.option("--rapid-speed", "rapid_speed", type=BoundedFloat(0.0, 10_000.0), default=None,
              help="With --job: the GUI's rapid speed [mm/s] (default: the record's, else "
              "stage.toml).")  # fmt: skip
@click.option(
    "--tolerance",
    type=ToleranceType(),
    default=None,
    help="With --job: the part's linewidth tolerance in µm (45±3, 45+-3, 42:48), kept with "
    "the job for reports and the dashboard.",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
@switched_on_option
@record_options
@store_option
def ingest(
    machine_name,
    record,
    video,
    um_per_px,
    program,
    process_speed,
    rapid_speed,
    tolerance,
    progress,
    switched_on_s,
    csv_dialect,
    aliases,
    store,
):
    """Run the machine's twin over RECORD (from its last state and θ) and store it
    (with the program it ran: --job)."""

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.engine.ingest import ingest_file

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.job import ProgramError

    if video is not None and um_per_px is None:
        raise click.BadParameter("--video needs --um-per-px", param_hint="--um-per-px")
    job_options = {"process_speed_mm_s": process_speed, "rapid_speed_mm_s": rapid_speed,
                   "tolerance": tolerance}  # fmt: skip
    if program is None and any(v is not None for v in job_options.values()):
        raise click.UsageError("--process-speed, --rapid-speed and --tolerance go with --job")
    reg = open_registry(store, write=True)
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
            program=program,
            job_options=job_options,
            switched_on_s=switched_on_s,
        )
    except (RegistryError, RecordError, ProgramError, ValueError, FileNotFoundError) as exc:
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
        f"ingested {record} as print #{result.seq} of {printable(machine_name)!r} "
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
    if program is not None:
        click.echo(f"  job {program.name} kept with the print")
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.detection.causes import alarm_lines
    from ajtwin.engine.commissioning import aerosol_level
    from ajtwin.estimation.commission import aerosol_level_note
    from ajtwin.store.calibration import active_calibration
    from ajtwin.units import readable

    end = result.summary["end_state"]
    for (key, short, unit), scale in zip(STATE_LABELS, STATE_DISPLAY_SCALE, strict=True):
        click.echo(f"  end {short:5s} = {readable(end[key] * scale, 4)} {unit}")

    active = active_calibration(reg, machine_name)
    click.echo(f"  note: {aerosol_level_note(None if active is None else aerosol_level(active))}")
    for note in result.run.visibility_notes() if result.run is not None else ():
        click.echo(note, err=True)  # e.g. no camera: which states the data cannot see
    if result.events:
        click.echo(f"  {len(result.events)} anomaly event(s):")
        for ev in result.events:
            for line in alarm_lines(ev, machine_name):
                click.echo(f"    {line}")
    else:
        click.echo("  no anomalies")
