"""``ajtwin advise``: input settings that reach a target linewidth on a registered machine."""

from __future__ import annotations

import click

from ajtwin.cli.options import SHORT, open_registry, parse_inputs, store_option
from ajtwin.store.registry import RegistryError


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
    help="Use the drift rates θ = 0 instead of the machine's learned ones (e.g. after "
    "cleaning the nozzle).",
)
@click.option(
    "--anyway",
    is_flag=True,
    help="Advise even though the machine's newest print raised a fault no maintenance has "
    "closed (the advice then steers around the fault instead of fixing it).",
)
@store_option
def advise(
    machine_name,
    target_linewidth,
    max_overspray,
    settle,
    inputs_text,
    nominal_theta,
    anyway,
    store,
):
    """Inputs (I_A, Q_c, Q_s) within the machine's limits that reach a target linewidth
    with least overspray, from the machine's current state.

    Refuses a machine whose newest print raised a fault (a clog, a leak, …) that no
    `ajtwin machine maintain` has closed since, unless --anyway.
    """
    # lazy CLI loading: the library (JAX) is imported when the command runs, not for --help
    from ajtwin.apps.planning.advice import advise as run_advise
    from ajtwin.apps.planning.forecast import parse_duration
    from ajtwin.engine.start import machine_open_faults, machine_twin

    try:
        settle_s = int(round(parse_duration(settle)))
        user_inputs = parse_inputs(inputs_text)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    if target_linewidth <= 0:
        raise click.BadParameter("must be > 0 µm", param_hint="--target-linewidth")
    reg = open_registry(store)
    try:
        twin, mean, cov, u_last, machine, last = machine_twin(reg, machine_name, nominal_theta)
        seq, faults = machine_open_faults(reg, machine_name)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    if faults and not anyway:
        lines = "\n".join(f"  {fault['sentence']}" for fault in faults)
        raise click.ClickException(
            f"not advising {machine_name!r}: its print #{seq} raised a fault no maintenance "
            f"has closed since:\n{lines}\nadvice now would steer the inputs around the fault "
            "instead of fixing it; --anyway advises all the same"
        )
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
    if faults:
        click.echo(f"  WARNING advised --anyway with an open fault: {faults[0]['sentence']}")
    click.echo(f"  {'':22s} {'now':>12s}  {'advised':>12s}")
    for name, now, new, std in advice.rows():
        short, unit = SHORT[name]
        label = f"{short} [{unit}]"
        if std is None:
            side = advice.at_limits.get(name)
            flag = f"   ← on its {side} limit" if side else ""
            click.echo(f"  {label:22s} {now:12.4g}  {new:12.4g}{flag}")
        else:
            click.echo(f"  {label:22s} {now:12.4g}  {new:12.4g} ± {2 * std:.2g} (2σ)")
    click.echo(f"  {advice.message}")
    if advice.at_limits:
        click.echo(f"  note: {advice.limit_note()}")
    if not advice.reachable:
        raise SystemExit(2)
