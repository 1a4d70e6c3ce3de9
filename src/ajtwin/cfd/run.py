"""One case end to end: OpenFOAM gas solve, droplet tracking, line metrics.

A case directory holds the OpenFOAM case, ``flow.npz`` (the cell field),
``flow.json`` (convergence, timings, max speed, pressures, R_3^N) and, once the
droplets are done, ``result.json`` — the finished marker a resumed sweep skips.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from ajtwin import units
from ajtwin.cfd import foam
from ajtwin.cfd.case import CaseSpec, write_case
from ajtwin.cfd.flowfield import CellField, VelocityGrid, flow_summary
from ajtwin.cfd.geometry import Geometry, load_geometry
from ajtwin.cfd.physics import CfdParameters, load_cfd_parameters
from ajtwin.cfd.profile import height_profile, line_metrics
from ajtwin.cfd.tracker import LANDED, track_droplets

#: Final initial residuals of U_x, U_r below which a steady solve counts as converged.
#: Most cases reach 1e-9; with ΔR_N ≥ 22.5 µm the jet (≥ 200 m/s) keeps a weak
#: unsteadiness that holds the U_r residual at a few 1e-6, hence 1e-5.
CONVERGED_RESIDUAL = 1e-5


def solve_gas(
    spec: CaseSpec,
    case_dir: str | Path,
    geometry: Geometry | None = None,
    params: CfdParameters | None = None,
    keep_fields: bool = False,
) -> dict:
    """Write and run the OpenFOAM case; store ``flow.npz`` and ``flow.json``.

    Returns the flow summary (see :func:`ajtwin.cfd.flowfield.flow_summary`) plus
    convergence facts and timings. Raises :class:`~ajtwin.cfd.foam.OpenFoamError`
    when a tool fails and ``RuntimeError`` when the solve did not converge.
    """
    g = geometry or load_geometry()
    p = params or load_cfd_parameters()
    case_dir = Path(case_dir)
    write_case(spec, case_dir, g, kinematic_viscosity=p.gas_viscosity / g.gas_density)
    timings = {}
    timings["blockMesh_s"] = foam.run_tool(["blockMesh"], case_dir, "blockMesh")
    timings["simpleFoam_s"] = foam.run_tool(["simpleFoam"], case_dir, "simpleFoam")
    foam.run_tool(
        ["postProcess", "-func", "writeCellCentres", "-latestTime"], case_dir, "writeCellCentres"
    )
    foam.run_tool(
        ["postProcess", "-func", "writeCellVolumes", "-latestTime"], case_dir, "writeCellVolumes"
    )
    log = foam.parse_solver_log(case_dir / "log.simpleFoam")
    time_dir = case_dir / foam.latest_time(case_dir)
    centres = foam.read_internal_field(time_dir / "C")
    velocity = foam.read_internal_field(time_dir / "U")
    kinematic_p = foam.read_internal_field(time_dir / "p")
    volume = foam.read_internal_field(time_dir / "V")
    cells = CellField(
        x=centres[:, 0],
        r=np.hypot(centres[:, 1], centres[:, 2]),
        ux=velocity[:, 0],
        ur=velocity[:, 1],
        p=kinematic_p * g.gas_density,
        volume=volume,
    )
    cells.save(case_dir / "flow.npz")
    summary = flow_summary(cells, g, spec.total_flow_m3_s)
    residual = max(log["final_residuals"].get("Ux", 1.0), log["final_residuals"].get("Uy", 1.0))
    summary.update(
        {
            "spec": asdict(spec),
            "cells": int(cells.x.size),
            "iterations": log["iterations"],
            "final_residual_u": residual,
            "converged": bool(residual < CONVERGED_RESIDUAL),
            "openfoam_version": foam.openfoam_version(),
            "timings": timings,
        }
    )
    (case_dir / "flow.json").write_text(json.dumps(summary, indent=2))
    if not keep_fields:  # the case stays re-runnable; the heavy time directory goes
        shutil.rmtree(time_dir, ignore_errors=True)
        shutil.rmtree(case_dir / "constant" / "polyMesh", ignore_errors=True)
    if not summary["converged"]:
        raise RuntimeError(
            f"{case_dir}: simpleFoam not converged after {log['iterations']} iterations "
            f"(final U residual {residual:.2e} ≥ {CONVERGED_RESIDUAL:g})"
        )
    return summary


def droplet_sample(n: int, seed: int = 2024) -> tuple[np.ndarray, np.ndarray]:
    """Common random numbers for every case: standard normals (sizes), uniforms (start radii)."""
    rng = np.random.default_rng(seed)
    return rng.standard_normal(n), rng.uniform(0.0, 1.0, n)


def evaluate_droplets(
    cells: CellField,
    spec: CaseSpec,
    droplet_diameters_um,
    n_droplets: int = 3000,
    azimuths: int = 32,
    geometry: Geometry | None = None,
    params: CfdParameters | None = None,
    seed: int = 2024,
) -> list[dict]:
    """Track log-normal droplet populations (one per median d_a) and measure the line.

    Droplet diameters d = d_a exp(σ_ln z), σ_ln from the 25 % coefficient of
    variation; start radii area-uniform over the carrier inlet (uniform inflow),
    0.98 r_c at most so no droplet starts inside the wall's boundary cell, on the
    first cell layer with the local gas velocity.

    Returns one dict per d_a: linewidth_um, overspray_um, b_um, fractions
    landed/wall/escaped/stalled, steps.
    """
    g = geometry or load_geometry()
    p = params or load_cfd_parameters()
    grid = VelocityGrid(cells, g, spec.nozzle_deposition_um)
    sigma = np.sqrt(np.log1p(p.droplet_cv**2))
    z, u = droplet_sample(n_droplets, seed)
    medians = np.asarray(droplet_diameters_um, dtype=float)
    diam_um = (medians[:, None] * np.exp(sigma * z)[None, :]).ravel()
    start = np.tile(0.98 * g.carrier_radius * np.sqrt(u), medians.size)
    t0 = time.perf_counter()
    # start on the first cell layer, where the solved inflow is (not the interpolated plane)
    tracked = track_droplets(
        grid, units.um_to_m(diam_um), start, p, g.gas_density, start_x=float(cells.x.min())
    )
    track_s = time.perf_counter() - t0
    rows = []
    for k, d_a in enumerate(medians):
        part = slice(k * n_droplets, (k + 1) * n_droplets)
        status = tracked.status[part]
        ok = status == LANDED
        fractions = {
            name: float(np.mean(status == code))
            for code, name in ((1, "landed"), (2, "wall"), (3, "escaped"), (4, "stalled"))
        }
        row = {
            "droplet_diameter_um": float(d_a),
            **{f"fraction_{k2}": v for k2, v in fractions.items()},
        }
        if ok.sum() < 50:
            row.update(
                {
                    "linewidth_um": np.nan,
                    "overspray_um": np.nan,
                    "b_um": np.nan,
                    "error": f"only {int(ok.sum())} of {n_droplets} droplets landed",
                }
            )
        else:
            y, h = height_profile(
                units.m_to_um(tracked.landing_radius[part][ok]),
                diam_um[part][ok],
                spread_factor=p.droplet_spread_factor,
                azimuths=azimuths,
                seed=seed,
            )
            metrics = line_metrics(y, h, p.peak_fraction, p.width_ratio, p.edge_fraction)
            row.update(metrics)
            row["landing_radius_median_um"] = float(
                np.median(units.m_to_um(tracked.landing_radius[part][ok]))
            )
        row["tracking_s_shared"] = track_s
        row["tracking_steps"] = tracked.steps
        rows.append(row)
    return rows


def run_case(
    spec: CaseSpec,
    case_dir: str | Path,
    droplet_diameters_um=(3.5,),
    n_droplets: int = 3000,
    azimuths: int = 32,
    geometry: Geometry | None = None,
    params: CfdParameters | None = None,
    force: bool = False,
) -> dict:
    """Gas solve (skipped if ``flow.json`` exists) + droplets; writes ``result.json``.

    Returns the result dict: ``flow`` (summary), ``droplets`` (one row per d_a),
    ``wall_time_s``, ``finished`` (UTC ISO time).
    """
    case_dir = Path(case_dir)
    result_path = case_dir / "result.json"
    if result_path.exists() and not force:
        return json.loads(result_path.read_text())
    g = geometry or load_geometry()
    p = params or load_cfd_parameters()
    start = time.perf_counter()
    flow_path = case_dir / "flow.json"
    if flow_path.exists() and (case_dir / "flow.npz").exists() and not force:
        flow = json.loads(flow_path.read_text())
        flow["converged"] = bool(flow["final_residual_u"] < CONVERGED_RESIDUAL)
        if not flow["converged"]:
            raise RuntimeError(f"{case_dir}: stored gas solve did not converge")
    else:
        flow = solve_gas(spec, case_dir, g, p)
    cells = CellField.load(case_dir / "flow.npz")
    droplets = evaluate_droplets(cells, spec, droplet_diameters_um, n_droplets, azimuths, g, p)
    result = {
        "case": spec.name,
        "spec": asdict(spec),
        "flow": flow,
        "droplets": droplets,
        "n_droplets": n_droplets,
        "azimuths": azimuths,
        "wall_time_s": time.perf_counter() - start,
        "finished": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    tmp = result_path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2, default=float))
    tmp.replace(result_path)
    return result
