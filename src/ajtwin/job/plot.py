"""Draw a job's part: printed strokes coloured per feature, rapid moves dashed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_part", "plot_part_values", "repetition_layout"]


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


def repetition_layout(job, gap_fraction: float = 0.12) -> np.ndarray:
    """Where each run of a looped job is drawn: (repetitions, 2) offsets [mm].

    A looped job prints the same part again and again; drawn on top of each other the
    runs would hide one another, so each run is drawn as its own copy of the part, in a
    grid of about as many columns as rows on the page (run 1 top left, reading order).
    One run: no offset.
    """
    n = int(job.repetitions)
    if n <= 1:
        return np.zeros((1, 2))
    box = job.summary()["bbox_mm"] or [0.0, 0.0, 1.0, 1.0]
    width, height = max(box[2] - box[0], 1e-3), max(box[3] - box[1], 1e-3)
    columns = int(np.clip(round(np.sqrt(n * height / width * 1.6)), 1, n))
    rows = np.arange(n) // columns
    cols = np.arange(n) % columns
    return np.stack(
        [cols * width * (1 + gap_fraction), -rows * height * (1 + 2 * gap_fraction)], axis=1
    )


def plot_part_values(
    job,
    points,
    values,
    path: str | Path | None = None,
    *,
    value_label: str = "",
    limit: float | None = None,
    outlined=None,
    markers=None,
    title: str | None = None,
):
    """Draw the part with a value along its traces: a diverging colour map around 0.

    Parameters
    ----------
    job : ajtwin.job.Job
    points : DataFrame
        Points along the printed portions in print order: ``portion``, ``x_mm``, ``y_mm``
        and the portion's ``repetition`` (consecutive points of one portion are joined).
    values : array (n_points,)
        The value at each point (e.g. the linewidth's deviation from its target [µm]).
    path : str or Path, optional
        Write the figure there (PNG, PDF, SVG by extension) and close it.
    value_label : str
        The colour bar's label.
    limit : float, optional
        ±limit marked on the colour bar (e.g. the tolerance's half-width).
    outlined : array of bool (n_portions,), optional
        Portions drawn with a black outline (e.g. flagged).
    markers : list of dict, optional
        Points to mark: ``x_mm``, ``y_mm`` (program coordinates), ``repetition``,
        ``label``, ``kind`` ("raised" red cross, "onset" red ring).
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize
    from matplotlib.lines import Line2D

    layout = repetition_layout(job)
    portion = points["portion"].to_numpy()
    rep = np.clip(points["repetition"].to_numpy(dtype=np.int64), 0, len(layout) - 1)
    x = points["x_mm"].to_numpy(dtype=float) + layout[rep, 0]
    y = points["y_mm"].to_numpy(dtype=float) + layout[rep, 1]
    values = np.asarray(values, dtype=float)
    joined = portion[1:] == portion[:-1]
    segments = np.stack([np.c_[x[:-1], y[:-1]], np.c_[x[1:], y[1:]]], axis=1)[joined]
    segment_value = 0.5 * (values[:-1] + values[1:])[joined]
    finite = np.abs(values[np.isfinite(values)])
    scale = max(float(np.quantile(finite, 0.995)) if finite.size else 1.0, (limit or 0.0) * 1.5)
    scale = scale if scale > 0 else 1.0

    extent_x, extent_y = np.ptp(x) if x.size else 1.0, np.ptp(y) if y.size else 1.0
    fig_w = 11.0
    fig_h = float(np.clip(fig_w * 0.8 * max(extent_y, 1e-3) / max(extent_x, 1e-3) + 1.6, 3.5, 16))
    fig, ax = plt.subplots(figsize=(fig_w, fig_h), constrained_layout=True)
    handles = []
    if outlined is not None and np.any(outlined):
        flagged_segments = np.asarray(outlined, dtype=bool)[portion[:-1][joined]]
        outline = LineCollection(segments[flagged_segments], colors="k", linewidths=2.6, zorder=2)
        ax.add_collection(outline)
        handles.append(Line2D([], [], color="k", lw=2.6, label="flagged portion (outlined)"))
    lines = LineCollection(
        segments, cmap="RdBu_r", norm=Normalize(-scale, scale), linewidths=1.0, zorder=3
    )
    lines.set_array(segment_value)
    ax.add_collection(lines)
    bar = fig.colorbar(lines, ax=ax, label=value_label, shrink=0.85, extend="both")
    if limit:
        for level in (-limit, limit):
            bar.ax.axhline(level, color="k", lw=1.2)
    handles += _draw_markers(ax, markers or (), layout)
    if len(layout) > 1:
        box = job.summary()["bbox_mm"]
        offsets = job.repetition_offsets_s
        for r, (dx, dy) in enumerate(layout):
            ax.text(box[0] + dx, box[3] + dy, f"run {r + 1} ({offsets[r] / 60:.1f} min)",
                    fontsize=7, va="bottom", color="0.3")  # fmt: skip
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.margins(0.03)
    ax.set_xlabel("x [mm]" + ("  (runs of the looped job side by side)" if len(layout) > 1 else ""))
    ax.set_ylabel("y [mm]")
    ax.set_title(title or Path(job.path).name)
    if handles:
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.0, -0.08 if len(layout) > 1
                  else -0.12), ncol=3, fontsize="small", frameon=False)  # fmt: skip
    if path is not None:
        fig.savefig(path, dpi=150)
        plt.close(fig)
    return fig


def _draw_markers(ax, markers, layout) -> list:
    """Alarm markers (raised: red cross, onset: red ring) with their labels; the legend
    handles (none without markers)."""
    import matplotlib.patheffects as effects
    from matplotlib.lines import Line2D

    for marker in markers:
        r = min(max(int(marker.get("repetition", 0)), 0), len(layout) - 1)
        mx, my = marker["x_mm"] + layout[r, 0], marker["y_mm"] + layout[r, 1]
        style = ("x", 11, 2.5) if marker.get("kind") == "raised" else ("o", 9, 1.8)
        ax.plot(mx, my, style[0], ms=style[1], mew=style[2], color="#d00000", mfc="none", zorder=5)
        raised = marker.get("kind") == "raised"
        ax.annotate(
            marker.get("label", ""),
            (mx, my),
            xytext=(6, 6) if raised else (-6, 6),  # the onset's label to the left: no overlap
            ha="left" if raised else "right",
            textcoords="offset points",
            fontsize=8,
            color="#900000",
            zorder=6,
            path_effects=[effects.withStroke(linewidth=2.5, foreground="w")],
        )
    if not markers:
        return []
    raised = {"marker": "x", "ms": 9, "mew": 2.5, "label": "alarm raised (nozzle there)"}
    onset = {
        "marker": "o",
        "ms": 8,
        "mew": 1.8,
        "mfc": "none",
        "label": "alarm onset (nozzle there)",
    }
    return [Line2D([], [], ls="", color="#d00000", **style) for style in (raised, onset)]
