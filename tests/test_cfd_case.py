"""Geometry, case generation, droplet tracking on synthetic fields, and the fit (no OpenFOAM)."""

import copy
import math
import re

import numpy as np
import pandas as pd
import pytest

from ajtwin import units
from ajtwin.cfd.case import CaseSpec, block_mesh_dict, inlet_velocities, write_case
from ajtwin.cfd.fit import (
    coefficient_document,
    fit_output_model,
    fit_tip_resistance,
    predict,
    sensitivity_signs,
    write_toml,
)
from ajtwin.cfd.flowfield import CellField, VelocityGrid
from ajtwin.cfd.geometry import load_geometry
from ajtwin.cfd.physics import load_cfd_parameters
from ajtwin.cfd.tracker import LANDED, WALL, track_droplets


@pytest.fixture(scope="module")
def geometry():
    return load_geometry()


def test_geometry_matches_parameters_and_moves_tip_walls(geometry):
    params = load_cfd_parameters()
    assert geometry.tip_radius == pytest.approx(params.nozzle_radius)
    assert geometry.standoff == pytest.approx(2e-3)  # paper: substrate 2 mm below
    tip = geometry.tip_radius_at(7.5)
    assert tip == pytest.approx(67.5e-6)
    # bore and cone end move in; the chamber does not
    assert geometry.wall_radius(geometry.exit_x - 1e-6, 7.5) == pytest.approx(tip)
    assert geometry.wall_radius(geometry.cone_x - 1e-6, 7.5) == pytest.approx(
        geometry.chamber_radius
    )
    mid = geometry.cone_x + 0.5 * geometry.cone_length
    assert geometry.wall_radius(mid, 0.0) == pytest.approx(
        0.5 * (geometry.chamber_radius + geometry.tip_radius)
    )


def test_inside_fluid_excludes_walls(geometry):
    g = geometry
    assert g.inside_fluid(1e-4, 0.0)
    assert not g.inside_fluid(1e-4, g.carrier_radius + 0.5 * g.carrier_wall)  # aerosol-tube wall
    assert not g.inside_fluid(g.exit_x - 1e-5, g.tip_radius * 1.01)  # nozzle body
    assert g.inside_fluid(g.exit_x + 1e-5, g.tip_radius * 1.5)  # gap below the nozzle
    assert not g.inside_fluid(g.substrate_x + 1e-6, 0.0)
    assert g.inside_fluid(g.exit_x - 1e-5, -0.5 * g.tip_radius)  # mirror side


@pytest.mark.parametrize("bad", [-1.0, np.nan, 70.0])
def test_bad_nozzle_deposition_is_rejected(geometry, bad):
    with pytest.raises(ValueError, match="nozzle deposition"):
        geometry.tip_radius_at(bad)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"carrier_flow_sccm": 0.0},
        {"sheath_flow_sccm": np.nan},
        {"nozzle_deposition_um": -2.0},
        {"mesh_level": 0},
    ],
)
def test_case_spec_validates(kwargs):
    base = {"nozzle_deposition_um": 0.0, "carrier_flow_sccm": 23.0, "sheath_flow_sccm": 50.0}
    with pytest.raises(ValueError):
        CaseSpec(**{**base, **kwargs})


def test_inlet_velocities_carry_the_flows(geometry):
    spec = CaseSpec(0.0, 23.0, 50.0)
    v = inlet_velocities(geometry, spec)
    carrier = v["carrierInlet"][0] * math.pi * geometry.carrier_radius**2
    tube_out = geometry.carrier_radius + geometry.carrier_wall
    sheath = v["sheathInlet"][0] * math.pi * (geometry.chamber_radius**2 - tube_out**2)
    assert carrier == pytest.approx(units.sccm_to_m3_per_s(23.0))
    assert sheath == pytest.approx(units.sccm_to_m3_per_s(50.0))
    angle = math.degrees(math.atan2(-v["sheathInlet"][1], v["sheathInlet"][0]))
    assert angle == pytest.approx(30.0)


