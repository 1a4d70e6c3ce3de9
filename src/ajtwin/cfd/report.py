"""Sweep metadata and the validation figures the issue asks for (paper §6.2, App. C, D)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.cfd.fit import (
    COEFFICIENT_KEYS,
    fit_output_model,
    fit_settings,
    predict,
    sensitivity_signs,
)


def sweep_metadata(sweep_dir: str | Path, table: pd.DataFrame) -> dict:
    """Design, mesh, OpenFOAM version, wall time and cell count of a finished sweep."""
    sweep_dir = Path(sweep_dir)
    meta_path = sweep_dir / "sweep.json"
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    runs = meta.get("runs", [])
    meta["wall_time_s"] = float(sum(r.get("wall_time_s", 0.0) for r in runs)) or meta.get(
        "wall_time_s", 0.0
    )
    ok = table[table["status"] == "ok"]
    if "nominal" not in meta:
        meta["nominal"] = [0.0, 23.0, 50.0]
    nominal = ok[
        np.isclose(ok["nozzle_deposition_um"], meta["nominal"][0])
        & np.isclose(ok["carrier_flow_sccm"], meta["nominal"][1])
        & np.isclose(ok["sheath_flow_sccm"], meta["nominal"][2])
    ]
    meta["cells"] = int(nominal["cells"].iloc[0]) if len(nominal) else 0
    meta["mesh_level"] = int(ok["mesh_level"].iloc[0]) if len(ok) else meta.get("mesh_level", 0)
    meta["openfoam_version"] = "unknown"
    for flow_json in sorted(sweep_dir.glob("*/flow.json")):
        meta["openfoam_version"] = json.loads(flow_json.read_text()).get(
            "openfoam_version", "unknown"
        )
        break
    return meta


def case_value(
    table: pd.DataFrame,
    column: str,
    deposition: float,
    carrier: float,
    sheath: float,
    droplet: float | None = None,
) -> float:
    """One value of the summary table (NaN when the case is absent or failed)."""
    sel = (
        (table["status"] == "ok")
        & np.isclose(table["nozzle_deposition_um"], deposition)
        & np.isclose(table["carrier_flow_sccm"], carrier)
        & np.isclose(table["sheath_flow_sccm"], sheath)
    )
    if droplet is not None:
        sel &= np.isclose(table["droplet_diameter_um"], droplet)
    rows = table[sel]
    return float(rows[column].iloc[0]) if len(rows) else float("nan")


def validation(table: pd.DataFrame, fit: dict, resistance: dict) -> dict:
    """The issue's validation figures from one sweep (display units); the paper's
    reference points come from ``[paper_reference]`` in sweep.toml."""

    paper = fit_settings()["paper_reference"]
    return {
        "max_speed_m_s_25_50": case_value(table, "max_speed_m_s", 0.0, 25.0, 50.0),
        "paper_max_speed_m_s_25_50": paper["max_speed_m_s_25_50"],
        "tip_resistance_a0_pa_s_m3": resistance["cfd_a0_pa_s_m3"],
        "tip_resistance_a1_pa_s_m3_per_um": resistance["cfd_a1_pa_s_m3_per_um"],
        "paper_a0_pa_s_m3": resistance["paper_a0_pa_s_m3"],
        "paper_a1_pa_s_m3_per_um": resistance["paper_a1_pa_s_m3_per_um"],
        "linewidth_um_23_50_da3.5": case_value(table, "linewidth_um", 0.0, 23.0, 50.0, 3.5),
        "overspray_um_23_50_da3.5": case_value(table, "overspray_um", 0.0, 23.0, 50.0, 3.5),
        "paper_linewidth_um": paper["linewidth_um"],
        "model_linewidth_um_23_50_da3.5": float(
            predict(fit["linewidth"], 3.5, 0.0, 23.0, 50.0, fit["anchor_aerosol_fraction"])
        ),
        "signs": sensitivity_signs(fit),
    }


def matched_rows(a: pd.DataFrame, b: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Rows of two sweeps at the same (ΔR_N, Q_c, Q_s, d_a), both usable, same order."""
    keys = ["nozzle_deposition_um", "carrier_flow_sccm", "sheath_flow_sccm", "droplet_diameter_um"]

    def keyed(t):
        t = t[t["status"] == "ok"].copy()
        t["_key"] = list(zip(*(t[k].round(6) for k in keys), strict=True))
        return t.set_index("_key")

    ka, kb = keyed(a), keyed(b)
    common = sorted(set(ka.index) & set(kb.index))
    return ka.loc[common].reset_index(drop=True), kb.loc[common].reset_index(drop=True)


def mesh_comparison(
    coarse: pd.DataFrame,
    fine: pd.DataFrame,
    reference: dict,
    max_speed_m_s: float | None = None,
    droplet_range_um: tuple[float, float] | None = None,
) -> dict:
    """Coefficients fitted to the same cases on two meshes, and their change."""

    a, b = matched_rows(coarse, fine)
    fit_a = fit_output_model(a, reference, max_speed_m_s, droplet_range_um)
    fit_b = fit_output_model(b, reference, max_speed_m_s, droplet_range_um)
    out = {
        "rows": len(a),
        "cells_coarse": int(a["cells"].max()),
        "cells_fine": int(b["cells"].max()),
    }
    for output in ("linewidth", "overspray"):
        out[output] = {
            key: {
                "coarse": fit_a[output][key],
                "fine": fit_b[output][key],
                "change": fit_b[output][key] - fit_a[output][key],
            }
            for key in COEFFICIENT_KEYS
            if key != "aerosol_fraction"
        }
        column = f"{output}_um"
        out[output]["mean_abs_case_change_um"] = float(np.mean(np.abs(b[column] - a[column])))
        out[output]["mean_case_change_um"] = float(np.mean(b[column] - a[column]))
    for column in ("max_speed_m_s", "tip_resistance_pa_s_m3"):
        rel = (b[column] - a[column]) / a[column]
        out[f"{column}_max_rel_change"] = float(np.max(np.abs(rel)))
    return out


def plot_nominal_line(tables: dict[str, pd.DataFrame], path, nominal=(0.0, 23.0, 50.0)):
    """Figure: L_w, L_o and median landing radius vs d_a at the nominal case, one line
    per sweep (e.g. per mesh level). Returns the written path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = (
        ("linewidth_um", "linewidth L_w [µm]"),
        ("overspray_um", "overspray L_o [µm]"),
        ("landing_radius_median_um", "median landing radius [µm]"),
    )
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), constrained_layout=True)
    for label, table in tables.items():
        ok = table[
            (table["status"] == "ok")
            & np.isclose(table["nozzle_deposition_um"], nominal[0])
            & np.isclose(table["carrier_flow_sccm"], nominal[1])
            & np.isclose(table["sheath_flow_sccm"], nominal[2])
        ].sort_values("droplet_diameter_um")
        if ok.empty:
            raise ValueError(f"sweep {label!r} has no finished nominal case {nominal}")
        for ax, (column, name) in zip(axes, columns, strict=True):
            ax.plot(ok["droplet_diameter_um"], ok[column], "o-", label=label)
            ax.set_xlabel("median droplet diameter d_a [µm]")
            ax.set_ylabel(name)
    axes[0].legend()
    fig.suptitle(
        f"CFD line at ΔR_N = {nominal[0]:g} µm, Q_c = {nominal[1]:g} sccm, "
        f"Q_s = {nominal[2]:g} sccm"
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
