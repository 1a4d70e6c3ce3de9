"""OpenFOAM end to end: one coarse case through the Dask sweep (default suite), errors.

Needs Debian's openfoam (v1912); `make test` installs it (`make openfoam`).
"""

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin import units
from ajtwin.cfd import foam
from ajtwin.cfd.flowfield import CellField
from ajtwin.cfd.geometry import load_geometry
from ajtwin.cfd.physics import load_cfd_parameters
from ajtwin.cfd.sweep import load_design, run_sweep


def _have_openfoam():
    try:
        foam.foam_environment()
        return True
    except foam.OpenFoamMissing:
        return False


needs_openfoam = pytest.mark.skipif(
    not _have_openfoam(), reason="OpenFOAM v1912 not installed: run `make openfoam`"
)


def test_missing_openfoam_says_what_to_do(monkeypatch, tmp_path):
    monkeypatch.setenv("AJTWIN_OPENFOAM_BASHRC", str(tmp_path / "nowhere" / "bashrc"))
    foam.foam_environment.cache_clear()
    try:
        with pytest.raises(foam.OpenFoamMissing, match="make openfoam"):
            foam.foam_environment()
        from ajtwin.cli.cfd import cfd

        result = CliRunner().invoke(cfd, ["run", str(tmp_path / "case")])
        assert result.exit_code != 0
        assert "make openfoam" in result.output and "apt-get install -y openfoam" in result.output
    finally:
        foam.foam_environment.cache_clear()


DESIGN = """
[designs.e2e]
description = "one coarse case and one impossible geometry"
mesh_level = 1
droplet_diameters_um = [3.5]
n_droplets = 800
azimuths = 16
nominal = [0.0, 23.0, 50.0]
cases = [[0.0, 23.0, 50.0], [70.0, 23.0, 50.0]]
"""


@needs_openfoam
def test_one_coarse_case_end_to_end_through_the_sweep(tmp_path):
    design_file = tmp_path / "design.toml"
    design_file.write_text(DESIGN)
    design = load_design("e2e", design_file)
    root = tmp_path / "sweep"
    table = run_sweep(design, root, workers=2, progress=False)

    # the impossible case (70 µm of a 75 µm tip) is recorded, the sweep went on
    failed = table[table["status"] == "failed"]
    assert len(failed) == 1 and "nozzle deposition" in failed["error"].iloc[0]
    assert json.loads((root / "sweep.json").read_text())["failed"] == [failed["case"].iloc[0]]
    row = table[table["status"] == "ok"].iloc[0]
    assert bool(row["converged"]) and row["final_residual_u"] < 1e-6

    g = load_geometry()
    p = load_cfd_parameters()
    q = units.sccm_to_m3_per_s(73.0)
    mean_speed = q / (math.pi * g.tip_radius**2)
    # max speed between the bore's mean (plug) and twice it (Poiseuille)
    assert mean_speed < row["max_speed_m_s"] < 2 * mean_speed
    # pressure to drive the flow out of the tip: at least the exit dynamic head plus the
    # Poiseuille loss of cone and bore; at most twice the head (parabolic flow) plus it
    head = 0.5 * g.gas_density * mean_speed**2
    cone = (
        8
        * p.gas_viscosity
        * q
        / math.pi
        * g.cone_length
        / (3 * (g.chamber_radius - g.tip_radius))
        * (g.tip_radius**-3 - g.chamber_radius**-3)
    )
    bore = 8 * p.gas_viscosity * g.orifice_length * q / (math.pi * g.tip_radius**4)
    drop = row["tip_resistance_pa_s_m3"] * q
    assert head + cone + bore < drop < 2 * head + cone + bore

    # mass conservation: volume flux through a bore cell layer equals Q_c + Q_s
    case_dir = root / row["case"]
    cells = CellField.load(case_dir / "flow.npz")
    bore_cells = (cells.x > g.orifice_x) & (cells.x < g.exit_x)
    layers = np.unique(np.round(cells.x[bore_cells], 10))
    layer = np.isclose(cells.x, layers[len(layers) // 2], atol=1e-10)
    thickness = g.orifice_length / len(layers)
    flux = np.sum(cells.ux[layer] * cells.volume[layer]) / thickness * 2 * math.pi / g.wedge_angle
    assert flux == pytest.approx(q, rel=0.01)

    # droplets reach the substrate and make a line of plausible width
    assert row["fraction_landed"] > 0.9
    assert 10.0 < row["linewidth_um"] < 200.0 and row["overspray_um"] > 0.0

    # resume: the finished case is not run again, the failed one is retried
    finished = (case_dir / "result.json").stat().st_mtime_ns
    again = run_sweep(design, root, workers=1, progress=False)
    assert (case_dir / "result.json").stat().st_mtime_ns == finished
    assert list(again["status"].sort_values()) == ["failed", "ok"]
