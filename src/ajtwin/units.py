"""Unit conversions — the only place in ajtwin where units are converted.

The public API and files speak the *display units* of model reference §3:

========  =====================================  =========
symbol    quantity                               unit
========  =====================================  =========
d_a       median droplet diameter                µm
V_l       ink volume in the vial                 mL
ΔR_T      radial ink deposition in the tube      µm
ΔR_N      radial ink deposition in the nozzle    µm
φ_A       aerosol volume fraction in carrier     –
I_A       atomizer current                       mA
Q_c, Q_s  carrier / sheath gas flow              sccm
L_w, L_o  linewidth / overspray                  µm
P_c, P_s  carrier / sheath pressure              Pa
Q_m       deposited material flow (silver)       mL/s
========  =====================================  =========

Physics inside :mod:`ajtwin.model` runs in SI. Every factor between the two
lives here; the functions work on floats, NumPy and JAX arrays alike.

Examples
--------
>>> round(sccm_to_m3_per_s(60.0), 12)
1e-06
>>> to_si(75.0, "um")
7.5e-05
"""

from __future__ import annotations

import math

# 1 sccm = 1 cm³/min at standard conditions = 1/60 mL/s (model reference §3).
SCCM_IN_ML_PER_S = 1.0 / 60.0
ML_IN_M3 = 1e-6
UM_IN_M = 1e-6
UM3_IN_ML = 1e-12  # 1 µm³ = 1e-12 cm³ = 1e-12 mL
MA_IN_A = 1e-3

# Unit strings used in the packaged data files, and their factor to SI.
_SI_FACTORS: dict[str, float] = {
    "m": 1.0,
    "mm": 1e-3,
    "um": UM_IN_M,
    "µm": UM_IN_M,
    "nm": 1e-9,
    "m3": 1.0,
    "mL": ML_IN_M3,
    "kg/m3": 1.0,
    "Pa": 1.0,
    "Pa*s": 1.0,
    "Pa*s/m3": 1.0,
    "m/s2": 1.0,
    "K": 1.0,
    "1": 1.0,
    "-": 1.0,
    "1/s": 1.0,
    "sccm": SCCM_IN_ML_PER_S * ML_IN_M3,
    "mL/s": ML_IN_M3,
    "J/K": 1.0,
    "mm/s": 1e-3,
    "um/s": UM_IN_M,
    "um3/s": UM3_IN_ML * ML_IN_M3,
    "deg": 3.141592653589793 / 180.0,
    "m/s": 1.0,
    # units instrument logs use for the record's columns (ajtwin.io reads them, convert())
    "s": 1.0,
    "ms": 1e-3,
    "min": 60.0,
    "h": 3600.0,
    "mA": MA_IN_A,
    "A": 1.0,
    "uA": 1e-6,
    "kPa": 1e3,
    "hPa": 1e2,
    "mbar": 1e2,
    "bar": 1e5,
    "psi": 6894.757293168,  # 1 lbf/in² (NIST SP 811)
    "Torr": 101325.0 / 760.0,
    "mL/min": ML_IN_M3 / 60.0,  # gas flows: standard mL/min = sccm (what MFCs report)
    "L/min": 1e-3 / 60.0,  # slm: standard litres per minute
    "mm/min": 1e-3 / 60.0,  # stage speeds as CNC and stage GUIs show them
    "m/min": 1.0 / 60.0,
    "uL/s": 1e-3 * ML_IN_M3,
    "nL/s": 1e-6 * ML_IN_M3,
    "pL/s": 1e-9 * ML_IN_M3,
    "%": 1e-2,
}

# What each unit measures: convert() refuses to turn one quantity into another.
_DIMENSIONS: dict[str, str] = {
    **dict.fromkeys(("s", "ms", "min", "h"), "time"),
    **dict.fromkeys(("mA", "A", "uA"), "current"),
    **dict.fromkeys(("Pa", "kPa", "hPa", "mbar", "bar", "psi", "Torr"), "pressure"),
    **dict.fromkeys(("m", "mm", "um", "µm", "nm"), "length"),
    **dict.fromkeys(
        ("sccm", "mL/s", "mL/min", "L/min", "uL/s", "nL/s", "pL/s", "m3/s"), "volume flow"
    ),
    **dict.fromkeys(("mL", "m3"), "volume"),
    **dict.fromkeys(("mm/s", "um/s", "m/s", "mm/min", "m/min"), "speed"),
    **dict.fromkeys(("1", "-", "%"), "fraction"),
}


def to_si(value, unit: str):
    """Convert ``value`` given in ``unit`` (a data-file unit string) to SI.

    Parameters
    ----------
    value : float or array
    unit : str
        One of the unit strings used by the packaged data files (``"um"``,
        ``"mL"``, ``"sccm"``, ``"Pa*s/m3"`` …).

    Raises
    ------
    ValueError
        For a unit string this module does not know.
    """
    try:
        return value * _SI_FACTORS[unit]
    except KeyError:
        known = ", ".join(sorted(_SI_FACTORS))
        raise ValueError(f"unknown unit {unit!r}; known units: {known}") from None


