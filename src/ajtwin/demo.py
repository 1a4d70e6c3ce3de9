"""``ajtwin demo``: the main job on the embedded default.

Runs the digital model open-loop at the Exp 1 inputs and writes a figure; later
stages (virtual printer, video, twin, anomaly detection, report) are added as
they land.
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np


@click.command("demo")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default="demo-output",
    show_default=True,
    help="Folder for the demo's files.",
)
def demo_command(out_dir):
    """Run the end-to-end demo on the embedded default."""
    from ajtwin.model import STATE_NAMES, DigitalModel
    from ajtwin.simulation.openloop import (
        EXP1_INPUTS,
        exp1_initial_state,
        plot_open_loop,
        run_open_loop,
    )

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = DigitalModel.default()
    x0 = exp1_initial_state(model)
    inputs = np.tile(np.array(EXP1_INPUTS), (90 * 60, 1))
    states, outputs = run_open_loop(model, x0, inputs)
    click.echo("Open-loop digital model at the Exp 1 inputs (I_A 375 mA, Q_c 23, Q_s 50 sccm)")
    for minute in (30, 60, 90):
        row = ", ".join(f"{n} {v:.6g}" for n, v in zip(STATE_NAMES, states[minute * 60]))
        click.echo(f"  {minute:2d} min: {row}")
    png = plot_open_loop(
        np.arange(len(states)),
        states,
        outputs,
        out / "openloop_exp1.png",
        title="Open-loop digital model, Exp 1 inputs",
    )
    click.echo(f"wrote {png}")
