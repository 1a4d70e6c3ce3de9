"""Parallel, resumable CFD sweep through Dask (model reference §8).

Each gas case (ΔR_N, Q_c, Q_s) is one Dask task: OpenFOAM solve, then every
droplet median d_a tracked on that one flow field. Cases whose ``result.json``
exists are skipped (resume); a failing case is recorded in the summary with its
error and the sweep carries on. The summary table (one row per case and d_a)
is written after every finished case, so nothing is lost if the sweep stops.

Examples
--------
>>> design = load_design("smoke")
>>> [c.name for c in design.cases]
['dRN0.000_Qc23.00_Qs50.00_m1']
"""

from __future__ import annotations

import json
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
from tqdm import tqdm

from ajtwin.cfd import foam
from ajtwin.cfd.case import CaseSpec
from ajtwin.cfd.run import run_case
from ajtwin.config import load_toml

SUMMARY_NAME = "summary.csv"
SWEEP_META = "sweep.json"


@dataclass
class Design:
    """A named sweep design of ``sweep.toml``: the cases and how droplets are tracked.

    Attributes
    ----------
    name, description : str
    cases : list of CaseSpec
    droplet_diameters_um : list of float
        Droplet sizes tracked on every case [µm].
    n_droplets, azimuths : int
        Droplets per size, and azimuthal copies of each.
    nominal : (float, float, float)
        The nominal (ΔR_N [µm], Q_c, Q_s [sccm]).
    mesh_level : int
    extra : dict
    """

    name: str
    description: str
    cases: list[CaseSpec]
    droplet_diameters_um: list[float]
    n_droplets: int
    azimuths: int
    nominal: tuple[float, float, float]
    mesh_level: int
    extra: dict = field(default_factory=dict)


def load_design(name: str, path: str | Path | None = None, mesh_level: int | None = None) -> Design:
    """A named sweep design from ``sweep.toml`` (or ``path``); ``mesh_level`` overrides."""
    designs = load_toml(path, "cfd/sweep.toml", what="sweep").get("designs", {})
    if name not in designs:
        raise ValueError(f"unknown sweep design {name!r}; known: {', '.join(sorted(designs))}")
    d = designs[name]
    level = int(mesh_level or d["mesh_level"])
    cases = []
    for i, row in enumerate(d["cases"]):
        if len(row) != 3:
            raise ValueError(f"design {name!r} case {i}: need [ΔR_N, Q_c, Q_s], got {row!r}")
        cases.append(CaseSpec(float(row[0]), float(row[1]), float(row[2]), mesh_level=level))
    return Design(
        name=name,
        description=d.get("description", ""),
        cases=cases,
        droplet_diameters_um=[float(v) for v in d["droplet_diameters_um"]],
        n_droplets=int(d["n_droplets"]),
        azimuths=int(d["azimuths"]),
        nominal=tuple(float(v) for v in d["nominal"]),
        mesh_level=level,
    )


def _case_task(
    spec_fields: dict, case_dir: str, diameters: list[float], n_droplets: int, azimuths: int
) -> dict:
    """Worker side: run one case; never raises (errors come back as data)."""

    spec = CaseSpec(**spec_fields)
    start = time.perf_counter()
    try:
        result = run_case(spec, case_dir, diameters, n_droplets, azimuths)
        result["status"] = "ok"
        return result
    except Exception as exc:  # recorded, the sweep goes on
        failure = {
            "case": spec.name,
            "spec": spec_fields,
            "status": "failed",
            "error": f"{type(exc).__name__}: {exc}",
            "traceback": traceback.format_exc(),
            "wall_time_s": time.perf_counter() - start,
        }
        Path(case_dir).mkdir(parents=True, exist_ok=True)
        (Path(case_dir) / "failed.json").write_text(json.dumps(failure, indent=2))
        return failure


def summary_rows(result: dict) -> list[dict]:
    """Flatten one case result into table rows (one per d_a; one row if it failed)."""
    spec = result["spec"]
    base = {
        "case": result["case"],
        "nozzle_deposition_um": spec["nozzle_deposition_um"],
        "carrier_flow_sccm": spec["carrier_flow_sccm"],
        "sheath_flow_sccm": spec["sheath_flow_sccm"],
        "mesh_level": spec["mesh_level"],
        "status": result.get("status", "ok"),
        "case_wall_time_s": result.get("wall_time_s"),
    }
    if base["status"] != "ok":
        return [{**base, "error": result.get("error", "")}]
    flow = result["flow"]
    base.update(
        {
            "cells": flow["cells"],
            "converged": flow["converged"],
            "final_residual_u": flow["final_residual_u"],
            "max_speed_m_s": flow["max_speed_m_s"],
            "carrier_inlet_pressure_pa": flow["carrier_inlet_pressure_pa"],
            "sheath_inlet_pressure_pa": flow["sheath_inlet_pressure_pa"],
            "tip_resistance_pa_s_m3": flow["tip_resistance_pa_s_m3"],
            "simpleFoam_s": flow["timings"]["simpleFoam_s"],
        }
    )
    rows = []
    for drop in result["droplets"]:
        row = dict(base)
        for key in (
            "droplet_diameter_um",
            "linewidth_um",
            "overspray_um",
            "b_um",
            "overspray_left_um",
            "overspray_right_um",
            "fraction_landed",
            "fraction_wall",
            "fraction_escaped",
            "fraction_stalled",
            "landing_radius_median_um",
        ):
            row[key] = drop.get(key)
        if drop.get("error"):
            row["status"] = "no-line"
            row["error"] = drop["error"]
        rows.append(row)
    return rows


