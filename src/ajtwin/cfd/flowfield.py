"""The solved gas flow as arrays, its summary figures, and a fast velocity lookup.

OpenFOAM's cell-centred solution (x, r, u_x, u_r, p) is resampled once onto a
rectilinear (x, r) grid — fine in r near the axis, following the mesh layers in
x — by linear interpolation on the Delaunay triangulation of the cell centres,
the no-slip wall points and the mirror image of the field across the axis
(u_r odd, u_x even). Droplet tracking then needs only a bilinear lookup, which
is vectorised over thousands of droplets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import LinearNDInterpolator

from ajtwin.cfd.geometry import Geometry


@dataclass
class CellField:
    """Cell-centred gas solution in SI: positions [m], velocity [m/s], pressure [Pa]."""

    x: np.ndarray
    r: np.ndarray
    ux: np.ndarray
    ur: np.ndarray
    p: np.ndarray
    volume: np.ndarray

    def save(self, path):
        """Write the cell field to a compressed ``.npz``."""
        np.savez_compressed(
            path, x=self.x, r=self.r, ux=self.ux, ur=self.ur, p=self.p, volume=self.volume
        )

    @classmethod
    def load(cls, path):
        """Read a cell field written by :meth:`save`."""
        with np.load(path) as data:
            return cls(**{k: data[k] for k in ("x", "r", "ux", "ur", "p", "volume")})


def plane_average(cells: CellField, x_plane: float, r_min: float = 0.0, r_max: float = np.inf):
    """Volume-weighted mean pressure [Pa] of the first cell layer downstream of x_plane.

    In the wedge a cell's volume is proportional to r·dA, so the volume weight
    is the area weight of the axisymmetric plane.
    """
    downstream = (cells.x > x_plane) & (cells.r >= r_min) & (cells.r <= r_max)
    if not downstream.any():
        raise ValueError(f"no cells downstream of x = {x_plane:g} m in r ∈ [{r_min:g}, {r_max:g}]")
    first = downstream & np.isclose(cells.x, cells.x[downstream].min(), rtol=0, atol=1e-9)
    return float(np.average(cells.p[first], weights=cells.volume[first]))


def flow_summary(cells: CellField, g: Geometry, total_flow_m3_s: float) -> dict:
    """Figures the report compares against the paper (model reference §8).

    Returns max gas speed [m/s], static pressures [Pa] at the carrier and sheath
    inlets, at the cone entry and at the nozzle exit, and R_3^N [Pa s/m³] =
    (p_cone_entry − p_ambient)/(Q_c + Q_s): the pressure the tip section (cone and
    bore, the walls that ΔR_N moves) needs to pass the flow to ambient.
    """
    speed = np.hypot(cells.ux, cells.ur)
    tube_out = g.carrier_radius + g.carrier_wall
    p_cone = plane_average(cells, g.cone_x)
    p_exit = plane_average(cells, g.exit_x, r_max=g.tip_radius)
    return {
        "max_speed_m_s": float(speed.max()),
        "max_speed_x_m": float(cells.x[np.argmax(speed)]),
        "carrier_inlet_pressure_pa": plane_average(cells, 0.0, r_max=g.carrier_radius),
        "sheath_inlet_pressure_pa": plane_average(cells, 0.0, r_min=tube_out),
        "cone_entry_pressure_pa": p_cone,
        "exit_pressure_pa": p_exit,
        "tip_resistance_pa_s_m3": p_cone / total_flow_m3_s,
        "bore_resistance_pa_s_m3": (p_cone - p_exit) / total_flow_m3_s,
    }


def _grid_axis(nodes: np.ndarray, lo: float, hi: float, step: float) -> np.ndarray:
    """Sorted unique union of ``nodes`` in [lo, hi] and a regular grid of ``step``."""
    regular = np.arange(lo, hi + 0.5 * step, step)
    merged = np.unique(np.concatenate([nodes[(nodes >= lo) & (nodes <= hi)], regular, [lo, hi]]))
    keep = np.concatenate([[True], np.diff(merged) > 1e-10])
    return merged[keep]


class VelocityGrid:
    """Gas velocity on a rectilinear (x, r) grid with r ∈ [−R, R] (mirrored field).

    Parameters
    ----------
    cells : CellField
    geometry : Geometry
    nozzle_deposition_um : float
        ΔR_N of the solved case (sets the solid mask).
    """

    def __init__(self, cells: CellField, geometry: Geometry, nozzle_deposition_um: float):
        g = geometry
        self.geometry = g
        self.nozzle_deposition_um = float(nozzle_deposition_um)
        tip = g.tip_radius_at(nozzle_deposition_um)
        # r grid: fine near the axis (tip bore and jet), coarser outward
        fine = min(tip / 40.0, 2e-6)
        r_pos = np.unique(
            np.concatenate(
                [
                    np.arange(0.0, 1.6 * g.tip_radius, fine),
                    np.arange(1.6 * g.tip_radius, g.chamber_radius, 10e-6),
                    np.arange(g.chamber_radius, g.outer_radius + 1e-9, 40e-6),
                    [
                        tip,
                        g.carrier_radius,
                        g.carrier_radius + g.carrier_wall,
                        g.chamber_radius,
                        g.lip_radius,
                        g.outer_radius,
                    ],
                ]
            )
        )
        self.r_nodes = np.concatenate([-r_pos[:0:-1], r_pos])
        x_layers = np.unique(np.round(cells.x, 10))
        x_mid = 0.5 * (x_layers[1:] + x_layers[:-1])
        self.x_nodes = _grid_axis(np.concatenate([x_layers, x_mid]), 0.0, g.substrate_x, 50e-6)

        # interpolation support: cells, their mirror image, no-slip wall points
        wall_x, wall_r = [], []
        for (x0, r0), (x1, r1) in g.wall_segments(nozzle_deposition_um):
            n = max(2, int(np.hypot(x1 - x0, r1 - r0) / 5e-6))
            t = np.linspace(0.0, 1.0, n)
            wall_x.append(x0 + t * (x1 - x0))
            wall_r.append(r0 + t * (r1 - r0))
        wall_x = np.concatenate(wall_x)
        wall_r = np.concatenate(wall_r)
        # inlet planes carry their uniform inflow (velocity of the first cell layer)
        inlet = cells.x == cells.x.min()
        in_r = cells.r[inlet]
        px = np.concatenate([cells.x, cells.x, wall_x, wall_x, 0 * in_r, 0 * in_r])
        pr = np.concatenate([cells.r, -cells.r, wall_r, -wall_r, in_r, -in_r])
        vx = np.concatenate(
            [cells.ux, cells.ux, 0 * wall_x, 0 * wall_x, cells.ux[inlet], cells.ux[inlet]]
        )
        vr = np.concatenate(
            [cells.ur, -cells.ur, 0 * wall_x, 0 * wall_x, cells.ur[inlet], -cells.ur[inlet]]
        )
        # a resting frame around the domain keeps every grid node inside the convex hull
        # (nodes outside it make scipy fall back to a brute-force simplex search)
        fx = np.linspace(-1e-4, g.substrate_x + 1e-4, 200)
        fr = np.linspace(-g.outer_radius - 1e-4, g.outer_radius + 1e-4, 100)
        frame_x = np.concatenate([fx, fx, np.full(fr.size, fx[0]), np.full(fr.size, fx[-1])])
        frame_r = np.concatenate([np.full(fx.size, fr[0]), np.full(fx.size, fr[-1]), fr, fr])
        px = np.concatenate([px, frame_x])
        pr = np.concatenate([pr, frame_r])
        vx = np.concatenate([vx, 0 * frame_x])
        vr = np.concatenate([vr, 0 * frame_x])
        interp = LinearNDInterpolator(
            np.column_stack([px, pr]), np.column_stack([vx, vr]), fill_value=0.0
        )
        gx, gr = np.meshgrid(self.x_nodes, self.r_nodes, indexing="ij")
        fluid = g.inside_fluid(gx, gr, nozzle_deposition_um)
        values = np.zeros((*gx.shape, 2))
        values[fluid] = interp(gx[fluid], gr[fluid])  # solid nodes stay at rest
        self.ux = np.ascontiguousarray(values[..., 0])
        self.ur = np.ascontiguousarray(values[..., 1])
        self.dx = np.diff(self.x_nodes)
        self.dr = np.diff(self.r_nodes)

    def locate(self, x, r):
        """Grid cell indices and fractional positions of points (clipped to the grid)."""
        i = np.clip(np.searchsorted(self.x_nodes, x, side="right") - 1, 0, len(self.dx) - 1)
        j = np.clip(np.searchsorted(self.r_nodes, r, side="right") - 1, 0, len(self.dr) - 1)
        fx = np.clip((x - self.x_nodes[i]) / self.dx[i], 0.0, 1.0)
        fr = np.clip((r - self.r_nodes[j]) / self.dr[j], 0.0, 1.0)
        return i, j, fx, fr

    def velocity(self, x, r):
        """Bilinear (u_x, u_r) [m/s] at points (x, r) [m]; also the local grid spacing."""
        i, j, fx, fr = self.locate(x, r)
        w00 = (1 - fx) * (1 - fr)
        w10 = fx * (1 - fr)
        w01 = (1 - fx) * fr
        w11 = fx * fr
        ux = (
            w00 * self.ux[i, j]
            + w10 * self.ux[i + 1, j]
            + w01 * self.ux[i, j + 1]
            + w11 * self.ux[i + 1, j + 1]
        )
        ur = (
            w00 * self.ur[i, j]
            + w10 * self.ur[i + 1, j]
            + w01 * self.ur[i, j + 1]
            + w11 * self.ur[i + 1, j + 1]
        )
        return ux, ur, self.dx[i], self.dr[j]
