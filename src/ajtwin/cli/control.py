"""``ajtwin control``: closed-loop control of linewidth (docs/howto/closed-loop-control.md).

``ajtwin control simulate`` runs the strategies in closed loop with the virtual printer.
``ajtwin control --machine M --target-linewidth W --opcua URL`` controls a live machine
over OPC UA (:mod:`ajtwin.live.control_link`).
"""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path

import click
from tqdm import tqdm

from ajtwin.cli.options import (
    OffsetMM,
    PitchMM,
    ProcessSpeed,
    ToleranceType,
    parse_seeds,
    process_speed_option,
    store_option,
)
from ajtwin.store.registry import Registry, RegistryError


def _parse_horizon(text) -> int | None:
    """``120s``, ``2min`` or ``120`` → seconds."""
    if text is None:
        return None
    raw = str(text).strip().lower()
    scale = 1
    for suffix, factor in (("min", 60), ("s", 1)):
        if raw.endswith(suffix):
            raw, scale = raw[: -len(suffix)].strip(), factor
            break
    try:
        seconds = float(raw) * scale
    except ValueError:
        raise click.BadParameter(f"{text!r}: give e.g. 120s or 2min") from None
    if not seconds >= 1 or seconds != int(seconds):
        raise click.BadParameter(f"{text!r}: a whole number of seconds ≥ 1")
    return int(seconds)


#: What an inspection pass only leaves the controllers (said before such a comparison runs)
INSPECTION_NOTE = (
    "note: an inspection pass after the print only: no line is measured while it prints, so "
    "PI has nothing to act on (it runs open loop) and the twin's MPC steers on the model and "
    "the pressures alone, which see the nozzle and the tube but not the droplet size or the "
    "aerosol density: expect it to do what the nominal MPC does"
)


@click.group(invoke_without_command=True)
@click.option(
    "--machine",
    default=None,
    help="Machine name (live control; see docs/howto/closed-loop-control.md).",
)
@click.option("--target-linewidth", "target", type=float, default=None, help="Target L_w [µm].")
@click.option("--max-overspray", type=float, default=None, help="Soft limit on L_o [µm].")
@click.option("--horizon", default=None, help="MPC horizon, e.g. 120s (default: control.toml).")
@click.option("--opcua", "url", default=None, help="Server endpoint, opc.tcp://host:port.")
@click.option("--username", default=None)
@click.option("--password", default=None, envvar="AJTWIN_OPCUA_PASSWORD")
@click.option("--security", default=None, help="e.g. Basic256Sha256_SignAndEncrypt.")
@click.option("--certificate", type=click.Path(path_type=Path), default=None)
@click.option("--private-key", type=click.Path(path_type=Path), default=None)
@click.option("--server-certificate", type=click.Path(path_type=Path), default=None)
@click.option(
    "--settings",
    "settings_path",
    type=click.Path(dir_okay=False, exists=True),
    default=None,
    help="A control.toml of your own (default: the packaged tuning).",
)
@click.option(
    "--vial-fill-ml",
    type=float,
    default=None,
    help="The vial's fill as weighed at the refill [mL] (ink balance; default 1 mL).",
)
@click.option(
    "--job",
    "program",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="The program the machine prints (.prg; time 0 = its start, run again when it ends): "
    "the MPC reads the speeds ahead, the twin files the camera at print times, the print is "
    "stored with its job and --dashboard shows the part map filling in.",
)
@click.option(
    "--process-speed",
    type=ProcessSpeed(),
    default=None,
    help="With --job: the process speed [mm/s] or speeds per layer (2,4,3, stroke:…, a file).",
)
@click.option(
    "--camera",
    "camera_mode",
    type=click.Choice(["trailing", "at_nozzle"]),
    default="trailing",
    show_default=True,
    help="With --job: where the machine's camera looks.",
)
@click.option(
    "--camera-offset-mm",
    type=OffsetMM(),
    default=None,
    help="With --job: a trailing camera's view centre relative to the nozzle, DX[,DY] mm "
    "(default data/virtual_camera.toml, -5,0).",
)
@click.option(
    "--tolerance",
    type=ToleranceType(),
    default=None,
    help="With --job: the part's linewidth tolerance in µm for the part map (55±2, 53:57).",
)
@click.option(
    "--dashboard",
    "dashboard_port",
    type=click.IntRange(min=0, max=65535),
    default=None,
    metavar="PORT",
    help="With --job: serve the dashboard (with the part map) on 127.0.0.1:PORT (0: free).",
)
@store_option
@click.option("--verbose", is_flag=True)
@click.pass_context
def control(
    ctx,
    machine,
    target,
    max_overspray,
    horizon,
    url,
    username,
    password,
    security,
    certificate,
    private_key,
    server_certificate,
    settings_path,
    vial_fill_ml,
    program,
    process_speed,
    camera_mode,
    camera_offset_mm,
    tolerance,
    dashboard_port,
    store,
    verbose,
):
    """Closed-loop control of linewidth: MPC from the twin's state
    (docs/howto/closed-loop-control.md).

    With --machine/--target-linewidth/--opcua: control a live machine, writing its three
    set-points over OPC UA every control period (within its limits and rate limits; held,
    with the reason, on a model–machine mismatch or an alarm). Subcommands: simulate.
    """
    if ctx.invoked_subcommand is not None:
        return
    missing = [
        flag
        for flag, value in (
            ("--machine", machine),
            ("--target-linewidth", target),
            ("--opcua", url),
        )
        if value is None
    ]
    if missing:
        if machine is None and target is None and url is None:
            click.echo(ctx.get_help())
            return
        raise click.UsageError(f"live control needs {', '.join(missing)}")
    _control_live(
        machine,
        target,
        max_overspray,
        _parse_horizon(horizon),
        url,
        dict(
            username=username,
            password=password,
            security=security,
            certificate=certificate,
            private_key=private_key,
            server_certificate=server_certificate,
        ),
        settings_path,
        store,
        verbose,
        vial_fill_ml,
        _live_job(program, process_speed, camera_mode, camera_offset_mm, tolerance, dashboard_port),
    )


