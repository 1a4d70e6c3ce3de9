"""From droplet landing radii to linewidth and overspray (model reference §8, paper App. C.1).

1. Each landing radius gets a random azimuth → a 2-D point on the substrate.
2. The printed line sums the points along the print direction, so only the
   coordinate across the line, y = r cos θ, matters.
3. Each droplet spreads on impact to a disc of 3.8× its diameter with its volume
   spread evenly over it; summed along the print direction a disc of diameter D
   contributes across the line the chord profile ∝ sqrt((D/2)² − (y − y_i)²).
   The profile h(y) is the sum over droplets, integrated exactly over each bin.
4. b = the longest interval where h > 0.8 h_max; L_w = 2.1 b (the paper's b/a).
5. Linewidth edges at the centre of b ± L_w/2; on each side the overspray is the
   distance from the edge outward to where h falls to 1 % of h at that edge;
   L_o is the mean of the two sides (model reference §9 convention).

All lengths in µm here (the display unit of L_w and L_o).

Examples
--------
>>> import numpy as np
>>> y, h = height_profile(np.zeros(1), np.full(1, 10.0), spread_factor=3.8, bin_um=0.05,
...                       half_width_um=30.0, azimuths=1)
>>> round(line_metrics(y, h)["b_um"], 2)   # chord kernel: h > 0.8 h_max for |y| < 0.6 R
22.8
"""

from __future__ import annotations

import numpy as np


def _semicircle_cdf(u):
    """CDF of the density (2/π) sqrt(1 − u²) on [−1, 1]."""
    u = np.clip(u, -1.0, 1.0)
    return 0.5 + (u * np.sqrt(1.0 - u * u) + np.arcsin(u)) / np.pi


def height_profile(
    landing_radius_um,
    diameter_um,
    spread_factor: float = 3.8,
    bin_um: float = 0.5,
    half_width_um: float | None = None,
    azimuths: int = 32,
    seed: int = 0,
    weights=None,
    chunk: int = 4000,
):
    """Height profile h(y) across the printed line from landing radii.

    Parameters
    ----------
    landing_radius_um : array (n,)
        Radial landing positions on the substrate [µm] (≥ 0).
    diameter_um : array (n,)
        Droplet diameters [µm] (set each droplet's volume and footprint).
    spread_factor : float
        Footprint diameter / droplet diameter (paper: 3.8).
    bin_um : float
        Bin width across the line [µm].
    half_width_um : float, optional
        Profile covers [−half_width, half_width]; default max landing radius +
        footprint radius + 10 bins.
    azimuths : int
        Random azimuths drawn per droplet (each carries 1/azimuths of it).
    seed : int
        Seed of the azimuth draws (reproducible profiles).
    weights : array (n,), optional
        Extra per-droplet weights (default 1).

    Returns
    -------
    y : array (m,)
        Bin centres [µm].
    h : array (m,)
        Deposited volume per unit width [µm³/µm] per droplet count, i.e. a height
        up to a constant (thresholds are relative, so the constant does not matter).
    """
    r = np.asarray(landing_radius_um, dtype=float)
    d = np.asarray(diameter_um, dtype=float)
    if r.shape != d.shape or r.ndim != 1:
        raise ValueError("landing_radius_um and diameter_um must be 1-D arrays of equal length")
    if r.size == 0:
        raise ValueError("no landed droplets: cannot build a height profile")
    if np.any(~np.isfinite(r)) or np.any(r < 0):
        raise ValueError("landing radii must be finite and ≥ 0 µm")
    if np.any(~np.isfinite(d)) or np.any(d <= 0):
        raise ValueError("droplet diameters must be finite and > 0 µm")
    w = np.ones_like(r) if weights is None else np.asarray(weights, dtype=float)
    footprint_radius = 0.5 * spread_factor * d
    if half_width_um is None:
        half_width_um = float(np.max(r + footprint_radius)) + 10 * bin_um
    n_bins = int(np.ceil(2 * half_width_um / bin_um))
    edges = (np.arange(n_bins + 1) - 0.5 * n_bins) * bin_um
    h = np.zeros(n_bins)
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, 2.0 * np.pi, size=(r.size, azimuths))
    y_all = (r[:, None] * np.cos(theta)).ravel()
    radius_all = np.repeat(footprint_radius, azimuths)
    volume_all = np.repeat(w * np.pi * d**3 / 6.0 / azimuths, azimuths)
    for start in range(0, y_all.size, chunk):
        y = y_all[start : start + chunk, None]
        rad = radius_all[start : start + chunk, None]
        lo = np.searchsorted(edges, (y - rad).ravel()) - 1
        hi = np.searchsorted(edges, (y + rad).ravel())
        span = int(np.max(hi - lo)) + 1
        idx = np.clip(lo[:, None] + np.arange(span + 1)[None, :], 0, n_bins)
        cdf = _semicircle_cdf((edges[idx] - y) / rad)
        mass = np.diff(cdf, axis=1) * volume_all[start : start + chunk, None]
        np.add.at(h, np.clip(idx[:, :-1], 0, n_bins - 1), mass)
    y_centres = 0.5 * (edges[1:] + edges[:-1])
    return y_centres, h / bin_um