def test_block_mesh_dict_structure(geometry, tmp_path):
    spec = CaseSpec(15.0, 23.0, 50.0, mesh_level=2)
    text = block_mesh_dict(geometry, spec)
    assert len(re.findall(r"hex \(", text)) == 16
    for patch in ("carrierInlet", "sheathInlet", "walls", "substrate", "ambient", "outlet"):
        assert re.search(rf"^\s+{patch}\s*$", text, re.M), patch
    assert text.count("type wedge;") == 2
    # the moved tip radius appears as a vertex radius (times cos of the half wedge angle)
    tip_y = 60e-6 * math.cos(0.5 * geometry.wedge_angle)
    assert f"{tip_y:.9e}" in text
    case_dir = write_case(spec, tmp_path / "c", geometry, kinematic_viscosity=1.5e-5)
    for name in (
        "system/blockMeshDict",
        "system/controlDict",
        "system/fvSchemes",
        "system/fvSolution",
        "constant/transportProperties",
        "0/U",
        "0/p",
    ):
        assert (case_dir / name).is_file(), name
    assert "endTime         1200;" in (case_dir / "system/controlDict").read_text()


def _uniform_axial_field(g, speed=10.0):
    """Synthetic 'solution': plug flow u = (speed, 0) on points filling the fluid domain."""
    xs = np.linspace(1e-5, g.substrate_x - 1e-5, 200)
    rs = np.concatenate([np.linspace(1e-6, 70e-6, 20), np.linspace(80e-6, g.outer_radius, 30)])
    x, r = (a.ravel() for a in np.meshgrid(xs, rs, indexing="ij"))
    keep = g.inside_fluid(x, r)
    x, r = x[keep], r[keep]
    return CellField(
        x=x,
        r=r,
        ux=np.full(x.size, speed),
        ur=np.zeros(x.size),
        p=np.zeros(x.size),
        volume=np.ones(x.size),
    )


@pytest.fixture(scope="module")
def plug_grid(geometry):
    return VelocityGrid(_uniform_axial_field(geometry), geometry, 0.0)


def test_droplets_in_plug_flow_land_where_they_start(geometry, plug_grid):
    params = load_cfd_parameters()
    start = np.array([0.0, 5e-6, 20e-6, 40e-6, 300e-6])
    diameters = np.full(start.size, 3.5e-6)
    result = track_droplets(plug_grid, diameters, start, params, geometry.gas_density)
    # no radial gas velocity: the first four go straight through the 75 µm bore ...
    assert np.all(result.status[:4] == LANDED)
    np.testing.assert_allclose(result.landing_radius[:4], start[:4], atol=1e-9)
    # ... the one starting at 300 µm flies straight into the converging cone
    assert result.status[4] == WALL
    # flight time: the domain length at 10 m/s (droplets start at the gas speed)
    assert result.flight_time[0] == pytest.approx(geometry.substrate_x / 10.0, rel=0.02)


def test_droplets_follow_a_uniform_radial_drift(geometry, plug_grid):
    # plug flow plus a small outward radial component (odd in the signed r of the mirrored
    # field); a droplet starting at the gas velocity keeps it (no slip to relax), so it
    # lands at r0 + (u_r/u_x) · L
    grid = copy.deepcopy(plug_grid)
    moving = grid.ux != 0.0
    r_nodes = np.broadcast_to(grid.r_nodes[None, :], grid.ux.shape)
    grid.ur = np.where(moving, 0.001 * np.sign(r_nodes), 0.0)
    params = load_cfd_parameters()
    r0 = 30e-6
    result = track_droplets(grid, np.array([1e-6]), np.array([r0]), params, geometry.gas_density)
    assert result.status[0] == LANDED
    drift = 0.001 / 10.0 * geometry.substrate_x  # 1.15 µm
    assert result.landing_radius[0] - r0 == pytest.approx(drift, rel=0.05)


