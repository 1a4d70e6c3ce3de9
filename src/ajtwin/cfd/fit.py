"""Fit the output-model coefficients and R_3^N(ΔR_N) to a CFD sweep (model reference §5, §8).

The output model (paper eqs. 14–15) with independent effects,

    L = α^da d_a + α^φ φ_A + α^N1 ΔR_N + α^N2 ΔR_N² + α^N3 ΔR_N³ + β^c Q_c + β^s Q_s + γ,

is fitted by least squares to every (case, d_a) row of the sweep. A one-way
coupled CFD cannot see φ_A (droplets do not change the flow), so α^φ is kept
from the reference (provisional) file, and γ absorbs α^φ φ_A0 at the reference
aerosol fraction φ_A0: the fitted model reproduces the CFD at φ_A = φ_A0.

The nozzle-tip resistance R_3^N(ΔR_N) = (p_cone entry − p_ambient)/(Q_c + Q_s)
at the nominal flows is fitted by a cubic in ΔR_N [µm] and set against the
paper's polynomial.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import tomli_w

from ajtwin.cfd.physics import load_cfd_parameters
from ajtwin.config import load_toml

#: The schema the twin reads (ajtwin.model.parameters.Coefficients).
COEFFICIENT_KEYS = (
    "droplet_diameter",
    "aerosol_fraction",
    "nozzle_deposition_1",
    "nozzle_deposition_2",
    "nozzle_deposition_3",
    "carrier_flow",
    "sheath_flow",
    "offset",
)
_OUTPUT_COLUMN = {"linewidth": "linewidth_um", "overspray": "overspray_um"}


def fit_settings(path: str | Path | None = None) -> dict:
    """Fit settings from ``sweep.toml``: the droplet window of the linear d_a term
    (``[fit]``) and the paper's reference points (``[paper_reference]``)."""
    doc = load_toml(path, "cfd/sweep.toml", what="sweep")
    settings = doc.get("fit", {})
    lo, hi = (float(v) for v in settings.get("droplet_range_um", (0.0, np.inf)))
    if not 0.0 <= lo < hi:
        raise ValueError(f"[fit] droplet_range_um must be 0 ≤ low < high, got {lo}, {hi}")
    paper = {k: float(v["value"]) for k, v in doc.get("paper_reference", {}).items()}
    return {"droplet_range_um": (lo, hi), "paper_reference": paper}


def _usable(
    table: pd.DataFrame,
    column: str,
    max_speed_m_s: float | None = None,
    droplet_range_um: tuple[float, float] | None = None,
):
    """Finished, converged rows with a finite ``column``, peak gas speed ≤ the limit and
    d_a inside ``droplet_range_um`` (inclusive)."""
    ok = table[(table["status"] == "ok") & np.isfinite(table[column].astype(float))]
    if droplet_range_um is not None:
        lo, hi = droplet_range_um
        d = ok["droplet_diameter_um"].astype(float)
        ok = ok[(d >= lo - 1e-9) & (d <= hi + 1e-9)]
    if "converged" in ok:
        ok = ok[ok["converged"].astype(bool)]
    if max_speed_m_s is not None:
        ok = ok[ok["max_speed_m_s"].astype(float) <= max_speed_m_s]
    return ok


def excluded_cases(table: pd.DataFrame, max_speed_m_s: float | None) -> list[str]:
    """Cases left out of the fits: failed, not converged, or faster than the limit."""
    cases = table.groupby("case").first()
    bad = cases["status"] != "ok"
    if "converged" in cases:
        bad |= ~cases["converged"].fillna(False).astype(bool)
    if max_speed_m_s is not None and "max_speed_m_s" in cases:
        bad |= ~(cases["max_speed_m_s"].astype(float) <= max_speed_m_s)
    return sorted(cases.index[bad])


def design_matrix(frame: pd.DataFrame) -> np.ndarray:
    """Columns: d_a, ΔR_N, ΔR_N², ΔR_N³, Q_c, Q_s, 1 (display units)."""
    dr = frame["nozzle_deposition_um"].to_numpy(float)
    return np.column_stack(
        [
            frame["droplet_diameter_um"].to_numpy(float),
            dr,
            dr**2,
            dr**3,
            frame["carrier_flow_sccm"].to_numpy(float),
            frame["sheath_flow_sccm"].to_numpy(float),
            np.ones(len(frame)),
        ]
    )


