"""Loading the packaged parameter and coefficient files.

The physical parameters (model reference §6) live in ``ajtwin/data/parameters.toml``, the
output-model coefficients (model reference §5) in ``ajtwin/data/output_coefficients.toml``;
each value carries a unit and a provenance. This module reads them and returns
immutable pytrees of floats in SI (:class:`PhysicalParameters`) or display units
(:class:`OutputCoefficients`), ready to pass to the pure JAX model functions.

Examples
--------
>>> p = load_parameters()
>>> round(p.nozzle_radius, 9)      # m
7.5e-05
>>> c = load_output_coefficients()
>>> c.status
'fitted-cfd'
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from ajtwin import units
from ajtwin.config import load_toml


class PhysicalParameters(NamedTuple):
    """Physical parameters in SI units (a JAX pytree)."""

    tube_length: float  # L_T [m]
    tube_radius: float  # r_T0 [m]
    droplet_density: float  # rho_p [kg/m3]
    settling_viscosity: float  # eta_settle [Pa s]
    gas_viscosity: float  # eta_gas [Pa s]
    gravity: float  # g [m/s2]
    temperature: float  # T [K]
    mean_free_path: float  # lambda [m]
    boltzmann: float  # k_B [J/K]
    nozzle_radius: float  # r_N0 [m]
    nozzle_length: float  # L_N [m]
    vial_volume: float  # V_v [m3]
    silver_volume_fraction: float  # phi_m [-]
    droplet_cv: float  # coefficient of variation of the droplet size [-]
    carrier_inlet_r1: float  # R_1 [Pa s/m3]
    carrier_inlet_r2: float
    carrier_inlet_r3: float
    sheath_inlet_r1: float  # R_1^sh [Pa s/m3]
    sheath_inlet_r2: float
    sheath_inlet_r3: float
    nozzle_r1: float  # R_1^N [Pa s/m3]
    nozzle_r2: float  # R_2^N [Pa s/m3]
    nozzle_tip_resistance_poly: tuple  # a_0..a_7 [Pa s/m3 per µm^i]
    generation_fit: tuple  # Box-Behnken coefficients of H [µm³/s in sccm, mL, mA]


# Fits kept in their published units (the nozzle-tip polynomial in ΔR_N [µm], the
# generation fit in sccm/mL/mA → µm³/s): their coefficients are not rescaled; the
# unit string only names the result, and the model converts the result.
_KEEP_AS_PUBLISHED = {"nozzle_tip_resistance_poly", "generation_fit"}


class Coefficients(NamedTuple):
    """One output's coefficients, in display units (µm per µm, per sccm …)."""

    droplet_diameter: float
    aerosol_fraction: float
    nozzle_deposition_1: float
    nozzle_deposition_2: float
    nozzle_deposition_3: float
    carrier_flow: float
    sheath_flow: float
    offset: float


class OutputCoefficients(NamedTuple):
    """Linewidth and overspray coefficients plus the file's status string."""

    linewidth: Coefficients
    overspray: Coefficients
    status: str = "unknown"


@dataclass(frozen=True)
class ParameterRecord:
    """One row of a parameter file: value in its file unit, unit, provenance, note."""

    name: str
    value: object
    unit: str
    provenance: str
    note: str = field(default="")


def _read_toml(path: Path | None, default_name: str) -> dict:
    # a user's file must be a regular file of bounded size (no hang on a FIFO)
    return load_toml(path, f"data/{default_name}", what="parameter")


def parameter_records(path: str | Path | None = None) -> list[ParameterRecord]:
    """The parameter file as records (value in the file's unit), for display."""
    raw = _read_toml(path, "parameters.toml")
    return [
        ParameterRecord(name, e["value"], e["unit"], e["provenance"], e.get("note", ""))
        for name, e in raw.items()
        if isinstance(e, dict)
    ]


def load_parameters(path: str | Path | None = None) -> PhysicalParameters:
    """Read a parameter file (default: the packaged one) into SI floats.

    Parameters
    ----------
    path : str or Path, optional
        A TOML file of the same schema as ``ajtwin/data/parameters.toml``.

    Raises
    ------
    ValueError
        When a parameter is missing, has no unit/provenance, or an unknown unit.
    """
    raw = _read_toml(path, "parameters.toml")
    where = path or "packaged parameters.toml"
    values = {}
    for name in PhysicalParameters._fields:
        if name not in raw:
            raise ValueError(f"{where}: parameter {name!r} is missing")
        entry = raw[name]
        for key in ("value", "unit", "provenance"):
            if key not in entry:
                raise ValueError(f"{where}: parameter {name!r} has no {key!r}")
        if name in _KEEP_AS_PUBLISHED:
            values[name] = tuple(float(v) for v in entry["value"])
        else:
            values[name] = float(units.to_si(float(entry["value"]), entry["unit"]))
    return PhysicalParameters(**values)


def load_output_coefficients(path: str | Path | None = None) -> OutputCoefficients:
    """Read an output-coefficient file (default: the packaged one)."""
    raw = _read_toml(path, "output_coefficients.toml")
    where = path or "packaged output_coefficients.toml"
    tables = {}
    for output in ("linewidth", "overspray"):
        if output not in raw:
            raise ValueError(f"{where}: table [{output}] is missing")
        missing = [k for k in Coefficients._fields if k not in raw[output]]
        if missing:
            raise ValueError(f"{where}: [{output}] lacks {', '.join(missing)}")
        tables[output] = Coefficients(**{k: float(raw[output][k]) for k in Coefficients._fields})
    return OutputCoefficients(status=str(raw.get("status", "unknown")), **tables)


def read_output_coefficient_file(path: str | Path | None = None) -> dict:
    """The raw coefficient file (with its derivation and provenance tables)."""
    return _read_toml(path, "output_coefficients.toml")


#: the filter tunings of ``noise.toml``
NOISE_TUNINGS = ("calibrated", "paper")


def load_noise(path: str | Path | None = None, tuning: str = "paper") -> dict:
    """Filter tuning noise as ``{"process": {...}, "measurement": {...}, "initial": {...}}``.

    ``tuning="paper"`` gives the model reference §6 / paper App. E values; ``"calibrated"``
    the twin's default, tuned on virtual-printer training prints (see the file).
    """
    raw = _read_toml(path, "noise.toml")
    if tuning not in NOISE_TUNINGS:
        raise ValueError(f"noise tuning {tuning!r}; choose one of {NOISE_TUNINGS}")
    source = raw if tuning == "paper" else raw[tuning]
    out = {
        group: {name: float(v["value"]) for name, v in source[group].items()}
        for group in ("process", "measurement")
    }
    out["initial"] = {n: float(v["value"]) for n, v in source.get("initial", {}).items()}
    priors = raw.get("priors", {})
    out["prior_initial"] = {n: float(v["value"]) for n, v in priors.get("initial", {}).items()}
    out["theta_prior"] = {n: float(v["value"]) for n, v in priors.get("theta", {}).items()}
    return out
