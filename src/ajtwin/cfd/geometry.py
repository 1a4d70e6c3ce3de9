"""Axisymmetric geometry of the deposition head (model reference §8, paper App. C).

The dimensions live in ``geometry.toml`` (µm, each with its source); this module
turns them into SI lengths, the axial stations of the model and the wall radius
as a function of the axial coordinate, for a given nozzle deposition ΔR_N (the
tip walls moved inward by ΔR_N, paper Fig. C.2).

Coordinates: x along the axis in the flow direction (x = 0 at the inlets,
x = ``substrate_x`` at the substrate), r the radial distance, both in m.

Examples
--------
>>> g = load_geometry()
>>> round(g.tip_radius * 1e6, 3)
75.0
>>> round(g.tip_radius_at(7.5) * 1e6, 3)
67.5
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ajtwin import units
from ajtwin.config import load_toml

_LENGTHS = (
    "carrier_radius",
    "carrier_wall",
    "chamber_radius",
    "inlet_length",
    "mixing_length",
    "cone_length",
    "orifice_length",
    "tip_radius",
    "standoff",
    "lip_radius",
    "outer_radius",
)


@dataclass(frozen=True)
class Geometry:
    """Deposition-head dimensions in SI (m, rad, kg/m³), gas sound speed, mesh settings."""

    @property
    def max_trusted_speed(self) -> float:
        """Peak gas speed [m/s] up to which the incompressible solve is used in fits."""
        return self.max_mach * self.sound_speed

    carrier_radius: float
    carrier_wall: float
    chamber_radius: float
    inlet_length: float
    mixing_length: float
    cone_length: float
    orifice_length: float
    tip_radius: float
    standoff: float
    lip_radius: float
    outer_radius: float
    sheath_angle: float
    wedge_angle: float
    gas_density: float
    sound_speed: float = 349.0
    max_mach: float = 0.6
    mesh: dict = field(default_factory=dict)
    source: str = "packaged geometry.toml"

    # axial stations ---------------------------------------------------------
    @property
    def mixing_x(self) -> float:
        """End of the aerosol tube (streams meet)."""
        return self.inlet_length

    @property
    def cone_x(self) -> float:
        """Start of the converging cone."""
        return self.inlet_length + self.mixing_length

    @property
    def orifice_x(self) -> float:
        """End of the cone, start of the straight tip bore."""
        return self.cone_x + self.cone_length

    @property
    def exit_x(self) -> float:
        """Nozzle exit plane."""
        return self.orifice_x + self.orifice_length

    @property
    def substrate_x(self) -> float:
        """Axial position of the substrate [m]: the nozzle exit plus the standoff."""
        return self.exit_x + self.standoff

    def tip_radius_at(self, nozzle_deposition_um: float) -> float:
        """Tip radius [m] with ΔR_N [µm] of ink on the tip walls.

        Raises
        ------
        ValueError
            If ΔR_N is negative, not finite, or closes the tip (≥ 90 % of it).
        """
        deposition = units.um_to_m(float(nozzle_deposition_um))
        if not np.isfinite(deposition) or deposition < 0.0:
            raise ValueError(f"nozzle deposition must be ≥ 0 µm, got {nozzle_deposition_um!r}")
        if deposition >= 0.9 * self.tip_radius:
            raise ValueError(
                f"nozzle deposition {nozzle_deposition_um} µm leaves less than 10 % of the "
                f"{units.m_to_um(self.tip_radius):g} µm tip radius"
            )
        return self.tip_radius - deposition

    def wall_radius(self, x, nozzle_deposition_um: float = 0.0):
        """Radius [m] of the outer flow boundary at axial position(s) x [m].

        Inside the head this is the chamber wall, the cone and the bore; in the
        gap below the nozzle it is ``outer_radius`` (the outlet).
        """
        x = np.asarray(x, dtype=float)
        tip = self.tip_radius_at(nozzle_deposition_um)
        fraction = np.clip((x - self.cone_x) / self.cone_length, 0.0, 1.0)
        cone = self.chamber_radius + (tip - self.chamber_radius) * fraction
        return np.where(
            x < self.cone_x,
            self.chamber_radius,
            np.where(x < self.orifice_x, cone, np.where(x <= self.exit_x, tip, self.outer_radius)),
        )

    def inside_fluid(self, x, r, nozzle_deposition_um: float = 0.0):
        """True where (x, |r|) lies in the gas domain (walls and outside are False)."""
        x = np.asarray(x, dtype=float)
        r = np.abs(np.asarray(r, dtype=float))
        inside = (
            (x >= 0.0) & (x <= self.substrate_x) & (r < self.wall_radius(x, nozzle_deposition_um))
        )
        in_tube_wall = (
            (x < self.mixing_x)
            & (r > self.carrier_radius)
            & (r < self.carrier_radius + self.carrier_wall)
        )
        return inside & ~in_tube_wall

    def wall_segments(self, nozzle_deposition_um: float = 0.0) -> list[tuple[tuple, tuple]]:
        """No-slip wall segments ((x0, r0), (x1, r1)) of the meridional plane [m]."""
        tip = self.tip_radius_at(nozzle_deposition_um)
        tube_out = self.carrier_radius + self.carrier_wall
        return [
            ((0.0, self.carrier_radius), (self.mixing_x, self.carrier_radius)),
            ((self.mixing_x, self.carrier_radius), (self.mixing_x, tube_out)),
            ((0.0, tube_out), (self.mixing_x, tube_out)),
            ((0.0, self.chamber_radius), (self.cone_x, self.chamber_radius)),
            ((self.cone_x, self.chamber_radius), (self.orifice_x, tip)),
            ((self.orifice_x, tip), (self.exit_x, tip)),
            ((self.exit_x, tip), (self.exit_x, self.lip_radius)),
            ((self.substrate_x, 0.0), (self.substrate_x, self.outer_radius)),
        ]


def load_geometry(path: str | Path | None = None) -> Geometry:
    """Read a geometry file (default: the packaged ``geometry.toml``) into SI.

    Raises
    ------
    ValueError
        Naming the file and entry when a dimension is missing, not positive, or
        the layout is inconsistent (e.g. tube wider than the chamber).
    """
    where = "packaged geometry.toml" if path is None else str(path)
    raw = load_toml(path, "cfd/geometry.toml", what="geometry")
    values: dict[str, float] = {}
    for name in (
        *_LENGTHS,
        "sheath_angle",
        "wedge_angle",
        "gas_density",
        "sound_speed",
        "max_mach",
    ):
        if name not in raw:
            raise ValueError(f"{where}: entry [{name}] is missing")
        entry = raw[name]
        if "value" not in entry or "unit" not in entry:
            raise ValueError(f"{where}: [{name}] needs 'value' and 'unit'")
        value = float(units.to_si(float(entry["value"]), entry["unit"]))
        if not np.isfinite(value) or (value <= 0.0 and name != "sheath_angle"):
            raise ValueError(f"{where}: [{name}] value {entry['value']!r} must be positive")
        values[name] = value
    g = Geometry(**values, mesh=dict(raw.get("mesh", {})), source=where)
    if g.carrier_radius + g.carrier_wall >= g.chamber_radius:
        raise ValueError(f"{where}: carrier_radius + carrier_wall must be < chamber_radius")
    if not g.tip_radius < g.lip_radius < g.outer_radius:
        raise ValueError(f"{where}: need tip_radius < lip_radius < outer_radius")
    if g.tip_radius >= g.chamber_radius:
        raise ValueError(f"{where}: tip_radius must be < chamber_radius")
    return g
