"""``ajtwin forecast`` and ``ajtwin advise``: what-if and input advice for a registered machine."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ajtwin.store.cli import open_registry, store_option

SHORT = {
    "atomizer_current_mA": ("I_A", "mA"),
    "carrier_flow_sccm": ("Q_c", "sccm"),
    "sheath_flow_sccm": ("Q_s", "sccm"),
    "linewidth_um": ("L_w", "µm"),
    "overspray_um": ("L_o", "µm"),
    "carrier_pressure_Pa": ("P_c", "Pa"),
    "sheath_pressure_Pa": ("P_s", "Pa"),
}


def machine_twin(reg, name, nominal_theta=False, transition="paper"):
    """(twin with the machine's θ, mean, cov, last inputs, machine row) from the registry.

    ``transition``: a profile of ``data/transition.toml`` for the twin's droplet row. A
    profile with a bounded θ_da prior (σ) clips the machine's learned θ_da to ±2σ.
    """
    from ajtwin.estimation import Twin
    from ajtwin.store.registry import RegistryError

    try:
        machine = reg.machine(name)
        last = reg.last_print(name)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    if last is None:
        raise click.ClickException(
            f"machine {name!r} has no prints yet: ingest one first "
            f"(`ajtwin ingest --machine {name} print.parquet`)"
        )
    from ajtwin.store.calibration import active_calibration

    # the machine's calibration (SPEC §11): forecasts and advice speak its outputs
    active = active_calibration(reg, name)
    calibrated = {}
    if active is not None:
        calibrated = {
            "calibration": active["calibration"],
            "calibration_cov": active["calibration_cov"],
            "noise_factors": active.get("noise_factors"),
        }
    twin = Twin.default(transition=transition, **calibrated)
    if not nominal_theta:
        twin.theta = np.asarray(last["theta_after"], dtype=float)
        bound = 2.0 * twin.droplet_dynamics.theta_prior_std
        if transition != "paper" and bound > 0:
            twin.theta[0] = float(np.clip(twin.theta[0], -bound, bound))
    inputs = reg.print_arrays(last["id"]).get("inputs")
    u_last = np.nanmedian(inputs[-60:], axis=0) if inputs is not None else np.array([375, 23, 50])
    return twin, last["end_mean"], last["end_cov"], u_last, machine, last


def _input_response_at_end(twin, reg, last):
    """The droplet size's input response at the end of the last print (None: equilibrium)."""
    if not twin.droplet_dynamics.follows_inputs:
        return None
    inputs = reg.print_arrays(last["id"]).get("inputs")
    if inputs is None or not np.isfinite(inputs).all():
        return None
    from ajtwin.model.droplet_dynamics import next_response

    response = float(twin.model_inputs(inputs)[-1, 3])
    return next_response(response, inputs[-1], twin.droplet_dynamics)


def _parse_inputs(text):
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise click.BadParameter(f"expected I_A,Q_c,Q_s (mA, sccm, sccm), got {text!r}")
    return np.array(values)


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
@click.option(
    "--transition",
    default="paper",
    show_default=True,
    help="Droplet-size row of the twin: a profile of ajtwin/data/transition.toml; "
    "input_following lets d_a follow planned Q_c/I_A changes (docs/forecast.md).",
)
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
    from ajtwin.apps.forecast import forecast as run_forecast
    from ajtwin.apps.forecast import input_schedule, parse_change, parse_duration, plot_forecast

    try:
        horizon_s = parse_duration(horizon)
        parsed = [parse_change(c) for c in changes]
        user_inputs = _parse_inputs(inputs_text)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    reg = open_registry(store)
    try:
        twin, mean, cov, u_last, _, last = machine_twin(
            reg, machine_name, nominal_theta, transition
        )
    except ValueError as exc:  # an unknown transition profile
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
        input_response0=_input_response_at_end(twin, reg, last),
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
    theta = ", ".join(f"{v:.3g}" for v in twin.theta)
    click.echo(f"  θ [1/s] used: [{theta}]" + (" (nominal)" if nominal_theta else " (learned)"))
    for text in fc.warnings:
        click.echo(f"  warning: {text}")
    # beside the CSV by default, so a run never litters the working directory
    plot = out.with_suffix(".png") if plot is None else plot
    plot_forecast(fc, plot, title=f"{machine_name}: forecast (±2σ)")
    click.echo(f"wrote {out} and {plot}")


@click.command()
@click.option("--machine", "machine_name", required=True, help="Registered machine name.")
@click.option("--target-linewidth", type=float, required=True, help="Target L_w, µm.")
@click.option("--max-overspray", type=float, default=None, help="Upper limit of L_o, µm.")
@click.option(
    "--settle",
    default="120s",
    show_default=True,
    help="Judge the outputs this long after the change.",
)
@click.option(
    "--inputs",
    "inputs_text",
    default=None,
    help="Inputs now, I_A,Q_c,Q_s (default: the last print's final inputs).",
)
@click.option(
    "--nominal-theta",
    is_flag=True,
    help="Use θ = 0 instead of the machine's learned θ (e.g. after cleaning the nozzle).",
)
@store_option
def advise(
    machine_name, target_linewidth, max_overspray, settle, inputs_text, nominal_theta, store
):
    """Inputs (I_A, Q_c, Q_s) within the machine's limits that reach a target linewidth
    with least overspray, from the machine's current state."""
    from ajtwin.apps.advise import advise as run_advise
    from ajtwin.apps.forecast import parse_duration

    try:
        settle_s = int(round(parse_duration(settle)))
        user_inputs = _parse_inputs(inputs_text)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    if target_linewidth <= 0:
        raise click.BadParameter("must be > 0 µm", param_hint="--target-linewidth")
    reg = open_registry(store)
    twin, mean, cov, u_last, machine, last = machine_twin(reg, machine_name, nominal_theta)
    u0 = u_last if user_inputs is None else user_inputs
    try:
        advice = run_advise(
            twin,
            mean,
            cov,
            u0,
            target_linewidth,
            max_overspray_um=max_overspray,
            limits=machine["limits"],
            settle_s=settle_s,
        )
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(
        f"advice for {machine_name!r} (state at the end of print #{last['seq']}), "
        f"target L_w {target_linewidth:g} µm"
        + (f", L_o ≤ {max_overspray:g} µm" if max_overspray is not None else "")
    )
    bounds = ", ".join(
        f"{SHORT[n][0]} {lo:g}–{hi:g}"
        for n, (lo, hi) in zip(
            ("atomizer_current_mA", "carrier_flow_sccm", "sheath_flow_sccm"),
            advice.bounds,
            strict=True,
        )
    )
    click.echo(f"  search range: {bounds}")
    click.echo(f"  {'':22s} {'now':>12s}  {'advised':>12s}")
    for name, now, new, std in advice.rows():
        short, unit = SHORT[name]
        label = f"{short} [{unit}]"
        if std is None:
            click.echo(f"  {label:22s} {now:12.4g}  {new:12.4g}")
        else:
            click.echo(f"  {label:22s} {now:12.4g}  {new:12.4g} ± {2 * std:.2g} (2σ)")
    click.echo(f"  outputs judged {settle_s} s after the change; {advice.message}")
    if not advice.reachable:
        raise SystemExit(2)
