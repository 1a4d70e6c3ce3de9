"""Figures of a twin run: states ± 2σ (and the truth of a virtual print), measured and
predicted outputs (``ajtwin estimate --plot``); matplotlib, PNG.

Every quantity is drawn in its display unit (:data:`ajtwin.units.DISPLAY_UNITS`: φ_A in
ppm, Q_m in nL/s) against print time in minutes past the print's start.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ajtwin import units  # noqa: E402
from ajtwin.model.names import INPUT_NAMES, OUTPUT_NAMES, STATE_NAMES  # noqa: E402

STATE_LABELS = tuple(units.display(n).label for n in STATE_NAMES)
#: from the states' computed units to the ones of :data:`STATE_LABELS` (φ_A → ppm)
STATE_SCALE = np.array([units.display(n).scale for n in STATE_NAMES])
OUTPUT_LABELS = tuple(units.display(n).label for n in OUTPUT_NAMES)
#: from the outputs' computed units to the ones of :data:`OUTPUT_LABELS` (Q_m → nL/s)
OUTPUT_SCALE = np.array([units.display(n).scale for n in OUTPUT_NAMES])
INPUT_LABELS = tuple(units.display(n).label for n in INPUT_NAMES)
#: the time axis of every figure a person reads
TIME_LABEL = "print time [min]"


def minutes_of(record):
    """The record's time axis in minutes past the print's start."""
    return units.print_minutes(np.asarray(record.time_s, dtype=float))


def plot_states(ax_row, minutes, runs: dict, truth=None, check_minutes=(30, 60, 90)):
    """runs: label -> (means (T,5), stds (T,5) or None, style dict), in the states'
    computed units (drawn in their display units)."""
    for i, ax in enumerate(ax_row):
        for label, (means, stds, style) in runs.items():
            means = np.asarray(means) * STATE_SCALE
            stds = None if stds is None else np.asarray(stds) * STATE_SCALE
            ax.plot(minutes[: len(means)], means[:, i], label=label, lw=1.1, **style)
            if stds is not None:
                ax.plot(
                    minutes,
                    means[:, i] + 2 * stds[:, i],
                    ls=":",
                    lw=0.8,
                    color=style.get("color", "k"),
                )
                ax.plot(
                    minutes,
                    means[:, i] - 2 * stds[:, i],
                    ls=":",
                    lw=0.8,
                    color=style.get("color", "k"),
                )
        if truth is not None:
            shown = np.asarray(truth)[:, i] * STATE_SCALE[i]
            ax.plot(minutes, shown, color="tab:red", lw=0.8, alpha=0.6, label="truth")
            ks = [min(int(m * 60), len(shown) - 1) for m in check_minutes]
            ax.plot(minutes[ks], shown[ks], "o", color="tab:red", ms=5)
        ax.set_title(STATE_LABELS[i], fontsize=9)
        ax.set_xlabel(TIME_LABEL)
        ax.tick_params(labelsize=7)
    ax_row[0].legend(fontsize=7, loc="best")


def save_figure(fig, path):
    """Lay out, write as PNG (110 dpi) and close ``fig``; the path."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def estimate_figure(record, run, path):
    """States (±2σ, truth when present) and measured vs predicted outputs of one run (on a
    job print the camera's measurements at their print times, as the filter used them)."""
    minutes = minutes_of(record)
    measured = record.outputs if run.measurements is None else run.measurements
    fig, axes = plt.subplots(2, 5, figsize=(20, 7.5))
    truth = record.true_states if record.has_truth else None
    plot_states(axes[0], minutes, {"twin ±2σ": (run.means, run.stds, {"color": "k"})}, truth)
    pred = np.asarray(run.filtered.predicted_outputs)
    for i, ax in enumerate(axes[1]):
        scale = OUTPUT_SCALE[i]
        ax.plot(minutes, measured[:, i] * scale, lw=0.4, color="tab:gray", label="measured")
        ax.plot(minutes, pred[:, i] * scale, lw=1, color="k", label="twin")
        ax.set_title(OUTPUT_LABELS[i], fontsize=9)
        ax.set_xlabel(TIME_LABEL)
    axes[1, 0].legend(fontsize=7)
    return save_figure(fig, path)
