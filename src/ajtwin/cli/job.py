"""``ajtwin job``: the machine's program — summary, timeline, part plot."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import click

from ajtwin.cli.options import (
    BoundedFloat,
    PitchMM,
    ToleranceType,
    open_registry,
    record_options,
    store_option,
)
from ajtwin.io.schema import MAX_PLATEN_SPEED_MM_S, MAX_RECORD_SECONDS

__all__ = ["job"]

_SPEED = BoundedFloat(0.0, MAX_PLATEN_SPEED_MM_S, closed=True)
#: What `job show --plot` draws (matplotlib's vector and raster formats used in the docs).
PLOT_SUFFIXES = (".png", ".pdf", ".svg")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def job():
    """The machine's program (Optomec AJ ACSPL+ .prg): summary, timeline, part plot, and the
    part quality map of a print (report)."""


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
    type=BoundedFloat(0.0, MAX_RECORD_SECONDS, closed=True),
    default=None,
    help="Loop the program to this many seconds (the timeline and plot then cover every run; "
    "at most 14 days, a print record's limit).",
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
    if plot is not None and plot.suffix.lower() not in PLOT_SUFFIXES:
        raise click.BadParameter(
            f"the part is drawn as {', '.join(PLOT_SUFFIXES)}, not {plot.suffix or 'no suffix'!r}",
            param_hint="--plot",
        )
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
        try:
            the_job = the_job.repeat(repeat_to)
        except ValueError as exc:
            raise click.ClickException(str(exc)) from None
    summary = the_job.summary()
    for path in (out, plot):  # as simulate, estimate and extract do: the folder is made
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
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


def _bars(progress: bool):
    """(twin progress, line progress, close): one tqdm bar at a time, created on first use.

    The twin's bar says it is starting until its first second is done (on a machine's first
    run the twin's programs are compiled then: 10-30 s); it is closed, kept as one finished
    line, before the line's bar opens, so the two never share the terminal's last line."""
    # lazy CLI loading: tqdm only when the command runs
    from tqdm import tqdm

    bars = {}

    def twin_step(done):
        if "twin" not in bars:
            bars["twin"] = tqdm(unit="s", desc="twin", disable=not progress)
            bars["twin"].set_postfix_str("starting: a first run compiles the twin first")
        bar = bars["twin"]
        if done > bar.n and bar.n == 0:
            bar.set_postfix_str("", refresh=False)
        bar.update(done - bar.n)

    def line_step(done, total):
        if "line" not in bars:
            if "twin" in bars:
                bars["twin"].close()
            bars["line"] = tqdm(
                total=total, unit="pt", desc="line along strokes", disable=not progress
            )
        bars["line"].update(done - bars["line"].n)

    def close():
        for bar in bars.values():
            bar.close()

    return twin_step, line_step, close


def _echo_part_report(part, paths) -> None:
    """What `job report` prints: the headline, why the flagged portions are out (by cause,
    with what to do), the worst of them, the alarms, the files. Times in minutes past the
    print's start."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.detection.causes import alarm_sentence, detector_words
    from ajtwin.apps.quality.part_map import cause_groups
    from ajtwin.apps.quality.report import summary_facts
    from ajtwin.units import minutes_text

    facts = summary_facts(part)
    tolerance = part.tolerance.text if part.tolerance else "none (nothing flagged)"
    click.echo(f"print       {part.source}")
    click.echo(f"program     {facts['program']}")
    click.echo(
        f"printed     {facts['strokes']} strokes, {facts['portions']} portions, "
        f"{facts['printed_mm']:.1f} mm over {facts['print_min']:.1f} min; mean L_w "
        f"{facts['lw_mean_um']:.1f} µm"
    )
    click.echo(f"tolerance   {tolerance}; flagged when P(out) ≥ {part.flag_probability:g}")
    if facts["speed_law"]:
        click.echo(f"speed law   {facts['speed_law']}")
    click.echo(
        f"flagged     {facts['flagged_portions']} portions ({facts['flagged_mm']:.1f} mm) on "
        f"{facts['flagged_strokes']} strokes"
    )
    for group in cause_groups(part):
        click.echo(f"why         {group['sentence']}")
        click.echo(
            f"              {group['portions']} portions ({group['length_mm']:.1f} mm) printed "
            f"{group['from_min']:.1f}–{group['to_min']:.1f} min; {group['driver']}"
        )
    looped = part.job.repetitions > 1
    for row in part.flagged().head(5).itertuples(index=False):
        where = f"run {row.repetition + 1}, " if looped else ""
        feature = f" ({part.feature_label(row.feature)})" if part.has_features else ""
        cause = f"A{row.alarm}" if row.alarm else "no alarm"
        click.echo(
            f"  worst: {where}stroke {row.stroke} portion {row.portion}{feature}: "
            f"({row.from_x_mm:.2f}, {row.from_y_mm:.2f}) → ({row.to_x_mm:.2f}, "
            f"{row.to_y_mm:.2f}) mm, printed {minutes_text(row.printed_from_s)}, L_w "
            f"{row.lw_mean_um:.1f} µm ({row.lw_lo_um:.1f}–{row.lw_hi_um:.1f}), "
            f"P(out) {row.p_out:.2f}, {cause}"
        )
    for row in part.alarms.itertuples(index=False):
        detectors = "; ".join(detector_words(d.strip()) for d in row.detectors.split(",") if d)
        click.echo(f"alarm A{row.alarm}    {alarm_sentence(row.cause, row.onset_s, part.machine)}")
        click.echo(
            f"              raised {minutes_text(row.detected_s)} at ({row.detected_x_mm:.2f}, "
            f"{row.detected_y_mm:.2f}) mm by: {detectors}"
        )
    for note in part.notes:
        click.echo(f"note: {note}", err=True)
    for path in paths.values():
        click.echo(f"wrote       {path}")


