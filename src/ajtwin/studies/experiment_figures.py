"""Figures of the paper's experiments (paper §8, App. G–H), matplotlib, PNG."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ajtwin import units  # noqa: E402
from ajtwin.estimation.plotting import (  # noqa: E402
    INPUT_LABELS,
    OUTPUT_LABELS,
    OUTPUT_SCALE,
    TIME_LABEL,
    minutes_of,
    plot_states,
    save_figure,
)
from ajtwin.estimation.twin import Twin  # noqa: E402
from ajtwin.model.names import STATE_NAMES  # noqa: E402
from ajtwin.studies.experiments import explain_linewidth_changes, setpoints  # noqa: E402


def exp1_figures(record, series, out: Path):
    """Exp 1: states ± 2σ (EKF+EM and EKF alone) against the truth, and θ over time."""
    minutes = minutes_of(record)
    truth = record.true_states
    em, ekf = series["em"], series["ekf"]
    fig, axes = plt.subplots(1, 5, figsize=(20, 4))
    plot_states(
        axes,
        minutes,
        {
            "open loop (physics)": (series["open_loop"], None, {"color": "tab:blue"}),
            "closed loop (EKF+EM) ±2σ": (em.means, em.stds, {"color": "k"}),
        },
        truth,
    )
    fig.suptitle("Exp 1: open-loop vs closed-loop states; truth (red) with checks at 30/60/90 min")
    paths = [save_figure(fig, out / "exp1_states.png")]

    fig, axes = plt.subplots(1, 5, figsize=(20, 3.6))
    pred = np.asarray(em.filtered.predicted_outputs)
    with np.errstate(invalid="ignore", divide="ignore"):
        pct = 100 * (pred - record.outputs) / record.outputs
    for i, ax in enumerate(axes):
        ax.plot(minutes, pct[:, i], lw=0.5, color="tab:gray")
        ax.axhline(0, color="k", lw=0.6)
        ax.set_title(f"{OUTPUT_LABELS[i]}: predicted − measured [%]", fontsize=9)
        ax.set_xlabel(TIME_LABEL)
    fig.suptitle("Exp 1: output percentage error of the closed-loop twin (one-step prediction)")
    paths.append(save_figure(fig, out / "exp1_output_errors.png"))

    fig, axes = plt.subplots(1, 5, figsize=(20, 4))
    plot_states(
        axes,
        minutes,
        {
            "EKF alone ±2σ": (ekf.means, ekf.stds, {"color": "tab:green"}),
            "EKF + EM ±2σ": (em.means, em.stds, {"color": "k"}),
        },
        truth,
    )
    fig.suptitle("Exp 1 ablation (App. G): EKF alone vs EKF + EM")
    paths.append(save_figure(fig, out / "exp1_ablation.png"))
    paths.append(
        theta_figure(
            em.theta_history,
            out / "exp1_theta.png",
            "Exp 1: θ learned by EM over the moving window",
        )
    )
    return paths


def theta_figure(history, path, title):
    """θ per state over the print (EM's updates)."""
    fig, axes = plt.subplots(1, 5, figsize=(20, 3.4))
    for i, ax in enumerate(axes):
        col = f"theta_{STATE_NAMES[i]}"
        if len(history):
            rate = units.drift_rate_percent_per_hour(history[col])
            ax.step(units.print_minutes(history["time_s"]), rate, where="post", color="k")
            ax.plot(units.print_minutes(history["time_s"]), rate, "k.", ms=4)
        ax.axhline(0, color="tab:gray", lw=0.6)
        ax.set_title(units.display(STATE_NAMES[i]).rate_label, fontsize=9)
        ax.set_xlabel(TIME_LABEL)
        ax.tick_params(labelsize=7)
    fig.suptitle(title)
    return save_figure(fig, path)


def exp2_figures(record, series, out: Path):
    """Exp 2: inputs and set-points, outputs measured and predicted, states ± 2σ."""
    minutes = minutes_of(record)
    em = series["em"]
    fig, axes = plt.subplots(3, 5, figsize=(20, 10))
    for i in range(3):
        axes[0, i].plot(minutes, record.inputs[:, i], lw=0.5, color="tab:gray")
        axes[0, i].plot(minutes, setpoints(record.inputs)[:, i], lw=1.2, color="k")
        axes[0, i].set_title(INPUT_LABELS[i], fontsize=9)
    for i in (0, 1):
        axes[0, 3 + i].plot(
            minutes, record.outputs[:, i], lw=0.4, color="tab:gray", label="measured"
        )
        axes[0, 3 + i].plot(
            minutes, np.asarray(em.filtered.predicted_outputs)[:, i], lw=1, color="k", label="twin"
        )
        axes[0, 3 + i].set_title(OUTPUT_LABELS[i], fontsize=9)
        axes[0, 3 + i].legend(fontsize=7)
    plot_states(
        axes[1],
        minutes,
        {"closed loop ±2σ": (em.means, em.stds, {"color": "k"})},
        record.true_states,
    )
    for i in range(2, 5):
        scale = OUTPUT_SCALE[i]
        axes[2, i - 2].plot(minutes, record.outputs[:, i] * scale, lw=0.4, color="tab:gray")
        axes[2, i - 2].plot(
            minutes, np.asarray(em.filtered.predicted_outputs)[:, i] * scale, lw=1, color="k"
        )
        axes[2, i - 2].set_title(OUTPUT_LABELS[i], fontsize=9)
    axes[2, 3].axis("off")
    axes[2, 4].axis("off")
    fig.suptitle("Exp 2: input steps; inferred states explain the output drift")
    paths = [save_figure(fig, out / "exp2_states.png")]
    return paths


def exp2_drift_figure(explained: list, path):
    """The linewidth change between steady stretches split into its contributions."""
    labels = [
        "droplet_diameter",
        "aerosol_fraction",
        "nozzle_deposition",
        "carrier_flow",
        "sheath_flow",
    ]
    fig, ax = plt.subplots(figsize=(9, 4))
    width = 0.8 / max(len(explained), 1)
    for j, item in enumerate(explained):
        values = [item["contributions_um"][k] for k in labels]
        ax.bar(
            np.arange(len(labels)) + j * width,
            values,
            width,
            label=f"{item['from_s'] / 60:.0f}→{item['to_s'] / 60:.0f} min: measured "
            f"{item['measured_change_um']:+.2f}, explained {item['explained_change_um']:+.2f} µm",
        )
    ax.set_xticks(np.arange(len(labels)) + width * (len(explained) - 1) / 2)
    ax.set_xticklabels(labels, fontsize=8)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_ylabel("contribution to ΔL_w [µm]")
    ax.legend(fontsize=7)
    ax.set_title("Exp 2: which state explains the linewidth change")
    return save_figure(fig, path)


def exp3_figures(record, series, out: Path):
    """Exp 3: the forecast after the calibration window against the noise-free truth."""
    minutes = minutes_of(record)
    n_cal = series["n_cal"]
    after = minutes[n_cal:]
    fig, axes = plt.subplots(1, 2, figsize=(15, 4.5))
    for i, ax in enumerate(axes):
        ax.plot(minutes, record.outputs[:, i], lw=0.3, color="tab:gray", label="measured")
        ax.plot(after, series["y_true"][:, i], color="tab:red", lw=1.2, label="truth (noise-free)")
        ax.plot(
            after,
            series["y_uncal"][:, i],
            color="tab:orange",
            lw=1.5,
            label="uncalibrated physics model (open loop from t = 0)",
        )
        ax.plot(
            after,
            series["y_theta_only"][:, i],
            color="tab:purple",
            lw=1,
            ls="--",
            label="ablation: twin state at 37.6 min, θ = 0",
        )
        ax.plot(after, series["y_cal"][:, i], color="k", lw=1.5, label="twin calibrated by EM")
        if "y_cal_std" in series:
            mean, std = series["y_cal"][:, i], series["y_cal_std"][:, i]
            ax.fill_between(
                after, mean - 2 * std, mean + 2 * std, color="tab:green", alpha=0.3, label="its ±2σ"
            )
        ax.axvline(n_cal / 60, color="tab:blue", ls="--", lw=1)
        ax.text(n_cal / 60, ax.get_ylim()[1], " forecast →", va="top", fontsize=8, color="tab:blue")
        ax.set_title(OUTPUT_LABELS[i])
        ax.set_xlabel(TIME_LABEL)
    axes[0].legend(fontsize=8)
    fig.suptitle("Exp 3: θ calibrated on t < 37.6 min, open-loop forecast afterwards")
    return [save_figure(fig, out / "exp3_forecast.png")]


def experiment_figures(name, record, series, out: Path):
    """The figures of experiment ``name`` (exp1, exp2, exp3) into ``out``; their paths."""
    if name == "exp1":
        return exp1_figures(record, series, out)
    if name == "exp2":
        paths = exp2_figures(record, series, out)
        explained = explain_linewidth_changes(Twin.default(), series["em"], record)
        paths.append(exp2_drift_figure(explained, out / "exp2_drift_explained.png"))
        return paths
    if name == "exp3":
        return exp3_figures(record, series, out)
    raise ValueError(name)
