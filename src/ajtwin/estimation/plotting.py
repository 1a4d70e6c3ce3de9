"""Figures of a twin run: states ± 2σ (and the truth of a virtual print), measured and
predicted outputs (``ajtwin estimate --plot``); matplotlib, PNG.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

STATE_LABELS = ("d_a [µm]", "V_l [mL]", "ΔR_T [µm]", "ΔR_N [µm]", "φ_A [–]")


OUTPUT_LABELS = ("L_w [µm]", "L_o [µm]", "P_c [Pa]", "P_s [Pa]", "Q_m [mL/s]")


INPUT_LABELS = ("I_A [mA]", "Q_c [sccm]", "Q_s [sccm]")


def minutes_of(record):
    """The record's time axis in minutes."""
    return np.asarray(record.time_s) / 60.0


def plot_states(ax_row, minutes, runs: dict, truth=None, check_minutes=(30, 60, 90)):
    """runs: label -> (means (T,5), stds (T,5) or None, style dict)."""
    for i, ax in enumerate(ax_row):
        for label, (means, stds, style) in runs.items():
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
            ax.plot(minutes, truth[:, i], color="tab:red", lw=0.8, alpha=0.6, label="truth")
            ks = [min(int(m * 60), len(truth) - 1) for m in check_minutes]
            ax.plot(minutes[ks], truth[ks, i], "o", color="tab:red", ms=5)
        ax.set_title(STATE_LABELS[i], fontsize=9)
        ax.set_xlabel("time [min]")
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
        ax.plot(minutes, measured[:, i], lw=0.4, color="tab:gray", label="measured")
        ax.plot(minutes, pred[:, i], lw=1, color="k", label="twin")
        ax.set_title(OUTPUT_LABELS[i], fontsize=9)
        ax.set_xlabel("time [min]")
    axes[1, 0].legend(fontsize=7)
    return save_figure(fig, path)
