"""The CFD macro-model: one coarse OpenFOAM case end to end, by stage.

blockMesh + simpleFoam (mesh level 1, 4400 cells, 600 SIMPLE iterations) run once per
benchmark run (their own timings are the ``track_*`` figures); the velocity-grid resampling,
the tracking of 3000 droplets (d_a = 3.5 µm) and the model reference §8 post-processing
(32 azimuths per droplet) are timed on its flow field. Skipped where OpenFOAM is missing
(``make openfoam``).
"""

from __future__ import annotations

import os
import shutil

import numpy as np

DROPLETS = 3000


class GasCase:
    """The gas flow of one level-1 case (Q_c 23, Q_s 50 sccm)."""

    timeout = 900

    def setup_cache(self):
        if shutil.which("blockMesh") is None and not os.path.exists("/usr/bin/blockMesh"):
            raise NotImplementedError("OpenFOAM not installed: make openfoam")
        from pathlib import Path

        from ajtwin.cfd.case import CaseSpec
        from ajtwin.cfd.geometry import load_geometry
        from ajtwin.cfd.physics import load_cfd_parameters
        from ajtwin.cfd.run import solve_gas

        spec = CaseSpec(0.0, 23.0, 50.0, mesh_level=1)
        case_dir = Path(spec.name).resolve()
        flow = solve_gas(spec, case_dir, load_geometry(), load_cfd_parameters())
        return {"flow": str(case_dir / "flow.npz"), **flow["timings"]}

    def setup(self, case):
        from ajtwin.cfd.flowfield import CellField, VelocityGrid
        from ajtwin.cfd.geometry import load_geometry
        from ajtwin.cfd.physics import load_cfd_parameters
        from ajtwin.cfd.run import droplet_sample

        self.g, self.p = load_geometry(), load_cfd_parameters()
        self.cells = CellField.load(case["flow"])
        self.grid = VelocityGrid(self.cells, self.g, 0.0)
        z, u = droplet_sample(DROPLETS)
        sigma = np.sqrt(np.log1p(self.p.droplet_cv**2))
        self.d_um = 3.5 * np.exp(sigma * z)
        self.u = u
        self.tracked = self.track()

    def track(self):
        from ajtwin import units
        from ajtwin.cfd.tracker import track_droplets

        return track_droplets(
            self.grid,
            units.um_to_m(self.d_um),
            0.98 * self.g.carrier_radius * np.sqrt(self.u),
            self.p,
            self.g.gas_density,
            start_x=float(self.cells.x.min()),
        )

    def track_blockMesh_s(self, case):
        return case["blockMesh_s"]

    def track_simpleFoam_600_iterations_s(self, case):
        return case["simpleFoam_s"]

    track_blockMesh_s.unit = track_simpleFoam_600_iterations_s.unit = "s"

    def time_velocity_grid(self, case):
        from ajtwin.cfd.flowfield import VelocityGrid

        VelocityGrid(self.cells, self.g, 0.0)

    def time_track_3000_droplets(self, case):
        self.track()

    def time_profile_and_metrics(self, case):
        from ajtwin import units
        from ajtwin.cfd.profile import height_profile, line_metrics
        from ajtwin.cfd.tracker import LANDED

        ok = self.tracked.status == LANDED
        radius = units.m_to_um(self.tracked.landing_radius[ok])
        y, h = height_profile(radius, self.d_um[ok], azimuths=32)
        line_metrics(y, h)