def _live_job(program, process_speed, camera_mode, offset_mm, tolerance, dashboard_port):
    """The job options of live control, checked (None without --job)."""
    given = {
        "--process-speed": process_speed,
        "--camera-offset-mm": offset_mm,
        "--tolerance": tolerance,
        "--dashboard": dashboard_port,
    }
    if program is None:
        named = [k for k, v in given.items() if v is not None]
        if named:
            raise click.UsageError(f"{', '.join(named)} go with --job")
        return None
    if camera_mode == "at_nozzle" and offset_mm is not None and any(offset_mm):
        raise click.BadParameter("a camera at the nozzle has no offset", param_hint="--camera")
    return {
        "program": program,
        "process_speed": process_speed,
        "camera_mode": camera_mode,
        "offset_mm": offset_mm,
        "tolerance": tolerance,
        "dashboard_port": dashboard_port,
    }


def _control_live(
    machine,
    target,
    max_overspray,
    horizon_s,
    url,
    login,
    settings_path,
    store,
    verbose,
    vial_fill_ml=None,
    job=None,
):

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.planning.mpc import ControlSettings, TargetError
    from ajtwin.apps.planning.supervisor import ControlTarget
    from ajtwin.live.control_link import ControlLink, LinkRefused
    from ajtwin.live.link import OpcUaLogin

    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    limits = None
    try:
        with Registry(store, create=False) as registry:
            limits = registry.machine(machine)["limits"]
    except (RegistryError, FileNotFoundError, KeyError):
        click.echo(
            f"{machine}: not in the registry; using the default limits (ajtwin machine add "
            "sets a machine's own)",
            err=True,
        )
    try:
        overrides = {} if horizon_s is None else {"horizon_s": horizon_s}
        settings = ControlSettings.load(settings_path, **overrides)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--horizon/--settings") from None

    def show(d):
        written = ", ".join(f"{k} → {v:.4g}" for k, v in d.written.items()) or "nothing written"
        line = f"t = {d.time_s:6.0f} s  {d.status:7s}  {written}"
        if d.status == "act" and d.predicted_linewidth_um == d.predicted_linewidth_um:
            line += f"  (L_w → {d.predicted_linewidth_um:.1f} µm, solve {d.solve_ms:.0f} ms)"
        if d.reason:
            line += f"  [{d.reason}]"
        click.echo(line)

    engine = dashboard = None
    try:
        job_options = {}
        if job is not None:
            engine, dashboard, job_options = _job_engine(machine, job, store)
        goal = ControlTarget(target, max_overspray, limits, settings, vial_fill_ml)
        link = ControlLink(
            url,
            machine,
            goal,
            login=OpcUaLogin(**login),
            engine=engine,
            on_decision=show,
            **job_options,
        )
        asyncio.run(link.run())
    except TargetError as exc:
        raise click.ClickException(str(exc)) from None
    except LinkRefused as exc:
        raise click.ClickException(str(exc)) from None
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    except KeyboardInterrupt:
        click.echo("stopped; the machine keeps its last set-points", err=True)
        return
    finally:
        if engine is not None:
            engine.shutdown()
        if dashboard is not None:
            dashboard.stop()
    click.echo(f"{machine}: print finished; {len(link.decisions)} control periods")
    if link.print_id is not None:
        click.echo(f"print stored as registry print id {link.print_id} (with its job)")


