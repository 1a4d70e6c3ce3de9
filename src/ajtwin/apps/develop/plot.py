"""The process window as a picture: P(feasible) over two slices of the input box."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ajtwin.apps.develop.bringup import TEST_INPUTS, feasibility

#: points per axis of each slice
GRID = 41
LABELS = {
    "atomizer_current_mA": "I_A [mA]",
    "carrier_flow_sccm": "Q_c [sccm]",
    "sheath_flow_sccm": "Q_s [sccm]",
}


def window_slices(bringup, posterior, centre) -> list[dict]:
    """Two slices through ``centre`` (4,) [mA, sccm, sccm, mm/s]: Q_s over Q_c, and Q_c over
    I_A; each a dict of the axes' names and values and P(feasible) (GRID, GRID)."""
    out = []
    for ix, iy in ((1, 2), (0, 1)):
        xs = np.linspace(*bringup.box.bounds[ix], GRID)
        ys = np.linspace(*bringup.box.bounds[iy], GRID)
        gx, gy = np.meshgrid(xs, ys)
        points = np.tile(np.asarray(centre, dtype=float), (gx.size, 1))
        points[:, ix], points[:, iy] = gx.ravel(), gy.ravel()
        p = feasibility(posterior.predict(points), bringup.goal).reshape(gx.shape)
        out.append({"x": TEST_INPUTS[ix], "y": TEST_INPUTS[iy], "xs": xs, "ys": ys, "p": p})
    return out


def window_figure(bringup, posterior, centre, path, title: str = "") -> Path:
    """Write the window's picture (PNG) around ``centre``: P(feasible) shaded, the P ≥ p
    contour drawn, the tests and the centre marked."""
    # lazy: matplotlib only when a picture is asked for
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    slices = window_slices(bringup, posterior, centre)
    tests = (
        np.array([[t[n] for n in TEST_INPUTS] for t in bringup.tests]) if bringup.tests else None
    )
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), constrained_layout=True)
    for ax, s in zip(axes, slices):
        ix, iy = TEST_INPUTS.index(s["x"]), TEST_INPUTS.index(s["y"])
        shade = ax.contourf(s["xs"], s["ys"], s["p"], levels=np.linspace(0, 1, 11), cmap="Greens")
        if s["p"].max() >= bringup.goal.probability:
            ax.contour(s["xs"], s["ys"], s["p"], levels=[bringup.goal.probability], colors="k")
        if tests is not None:
            ax.plot(tests[:, ix], tests[:, iy], "o", mfc="none", mec="tab:blue", label="tests")
            for k, t in enumerate(tests, 1):
                ax.annotate(
                    str(k), (t[ix], t[iy]), fontsize=7, xytext=(3, 3), textcoords="offset points"
                )
        ax.plot(centre[ix], centre[iy], "*", ms=14, color="tab:red", label="recipe / best")
        ax.set_xlabel(LABELS[s["x"]])
        ax.set_ylabel(LABELS[s["y"]])
        fixed = [n for n in TEST_INPUTS[:3] if n not in (s["x"], s["y"])][0]
        ax.set_title(
            f"{LABELS[fixed]} = {centre[TEST_INPUTS.index(fixed)]:g}, ν = {centre[3]:g} mm/s",
            fontsize=9,
        )
    axes[0].legend(loc="upper right", fontsize=8)
    fig.colorbar(shade, ax=axes, label="P(L_w within tolerance and L_o ≤ max)")
    g = bringup.goal
    fig.suptitle(
        title
        or f"process window: L_w {g.target_linewidth_um:g} ± {g.tolerance_um:g} µm, L_o ≤ "
        f"{g.max_overspray_um:g} µm "
        f"(line: P = {g.probability:g})"
    )
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
