"""``ajtwin develop``: bring up a new ink in a few test lines (operator in the loop, file based)."""

from __future__ import annotations

import json
from pathlib import Path

import click

INPUT_LABELS = (
    ("atomizer_current_mA", "I_A", "mA"),
    ("carrier_flow_sccm", "Q_c", "sccm"),
    ("sheath_flow_sccm", "Q_s", "sccm"),
    ("speed_mm_s", "ν", "mm/s"),
)


def _pair(text: str, what: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in str(text).split(","))
    except ValueError:
        raise click.BadParameter(f"{text!r}: give LOW,HIGH", param_hint=what) from None
    if not 0 < low < high:
        raise click.BadParameter(f"{text!r}: need 0 < LOW < HIGH", param_hint=what)
    return low, high


def _read_limits(path) -> dict:
    """``--limits FILE``: a TOML file with ``[limits]`` input = [low, high]."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.config import read_toml

    try:
        table = read_toml(Path(path), what="limits").get("limits")
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    if not isinstance(table, dict):
        raise click.ClickException(f"{path}: no [limits] table (input = [low, high])")
    known = {name for name, _, _ in INPUT_LABELS[:3]}
    unknown = set(table) - known
    if unknown:
        raise click.ClickException(f"{path}: unknown inputs {sorted(unknown)}; use {sorted(known)}")
    return table


def _load(path):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.develop.bringup import BringUp

    try:
        return BringUp.load(path)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None


def _inputs_text(values: dict) -> str:
    return ", ".join(f"{short} {values[name]:g} {unit}" for name, short, unit in INPUT_LABELS)


@click.group()
def develop():
    """Bring up a new ink, nozzle or substrate: which inputs print a target linewidth with
    little overspray, in few test lines. The twin's physics is the prior; each test line's
    reading updates it (docs/howto/bring-up-a-new-ink.md)."""


@develop.command("start")
@click.option("--target-linewidth", type=float, required=True, help="Target L_w [µm].")
@click.option("--max-overspray", type=float, required=True, help="Upper limit of L_o [µm].")
@click.option("--tolerance", type=float, default=2.0, show_default=True, help="± on L_w [µm].")
@click.option(
    "--machine",
    "machine_name",
    default=None,
    help="A registered machine: its calibration, nozzle and limits.",
)
@click.option("--speed", type=float, default=None, help="Platen speed [mm/s] (default 2).")
@click.option("--speed-range", default=None, help="Let the speed vary, LOW,HIGH [mm/s].")
@click.option(
    "--limits",
    "limits_path",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="TOML file with [limits] input = [low, high] (default: the machine's, or the defaults).",
)
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="The bring-up file to write (JSON).",
)
@click.option("--force", is_flag=True, help="Overwrite an existing file.")
@click.option("--store", default=None, help="Registry (with --machine; default: the user's).")
def start(
    target_linewidth,
    max_overspray,
    tolerance,
    machine_name,
    speed,
    speed_range,
    limits_path,
    out_path,
    force,
    store,
):
    """Start a bring-up: the goal, the inputs it may set, the machine."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.develop.bringup import BringUp, Goal
    from ajtwin.apps.develop.prior import InputBox, MachineLine

    if speed is not None and speed_range is not None:
        raise click.UsageError("give --speed or --speed-range, not both")
    if out_path.exists() and not force:
        raise click.ClickException(f"{out_path} exists (use --force to start over)")
    limits = _read_limits(limits_path) if limits_path else None
    machine = MachineLine()
    if machine_name:
        machine, machine_limits = _machine_line(machine_name, store)
        limits = limits or machine_limits
    try:
        goal = Goal(target_linewidth, max_overspray, tolerance)
        span = _pair(speed_range, "--speed-range") if speed_range else None
        box = InputBox.from_limits(limits, 2.0 if speed is None else speed, span)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    bringup = BringUp.create(goal, box, machine)
    bringup.save(out_path)
    bounds = ", ".join(
        f"{short} {lo:g}–{hi:g} {unit}"
        for (_, short, unit), (lo, hi) in zip(INPUT_LABELS, box.bounds)
    )
    speeds = box.speed_mm_s
    click.echo(
        f"wrote {out_path}: L_w {target_linewidth:g} ± {tolerance:g} µm, L_o ≤ "
        f"{max_overspray:g} µm; "
        f"{bounds}, ν {speeds[0]:g}"
        + (f"–{speeds[1]:g}" if speeds[1] > speeds[0] else "")
        + " mm/s"
        + (f"; machine {machine_name}" if machine_name else "; nominal machine")
    )
    click.echo(f"next: ajtwin develop next {out_path}")