def _job_engine(machine, job: dict, store):
    """A job print under live control: the live engine (the machine's twin, its print stored
    with the job in the registry), the dashboard with the part map when asked, and the
    link's job options."""

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cli.live import _follow_parts
    from ajtwin.cli.options import job_speeds, open_registry
    from ajtwin.engine.control import CameraOnJob
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.engine.print_job import entry_job, job_entry
    from ajtwin.simulation.job_print import load_camera_defaults

    speeds = job_speeds(job["process_speed"])
    entry = job_entry(
        job["program"],
        process_speed_mm_s=speeds["process_speed_mm_s"],
        speed_schedule=speeds["speed_schedule"],
        tolerance=job["tolerance"],
    )
    engine = LiveEngine(open_registry(store, create=True), asynchronous=False)
    engine.warm_up(1)
    engine.jobs[machine] = entry  # stored with the print
    dashboard = None
    if job["dashboard_port"] is not None:
        # lazy CLI loading: imported when the command runs, not for --help
        from ajtwin.web.publisher import LivePublisher
        from ajtwin.web.server import BackgroundServer

        publisher = LivePublisher()
        engine.subscribe(publisher.publish_engine)
        publisher.open_print(machine)
        _follow_parts(engine, publisher, [machine], entry, job["tolerance"])
        dashboard = BackgroundServer(engine.registry.path, publisher, port=job["dashboard_port"])
        click.echo(f"dashboard: open {dashboard.url}", err=True)
    offset = (0.0, 0.0)
    if job["offset_mm"] is not None:
        offset = tuple(job["offset_mm"])
    elif job["camera_mode"] == "trailing":
        offset = tuple(load_camera_defaults()["offset_mm"])
    camera = CameraOnJob(job["camera_mode"], offset)
    return engine, dashboard, {"job": entry_job(entry), "camera": camera}