def write_summary(results: list[dict], root: Path) -> pd.DataFrame:
    """Write ``summary.csv`` (one row per case and droplet size, sorted); the table."""
    rows = [row for result in results for row in summary_rows(result)]
    table = pd.DataFrame(rows)
    if not table.empty:
        table = table.sort_values(
            ["nozzle_deposition_um", "carrier_flow_sccm", "sheath_flow_sccm"]
            + (["droplet_diameter_um"] if "droplet_diameter_um" in table else [])
        )
    table.to_csv(root / SUMMARY_NAME, index=False, float_format="%.6g")
    return table


def run_sweep(
    design: Design,
    root: str | Path,
    scheduler: str | None = None,
    workers: int = 2,
    progress: bool = True,
    retry_failed: bool = True,
) -> pd.DataFrame:
    """Run (or resume) a sweep; returns the summary table (also ``root/summary.csv``).

    Parameters
    ----------
    design : Design
    root : path
        Sweep directory; one sub-directory per gas case.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:8786``); default: a
        local cluster of ``workers`` processes with one thread each.
    workers : int
        Local workers when no scheduler is given.
    progress : bool
        Show a tqdm bar.
    retry_failed : bool
        Re-run cases that failed before (their ``failed.json`` is replaced).
    """
    from dask.distributed import Client, LocalCluster, as_completed

    foam.foam_environment()  # fail early and clearly without OpenFOAM
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    results, todo = [], []
    for spec in design.cases:
        case_dir = root / spec.name
        done = case_dir / "result.json"
        failed = case_dir / "failed.json"
        if done.exists():
            result = json.loads(done.read_text())
            result["status"] = "ok"
            results.append(result)
        elif failed.exists() and not retry_failed:
            results.append(json.loads(failed.read_text()))
        else:
            todo.append(spec)
    meta = {
        "design": design.name,
        "description": design.description,
        "mesh_level": design.mesh_level,
        "droplet_diameters_um": design.droplet_diameters_um,
        "n_droplets": design.n_droplets,
        "azimuths": design.azimuths,
        "nominal": design.nominal,
        "cases": len(design.cases),
        "skipped_finished": len(design.cases) - len(todo),
    }
    if todo:
        cluster = None
        if scheduler:
            client = Client(scheduler)
        else:
            cluster = LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0"
            )
            client = Client(cluster)
        try:
            futures = [
                client.submit(
                    _case_task,
                    {
                        k: getattr(s, k)
                        for k in (
                            "nozzle_deposition_um",
                            "carrier_flow_sccm",
                            "sheath_flow_sccm",
                            "mesh_level",
                            "max_iterations",
                        )
                    },
                    str(root / s.name),
                    design.droplet_diameters_um,
                    design.n_droplets,
                    design.azimuths,
                    key=f"cfd-{s.name}",
                    pure=False,
                )
                for s in todo
            ]
            bar = tqdm(
                total=len(futures),
                desc=f"cfd sweep {design.name}",
                disable=not progress,
                unit="case",
            )
            for future in as_completed(futures):
                result = future.result()
                results.append(result)
                bar.set_postfix_str(f"{result['case']} {result['status']}")
                bar.update()
                write_summary(results, root)
            bar.close()
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    meta["wall_time_s"] = time.perf_counter() - start
    meta["failed"] = [r["case"] for r in results if r.get("status") != "ok"]
    previous = root / SWEEP_META
    if previous.exists():  # keep the history of runs (resumes add wall time)
        old = json.loads(previous.read_text())
        meta["runs"] = old.get("runs", []) + [
            {"wall_time_s": meta["wall_time_s"], "ran": len(todo)}
        ]
    else:
        meta["runs"] = [{"wall_time_s": meta["wall_time_s"], "ran": len(todo)}]
    previous.write_text(json.dumps(meta, indent=2))
    return write_summary(results, root)
