"""Draw a job's part: printed strokes coloured per feature, rapid moves dashed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_part"]


def plot_part(job, path: str | Path | None = None, *, ax=None, title: str | None = None):
    """Draw the part a job prints.

    Printed traces are coloured per feature (``!Feature N`` comments); a program without
    features is coloured by print time instead (a colour bar in seconds). Rapid moves
    (stage moving, shutter closed) are thin dashed grey lines; stroke starts are dots.

    Parameters
    ----------
    job : ajtwin.job.Job
    path : str or Path, optional
        Write the figure there (PNG, PDF, SVG by extension) and close it.
    ax : matplotlib Axes, optional
        Draw into these axes instead of a new figure.
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib

    if ax is None and path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    table = job.timeline()
    x, y = table["x_mm"].to_numpy(), table["y_mm"].to_numpy()
    chords = np.stack([np.c_[x[:-1], y[:-1]], np.c_[x[1:], y[1:]]], axis=1)
    is_open = table["shutter_open"].to_numpy()[:-1].astype(bool)
    moving = table["speed_mm_s"].to_numpy()[:-1] > 0
    feature = table["feature"].to_numpy()[:-1]
    time_s = table["time_s"].to_numpy()[:-1]

    own_figure = ax is None
    if own_figure:
        xmin, ymin, xmax, ymax = job.summary()["travel_bbox_mm"]
        width, height = max(xmax - xmin, 1e-3), max(ymax - ymin, 1e-3)
        fig_w = 10.0
        fig_h = float(np.clip(fig_w * height / width + 1.2, 3.0, 10.0))
        fig, ax = plt.subplots(figsize=(fig_w, fig_h), constrained_layout=True)
    else:
        fig = ax.figure

    rapid = ~is_open & moving
    if rapid.any():
        ax.add_collection(
            LineCollection(
                chords[rapid],
                colors="0.6",
                linewidths=0.5,
                linestyles=(0, (4, 3)),
                label="rapid (shutter closed)",
            )
        )
    printed = is_open & moving
    features = np.unique(feature[printed])
    if printed.any():
        if features.size > 1 or (features.size == 1 and features[0] >= 0):
            cmap = plt.get_cmap("tab10" if features.size <= 10 else "tab20")
            for i, value in enumerate(features):
                sel = printed & (feature == value)
                name = job.feature_names.get(int(value), "")
                label = (
                    f"feature {value}" + (f": {name}" if name else "")
                    if value >= 0
                    else "no feature"
                )
                ax.add_collection(
                    LineCollection(
                        chords[sel], colors=[cmap(i % cmap.N)], linewidths=1.2, label=label
                    )
                )
        else:
            lines = LineCollection(chords[printed], cmap="viridis", linewidths=1.2)
            lines.set_array(time_s[printed])
            ax.add_collection(lines)
            fig.colorbar(lines, ax=ax, label="print time [s]", shrink=0.8)
    strokes = job.strokes
    if len(strokes):
        ax.plot(
            strokes["x_start_mm"],
            strokes["y_start_mm"],
            "o",
            ms=2.5,
            color="k",
            label="stroke start",
        )
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.margins(0.02)
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    summary = job.summary()
    ax.set_title(
        title
        or f"{Path(job.path).name}: {summary['strokes']} strokes, "
        f"{summary['printed_length_mm']:.1f} mm printed, "
        f"{summary['print_time_s']:.0f} s"
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize="small", frameon=False)
    if path is not None:
        fig.savefig(path, dpi=150)
        if own_figure:
            plt.close(fig)
    return fig
