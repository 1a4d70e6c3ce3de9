"""``ajtwin estimate`` and ``ajtwin experiment``: thin shells over the estimators."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from ajtwin.cli.options import (
    BoundedFloat,
    check_vial_fill,
    record_options,
    switched_on_option,
    transition_option,
    transition_overrides,
)
from ajtwin.io.csv_table import write_csv
from ajtwin.io.records import read_record
from ajtwin.model import OUTPUT_NAMES, STATE_NAMES


def parse_early_em(text: str) -> tuple:
    """'120' / '120,300' / 'none' → the early EM steps [s] (each a whole number ≥ 2)."""
    text = str(text).strip().lower()
    if text in ("", "none", "off"):
        return ()
    steps = []
    for part in text.split(","):
        try:
            value = float(part)
        except ValueError:
            raise ValueError(f"{part!r} is not a number of seconds (e.g. 120 or 120,300)") from None
        if not value.is_integer() or value < 2:
            raise ValueError(f"{part!r}: an early EM step is a whole number of seconds >= 2")
        steps.append(int(value))
    return tuple(steps)


def _read_calibration(calibration_path):
    """(calibration, its covariance, per-output noise factors, φ_A's level) of
    ``--calibration``, or Nones."""
    if calibration_path is None:
        return None, None, None, None
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.model.calibration import read_calibration_file

    try:
        calibration, content = read_calibration_file(calibration_path)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    calibration_cov = noise_factors = None
    if "covariance" in content:
        calibration_cov = np.asarray(content["covariance"]["matrix"], dtype=float)
    if "noise_factor" in content:
        factors = content["noise_factor"]
        noise_factors = np.array([float(factors.get(n, 1.0)) for n in OUTPUT_NAMES])
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.estimation.commission import unpinned_aerosol_level

    level = content.get("aerosol_level") or unpinned_aerosol_level()
    return calibration, calibration_cov, noise_factors, level


@click.command("estimate")
@click.argument("record_path", type=click.Path(exists=True, dir_okay=False))
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False),
    required=True,
    help="CSV of the hidden states (with _std), predicted outputs and NIS (normalised "
    "innovation squared).",
)
@click.option(
    "--em/--no-em",
    default=True,
    show_default=True,
    help="Learn the drift rates θ by EM (expectation–maximisation) while filtering.",
)
@click.option("--smooth", is_flag=True, help="Write RTS-smoothed states instead of filtered.")
@click.option(
    "--window", type=click.IntRange(min=2), default=600, show_default=True, help="EM window T [s]."
)
@click.option(
    "--every",
    type=click.IntRange(min=1),
    default=300,
    show_default=True,
    help="EM update interval [s].",
)
@click.option(
    "--early-em",
    "early_em",
    default="120",
    show_default=True,
    help="Extra EM updates before the first full window, each over the print so far "
    "(seconds, comma-separated; 'none' = off): the print's atomizer level is learned "
    "from the first of them.",
)
@click.option(
    "--gate",
    type=BoundedFloat(0.0, float("inf"), allow_inf=True),
    default=float("inf"),
    show_default=True,
    help="Per-output innovation gate [σ], > 0; inf = off.",
)
@click.option(
    "--noise",
    "noise_tuning",
    type=click.Choice(["calibrated", "paper"]),
    default="calibrated",
    show_default=True,
    help="The filter's noise tuning (noise.toml).",
)
@click.option(
    "--vial-ml",
    type=BoundedFloat(0.0, None),
    callback=check_vial_fill,
    default=1.0,
    show_default=True,
    help="Vial fill level at the start [mL], in (0, V_v).",
)
@click.option(
    "--calibration",
    "calibration_path",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="The machine's calibration TOML (`ajtwin machine commission --out`); default: "
    "the nominal model.",
)
@transition_option
@click.option(
    "--job",
    "job_program",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="The program (.prg) a job print ran: the speeds at print times come from it "
    "(it must be the file the record names, by sha256). Optional: without it the record's "
    "own job columns are used.",
)
@click.option(
    "--camera-horizon",
    "camera_horizon",
    type=BoundedFloat(0.0, float("inf"), allow_inf=True),
    default=None,
    help="Job prints: a step is final this many seconds after it was printed; camera "
    "measurements of a trace printed longer ago are dropped (inf: keep all). Default: from "
    "the camera (data/print_time.toml).",
)
@click.option(
    "--theta-out",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also write the history of the drift rates θ (one row per EM update) to this CSV "
    "(default: not written).",
)
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also write a PNG of states and outputs.",
)
@switched_on_option
@record_options
def estimate(
    record_path,
    out_path,
    em,
    smooth,
    window,
    every,
    early_em,
    gate,
    noise_tuning,
    vial_ml,
    calibration_path,
    transition,
    job_program,
    camera_horizon,
    theta_out,
    plot_path,
    switched_on_s,
    csv_dialect,
    aliases,
):
    """Run the twin over a print record: hidden states with uncertainty, θ history.

    On a job print (a format-2 record with the job columns) the camera's measurements are
    filed at the time their trace was printed and the line is read at the speed it was
    printed (--job gives the program; --camera-horizon the horizon).
    """

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.engine.estimate import estimate_to_csv
    from ajtwin.estimation.twin import Twin

    try:
        record = read_record(record_path, aliases=aliases, dialect=csv_dialect)
    except (ValueError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    if switched_on_s is not None:
        record.meta["atomizer_switched_on_s"] = switched_on_s
    calibration, calibration_cov, noise_factors, level = _read_calibration(calibration_path)
    try:
        early = parse_early_em(early_em)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--early-em") from None
    job = _read_job(record, job_program, camera_horizon)
    twin = Twin.default(
        calibration=calibration,
        calibration_cov=calibration_cov,
        noise_factors=noise_factors,
        noise_tuning=noise_tuning,
        em=em,
        window_s=window,
        every_s=every,
        early_em_s=early,
        gate_sigma=gate,
        vial_fill_ml=vial_ml,
        aerosol_level_std=float((level or {}).get("relative_std", 0.0)),
        camera_horizon_s=camera_horizon,
        **transition_overrides(transition),
    )
    n = len(record)
    with tqdm(total=n, unit="s", desc="twin", disable=None) as bar:

        def progress(done):
            bar.update(done - bar.n)

        try:
            done = estimate_to_csv(
                twin,
                record,
                out_path,
                smooth=smooth,
                whole=bool(plot_path),
                progress=progress,
                job=job,
            )
        except ValueError as exc:
            raise click.ClickException(str(exc)) from None
    run, mismatch = done.run, done.mismatch
    out = Path(out_path)
    click.echo(f"wrote {out} ({n} rows)")
    if theta_out:
        theta_path = Path(theta_out)
        theta_path.parent.mkdir(parents=True, exist_ok=True)
        write_csv(run.theta_history, theta_path)
        click.echo(f"wrote {theta_path} (drift rates θ after each of {len(run.theta_history)} "
                   "EM updates)")  # fmt: skip
    _echo_summary(run, done, mismatch, level, has_job=job is not None)
    click.echo(f"start-up: {_readiness(out).sentence()}")
    if plot_path:
        # lazy CLI loading: imported when the command runs, not for --help
        from ajtwin.estimation.plotting import estimate_figure

        estimate_figure(record, run, plot_path)
        click.echo(f"wrote {plot_path}")


def _echo_summary(run, done, mismatch, level, has_job: bool) -> None:
    """What ``estimate`` says after writing its files: the end state, the fit, the guard,
    φ_A's level and the states the print's data did not determine (``done``: what
    :func:`ajtwin.engine.estimate.estimate_to_csv` reports)."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.units import display

    end = ", ".join(
        f"{display(name).symbol} {display(name).text(value, 4)}"
        for name, value in zip(STATE_NAMES, run.end_mean, strict=True)
    )
    click.echo(f"hidden states at the end: {end}")
    click.echo(
        "how well the model explains the data — mean normalised innovation squared (NIS) per "
        f"measured output: {done.mean_nis_per_output:.2f} (1 = as the model's noise expects)"
    )
    if run.camera_counts:
        click.echo(_camera_line(run.camera_counts, has_job))
    if mismatch.mismatch:
        click.echo(f"WARNING {mismatch.message}", err=True)
        click.echo(
            "         the states above are not trustworthy for this machine "
            "(column 'mismatch' marks the seconds)",
            err=True,
        )
    else:
        click.echo("model–machine fit: ok (no mismatch found)")
    if done.reinitialised:
        click.echo(
            f"warning: the divergence guard re-initialised the filter {done.reinitialised} time(s)",
            err=True,
        )
    for note in run.visibility_notes():
        click.echo(note, err=True)
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.estimation.commission import aerosol_level_note

    click.echo(f"note: {aerosol_level_note(level)}", err=True)
    if done.undetermined:
        click.echo(
            f"note: not determined by this print's data: {', '.join(done.undetermined)} — "
            "their bands are the start prior's, carried by the model (columns determined_* "
            "= False)",
            err=True,
        )


def _readiness(table_path):
    """Whether and when the print's states and line settled after start-up, read from the
    states table a chunk at a time (:mod:`ajtwin.apps.detection.settling`)."""
    # lazy CLI loading: imported when the command runs, not for --help
    import pandas as pd

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.detection.settling import settling_from_table

    columns = ["time_s", *STATE_NAMES, *("pred_" + name for name in OUTPUT_NAMES)]
    with pd.read_csv(table_path, usecols=columns, chunksize=3600) as chunks:
        return settling_from_table(chunks)


def _read_job(record, job_program, camera_horizon):
    """The program of a job record (``--job``), checked against it; None without one."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.estimation.print_time import is_job_record, program_for_record
    from ajtwin.job import ProgramError

    if job_program is None and camera_horizon is not None and not is_job_record(record):
        raise click.UsageError("--camera-horizon is for a job print (a record with job columns)")
    if job_program is None:
        return None
    if not is_job_record(record):
        raise click.ClickException(
            f"--job {job_program}: the record has no job columns (shutter_open, "
            "platen_speed_mm_s, printed_at_s) — it is not a job print"
        )
    try:
        # the twin asks a looped program only where the stage is and what the camera sees
        return program_for_record(record, job_program, held=False)
    except (ProgramError, ValueError, OSError) as exc:
        raise click.ClickException(str(exc)) from None


def _camera_line(counts: dict, with_program: bool) -> str:
    """One line on a job print's camera: frames filed at print times, dropped, horizon."""
    dropped = {
        key.removeprefix("dropped_").replace("_", " "): value
        for key, value in counts.items()
        if key.startswith("dropped_") and value
    }
    horizon = counts["horizon_s"]
    text = (
        f"job print: {counts['filed']} camera frames filed at their print times "
        f"(horizon {'none: all kept' if horizon == float('inf') else f'{horizon:g} s'}; "
        f"speeds from the {'program' if with_program else 'record'})"
    )
    if dropped:
        text += "; dropped: " + ", ".join(f"{n} {why}" for why, n in dropped.items())
    if counts.get("material_flow_shutter_closed"):
        text += (
            f"; {counts['material_flow_shutter_closed']} Q_m values with the shutter closed "
            "not used"
        )
    return text
