"""CFD macro-model speed: one coarse OpenFOAM case end to end, split by stage.

Times blockMesh + simpleFoam (mesh level 1, 4400 cells, 600 SIMPLE iterations),
the velocity-grid resampling, droplet tracking (3000 droplets of d_a = 3.5 µm)
and the model reference §8 post-processing (32 azimuths per droplet).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> dict:
    from ajtwin import units
    from ajtwin.cfd.case import CaseSpec
    from ajtwin.cfd.flowfield import CellField, VelocityGrid
    from ajtwin.cfd.geometry import load_geometry
    from ajtwin.cfd.physics import load_cfd_parameters
    from ajtwin.cfd.profile import height_profile, line_metrics
    from ajtwin.cfd.run import droplet_sample, solve_gas
    from ajtwin.cfd.tracker import LANDED, track_droplets

    g = load_geometry()
    p = load_cfd_parameters()
    spec = CaseSpec(0.0, 23.0, 50.0, mesh_level=1)
    with tempfile.TemporaryDirectory() as tmp:
        case_dir = Path(tmp) / spec.name
        t0 = time.perf_counter()
        flow = solve_gas(spec, case_dir, g, p)
        solve_s = time.perf_counter() - t0
        cells = CellField.load(case_dir / "flow.npz")
    t0 = time.perf_counter()
    grid = VelocityGrid(cells, g, 0.0)
    grid_s = time.perf_counter() - t0
    z, u = droplet_sample(3000)
    sigma = np.sqrt(np.log1p(p.droplet_cv**2))
    d_um = 3.5 * np.exp(sigma * z)
    t0 = time.perf_counter()
    tracked = track_droplets(
        grid,
        units.um_to_m(d_um),
        0.98 * g.carrier_radius * np.sqrt(u),
        p,
        g.gas_density,
        start_x=float(cells.x.min()),
    )
    track_s = time.perf_counter() - t0
    ok = tracked.status == LANDED
    t0 = time.perf_counter()
    y, h = height_profile(units.m_to_um(tracked.landing_radius[ok]), d_um[ok], azimuths=32)
    metrics = line_metrics(y, h)
    profile_s = time.perf_counter() - t0
    return {
        "cells": flow["cells"],
        "blockMesh_s": round(flow["timings"]["blockMesh_s"], 2),
        "simpleFoam_600_iterations_s": round(flow["timings"]["simpleFoam_s"], 2),
        "gas_case_total_s": round(solve_s, 2),
        "velocity_grid_s": round(grid_s, 2),
        "tracking_3000_droplets_s": round(track_s, 2),
        "tracking_steps": tracked.steps,
        "profile_and_metrics_s": round(profile_s, 2),
        "linewidth_um_23_50_da3.5": round(metrics["linewidth_um"], 2),
        "max_speed_m_s_23_50": round(flow["max_speed_m_s"], 2),
    }


if __name__ == "__main__":
    for key, value in main().items():
        print(f"{key}: {value}")
