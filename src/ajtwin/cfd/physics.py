"""Parameters the CFD macro-model takes from ``ajtwin/data/parameters.toml``.

Only values, converted to SI through :mod:`ajtwin.units`; nothing is duplicated
in code. Spread factor, b/a ratio, 80 % peak and 1 % edge are the paper's CFD
post-processing constants (model reference §6, §8).

Examples
--------
>>> p = load_cfd_parameters()
>>> p.droplet_spread_factor, p.width_ratio, p.peak_fraction, p.edge_fraction
(3.8, 2.1, 0.8, 0.01)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ajtwin import units
from ajtwin.config import load_toml


@dataclass(frozen=True)
class CfdParameters:
    """The physical parameters the CFD macro-model uses (SI units).

    Attributes
    ----------
    gas_viscosity : float
        η_gas [Pa s].
    droplet_density : float
        ρ_p [kg/m³].
    mean_free_path : float
        λ [m].
    gravity : float
        g [m/s²].
    nozzle_radius : float
        r_N0 [m].
    droplet_cv : float
        Coefficient of variation of the droplet size [–].
    droplet_spread_factor : float
        Footprint diameter / droplet diameter [–].
    """

    gas_viscosity: float  # η_gas [Pa s]
    droplet_density: float  # ρ_p [kg/m³]
    mean_free_path: float  # λ [m]
    gravity: float  # g [m/s²]
    nozzle_radius: float  # r_N0 [m]
    droplet_cv: float  # coefficient of variation of the droplet size [-]
    droplet_spread_factor: float  # footprint diameter / droplet diameter [-]
    width_ratio: float  # b/a [-]
    peak_fraction: float  # fraction of the peak defining b [-]
    edge_fraction: float  # overspray edge fraction [-]
    nozzle_tip_resistance_poly: tuple  # paper's a_0..a_7 [Pa s/m³ per µm^i]


_NAMES = {
    "gas_viscosity": "gas_viscosity",
    "droplet_density": "droplet_density",
    "mean_free_path": "mean_free_path",
    "gravity": "gravity",
    "nozzle_radius": "nozzle_radius",
    "droplet_cv": "droplet_cv",
    "droplet_spread_factor": "droplet_spread_factor",
    "width_ratio": "cfd_width_ratio",
    "peak_fraction": "cfd_peak_fraction",
    "edge_fraction": "cfd_edge_fraction",
}


def load_cfd_parameters(path: str | Path | None = None) -> CfdParameters:
    """Read the CFD-relevant entries of a parameter file (default: the packaged one)."""
    where = "packaged parameters.toml" if path is None else str(path)
    raw = load_toml(path, "data/parameters.toml", what="parameter")
    values = {}
    for field_name, key in _NAMES.items():
        if key not in raw or "value" not in raw[key] or "unit" not in raw[key]:
            raise ValueError(f"{where}: parameter {key!r} (value and unit) is missing")
        values[field_name] = float(units.to_si(float(raw[key]["value"]), raw[key]["unit"]))
    poly = raw.get("nozzle_tip_resistance_poly", {}).get("value")
    if poly is None:
        raise ValueError(f"{where}: parameter 'nozzle_tip_resistance_poly' is missing")
    values["nozzle_tip_resistance_poly"] = tuple(float(a) for a in poly)
    return CfdParameters(**values)