def _machine_line(name, store):
    """(MachineLine, limits) of a registered machine."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.develop.prior import MachineLine
    from ajtwin.cli.options import open_registry
    from ajtwin.engine.start import machine_twin
    from ajtwin.model.calibration import Calibration
    from ajtwin.store.registry import RegistryError

    reg = open_registry(store)
    try:
        twin, mean, _, _, machine, _ = machine_twin(reg, name)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    calibration = twin.calibration or Calibration.identity()
    return MachineLine(name, calibration, float(max(mean[3], 0.0))), machine["limits"]


@develop.command("next")
@click.argument("path", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="End with one JSON line of the answer.")
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Where to draw the window when done (default: beside the file, .window.png).",
)
def next_step(path, as_json, plot_path):
    """The next test line to print, or the recipe (done), or that the target is out of reach."""
    bringup = _load(path)
    decision = bringup.decide()
    bringup.save(path)
    answer = decision.as_dict()
    if decision.kind == "test":
        t = decision.test
        click.echo(f"test line {len(bringup.tests) + 1}: {_inputs_text(t)}")
        click.echo(
            f"  settle {t['settle_s']} s after setting the inputs, then print "
            f"{t['print_s']} s of line"
        )
        click.echo(f"  then: ajtwin develop add {path} --linewidth-um L_W --overspray-um L_O")
    elif decision.kind == "done":
        r = decision.recipe
        click.echo(f"done: {decision.message}")
        click.echo(f"  recipe: {_inputs_text(r)}")
        click.echo(
            f"  predicted L_w {r['linewidth_um']:.1f} ± {r['linewidth_2sd_um']:.1f} µm, "
            f"L_o {r['overspray_um']:.1f} ± {r['overspray_2sd_um']:.1f} µm (2σ); "
            f"P(within ± {bringup.goal.tolerance_um:g} µm and L_o ≤ max) = {r['probability']:.2f}"
        )
        plot_path = plot_path or path.with_suffix(".window.png")
        _draw(bringup, [r[n] for n, _, _ in INPUT_LABELS], plot_path)
        answer["window_plot"] = str(plot_path)
        click.echo(
            f"  window: {100 * decision.window['share']:.1f} % of the input box; drawn in "
            f"{plot_path}"
        )
    else:
        c = decision.closest
        click.echo(f"out of reach: {decision.message}")
        click.echo(f"  closest: {_inputs_text(c)}")
    if as_json:
        click.echo(json.dumps(answer))


def _draw(bringup, centre, path):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.develop.plot import window_figure

    window_figure(bringup, bringup.posterior(), centre, path)


@develop.command("add")
@click.argument("path", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--linewidth-um",
    type=float,
    default=None,
    help="The test line's L_w [µm] (a microscope reading).",
)
@click.option("--overspray-um", type=float, default=None, help="Its L_o [µm] (one side).")
@click.option("--std-um", type=float, default=None, help="σ of each reading [µm] (default 1).")
@click.option(
    "--record",
    "record_path",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="The test line's print record (camera and MFCs); its held inputs are the test's.",
)
@click.option(
    "--inputs",
    "inputs_text",
    default=None,
    help="The inputs printed, I_A,Q_c,Q_s[,ν] (default: what `next` asked for).",
)
def add(path, linewidth_um, overspray_um, std_um, record_path, inputs_text):
    """Add what a test line measured."""
    bringup = _load(path)
    if record_path is not None and (linewidth_um is not None or overspray_um is not None):
        raise click.UsageError("give --record or --linewidth-um/--overspray-um, not both")
    if record_path is None and (linewidth_um is None or overspray_um is None):
        raise click.UsageError("give --linewidth-um and --overspray-um (or --record)")
    if std_um is not None and not std_um > 0:
        raise click.BadParameter("must be > 0", param_hint="--std-um")
    inputs = _test_inputs(bringup, inputs_text, record_path is None)
    try:
        if record_path is not None:
            test = _add_record(bringup, record_path, inputs)
        else:
            test = bringup.add_test(
                inputs, linewidth_um, overspray_um, linewidth_std_um=std_um, overspray_std_um=std_um
            )
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    bringup.save(path)
    click.echo(
        f"test {len(bringup.tests)}: {_inputs_text(test)} → L_w {test['linewidth_um']:.2f} ± "
        f"{test['linewidth_std_um']:.2f} µm, L_o {test['overspray_um']:.2f} ± "
        f"{test['overspray_std_um']:.2f} µm"
    )
    click.echo(f"next: ajtwin develop next {path}")


def _test_inputs(bringup, text, required):
    """The inputs of the test being added: --inputs, or what `next` suggested."""
    if text:
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            raise click.BadParameter(
                f"{text!r}: give I_A,Q_c,Q_s[,ν]", param_hint="--inputs"
            ) from None
        if len(values) not in (3, 4):
            raise click.BadParameter("give 3 or 4 numbers", param_hint="--inputs")
        if len(values) == 3:
            values.append(bringup.box.speed_mm_s[0])
        return values
    if bringup.suggested:
        return [bringup.suggested[n] for n, _, _ in INPUT_LABELS]
    if required:
        raise click.UsageError(
            "no test was asked for: run `ajtwin develop next` first, or give --inputs"
        )
    return None


def _add_record(bringup, record_path, inputs):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.develop.bringup import reading_from_record
    from ajtwin.io.records import read_record

    record = read_record(record_path)
    speed = inputs[3] if inputs is not None else bringup.box.speed_mm_s[0]
    settle, _ = bringup.timing(speed)
    reading = reading_from_record(record, settle, speed)
    used = reading["inputs"] if inputs is None else inputs
    return bringup.add_test(
        used,
        reading["linewidth_um"],
        reading["overspray_um"],
        linewidth_std_um=reading["linewidth_std_um"],
        overspray_std_um=reading["overspray_std_um"],
        source=f"record {Path(record_path).name}",
        extra=reading["extra"],
    )


@develop.command("report")
@click.argument("path", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Folder to write the report into.",
)
def report(path, out_dir):
    """The tests, the fitted ink, the window plot and the recipe, in a folder."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.develop.report import write_report

    bringup = _load(path)
    try:
        written = write_report(bringup, out_dir)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    for item in written:
        click.echo(f"wrote {item}")