def _synthetic_table(coef_lw, coef_lo, rng):
    rows = []
    for dr in (0.0, 7.5, 15.0, 30.0):
        for qc, qs in ((17, 50), (23, 50), (29, 50), (23, 35), (23, 65)):
            for da in (2.0, 3.0, 4.0):
                x = np.array([da, dr, dr**2, dr**3, qc, qs, 1.0])
                rows.append(
                    {
                        "case": f"dRN{dr}_Qc{qc}_Qs{qs}",
                        "max_speed_m_s": 100.0 + 2.0 * dr,
                        "status": "ok",
                        "converged": True,
                        "nozzle_deposition_um": dr,
                        "carrier_flow_sccm": qc,
                        "sheath_flow_sccm": qs,
                        "droplet_diameter_um": da,
                        "linewidth_um": x @ coef_lw,
                        "overspray_um": x @ coef_lo,
                        "tip_resistance_pa_s_m3": 4e9 + 1e8 * dr + 2e6 * dr**2 + 3e4 * dr**3,
                    }
                )
    # a supersonic case with nonsense outputs: the Mach filter must keep it out of the fit
    for da in (2.0, 3.0, 4.0):
        rows.append(
            {
                "case": "dRN40_Qc23_Qs50",
                "max_speed_m_s": 400.0,
                "status": "ok",
                "converged": True,
                "nozzle_deposition_um": 40.0,
                "carrier_flow_sccm": 23,
                "sheath_flow_sccm": 50,
                "droplet_diameter_um": da,
                "linewidth_um": 1000.0,
                "overspray_um": 1000.0,
                "tip_resistance_pa_s_m3": 1e12,
            }
        )
    rows.append(
        {
            "case": "dRN60_Qc23_Qs50",
            "status": "failed",
            "nozzle_deposition_um": 60.0,
            "carrier_flow_sccm": 23,
            "sheath_flow_sccm": 50,
            "droplet_diameter_um": np.nan,
            "linewidth_um": np.nan,
            "overspray_um": np.nan,
        }
    )
    return pd.DataFrame(rows)


def test_fit_recovers_known_coefficients_and_keeps_alpha_phi(tmp_path):
    lw = np.array([-3.0, 0.4, 0.02, 0.001, 0.9, -0.3, 40.0])
    lo = np.array([-2.0, 0.2, 0.01, 0.0005, 0.5, -0.2, 20.0])
    table = _synthetic_table(lw, lo, np.random.default_rng(0))
    reference = {
        "derivation": {"anchor_aerosol_fraction": 5e-7},
        "linewidth": {"aerosol_fraction": 2e7},
        "overspray": {"aerosol_fraction": 1e7},
    }
    fit = fit_output_model(table, reference, max_speed_m_s=209.0)
    assert fit["excluded_cases"] == ["dRN40_Qc23_Qs50", "dRN60_Qc23_Qs50"]
    got = fit["linewidth"]
    assert got["droplet_diameter"] == pytest.approx(-3.0)
    assert got["nozzle_deposition_3"] == pytest.approx(0.001)
    assert got["carrier_flow"] == pytest.approx(0.9)
    assert got["aerosol_fraction"] == 2e7
    # with phi_A at the anchor the model reproduces the CFD intercept
    assert got["offset"] + 2e7 * 5e-7 == pytest.approx(40.0)
    assert got["rms_um"] < 1e-9 and got["rows"] == 60
    value = predict(got, 3.0, 7.5, 23.0, 50.0, aerosol_fraction=5e-7)
    assert value == pytest.approx(np.array([3.0, 7.5, 56.25, 421.875, 23, 50, 1]) @ lw)
    assert sensitivity_signs(fit) == {
        "linewidth_up_with_carrier": True,
        "linewidth_down_with_sheath": True,
        "linewidth_down_with_droplet": True,
        "linewidth_up_with_nozzle_deposition": True,
    }
    resistance = fit_tip_resistance(table, (0.0, 23.0, 50.0), max_speed_m_s=209.0)
    assert resistance["excluded_nozzle_deposition_um"] == [40.0]
    np.testing.assert_allclose(resistance["fit_coefficients"], [4e9, 1e8, 2e6, 3e4], rtol=1e-6)
    assert resistance["paper_a0_pa_s_m3"] == 4.57e9
    # the written file has the schema the twin loads
    doc = coefficient_document(
        fit,
        {
            "design": "synthetic",
            "mesh_level": 1,
            "cells": 10,
            "openfoam_version": "v1912",
            "cases": 20,
        },
    )
    path = write_toml(doc, tmp_path / "coeffs.toml")
    from ajtwin.model.parameters import load_output_coefficients

    loaded = load_output_coefficients(path)
    assert loaded.status == "fitted-cfd"
    assert loaded.linewidth.sheath_flow == pytest.approx(-0.3)