def dimension(unit: str) -> str | None:
    """What ``unit`` measures ("time", "pressure", "volume flow", …), or None if unknown."""
    return _DIMENSIONS.get(unit)


def convert(value, from_unit: str, to_unit: str):
    """``value`` in ``from_unit`` expressed in ``to_unit`` (both of the same quantity).

    Raises
    ------
    ValueError
        An unknown unit, or two units of different quantities (kPa → sccm).

    Examples
    --------
    >>> convert(5.661, "kPa", "Pa")
    5661.0
    >>> round(convert(1.0, "L/min", "sccm"), 9)
    1000.0
    """
    for unit in (from_unit, to_unit):
        if unit not in _DIMENSIONS:
            known = ", ".join(sorted(_DIMENSIONS))
            raise ValueError(f"unknown unit {unit!r}; known units: {known}")
    if _DIMENSIONS[from_unit] != _DIMENSIONS[to_unit]:
        raise ValueError(
            f"cannot convert {from_unit} ({_DIMENSIONS[from_unit]}) to {to_unit} "
            f"({_DIMENSIONS[to_unit]})"
        )
    if from_unit == to_unit:
        return value
    return value * (_SI_FACTORS[from_unit] / _SI_FACTORS[to_unit])


def sccm_to_ml_per_s(q):
    """Gas flow in sccm → mL/s."""
    return q * SCCM_IN_ML_PER_S


def ml_per_s_to_sccm(q):
    """Gas flow in mL/s → sccm."""
    return q / SCCM_IN_ML_PER_S


def sccm_to_m3_per_s(q):
    """Gas flow in sccm → m³/s."""
    return q * (SCCM_IN_ML_PER_S * ML_IN_M3)


def um_to_m(length):
    """µm → m."""
    return length * UM_IN_M


def m_to_um(length):
    """m → µm."""
    return length / UM_IN_M


def um_to_nm(length):
    """Length in µm → nm (reports of nozzle deposition)."""
    return length * 1e3


def per_sqrt_h_to_per_sqrt_s(rate):
    """A random walk's σ per √hour → per √second (the twin's 1 s step)."""
    return rate / 60.0


def ml_to_m3(volume):
    """mL → m³."""
    return volume * ML_IN_M3


def m3_to_ml(volume):
    """m³ → mL."""
    return volume / ML_IN_M3


#: parts per million by volume in one volume fraction (φ_A as a person reads it)
PPM_IN_FRACTION = 1e6


def fraction_to_ppm(fraction):
    """A volume fraction (φ_A) → parts per million by volume.

    >>> round(fraction_to_ppm(4.377e-7), 4)
    0.4377
    """
    return fraction * PPM_IN_FRACTION


def ppm_to_fraction(ppm):
    """Parts per million by volume → a volume fraction."""
    return ppm / PPM_IN_FRACTION


def um3_per_s_to_ml_per_s(rate):
    """Volume rate in µm³/s → mL/s (the generation fit H is in µm³/s)."""
    return rate * UM3_IN_ML


def mm_per_s_to_um_per_s(speed):
    """mm/s → µm/s."""
    return speed * 1e3


def um2_to_ml_per_um(area_um2):
    """Cross-section area in µm² → volume per unit length in mL/µm."""
    return area_um2 * UM3_IN_ML


def cross_section_um2(material_flow_ml_s, platen_speed_mm_s):
    """Line cross-section area (µm²) deposited by material flow Q_m [mL/s] at platen speed ν.

    ``Q_m = ν ∫h dr`` (paper eq. qink_measurement), so ``∫h dr = Q_m / ν``.

    >>> round(cross_section_um2(1.5e-8, 1.0), 9)
    15.0
    """
    return (material_flow_ml_s / UM3_IN_ML) / mm_per_s_to_um_per_s(platen_speed_mm_s)


def material_flow_ml_s(cross_section_area_um2, platen_speed_mm_s):
    """Material flow Q_m [mL/s] from a line cross-section (µm²) at platen speed ν [mm/s]."""
    return cross_section_area_um2 * UM3_IN_ML * mm_per_s_to_um_per_s(platen_speed_mm_s)


# --------------------------------------------------------------------------- #
# What a person reads: one display unit per quantity
# --------------------------------------------------------------------------- #