@control.command()
@click.option(
    "--scenario",
    "scenarios",
    multiple=True,
    required=True,
    help="Scenario name or .toml file (repeat for several); slow_clog ships with the controller.",
)
@click.option("--target-linewidth", "target", required=True, type=float, help="Target L_w [µm].")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Folder.")
@click.option("--seeds", default="1", show_default=True, help="Seeds, e.g. 1-5 or 1,3.")
@click.option(
    "--strategies",
    default="open_loop,pi,mpc_nominal,mpc_twin",
    show_default=True,
    help="Comma-separated subset of open_loop, pi, mpc_nominal, mpc_twin.",
)
@click.option("--duration-min", type=float, default=None, help="Shorten every print [min].")
@click.option("--max-overspray", type=float, default=None, help="Soft limit on L_o [µm].")
@click.option(
    "--settings",
    "settings_path",
    type=click.Path(dir_okay=False, exists=True),
    default=None,
    help="A control.toml of your own (default: the packaged tuning).",
)
@click.option(
    "--truth",
    type=click.Choice(["model", "alt"]),
    default="model",
    show_default=True,
    help="Virtual printer's truth generator: model (tuned the controller) or alt (evaluation).",
)
@click.option(
    "--job",
    "program",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Print this machine program (.prg), looped to each print's length: the shutter, the "
    "speeds and a camera on the part (docs/howto/closed-loop-control.md).",
)
@process_speed_option
@click.option(
    "--camera",
    "camera_mode",
    type=click.Choice(["trailing", "inspection", "at_nozzle"]),
    default=None,
    help="With --job: the camera trails the nozzle, inspects the part after the print only, "
    "or sees the line as printed (default: trailing; at_nozzle when the offset is 0).",
)
@click.option(
    "--camera-offset-mm",
    type=OffsetMM(),
    default=None,
    help="With --job: the trailing camera's view centre relative to the nozzle, DX[,DY] mm "
    "(default data/virtual_camera.toml, -5,0: 5 mm behind the public programs' fills).",
)
@click.option(
    "--repeat-pitch-mm",
    type=PitchMM(),
    default=None,
    help="With --job: loop the job as parts side by side, DX[,DY] mm apart.",
)
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def simulate(
    scenarios,
    target,
    out_dir,
    seeds,
    strategies,
    duration_min,
    max_overspray,
    settings_path,
    truth,
    program,
    process_speed,
    camera_mode,
    camera_offset_mm,
    repeat_pitch_mm,
    no_progress,
):
    """Run the strategies in closed loop with the virtual printer and compare them.

    Writes DIR/<scenario>/seed<N>/<strategy>.parquet (the closed-loop print, record format;
    a job print's with the job columns) with <strategy>_commands.csv, DIR/metrics.json and
    one figure DIR/<scenario>.png. With --job every strategy prints the program and sees
    what its camera sees; the figures are per printed length.
    """

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.planning.closed_loop import STRATEGIES, resolve_scenario
    from ajtwin.apps.planning.mpc import ControlSettings, TargetError
    from ajtwin.job import ProgramError
    from ajtwin.simulation.scenarios import load_scenario
    from ajtwin.studies.control import ComparisonGrid, JobSetup, compare

    chosen = tuple(s.strip() for s in strategies.split(",") if s.strip())
    unknown = [s for s in chosen if s not in STRATEGIES]
    if unknown or not chosen:
        raise click.BadParameter(
            f"unknown strategies {unknown}; choose from {', '.join(STRATEGIES)}",
            param_hint="--strategies",
        )
    seed_list = parse_seeds(seeds)
    if duration_min is not None and not duration_min > 0:
        raise click.BadParameter("must be > 0", param_hint="--duration-min")
    job_options = {
        "--process-speed": process_speed,
        "--camera": camera_mode,
        "--camera-offset-mm": camera_offset_mm,
        "--repeat-pitch-mm": repeat_pitch_mm,
    }
    if program is None and any(v is not None for v in job_options.values()):
        given = ", ".join(k for k, v in job_options.items() if v is not None)
        raise click.UsageError(f"{given} describe a job print: give --job PROGRAM.prg")
    try:
        job = None
        if program is not None:
            job = JobSetup.read(
                program, process_speed, camera_mode, camera_offset_mm, repeat_pitch_mm
            )
            if job.camera.meta()["mode"] == "inspection":
                click.echo(INSPECTION_NOTE, err=True)
        settings = ControlSettings.load(settings_path)
        total = 0
        for name in scenarios:
            sc = load_scenario(resolve_scenario(name))
            total += (duration_min * 60 if duration_min else sc.duration_s) * len(seed_list)
        total = int(total * len(chosen))
        bar = tqdm(total=total, unit="s", desc="closed loop", disable=no_progress)
        with bar:
            grid = ComparisonGrid(
                scenarios, seed_list, target, strategies=chosen, duration_min=duration_min
            )
            results = compare(
                grid,
                out_dir,
                settings=settings,
                max_overspray_um=max_overspray,
                progress=bar.update,
                log=lambda text: tqdm.write(text) if not no_progress else click.echo(text),
                truth=truth,
                job=job,
            )
    except TargetError as exc:
        raise click.ClickException(str(exc)) from None
    except (ProgramError, ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    for name, block in results["scenarios"].items():
        click.echo(f"\n{name} (mean over seeds {seeds}):")
        summary = block["summary"]
        for strategy in chosen:
            row = summary.get(strategy)
            if row is None:
                continue
            solve = row["solve_ms_mean"]
            click.echo(
                f"  {strategy:12s} rms {row['rms_error_um_mean']:6.2f} µm  "
                f"within ±2 µm {row['within_2um_fraction_mean']:5.0%}  "
                f"L_o {row['mean_overspray_um']:5.2f} µm  holds {row['holds_mean']:6.1f}"
                + (f"  solve {solve:5.1f} ms" if solve is not None else "")
            )
    click.echo(f"\nwrote {out_dir}/metrics.json and one figure per scenario")


@control.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(exists=True))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Folder.")
def merge(runs, out_dir):
    """Merge runs of ``control simulate`` (per seed, scenario or --truth) into one table.

    RUNS are --out folders (or their metrics.json). Writes OUT/metrics.json (per seed and
    recomputed summaries; a scenario of the second truth generator as NAME@alt) and
    OUT/metrics.md (the comparison table), and prints the table.
    """

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.studies.control import merge_results, metrics_table

    try:
        merged = merge_results(runs)
    except (ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(merged, indent=2))
    table = metrics_table(merged)
    (out / "metrics.md").write_text(table)
    click.echo(table, nl=False)
    click.echo(f"wrote {out / 'metrics.json'} and {out / 'metrics.md'} ({len(runs)} runs)")
