"""``ajtwin openloop``: an open-loop run of the digital model (no measurements)."""

from __future__ import annotations

import click
import numpy as np

from ajtwin.config import packaged_toml
from ajtwin.model.names import INPUT_NAMES

#: (I_A [mA], Q_c [sccm], Q_s [sccm]) of the paper's Exp 1: its scenario's values at the start
EXP1_INPUTS = tuple(
    float(packaged_toml("simulation/scenarios/exp1.toml")["inputs"][name][0][1])
    for name in INPUT_NAMES
)


@click.command("openloop")
@click.option("--minutes", default=90.0, show_default=True, help="Length of the run.")
@click.option("--current-ma", default=EXP1_INPUTS[0], show_default=True)
@click.option("--carrier-sccm", default=EXP1_INPUTS[1], show_default=True)
@click.option("--sheath-sccm", default=EXP1_INPUTS[2], show_default=True)
@click.option("--droplet-um", default=3.5, show_default=True, help="Initial d_a.")
@click.option("--vial-ml", default=1.0, show_default=True, help="Initial V_l.")
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write a PNG of states and outputs.",
)
@click.option(
    "--out", type=click.Path(dir_okay=False), default=None, help="Write the trajectory as CSV."
)
def openloop(minutes, current_ma, carrier_sccm, sheath_sccm, droplet_um, vial_ml, plot_path, out):
    """Open-loop run of the digital model at constant inputs (default: Exp 1).

    Prints the states at 30/60/90 min (or the run's thirds).
    """
    # lazy CLI loading: pandas, and the model (JAX) when the run starts, not for --help
    import pandas as pd

    # lazy CLI loading
    from ajtwin.model import OUTPUT_NAMES, STATE_NAMES, DigitalModel
    from ajtwin.simulation.openloop import plot_open_loop, run_open_loop

    model = DigitalModel.default()
    u = np.array([current_ma, carrier_sccm, sheath_sccm], dtype=float)
    steps = int(round(minutes * 60))
    if steps < 1:
        raise click.BadParameter("must be at least 1/60 min", param_hint="--minutes")
    try:
        phi0 = float(model.steady_aerosol_fraction(u, vial_ml))
        x0 = np.array([droplet_um, vial_ml, 0.0, 0.0, phi0])
        states, outputs = run_open_loop(model, x0, np.tile(u, (steps, 1)))
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    marks = [30, 60, 90] if minutes >= 90 else [minutes / 3, 2 * minutes / 3, minutes]
    header = "time_min  " + "  ".join(f"{n:>22s}" for n in STATE_NAMES)
    click.echo(
        f"open loop: I_A {current_ma:g} mA, Q_c {carrier_sccm:g} sccm, "
        f"Q_s {sheath_sccm:g} sccm, x0 = {np.array2string(x0, precision=4)}"
    )
    click.echo(header)
    for m in marks:
        k = min(int(round(m * 60)), steps)
        click.echo(f"{m:8.1f}  " + "  ".join(f"{v:22.6g}" for v in states[k]))
    if out:
        frame = pd.DataFrame(states, columns=STATE_NAMES)
        frame.insert(0, "time_s", np.arange(steps + 1, dtype=float))
        for i, name in enumerate(OUTPUT_NAMES):
            frame["pred_" + name] = outputs[:, i]
        frame.to_csv(out, index=False)
        click.echo(f"wrote {out}")
    if plot_path:
        plot_open_loop(
            np.arange(steps + 1),
            states,
            outputs,
            plot_path,
            title=f"Open-loop digital model, Q_c {carrier_sccm:g} / Q_s {sheath_sccm:g}"
            f" sccm, I_A {current_ma:g} mA",
        )
        click.echo(f"wrote {plot_path}")
