"""One-figure overview of a print record: inputs, outputs and (when present) truth.

Measured outputs are drawn as thin raw traces with a 60 s rolling median on top
(NaN samples are simply absent); a fault onset in the metadata is a dashed line. Every
quantity is drawn in its display unit (:data:`ajtwin.units.DISPLAY_UNITS`: φ_A in ppm, Q_m
in nL/s) against print time in minutes past the print's start.
With ``nominal=True`` and truth present, the twin's nominal open-loop prediction
(the digital model from the true initial state, driven by the measured inputs) is
overlaid on the truth and on the outputs — the gap is what the twin must infer. A job
print (format 2) also shows its shutter and platen speed, and the overlay follows them.
"""

from __future__ import annotations

import textwrap
import warnings
from pathlib import Path

import numpy as np

from ajtwin import units
from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS, TRUTH_COLUMNS, PrintRecord
from ajtwin.model import DigitalModel


def _unit(column: str) -> units.DisplayUnit:
    """The display unit of a record's input, output or truth (``true_<state>``) column."""
    return units.display(column.removeprefix("true_"))


#: the axis label of each drawn column
LABELS = {c: _unit(c).label for c in (*INPUT_COLUMNS, *OUTPUT_COLUMNS, *TRUTH_COLUMNS)}
TIME_LABEL = "print time [min]"
SMOOTHING_S = 60


def nominal_open_loop(record: PrintRecord):
    """The nominal digital model's open-loop states and outputs for a record with truth.

    Starts from the true state at the first sample, with the twin's prior of a clean
    tube and nozzle (ΔR_T = ΔR_N = 0, model reference §7), θ = 0, Euler at 1 s, driven by the
    measured inputs. Returns (states (T, 5), outputs (T, 5)).
    """

    model = DigitalModel.default()
    x0 = record.true_states[0].copy()
    x0[2:4] = 0.0
    inputs = record.inputs
    states = model.simulate(x0, inputs[:-1]) if len(inputs) > 1 else x0[None]
    if not record.has_job:
        return states, model.outputs(states, inputs)
    # a job print: the line at each second's platen speed, nothing printed with the shutter shut
    outputs = np.array(model.outputs(states, inputs, record.platen_speed))
    outputs[np.ix_(record.shutter_open <= 0, [0, 1, 4])] = np.nan
    return states, outputs


def plot_job_panel(ax, record: PrintRecord) -> None:
    """Shutter (shaded where open) and platen speed of a job print on one axis."""
    minutes = record.time_s / 60.0
    speed = record.platen_speed
    ax.fill_between(
        minutes,
        0.0,
        max(float(speed.max()), 1e-9),
        where=record.shutter_open > 0,
        step="post",
        color="tab:green",
        alpha=0.2,
        lw=0,
        label="shutter open",
    )
    ax.step(minutes, speed, where="post", lw=0.6, color="tab:purple", label="platen speed")
    ax.set_ylabel("ν [mm/s]")
    ax.legend(loc="upper right", fontsize=7, frameon=False)


def plot_record(record: PrintRecord, path: str | Path | None = None, nominal: bool = True):
    """Draw a record's inputs, outputs and truth in one figure.

    Parameters
    ----------
    record : PrintRecord
    path : str or Path, optional
        Save the figure there (PNG, PDF or SVG by suffix).
    nominal : bool
        Overlay the nominal model's open-loop prediction when truth is present.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    data = record.data
    minutes = units.print_minutes(record.time_s)
    truth = record.has_truth
    ncols = 3 if truth else 2
    fig, axes = plt.subplots(5, ncols, figsize=(5.2 * ncols, 12), sharex=True, squeeze=False)
    onset = record.meta.get("fault_onset_s")
    predicted = None
    if truth and nominal:
        try:
            predicted = nominal_open_loop(record)
        except ValueError as exc:  # e.g. the nominal run leaves the model's valid range
            warnings.warn(f"no nominal overlay: {exc}", stacklevel=2)

    def mark(ax):
        if onset is not None:
            ax.axvline(onset / 60.0, color="crimson", ls="--", lw=1)

    for row, column in enumerate(INPUT_COLUMNS):
        ax = axes[row, 0]
        ax.plot(minutes, data[column], lw=0.6, color="tab:blue")
        ax.set_ylabel(LABELS[column])
        mark(ax)
    meta_ax = axes[3, 0]
    meta_ax.axis("off")
    if record.has_job:
        plot_job_panel(axes[4, 0], record)
        mark(axes[4, 0])
    else:
        axes[4, 0].axis("off")
    meta = record.meta
    lines = [
        f"scenario: {meta.get('scenario')}",
        f"seed: {meta.get('seed')}",
        f"machine: {meta.get('machine_id')}",
        f"platen speed: {meta.get('platen_speed_mm_s')} mm/s",
        f"fault: {meta.get('fault_kind')}"
        + (f" at {onset / 60:.1f} min" if onset is not None else ""),
        f"samples: {len(record)} ({record.duration_s / 60:.1f} min)",
    ]
    if isinstance(meta.get("job"), dict) and isinstance(meta.get("camera"), dict):
        offset = meta["camera"].get("offset_mm", [0.0, 0.0])
        lines.append(f"job: {meta['job'].get('program')}")
        lines.append(f"camera: {meta['camera'].get('mode')} at ({offset[0]:g}, {offset[1]:g}) mm")
    if meta.get("description"):
        lines.extend(textwrap.wrap(str(meta["description"]), 48))
    meta_ax.text(0.0, 1.0, "\n".join(lines), va="top", fontsize=9, wrap=True)
    if predicted is not None:
        meta_ax.text(0.0, 0.05, "black dashed: nominal model, open loop", fontsize=8, color="0.2")

    for row, column in enumerate(OUTPUT_COLUMNS):
        ax = axes[row, 1]
        series = _unit(column).shown(data[column])
        ax.plot(minutes, series, lw=0.3, color="0.6")
        smooth = series.rolling(SMOOTHING_S, center=True, min_periods=SMOOTHING_S // 4).median()
        ax.plot(minutes, smooth, lw=1.2, color="tab:orange")
        if predicted is not None:
            ax.plot(minutes, _unit(column).shown(predicted[1][:, row]), lw=1.0, ls="--", color="k")
        ax.set_ylabel(LABELS[column])
        mark(ax)

    if truth:
        for row, column in enumerate(TRUTH_COLUMNS):
            ax = axes[row, 2]
            ax.plot(minutes, _unit(column).shown(data[column]), lw=1.2, color="tab:green")
            if predicted is not None:
                shown = _unit(column).shown(predicted[0][:, row])
                ax.plot(minutes, shown, lw=1.0, ls="--", color="k")
            ax.set_ylabel(LABELS[column])
            mark(ax)
        axes[0, 2].set_title("truth (hidden states)")
    axes[0, 0].set_title("measured inputs")
    axes[0, 1].set_title("measured outputs (grey) and 60 s median")
    for ax in axes[-1]:
        ax.set_xlabel(TIME_LABEL)
    axes[2, 0].set_xlabel(TIME_LABEL)
    axes[2, 0].xaxis.set_tick_params(labelbottom=True)
    fig.suptitle(f"ajtwin print record — {meta.get('scenario')} (seed {meta.get('seed')})")
    fig.tight_layout()
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    return fig
