"""``ajtwin control``: closed-loop control of linewidth (docs/control.md).

``ajtwin control simulate`` runs the strategies in closed loop with the virtual printer.
The live variant (``--machine … --opcua …``) waits for the OPC UA client of the live link.
"""

from __future__ import annotations

import click


def _parse_seeds(text: str) -> list[int]:
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part:
                a, b = (int(v) for v in part.split("-", 1))
                if b < a:
                    raise ValueError
                seeds += list(range(a, b + 1))
            else:
                seeds.append(int(part))
        except ValueError:
            raise click.BadParameter(
                f"cannot read seeds {text!r} (use e.g. 1-5 or 1,3,7)"
            ) from None
    if not seeds or any(s < 0 for s in seeds):
        raise click.BadParameter(f"seeds must be non-negative integers, got {text!r}")
    return seeds


@click.group()
def control():
    """Closed-loop control of linewidth: MPC from the twin's state (docs/control.md)."""


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
    no_progress,
):
    """Run the strategies in closed loop with the virtual printer and compare them.

    Writes DIR/<scenario>/seed<N>/<strategy>.parquet (the closed-loop print, record format)
    with <strategy>_commands.csv, DIR/metrics.json and one figure DIR/<scenario>.png.
    """
    from tqdm import tqdm

    from ajtwin.apps.control import ControlSettings, TargetError
    from ajtwin.apps.control_sim import STRATEGIES, compare, resolve_scenario
    from ajtwin.simulation.scenarios import load_scenario

    chosen = tuple(s.strip() for s in strategies.split(",") if s.strip())
    unknown = [s for s in chosen if s not in STRATEGIES]
    if unknown or not chosen:
        raise click.BadParameter(
            f"unknown strategies {unknown}; choose from {', '.join(STRATEGIES)}",
            param_hint="--strategies",
        )
    seed_list = _parse_seeds(seeds)
    if duration_min is not None and not duration_min > 0:
        raise click.BadParameter("must be > 0", param_hint="--duration-min")
    try:
        settings = ControlSettings.load(settings_path)
        total = 0
        for name in scenarios:
            sc = load_scenario(resolve_scenario(name))
            total += (duration_min * 60 if duration_min else sc.duration_s) * len(seed_list)
        total = int(total * len(chosen))
        bar = tqdm(total=total, unit="s", desc="closed loop", disable=no_progress)
        with bar:
            results = compare(
                scenarios,
                seed_list,
                target,
                out_dir,
                strategies=chosen,
                duration_min=duration_min,
                settings=settings,
                max_overspray_um=max_overspray,
                progress=bar.update,
                log=lambda text: tqdm.write(text) if not no_progress else click.echo(text),
            )
    except TargetError as exc:
        raise click.ClickException(str(exc)) from None
    except (ValueError, FileNotFoundError) as exc:
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