class DisplayUnit:
    """How one quantity is shown to a person: its symbol, unit, words and the factor from
    the unit it is computed in (model reference §3) to the one shown.

    >>> DISPLAY_UNITS["aerosol_fraction"].label
    'φ_A [ppm]'
    >>> round(float(DISPLAY_UNITS["material_flow_mL_s"].shown(1.5e-8)), 6)
    0.015
    """

    __slots__ = ("symbol", "unit", "scale", "words")

    def __init__(self, symbol: str, unit: str, scale: float, words: str):
        self.symbol, self.unit, self.scale, self.words = symbol, unit, float(scale), words

    @property
    def label(self) -> str:
        """``symbol [unit]``, an axis or column label."""
        return f"{self.symbol} [{self.unit}]"

    def shown(self, value):
        """``value`` (computed units) in the unit shown (floats and arrays)."""
        return value * self.scale

    def text(self, value, digits: int = 3) -> str:
        """``value`` as a person reads it: ``0.438 ppm``, ``9206 Pa`` (no e-notation)."""
        return f"{readable(self.shown(value), digits)} {self.unit}"

    @property
    def rate_label(self) -> str:
        """The label of this state's drift rate θ: ``drift rate θ of ΔR_N [%/h]``."""
        return f"drift rate θ of {self.symbol} [{DRIFT_RATE_UNIT}]"


#: nanolitres per second in one mL/s (Q_m, the deposited silver flow, as a person reads it)
NL_PER_S_IN_ML_PER_S = 1e6
#: seconds in one hour (θ, the drift rates, are shown per hour)
S_IN_H = 3600.0
#: θ as a person reads it: the relative drift of its state, per cent per hour
DRIFT_RATE_UNIT = "%/h"


def drift_rate_percent_per_hour(theta_per_s):
    """A drift rate θ [1/s] (dx/dt = θ x, model reference §4) → per cent of the state per
    hour.

    >>> round(drift_rate_percent_per_hour(1e-6), 3)
    0.36
    """
    return theta_per_s * S_IN_H * 100.0


#: The one display unit of every state, input and output (the names of
#: :mod:`ajtwin.model.names`); commands, reports and plots label and scale with these.
DISPLAY_UNITS: dict[str, DisplayUnit] = {
    "droplet_diameter_um": DisplayUnit("d_a", "µm", 1.0, "median droplet diameter"),
    "vial_volume_mL": DisplayUnit("V_l", "mL", 1.0, "ink left in the vial"),
    "tube_deposition_um": DisplayUnit("ΔR_T", "µm", 1.0, "ink built up in the tube"),
    "nozzle_deposition_um": DisplayUnit("ΔR_N", "µm", 1.0, "ink built up in the nozzle"),
    "aerosol_fraction": DisplayUnit(
        "φ_A", "ppm", PPM_IN_FRACTION, "aerosol density (ink volume fraction in the carrier gas)"
    ),
    "atomizer_current_mA": DisplayUnit("I_A", "mA", 1.0, "atomizer current"),
    "carrier_flow_sccm": DisplayUnit("Q_c", "sccm", 1.0, "carrier gas flow"),
    "sheath_flow_sccm": DisplayUnit("Q_s", "sccm", 1.0, "sheath gas flow"),
    "linewidth_um": DisplayUnit("L_w", "µm", 1.0, "linewidth"),
    "overspray_um": DisplayUnit("L_o", "µm", 1.0, "overspray"),
    "carrier_pressure_Pa": DisplayUnit("P_c", "Pa", 1.0, "carrier pressure"),
    "sheath_pressure_Pa": DisplayUnit("P_s", "Pa", 1.0, "sheath pressure"),
    "material_flow_mL_s": DisplayUnit(
        "Q_m", "nL/s", NL_PER_S_IN_ML_PER_S, "deposited ink flow (silver)"
    ),
}


def display(name: str) -> DisplayUnit:
    """The :class:`DisplayUnit` of a state, input or output name (KeyError names it)."""
    try:
        return DISPLAY_UNITS[name]
    except KeyError:
        raise KeyError(f"no display unit for {name!r}; known: {', '.join(DISPLAY_UNITS)}") from None


def readable(value, digits: int = 3, zero_below: float = 0.0) -> str:
    """A number as a person reads it: ``digits`` significant figures, never e-notation
    (``4750`` not ``4.75e+03``, ``0.0153`` not ``1.53e-02``); ``–`` for NaN; ``0`` for a
    magnitude below ``zero_below`` (a drift of 1e-25 %/h is none to a reader).

    >>> readable(4751.2), readable(0.015312), readable(73.96), readable(-2.0), readable(1e-9)
    ('4751', '0.0153', '74', '-2', '0.000000001')
    >>> readable(-1.9e-25, 2, zero_below=1e-4)
    '0'
    """
    value = float(value)
    if not math.isfinite(value):
        return "–"
    if abs(value) <= zero_below or value == 0:
        return "0"
    magnitude = math.floor(math.log10(abs(value)))
    decimals = max(0, digits - 1 - magnitude)
    text = f"{value:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return text


def print_minutes(seconds) -> float:
    """Seconds past the print's start → minutes past the print's start (the one time base
    a person reads)."""
    return seconds / 60.0


def minutes_text(seconds, decimals: int = 1) -> str:
    """``'20.5 min'``: a print time [s past the print's start] as a person reads it.

    >>> minutes_text(1231.8)
    '20.5 min'
    """
    return f"{print_minutes(float(seconds)):.{decimals}f} min"