def test_fit_refuses_too_few_rows():
    table = pd.DataFrame(
        [
            {
                "status": "ok",
                "converged": True,
                "nozzle_deposition_um": 0.0,
                "carrier_flow_sccm": 23,
                "sheath_flow_sccm": 50,
                "droplet_diameter_um": 3.5,
                "linewidth_um": 50.0,
                "overspray_um": 20.0,
            }
        ]
    )
    with pytest.raises(ValueError, match="usable rows"):
        fit_output_model(
            table, {"linewidth": {"aerosol_fraction": 0.0}, "overspray": {"aerosol_fraction": 0.0}}
        )


def test_fit_droplet_window_keeps_rows_outside_it_out_of_the_linear_term():
    lw = np.array([-7.0, 0.8, 0.0, 0.0, 1.1, -0.3, 50.0])
    lo = np.array([6.0, 0.0, 0.0, 0.0, 0.2, -0.07, -10.0])
    table = _synthetic_table(lw, lo, np.random.default_rng(1))
    # outside 3–4 µm the linewidth bends away from the line (as the CFD's does below 3 µm)
    small = table["droplet_diameter_um"] < 3.0
    table.loc[small, "linewidth_um"] -= 25.0
    reference = {"linewidth": {"aerosol_fraction": 0.0}, "overspray": {"aerosol_fraction": 0.0}}
    windowed = fit_output_model(table, reference, 209.0, droplet_range_um=(3.0, 4.0))
    assert windowed["linewidth"]["droplet_diameter"] == pytest.approx(-7.0)
    assert windowed["linewidth"]["rms_um"] < 1e-9
    assert windowed["droplet_range_um"] == [3.0, 4.0]
    everything = fit_output_model(table, reference, 209.0)
    assert everything["linewidth"]["droplet_diameter"] > -7.0 + 1.0  # the bend biases it
    assert everything["linewidth"]["rows"] > windowed["linewidth"]["rows"]


def test_fit_settings_reject_a_bad_window_and_carry_the_paper_points(tmp_path):
    from ajtwin.cfd.fit import fit_settings

    packaged = fit_settings()
    assert packaged["paper_reference"]["max_speed_m_s_25_50"] == 91.7  # model reference §8
    assert packaged["paper_reference"]["linewidth_um"] == 43.0
    bad = tmp_path / "sweep.toml"
    bad.write_text("[fit]\ndroplet_range_um = [4.0, 3.0]\n")
    with pytest.raises(ValueError, match="droplet_range_um"):
        fit_settings(bad)
    bad.write_text("format_version = 1\n")  # no [fit]: every d_a is used
    assert fit_settings(bad)["droplet_range_um"] == (0.0, np.inf)


def test_fit_needs_phi_anchor_when_alpha_phi_is_nonzero():
    lw = np.array([-3.0, 0.4, 0.0, 0.0, 0.9, -0.3, 40.0])
    table = _synthetic_table(lw, lw, np.random.default_rng(3))
    reference = {"linewidth": {"aerosol_fraction": 2e7}, "overspray": {"aerosol_fraction": 0.0}}
    with pytest.raises(ValueError, match="anchor_aerosol_fraction"):
        fit_output_model(table, reference, 209.0)


def test_nominal_line_plot_is_a_png_and_needs_the_nominal_case(tmp_path):
    from ajtwin.cfd.report import plot_nominal_line

    lw = np.array([-7.0, 0.8, 0.0, 0.0, 1.1, -0.3, 50.0])
    table = _synthetic_table(lw, lw, np.random.default_rng(2))
    table["landing_radius_median_um"] = 18.0
    out = plot_nominal_line({"a": table, "b": table}, tmp_path / "m.png", (0.0, 23.0, 50.0))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="no finished nominal case"):
        plot_nominal_line({"a": table}, tmp_path / "n.png", (0.0, 99.0, 50.0))
