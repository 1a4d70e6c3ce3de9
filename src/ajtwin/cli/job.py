"""``ajtwin job``: the machine's program — summary, timeline, part plot."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import click

from ajtwin.cli.options import BoundedFloat

__all__ = ["job"]

_SPEED = BoundedFloat(0.0, 10_000.0)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def job():
    """The machine's program (Optomec AJ ACSPL+ .prg): summary, timeline, part plot."""


def _duration(seconds: float) -> str:
    """``12.34 s``, or ``2600.96 s (43 min 21 s)`` from a minute on."""
    if seconds < 60:
        return f"{seconds:.2f} s"
    hours, rest = divmod(int(round(seconds)), 3600)
    minutes, secs = divmod(rest, 60)
    clock = f"{hours} h {minutes:02d} min {secs:02d} s" if hours else f"{minutes} min {secs:02d} s"
    return f"{seconds:.2f} s ({clock})"


def _origin(use: dict, option: str) -> str:
    if use["kind"] == "given":
        return f"from {option}"
    if use["kind"] == "default":
        return f"{use['source']}; pass {option} with the machine's value"
    return f"set by the program ({use['source']})"


def _format_summary(summary: dict) -> str:
    rows = [
        ("program", f"{summary['program']} ({summary['lines']} lines)"),
        ("strokes", f"{summary['strokes']} printed (a stroke = one span with the shutter open)"),
        (
            "printed",
            f"{summary['printed_length_mm']:.3f} mm, shutter open "
            f"{summary['printing_time_s']:.2f} s",
        ),
        ("rapids", f"{summary['rapid_length_mm']:.3f} mm with the shutter closed"),
        (
            "print time",
            f"{_duration(summary['print_time_s'])}, program start to end",
        ),
    ]
    box = summary["bbox_mm"]
    if box is None:
        rows.append(("bounding box", "nothing printed"))
    else:
        rows.append(
            (
                "bounding box",
                f"x {box[0]:.3f} to {box[2]:.3f} mm, y {box[1]:.3f} to {box[3]:.3f} mm "
                f"({box[2] - box[0]:.3f} x {box[3] - box[1]:.3f} mm)",
            )
        )
    if summary["features"]:
        text = "; ".join(
            f"{f['feature']}{' ' + f['name'] if f['name'] else ''}: {f['strokes']} strokes, "
            f"{f['printed_length_mm']:.2f} mm"
            for f in summary["features"]
        )
        rows.append(("features", text))
    else:
        rows.append(("features", "none named (no !Feature comments)"))
    for key, option, label in (
        ("print_speeds", "--process-speed", "print speed"),
        ("rapid_speeds", "--rapid-speed", "rapid speed"),
    ):
        for use in summary[key]:
            rows.append(
                (
                    label,
                    f"{use['speed_mm_s']:g} mm/s over {use['length_mm']:.3f} mm: "
                    f"{_origin(use, option)}",
                )
            )
            label = ""
    if summary["repetitions"] > 1:
        rows.append(("repetitions", str(summary["repetitions"])))
    for note in summary["notes"]:
        rows.append(("note", note))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{key:<{width}}  {value}" for key, value in rows)


@job.command("show")
@click.argument("program", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--process-speed",
    "process_speed",
    type=_SPEED,
    default=None,
    help="The machine GUI's process speed [mm/s], used where the program sets none (default: "
    "stage.toml, 2 mm/s).",
)
@click.option(
    "--rapid-speed",
    "rapid_speed",
    type=_SPEED,
    default=None,
    help="The GUI's rapid speed (gDblRapidSpeed) [mm/s], used where the program sets none "
    "(default: stage.toml, 10 mm/s).",
)
@click.option(
    "--out",
    "out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write the timeline table (.parquet or .csv).",
)
@click.option(
    "--plot",
    "plot",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Draw the part (.png, .pdf, .svg).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as one JSON object.")
@click.option(
    "--skip-unknown",
    is_flag=True,
    help="Skip unknown commands that do not move the stage (one warning per kind).",
)
@click.option(
    "--repeat-to",
    "repeat_to",
    type=BoundedFloat(0.0, math.inf),
    default=None,
    help="Loop the program to this many seconds (the timeline and plot then cover every run).",
)
@click.option(
    "--machine",
    default=None,
    help="Machine table of stage.toml (stage travel, GUI speeds); default aj300.",
)
def show(program, process_speed, rapid_speed, out, plot, as_json, skip_unknown, repeat_to, machine):
    """Read PROGRAM and print what it prints: strokes, lengths, time, box, speeds."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.job import ProgramError, read_program

    if out is not None and out.suffix.lower() not in (".parquet", ".pq", ".csv"):
        raise click.BadParameter("the timeline is written as .parquet or .csv", param_hint="--out")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            the_job = read_program(
                program, process_speed, rapid_speed, skip_unknown=skip_unknown, machine=machine
            )
        except (ProgramError, ValueError) as exc:
            raise click.ClickException(str(exc)) from None
    for warning in caught:
        click.echo(f"warning: {warning.message}", err=True)
    if repeat_to is not None:
        the_job = the_job.repeat(repeat_to)
    summary = the_job.summary()
    if out is not None:
        the_job.write_timeline(out)
    if plot is not None:
        # lazy CLI loading: imported when the command runs, not for --help
        from ajtwin.job.plot import plot_part

        plot_part(the_job, plot)
    if as_json:
        click.echo(json.dumps(summary))
        return
    click.echo(_format_summary(summary))
    if out is not None:
        click.echo(f"timeline     {out} ({the_job.n_segments} segments)")
    if plot is not None:
        click.echo(f"part plot    {plot}")