@job.command("report")
@click.argument(
    "record", required=False, type=click.Path(exists=True, dir_okay=False, path_type=Path)
)
@click.option(
    "--job",
    "program",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="The program the print ran (.prg). Optional for a stored print ingested with --job.",
)
@click.option(
    "--tolerance",
    type=ToleranceType(),
    default=None,
    help="The linewidth's tolerance in µm: 45±3, 45+-3 or 42:48 (default for a stored print: "
    "the one stored with its job).",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Folder for strokes.csv, part.png and report.html (created).",
)
@click.option(
    "--machine",
    default=None,
    help="A registered machine: without RECORD, map its stored print (--print, default the "
    "newest); with RECORD, run the machine's twin from where its next print starts.",
)
@click.option(
    "--print", "seq", type=click.IntRange(min=1), default=None, help="Stored print number."
)
@click.option("--process-speed", "process_speed", type=_SPEED, default=None,
              help="Process speed [mm/s] (default: the record's, else stage.toml).")  # fmt: skip
@click.option("--rapid-speed", "rapid_speed", type=_SPEED, default=None,
              help="Rapid speed [mm/s] (default: the record's, else stage.toml).")  # fmt: skip
@click.option(
    "--repeat-to",
    "repeat_to",
    type=BoundedFloat(0.0, math.inf),
    default=None,
    help="The print looped the program to this many seconds (default: the record's; else "
    "looped to the record's length when the print outlasts the program).",
)
@click.option(
    "--repeat-pitch-mm",
    "repeat_pitch",
    type=PitchMM(),
    default=None,
    help="The loops were placed side by side, DX[,DY] mm apart (default: the record's; else "
    "each run printed over the last).",
)
@click.option(
    "--portion-mm",
    type=BoundedFloat(0.0, 1000.0),
    default=1.0,
    show_default=True,
    help="Longest stroke portion [mm] (each stroke is cut into equal portions).",
)
@click.option(
    "--flag-probability",
    type=BoundedFloat(0.0, 1.0, closed=True),
    default=0.5,
    show_default=True,
    help="Flag a portion when its probability of being out of tolerance is at least this.",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
@record_options
@store_option
def report(
    record,
    program,
    tolerance,
    out_dir,
    machine,
    seq,
    process_speed,
    rapid_speed,
    repeat_to,
    repeat_pitch,
    portion_mm,
    flag_probability,
    progress,
    csv_dialect,
    aliases,
    store,
):
    """Which traces of the part are out of tolerance: every stroke's linewidth along its
    length from the twin's smoothed states (±2σ) and overspray, portions flagged with the
    probability that they are out, the alarms placed on the part.

    Give a print RECORD and its --job PROGRAM, or --machine NAME [--print SEQ] for a stored
    print. Writes OUT/strokes.csv, OUT/part.png and OUT/report.html.
    """
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.quality.part_map import MapSettings, part_map_of_record
    from ajtwin.apps.quality.report import write_report
    from ajtwin.engine.print_job import load_stored_print, map_stored_print, next_print_twin
    from ajtwin.estimation.print_time import program_for_record
    from ajtwin.io.records import RecordError, read_record
    from ajtwin.job import ProgramError
    from ajtwin.store.registry import RegistryError

    if record is None and machine is None:
        raise click.UsageError("give a print RECORD (with --job PROGRAM) or --machine NAME")
    if record is not None and seq is not None:
        raise click.UsageError("--print SEQ reads a stored print: give it without RECORD")
    if record is not None and program is None:
        raise click.UsageError("a print RECORD needs the program it ran: --job PROGRAM.prg")
    twin_step, line_step, close = _bars(progress)
    options = {
        "map_settings": MapSettings(portion_mm=portion_mm, flag_probability=flag_probability),
        "twin_progress": twin_step,
        "line_progress": line_step,
    }
    try:
        if record is None:
            stored = load_stored_print(open_registry(store), machine, seq, program)
            stored.job.check_portions(portion_mm)  # refused before the twin's work
            part = map_stored_print(stored, tolerance, **options)
        else:
            rec = read_record(record, aliases=aliases, dialect=csv_dialect)
            the_job = program_for_record(
                rec,
                program,
                process_speed_mm_s=process_speed,
                rapid_speed_mm_s=rapid_speed,
                repeat_to_s=repeat_to,
                repeat_pitch_mm=repeat_pitch,
            )
            the_job.check_portions(portion_mm)  # refused before the twin's work
            twin, start = None, None
            if machine is not None:  # the machine's twin, where its next print would start
                twin, start = next_print_twin(open_registry(store), machine)
            part = part_map_of_record(
                rec, the_job, tolerance, twin=twin, start=start, source=str(record), **options
            )
            part.machine = machine
        paths = write_report(part, out_dir)
    except (ProgramError, RecordError, RegistryError, ValueError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    finally:
        close()
    _echo_part_report(part, paths)
