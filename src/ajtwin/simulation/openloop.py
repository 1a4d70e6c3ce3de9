"""Open-loop runs of the digital model (no measurements): ``ajtwin openloop``.

The model alone, from an initial state, under an input schedule — what the
paper calls the static physics-derived prediction (§8.1).
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ajtwin.model import OUTPUT_NAMES, STATE_NAMES, DigitalModel

#: Exp 1 inputs (SPEC §10): I_A 375 mA, Q_c 23 sccm, Q_s 50 sccm.
EXP1_INPUTS = (375.0, 23.0, 50.0)


def exp1_initial_state(model: DigitalModel, droplet_um=3.5, vial_ml=1.0) -> np.ndarray:
    """x0 for Exp 1: d_a0 3.5 µm, V_l0 1 mL, clean tube and nozzle, φ_A0 from H."""
    u = np.array(EXP1_INPUTS)
    phi = float(model.steady_aerosol_fraction(u, vial_ml))
    return np.array([droplet_um, vial_ml, 0.0, 0.0, phi])


def run_open_loop(model: DigitalModel, x0, inputs, theta=None):
    """States (T+1, 5) and outputs (T+1, 5) of an open-loop run at 1 s steps."""
    inputs = np.asarray(inputs, dtype=float)
    states = model.simulate(x0, inputs, theta)
    outputs = model.outputs(states, np.vstack([inputs, inputs[-1:]]))
    return states, outputs


def plot_open_loop(times_s, states, outputs, path, title="Open-loop run"):
    """Five states and five outputs against time, one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    minutes = np.asarray(times_s) / 60.0
    fig, axes = plt.subplots(2, 5, figsize=(18, 6.5), sharex=True)
    for i, name in enumerate(STATE_NAMES):
        axes[0, i].plot(minutes, states[:, i], color="tab:blue")
        axes[0, i].set_title(name, fontsize=9)
    for i, name in enumerate(OUTPUT_NAMES):
        axes[1, i].plot(minutes, outputs[:, i], color="tab:red")
        axes[1, i].set_title(name, fontsize=9)
        axes[1, i].set_xlabel("time [min]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


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
        import pandas as pd

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
