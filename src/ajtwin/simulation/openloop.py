"""Open-loop runs of the digital model (no measurements): ``ajtwin openloop``.

The model alone, from an initial state, under an input schedule — what the
paper calls the static physics-derived prediction (§8.1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ajtwin.config import packaged_toml
from ajtwin.model import INPUT_NAMES, OUTPUT_NAMES, STATE_NAMES, DigitalModel

#: Exp 1 inputs (model reference §10), (I_A [mA], Q_c [sccm], Q_s [sccm]): the scenario's
#: values at its start (I_A 375 mA, Q_c 23 sccm, Q_s 50 sccm)
EXP1_INPUTS = tuple(
    float(packaged_toml("simulation/scenarios/exp1.toml")["inputs"][name][0][1])
    for name in INPUT_NAMES
)


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