@develop.command("simulate")
@click.option("--ink-seed", type=click.IntRange(min=0), required=True, help="The virtual ink.")
@click.option(
    "--truth",
    type=click.Choice(["model", "alt"]),
    default="model",
    show_default=True,
    help="The ink's generator (alt: for evaluation only).",
)
@click.option(
    "--target-linewidth",
    type=float,
    default=None,
    help="Target L_w [µm] (default: one the ink can print).",
)
@click.option(
    "--max-overspray",
    type=float,
    default=None,
    help="L_o limit [µm] (default: the ink's 60 % quantile).",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=None,
    help="The virtual printer's noise (default 500 + ink seed).",
)
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write the bring-up file.",
)
def simulate(ink_seed, truth, target_linewidth, max_overspray, seed, out_path):
    """A whole bring-up against a virtual ink, each test printed on the virtual printer."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.develop.bringup import BringUp, Goal
    from ajtwin.apps.develop.prior import InputBox
    from ajtwin.simulation.virtual_ink import draw_ink
    from ajtwin.studies.develop import SPEED_MM_S, VirtualLab, evaluate, goal_for, run_twin

    ink = draw_ink(ink_seed, truth)
    default = goal_for(ink)
    try:
        goal = Goal(
            target_linewidth or default.target_linewidth_um,
            max_overspray or default.max_overspray_um,
        )
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(
        f"virtual ink {ink_seed} ({truth}): L_w {goal.target_linewidth_um:g} ± 2 µm, L_o ≤ "
        f"{goal.max_overspray_um:g} µm"
    )
    lab = VirtualLab(
        ink,
        500 + ink_seed if seed is None else seed,
        BringUp.create(goal, InputBox.from_limits(None, SPEED_MM_S)),
    )
    outcome = evaluate(lab, run_twin(lab), len(lab.bringup.tests))
    for k, t in enumerate(lab.bringup.tests, 1):
        click.echo(
            f"  test {k}: {_inputs_text(t)} → L_w {t['linewidth_um']:.1f} µm (true "
            f"{t['true_linewidth_um']:.1f}), "
            f"L_o {t['overspray_um']:.1f} µm"
        )
    if outcome["kind"] == "done":
        verdict = "holds" if outcome["holds"] else "DOES NOT HOLD"
        nominal = "holds" if outcome["holds_nominal"] else "does not hold"
        click.echo(
            f"done after {outcome['tests']} test lines: the next line printed at the recipe "
            f"has true L_w {outcome['next_linewidth_um']:.1f} µm, "
            f"L_o {outcome['next_overspray_um']:.1f} µm: {verdict}; at the nominal machine "
            f"state the ink's line there is L_w {outcome['nominal_linewidth_um']:.1f} µm, "
            f"L_o {outcome['nominal_overspray_um']:.1f} µm ({nominal}); after ±5 % droplet "
            f"size / aerosol density the worst miss is {outcome['robust_worst_miss_um']:.1f} µm"
        )
    else:
        click.echo(f"{outcome['kind'].replace('_', ' ')} after {outcome['tests']} test lines")
    if out_path:
        lab.bringup.save(out_path)
        click.echo(f"wrote {out_path}")
