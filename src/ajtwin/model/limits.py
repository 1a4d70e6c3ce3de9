"""Physically possible ranges of the states, and checks against them.

An estimate of the hidden state outside the range a real printer can be in (a negative
vial volume, a 534 µm droplet, a deposit thicker than the nozzle's radius) is not a
machine state: it is a model–machine mismatch or bad data. The ranges live in
``data/state_limits.toml`` (with provenance); the geometry-dependent ones are resolved
against the physical parameters here, in one place, so the estimator's guard, the
registry's carry-over and the CLI all use the same numbers.

Examples
--------
>>> import numpy as np
>>> from ajtwin.model import load_parameters
>>> limits = StateLimits.load(load_parameters())
>>> limits.violations(np.array([534.0, 1.0, 0.0, 0.03, 4.6e-7]))
['droplet_diameter_um = 534 µm is outside the physical range [0.5, 15] µm']
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ajtwin import units
from ajtwin.config import load_toml
from ajtwin.model.names import STATE_NAMES
from ajtwin.model.parameters import PhysicalParameters, load_parameters

_DISPLAY_UNIT = ("µm", "mL", "µm", "µm", "")

#: Default operating limits of a machine's inputs (display units): the validity range of H's
#: Box–Behnken fit (Q_c 15–35 sccm, I_A 300–440 mA; model reference §4) and an assumed sheath
#: range around the paper's 48–53 sccm. A registered machine keeps its own (the registry).
DEFAULT_LIMITS = {
    "atomizer_current_mA": [300.0, 440.0],
    "carrier_flow_sccm": [15.0, 35.0],
    "sheath_flow_sccm": [30.0, 80.0],
}


#: Allowed ranges of the inputs, display units; outside them the model refuses the call.
INPUT_LIMITS = {
    "atomizer_current_mA": (50.0, 1000.0),
    "carrier_flow_sccm": (0.0, 200.0),
    "sheath_flow_sccm": (0.0, 500.0),
}


@dataclass(frozen=True)
class StateLimits:
    """Lower and upper physical bounds of each state (display units), from the data file.

    Attributes
    ----------
    lower, upper : array (5,)
        [µm, mL, µm, µm, –]; a state is physical when lower ≤ x ≤ upper (V_l > 0 strictly).
    provenance : dict
        State name → provenance string of its bound.
    """

    lower: np.ndarray
    upper: np.ndarray
    provenance: dict

    @classmethod
    def default(cls) -> StateLimits:
        """The packaged ranges on the packaged machine's parameters."""
        return cls.load(load_parameters())

    @classmethod
    def load(cls, params: PhysicalParameters, path: str | Path | None = None) -> StateLimits:
        """The ranges of ``data/state_limits.toml`` (or ``path``), the geometry-dependent ones
        resolved with ``params`` (tube and nozzle radius, vial capacity).
        """
        source = "ajtwin/data/state_limits.toml" if path is None else path
        data = load_toml(path, "data/state_limits.toml", what="state limits")
        vial_ml = units.m3_to_ml(params.vial_volume)
        radius_um = {
            "tube_deposition_um": units.m_to_um(params.tube_radius),
            "nozzle_deposition_um": units.m_to_um(params.nozzle_radius),
        }
        lower, upper, provenance = [], [], {}
        for name in STATE_NAMES:
            entry = data.get(name)
            if entry is None:
                raise ValueError(f"{source}: no [{name}] section")
            if name in radius_um:
                lower.append(entry["min_fraction_of_radius"] * radius_um[name])
                upper.append(entry["max_fraction_of_radius"] * radius_um[name])
            elif name == "vial_volume_mL":
                lower.append(entry["min"])
                upper.append(entry["max_fraction_of_vial"] * vial_ml)
            else:
                lower.append(entry["min"])
                upper.append(entry["max"])
            provenance[name] = entry.get("provenance", "")
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        if not np.all(lower < upper):
            raise ValueError(f"{source}: every lower bound must be below its upper bound")
        return cls(lower, upper, provenance)

    def inside(self, x) -> np.ndarray:
        """Boolean (..., 5): which entries of x (..., 5) are finite and inside their range."""
        x = np.asarray(x, dtype=float)
        ok = np.isfinite(x) & (x >= self.lower) & (x <= self.upper)
        # an empty vial is no state to print from: V_l must be strictly positive
        ok[..., 1] &= x[..., 1] > 0
        return ok

    def violations(self, x) -> list[str]:
        """One message per state of a single x (5,) outside its range (empty when physical)."""
        x = np.asarray(x, dtype=float).reshape(-1)
        ok = self.inside(x)
        return [
            f"{name} = {x[i]:.4g}{(' ' + _DISPLAY_UNIT[i]) if _DISPLAY_UNIT[i] else ''} is outside "
            f"the physical range [{self.lower[i]:.4g}, {self.upper[i]:.4g}]"
            f"{(' ' + _DISPLAY_UNIT[i]) if _DISPLAY_UNIT[i] else ''}"
            for i, name in enumerate(STATE_NAMES)
            if not ok[i]
        ]

    def first_violation_index(self, means) -> int | None:
        """Index of the first row of means (T, 5) with any state outside its range, or None."""
        bad = ~self.inside(np.asarray(means, dtype=float)).all(axis=-1)
        hits = np.flatnonzero(bad)
        return int(hits[0]) if hits.size else None