def _crossing(y, h, i_in, i_out, level):
    """Position where h crosses ``level`` between bin i_in (above) and i_out (below)."""
    h_in, h_out = h[i_in], h[i_out]
    if h_in == h_out:
        return 0.5 * (y[i_in] + y[i_out])
    return y[i_in] + (level - h_in) / (h_out - h_in) * (y[i_out] - y[i_in])


def line_metrics(
    y,
    h,
    peak_fraction: float = 0.8,
    width_ratio: float = 2.1,
    edge_fraction: float = 0.01,
) -> dict:
    """Linewidth and overspray of a CFD height profile (paper App. C.1, model reference §8).

    Parameters
    ----------
    y, h : arrays (m,)
        Bin centres [µm] (ascending, uniform) and profile heights.
    peak_fraction : float
        b is the longest interval with h > peak_fraction · h_max (paper: 0.8).
    width_ratio : float
        L_w = width_ratio · b (paper: b/a = 2.1).
    edge_fraction : float
        Overspray ends where h falls to edge_fraction · h(edge) (paper: 1 %).

    Returns
    -------
    dict
        b_um, linewidth_um, overspray_um (mean of sides; NaN when h vanishes at a
        linewidth edge), overspray_left_um, overspray_right_um, centre_um,
        edge_height_fraction (h at the edges / h_max).
    """
    y = np.asarray(y, dtype=float)
    h = np.asarray(h, dtype=float)
    if y.shape != h.shape or y.ndim != 1 or y.size < 3:
        raise ValueError("y and h must be 1-D arrays of equal length ≥ 3")
    if np.any(~np.isfinite(h)):
        raise ValueError("profile h contains NaN or inf")
    h_max = float(h.max())
    if h_max <= 0:
        raise ValueError("profile is empty (h_max ≤ 0)")
    level = peak_fraction * h_max
    above = h > level
    # longest run of consecutive bins above the level
    padded = np.concatenate([[False], above, [False]]).astype(np.int8)
    starts = np.flatnonzero(np.diff(padded) == 1)
    stops = np.flatnonzero(np.diff(padded) == -1) - 1
    k = int(np.argmax(stops - starts))
    i0, i1 = int(starts[k]), int(stops[k])
    left = _crossing(y, h, i0, i0 - 1, level) if i0 > 0 else y[0]
    right = _crossing(y, h, i1, i1 + 1, level) if i1 < y.size - 1 else y[-1]
    b = right - left
    linewidth = width_ratio * b
    centre = 0.5 * (left + right)
    sides = {}
    edge_heights = []
    for side, sign in (("left", -1.0), ("right", 1.0)):
        edge = centre + sign * 0.5 * linewidth
        h_edge = float(np.interp(edge, y, h, left=0.0, right=0.0))
        edge_heights.append(h_edge / h_max)
        if h_edge <= 0.0:
            sides[side] = np.nan
            continue
        target = edge_fraction * h_edge
        if sign > 0:
            idx = np.flatnonzero((y > edge) & (h <= target))
            if idx.size == 0:
                sides[side] = np.nan
                continue
            j = int(idx[0])
            inner = max(j - 1, 0)
            pos = _crossing(y, h, inner, j, target) if y[inner] > edge else y[j]
            sides[side] = float(max(pos, edge) - edge)
        else:
            idx = np.flatnonzero((y < edge) & (h <= target))
            if idx.size == 0:
                sides[side] = np.nan
                continue
            j = int(idx[-1])
            inner = min(j + 1, y.size - 1)
            pos = _crossing(y, h, inner, j, target) if y[inner] < edge else y[j]
            sides[side] = float(edge - min(pos, edge))
    overspray = 0.5 * (sides["left"] + sides["right"])
    return {
        "b_um": float(b),
        "linewidth_um": float(linewidth),
        "overspray_um": float(overspray),
        "overspray_left_um": float(sides["left"]),
        "overspray_right_um": float(sides["right"]),
        "centre_um": float(centre),
        "edge_height_fraction": float(np.mean(edge_heights)),
    }