def fit_output_model(
    table: pd.DataFrame,
    reference: dict,
    max_speed_m_s: float | None = None,
    droplet_range_um: tuple[float, float] | None = None,
) -> dict:
    """Least-squares output-model coefficients for linewidth and overspray.

    Parameters
    ----------
    table : DataFrame
        The sweep summary (one row per case and d_a).
    reference : dict
        A coefficient file as read by tomllib (supplies α^φ and φ_A0).
    max_speed_m_s : float, optional
        Leave out cases whose peak gas speed exceeds this (compressible tip flow).
    droplet_range_um : (float, float), optional
        Fit only rows with d_a in this window [µm]. The model is linear in d_a, so
        it is fitted where the twin's d_a lives (``[fit]`` in sweep.toml: 3.5 ± 0.5
        µm); over 2–4.5 µm the CFD linewidth is not monotonic in d_a.

    Returns
    -------
    dict
        ``{"linewidth": {...}, "overspray": {...}}`` with the eight schema keys,
        plus per output ``rms_um``, ``r2``, ``rows``, ``max_abs_residual_um``.
    """
    alpha_phi_used = any(float(reference[o]["aerosol_fraction"]) for o in _OUTPUT_COLUMN)
    anchor = reference.get("derivation", {}).get("anchor_aerosol_fraction")
    if anchor is None and alpha_phi_used:
        raise ValueError(
            "the reference coefficient file has no [derivation] anchor_aerosol_fraction "
            "(phi_A0), needed to move alpha^phi * phi_A0 into the offset"
        )
    anchor_fraction = float(anchor or 0.0)
    out = {}
    for output, column in _OUTPUT_COLUMN.items():
        rows = _usable(table, column, max_speed_m_s, droplet_range_um)
        if len(rows) < 8:
            raise ValueError(f"only {len(rows)} usable rows for {output}; need ≥ 8 to fit 7 terms")
        a = design_matrix(rows)
        y = rows[column].to_numpy(float)
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        residual = y - a @ coef
        alpha_phi = float(reference[output]["aerosol_fraction"])
        out[output] = {
            "droplet_diameter": float(coef[0]),
            "aerosol_fraction": alpha_phi,
            "nozzle_deposition_1": float(coef[1]),
            "nozzle_deposition_2": float(coef[2]),
            "nozzle_deposition_3": float(coef[3]),
            "carrier_flow": float(coef[4]),
            "sheath_flow": float(coef[5]),
            "offset": float(coef[6] - alpha_phi * anchor_fraction),
            "rms_um": float(np.sqrt(np.mean(residual**2))),
            "max_abs_residual_um": float(np.max(np.abs(residual))),
            "r2": float(1.0 - np.sum(residual**2) / np.sum((y - y.mean()) ** 2)),
            "rows": int(len(rows)),
        }
    out["anchor_aerosol_fraction"] = anchor_fraction
    out["max_speed_m_s"] = max_speed_m_s
    out["droplet_range_um"] = None if droplet_range_um is None else list(droplet_range_um)
    out["excluded_cases"] = excluded_cases(table, max_speed_m_s)
    return out


def predict(
    coefficients: dict,
    droplet_um,
    nozzle_deposition_um,
    carrier_sccm,
    sheath_sccm,
    aerosol_fraction: float,
) -> np.ndarray:
    """Evaluate one output of the §5 model (display units)."""
    c = coefficients
    dr = np.asarray(nozzle_deposition_um, dtype=float)
    return (
        c["droplet_diameter"] * np.asarray(droplet_um)
        + c["aerosol_fraction"] * aerosol_fraction
        + c["nozzle_deposition_1"] * dr
        + c["nozzle_deposition_2"] * dr**2
        + c["nozzle_deposition_3"] * dr**3
        + c["carrier_flow"] * np.asarray(carrier_sccm)
        + c["sheath_flow"] * np.asarray(sheath_sccm)
        + c["offset"]
    )


