"""``ajtwin forecast``: what a registered machine's outputs will do under planned inputs."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ajtwin.cli.options import (
    SHORT,
    open_registry,
    parse_inputs,
    store_option,
    theta_text,
    transition_option,
    transition_overrides,
)
from ajtwin.store.registry import RegistryError


@click.command()
@click.option("--machine", "machine_name", required=True, help="Registered machine name.")
@click.option(
    "--set",
    "changes",
    multiple=True,
    metavar="NAME=VALUE@+TIME",
    help="Planned input change, e.g. carrier_flow_sccm=26@+60s or Q_s=48@+10min (repeatable).",
)
@click.option("--horizon", default="30min", show_default=True, help="Forecast length (s/min/h).")
@click.option(
    "--inputs",
    "inputs_text",
    default=None,
    help="Inputs now, I_A,Q_c,Q_s (default: the last print's final inputs).",
)
@click.option(
    "--with-sensor-noise",
    is_flag=True,
    help="Bands for what the sensors will read (adds measurement noise).",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("forecast.csv"),
    show_default=True,
    help="CSV, one row per second.",
)
@click.option(
    "--plot",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Figure with ±2σ bands  [default: the --out path with .png].",
)
@click.option(
    "--nominal-theta",
    is_flag=True,
    help="Use θ = 0 instead of the machine's learned θ (e.g. after cleaning the nozzle).",
)
@transition_option
@store_option
def forecast(
    machine_name,
    changes,
    horizon,
    inputs_text,
    with_sensor_noise,
    out,
    plot,
    nominal_theta,
    transition,
    store,
):
    """Forecast L_w, L_o, P_c, P_s (± σ) from the machine's last state under planned inputs."""
    # lazy CLI loading: the library (JAX) is imported when the command runs, not for --help
    from ajtwin.apps.planning.forecast import forecast as run_forecast
    from ajtwin.apps.planning.forecast import (
        input_schedule,
        parse_change,
        parse_duration,
        plot_forecast,
    )
    from ajtwin.engine.start import input_response_at_end, machine_twin

    try:
        horizon_s = parse_duration(horizon)
        parsed = [parse_change(c) for c in changes]
        user_inputs = parse_inputs(inputs_text)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    reg = open_registry(store)
    try:
        twin, mean, cov, u_last, _, last = machine_twin(
            reg, machine_name, nominal_theta, transition_overrides(transition).get("transition")
        )
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    except ValueError as exc:  # an unknown transition variant
        raise click.BadParameter(str(exc)) from None
    u0 = u_last if user_inputs is None else user_inputs
    try:
        schedule = input_schedule(u0, parsed, horizon_s)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    fc = run_forecast(
        twin,
        mean,
        cov,
        schedule,
        include_measurement_noise=with_sensor_noise,
        input_response0=input_response_at_end(twin, reg, last),
    )
    frame = fc.to_frame()
    out.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(out, index=False)
    click.echo(
        f"forecast for {machine_name!r} from the end of print #{last['seq']} "
        f"({horizon_s / 60:g} min; inputs now I_A {u0[0]:g} mA, Q_c {u0[1]:g}, Q_s {u0[2]:g} sccm)"
    )
    for change in parsed:
        name = list(SHORT)[change.input_index]
        click.echo(
            f"  at +{change.time_s:g} s: {SHORT[name][0]} → {change.value:g} {SHORT[name][1]}"
        )
    names = ["linewidth_um", "overspray_um", "carrier_pressure_Pa", "sheath_pressure_Pa"]
    header = "  t [min]  " + "  ".join(
        f"{SHORT[n][0] + ' [' + SHORT[n][1] + ']':>16s}" for n in names
    )
    click.echo(header)
    picks = np.unique(np.linspace(0, len(frame) - 1, 7).round().astype(int))
    for k in picks:
        row = frame.iloc[k]
        cells = "  ".join(f"{row[n]:9.4g} ± {2 * row[n + '_std']:<5.2g}" for n in names)
        click.echo(f"  {row['time_s'] / 60:7.2f}  {cells}")
    click.echo("  (± = 2σ)")
    if nominal_theta:
        click.echo("  drift rates θ: none (--nominal-theta)")
    else:
        click.echo(f"  {theta_text(twin.theta)}")
    for text in fc.warnings:
        click.echo(f"  warning: {text}")
    # beside the CSV by default, so a run never litters the working directory
    plot = out.with_suffix(".png") if plot is None else plot
    plot_forecast(fc, plot, title=f"{machine_name}: forecast (±2σ)")
    click.echo(f"wrote {out} and {plot}")
