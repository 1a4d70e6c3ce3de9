"""``ajtwin simulate`` and ``ajtwin plot`` (registered in :mod:`ajtwin.cli`)."""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import click
import numpy as np

from ajtwin.cli.options import (
    BoundedFloat,
    OffsetMM,
    PitchMM,
    ProcessSpeed,
    csv_dialect_option,
    job_speeds,
)
from ajtwin.io.records import RecordError, read_record, write_record
from ajtwin.job.speeds import SpeedSchedule

_SPEED = BoundedFloat(0.0, 10_000.0)


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
@click.option(
    "--job",
    "job_program",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Print this machine program (.prg): shutter, speeds and a camera on the part; the "
    "job loops to the print's duration (format-2 record, docs/reference/record-format.md).",
)
@click.option(
    "--process-speed",
    type=ProcessSpeed(),
    default=None,
    help="With --job: the GUI's process speed [mm/s] where the program sets none "
    "(default: stage.toml, 2 mm/s); or speeds per layer, e.g. 2,4,3 (successive layers, "
    "repeating), stroke:2,4,3, feature:… or a schedule file speeds.toml.",
)
@click.option(
    "--rapid-speed",
    type=_SPEED,
    default=None,
    help="With --job: the GUI's rapid speed [mm/s] where the program sets none "
    "(default: stage.toml, 10 mm/s).",
)
@click.option(
    "--camera",
    "camera_mode",
    type=click.Choice(["trailing", "inspection", "at_nozzle"]),
    default=None,
    help="With --job: the alignment camera trails the nozzle at an offset, inspects the strokes "
    "after the print, or sees the line as printed (default: data/virtual_camera.toml, trailing).",
)
@click.option(
    "--camera-offset-mm",
    type=OffsetMM(),
    default=None,
    help="With --job: the camera's view centre relative to the nozzle, DX[,DY] in mm "
    "(default: data/virtual_camera.toml, -5,0).",
)
@click.option(
    "--repeat-pitch-mm",
    type=PitchMM(),
    default=None,
    help="With --job: loop the job as an array of parts side by side, DX[,DY] mm apart "
    "(columns across the stage's X travel, then rows); default: each run prints over the last.",
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
    job_program,
    process_speed,
    rapid_speed,
    camera_mode,
    camera_offset_mm,
    repeat_pitch_mm,
    list_only,
):
    """Virtual printer: simulate one print with known truth into a record file.

    Example: ajtwin simulate --scenario exp3 --seed 1 --out print.parquet

    With --job PROGRAM.prg the printer runs the program (looped to the duration): the
    machine evolves as on a straight line, the substrate gets material only while the
    shutter is open, the line follows the platen speed, and the camera measures what it
    sees (--camera, --camera-offset-mm); --repeat-pitch-mm lays the loops side by side.
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
    job_options = {
        "--process-speed": process_speed,
        "--rapid-speed": rapid_speed,
        "--camera": camera_mode,
        "--camera-offset-mm": camera_offset_mm,
        "--repeat-pitch-mm": repeat_pitch_mm,
    }
    if job_program is None and any(v is not None for v in job_options.values()):
        given = ", ".join(k for k, v in job_options.items() if v is not None)
        raise click.UsageError(f"{given} describe a job print: give --job PROGRAM.prg")
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.simulation.printer import simulate as run

    previous = None
    if continue_from is not None:
        try:
            previous = read_record(continue_from)
        except RecordError as exc:
            raise click.ClickException(str(exc)) from None
    t0 = time.perf_counter()
    if job_program is not None:
        record = _simulate_job(
            job_program,
            scenario,
            seed,
            duration_min,
            previous,
            machine_name,
            machine_seed,
            truth_generator,
            camera_mode,
            camera_offset_mm,
            process_speed,
            rapid_speed,
            repeat_pitch_mm,
        )
    else:
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
    if "job" in meta:
        click.echo(_job_line(record))
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


def _simulate_job(
    program,
    scenario,
    seed,
    duration_min,
    previous,
    machine_name,
    machine_seed,
    truth_generator,
    camera_mode,
    camera_offset_mm,
    process_speed,
    rapid_speed,
    repeat_pitch_mm=None,
):
    """Run the job print for ``simulate --job``; program errors and warnings for the user."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.job import ProgramError
    from ajtwin.simulation.job_print import CameraSettings, JobSettings, simulate_job

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            camera = CameraSettings(mode=camera_mode, offset_mm=camera_offset_mm)
            record = simulate_job(
                program,
                scenario,
                seed,
                duration_min=duration_min,
                continue_from=previous,
                machine=machine_name,
                machine_seed=machine_seed,
                truth_generator=truth_generator,
                camera=camera,
                job_settings=JobSettings(
                    rapid_speed_mm_s=rapid_speed,
                    repeat_pitch_mm=repeat_pitch_mm,
                    **job_speeds(process_speed),
                ),
            )
        except (ProgramError, ValueError, FileNotFoundError) as exc:
            raise click.ClickException(str(exc)) from None
    for warning in caught:
        click.echo(f"warning: {warning.message}", err=True)
    return record


def _job_line(record) -> str:
    """One line on a job print: program, speed, camera and what the camera saw."""
    job, camera = record.meta["job"], record.meta["camera"]
    printed_at = record.printed_at
    seen = np.isfinite(printed_at)
    delay = record.time_s[seen] - printed_at[seen]
    speeds = f"{job['process_speed_mm_s']:g} mm/s"
    if job.get("process_speed_schedule"):
        speeds = SpeedSchedule.from_meta(job["process_speed_schedule"]).describe()
    text = (
        f"job {job['program']} at {speeds} looped to "
        f"{job['repeat_to_s']:g} s; shutter open {100 * record.shutter_open.mean():.1f} % of "
        f"the seconds; camera {camera['mode']}"
    )
    if camera["mode"] == "trailing":
        text += f" at ({camera['offset_mm'][0]:g}, {camera['offset_mm'][1]:g}) mm"
    text += f": a measurement in {100 * seen.mean():.1f} % of the rows"
    if seen.any():
        text += f", of traces printed {np.median(delay):.1f} s earlier (median)"
    return text


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