def fit_tip_resistance(
    table: pd.DataFrame,
    nominal: tuple[float, float, float],
    degree: int = 3,
    max_speed_m_s: float | None = None,
) -> dict:
    """Cubic R_3^N(ΔR_N) [Pa s/m³, ΔR_N in µm] at the nominal flows, vs the paper's polynomial.

    Cases faster than ``max_speed_m_s`` (compressible tip flow) are left out of the
    fit but listed, with their values, under ``excluded_*``.
    """
    _, qc, qs = nominal
    at_nominal = table[
        (table["status"] == "ok")
        & np.isclose(table["carrier_flow_sccm"], qc)
        & np.isclose(table["sheath_flow_sccm"], qs)
    ]
    if "converged" in at_nominal:
        at_nominal = at_nominal[at_nominal["converged"].astype(bool)]
    fast = (
        at_nominal["max_speed_m_s"].astype(float) > max_speed_m_s
        if max_speed_m_s is not None
        else np.zeros(len(at_nominal), dtype=bool)
    )
    rows = at_nominal[~fast]
    excluded = (
        at_nominal[fast]
        .groupby("nozzle_deposition_um")[["tip_resistance_pa_s_m3", "max_speed_m_s"]]
        .first()
    )
    per_case = rows.groupby("nozzle_deposition_um")["tip_resistance_pa_s_m3"].first()
    dr = per_case.index.to_numpy(float)
    r = per_case.to_numpy(float)
    if dr.size < degree + 1:
        raise ValueError(f"{dr.size} ΔR_N levels at {qc}/{qs} sccm; need ≥ {degree + 1}")
    coef = np.polynomial.polynomial.polyfit(dr, r, degree)
    paper = np.asarray(load_cfd_parameters().nozzle_tip_resistance_poly)
    paper_at = np.polynomial.polynomial.polyval(dr, paper)
    slope0 = float(coef[1])
    return {
        "carrier_flow_sccm": qc,
        "sheath_flow_sccm": qs,
        "nozzle_deposition_um": dr.tolist(),
        "cfd_resistance_pa_s_m3": r.tolist(),
        "paper_polynomial_at_levels_pa_s_m3": paper_at.tolist(),
        "fit_degree": degree,
        "fit_coefficients": coef.tolist(),
        "fit_rms_pa_s_m3": float(
            np.sqrt(np.mean((np.polynomial.polynomial.polyval(dr, coef) - r) ** 2))
        ),
        "cfd_a0_pa_s_m3": float(coef[0]),
        "cfd_a1_pa_s_m3_per_um": slope0,
        "paper_a0_pa_s_m3": float(paper[0]),
        "paper_a1_pa_s_m3_per_um": float(paper[1]),
        "a0_ratio_cfd_to_paper": float(coef[0] / paper[0]),
        "a1_ratio_cfd_to_paper": float(slope0 / paper[1]),
        "max_speed_m_s_limit": max_speed_m_s,
        "excluded_nozzle_deposition_um": excluded.index.to_numpy(float).tolist(),
        "excluded_resistance_pa_s_m3": excluded["tip_resistance_pa_s_m3"].tolist(),
        "excluded_max_speed_m_s": excluded["max_speed_m_s"].tolist(),
    }


def sensitivity_signs(fit: dict) -> dict:
    """The signs the issue expects, checked on the fitted linewidth coefficients."""
    lw = fit["linewidth"]
    nozzle_slope_small = lw["nozzle_deposition_1"]
    return {
        "linewidth_up_with_carrier": lw["carrier_flow"] > 0,
        "linewidth_down_with_sheath": lw["sheath_flow"] < 0,
        "linewidth_down_with_droplet": lw["droplet_diameter"] < 0,
        "linewidth_up_with_nozzle_deposition": nozzle_slope_small > 0,
    }


def coefficient_document(fit: dict, meta: dict) -> dict:
    """The TOML document (schema of ajtwin/data/output_coefficients.toml) for a fit."""
    created = datetime.now(UTC).date().isoformat()
    doc = {
        "format_version": 1,
        "status": "fitted-cfd",
        "provenance": (
            f"fitted by `ajtwin cfd fit` to the OpenFOAM {meta.get('openfoam_version', '?')} "
            f"sweep '{meta.get('design', '?')}' (simpleFoam laminar, axisymmetric wedge, mesh "
            f"level {meta.get('mesh_level', '?')}, {meta.get('cells', '?')} cells; droplets by "
            "the ajtwin Python tracker with Cunningham slip); aerosol_fraction kept from the "
            "provisional file because a one-way coupled CFD cannot see phi_A"
        ),
        "created": created,
        "cfd": {
            "engine": "OpenFOAM (Debian openfoam package)",
            "engine_version": meta.get("openfoam_version", "unknown"),
            "solver": "simpleFoam, laminar, steady, incompressible N2",
            "droplet_tracker": "ajtwin.cfd.tracker (Stokes drag x Schiller-Naumann, "
            "Cunningham slip, gravity; exponential integrator)",
            "mesh_level": int(meta.get("mesh_level", 0)),
            "cells_nominal_case": int(meta.get("cells", 0)),
            "geometry": "ajtwin/cfd/geometry.toml",
            "sweep_design": meta.get("design", "?"),
            "summary_table": str(meta.get("summary_table", "summary.csv")),
            "sweep_cases": int(meta.get("cases", 0)),
            "sweep_rows_used": int(fit["linewidth"]["rows"]),
            "droplet_diameters_um": list(meta.get("droplet_diameters_um", [])),
            "droplets_per_case_and_size": int(meta.get("n_droplets", 0)),
            "sweep_wall_time_s": float(meta.get("wall_time_s", 0.0)),
            "fit_date": created,
            "fit_max_gas_speed_m_s": fit.get("max_speed_m_s") or 0.0,
            "fit_droplet_range_um": list(fit.get("droplet_range_um") or []),
            "fit_excluded_cases": list(fit.get("excluded_cases", [])),
            "linewidth_fit_rms_um": fit["linewidth"]["rms_um"],
            "overspray_fit_rms_um": fit["overspray"]["rms_um"],
            "linewidth_fit_r2": fit["linewidth"]["r2"],
            "overspray_fit_r2": fit["overspray"]["r2"],
            "aerosol_fraction_note": (
                "aerosol_fraction (alpha^phi) is the provisional value: droplets do not change "
                "the gas flow in a one-way coupled CFD, so the sweep holds no phi_A information; "
                f"offset = CFD intercept - alpha^phi * {fit['anchor_aerosol_fraction']:.6g} "
                "(the provisional anchor phi_A0)"
            ),
            "post_processing": "random azimuth, line summation, spread 3.8, b at 80 % of peak, "
            "L_w = 2.1 b, overspray to 1 % of h at each linewidth edge "
            "(model reference §8)",
        },
    }
    for output in ("linewidth", "overspray"):
        doc[output] = {key: fit[output][key] for key in COEFFICIENT_KEYS}
    return doc


def write_toml(document: dict, path: str | Path) -> Path:
    """Write a TOML document (tomli-w), creating the folder; the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(tomli_w.dumps(document))
    return path


def resistance_document(resistance: dict, meta: dict) -> dict:
    """TOML document of the R_3^N(ΔR_N) fit with its comparison to the paper."""
    created = datetime.now(UTC).date().isoformat()
    return {
        "format_version": 1,
        "status": "fitted-cfd",
        "created": created,
        "description": (
            "Nozzle-tip resistance R_3^N(ΔR_N) = (p at the cone entry - p ambient)/(Q_c + Q_s) "
            "from the OpenFOAM sweep at the nominal flows; cubic in ΔR_N [µm], Pa s/m3. "
            "For comparison only: the twin keeps the paper's polynomial (parameters.toml)."
        ),
        "provenance": (
            f"ajtwin cfd fit, OpenFOAM {meta.get('openfoam_version', '?')} sweep "
            f"'{meta.get('design', '?')}', mesh level {meta.get('mesh_level', '?')}"
        ),
        "unit": "Pa*s/m3",
        "deposition_unit": "um",
        **{k: v for k, v in resistance.items()},
    }
