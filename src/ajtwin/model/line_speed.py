"""The printed line's dependence on the platen speed ν (model reference §5, §12).

The material flow Q_m does not depend on ν; the deposited cross-section does,
A = Q_m/ν. Linewidth and overspray follow a power law in A at fixed Q_m:

    L_w(ν) = L_w(ν_ref) · (ν_ref/ν)^b          L_o(ν) = L_o(ν_ref) · (ν_ref/ν)^c

with L(ν_ref) the rest of the output model (the CFD polynomial and the machine's
calibration) and ν clipped to the law's validity range [ν_min, ν_max] (a still stage with
the shutter open is a dot, held at the slowest valid speed). At ν = ν_ref both factors
are exactly 1. Constants, provenance, validity and uncertainty: ``data/line_speed.toml``.

Examples
--------
>>> law = load_line_speed_law()
>>> float(law.reference_speed_mm_s), float(law.linewidth_exponent)
(2.0, 0.3)
>>> w, o = line_speed_factors(2.0, law)
>>> float(w), float(o)
(1.0, 1.0)
>>> round(float(line_speed_factors(4.0, law)[0]), 4)     # (2/4)^0.3
0.8123
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import NamedTuple

from ajtwin._jax import jnp
from ajtwin.config import packaged_toml, read_toml


class LineSpeedLaw(NamedTuple):
    """Constants of the speed law (a pytree of floats; display units)."""

    reference_speed_mm_s: float = 2.0  # ν_ref [mm/s]
    linewidth_exponent: float = 0.3  # b
    overspray_exponent: float = 0.3  # c
    min_speed_mm_s: float = 0.3  # validity range [mm/s]
    max_speed_mm_s: float = 20.0


def read_line_speed_file(path: str | Path | None = None) -> dict:
    """The whole ``line_speed.toml`` (packaged, or a user's file of the same form)."""
    if path is None:
        return packaged_toml("data/line_speed.toml")
    return read_toml(Path(path), what="line-speed")


def law_from_table(table: dict, where: str = "line_speed.toml [law]") -> LineSpeedLaw:
    """A :class:`LineSpeedLaw` from a ``[law]`` table, checked."""
    if table.get("form", "power") != "power":
        raise ValueError(f"{where}: form = {table.get('form')!r}; only 'power' is implemented")
    values = {}
    for name in LineSpeedLaw._fields:
        if name not in table:
            raise ValueError(f"{where}: missing {name}")
        value = table[name]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{where}: {name} = {value!r} is not a number")
        values[name] = float(value)
    low, high = values["min_speed_mm_s"], values["max_speed_mm_s"]
    if not 0.0 < low <= values["reference_speed_mm_s"] <= high:
        raise ValueError(
            f"{where}: need 0 < min_speed_mm_s <= reference_speed_mm_s <= max_speed_mm_s, "
            f"got {low}, {values['reference_speed_mm_s']}, {high}"
        )
    return LineSpeedLaw(**values)


@functools.lru_cache(maxsize=4)
def _packaged_law() -> LineSpeedLaw:
    return law_from_table(read_line_speed_file()["law"])


def load_line_speed_law(path: str | Path | None = None) -> LineSpeedLaw:
    """The speed law of ``data/line_speed.toml`` (or of a user's file)."""
    if path is None:
        return _packaged_law()
    return law_from_table(read_line_speed_file(path)["law"], f"{path} [law]")


def speed_factor(platen_speed_mm_s, exponent, law: LineSpeedLaw):
    """(ν_ref / clip(ν, ν_min, ν_max))^exponent: the line's scale at speed ν (array-wise)."""
    nu = jnp.clip(
        jnp.asarray(platen_speed_mm_s, dtype=float), law.min_speed_mm_s, law.max_speed_mm_s
    )
    return jnp.power(law.reference_speed_mm_s / nu, exponent)


def line_speed_factors(platen_speed_mm_s, law: LineSpeedLaw):
    """(f_w, f_o): the factors on L_w and L_o at platen speed ν [mm/s]."""
    return (
        speed_factor(platen_speed_mm_s, law.linewidth_exponent, law),
        speed_factor(platen_speed_mm_s, law.overspray_exponent, law),
    )


def apply_line_speed(outputs, platen_speed_mm_s, law: LineSpeedLaw):
    """Outputs (..., 5) at ν_ref → at platen speed ν: L_w, L_o scaled, P_c, P_s, Q_m unchanged.

    Parameters
    ----------
    outputs : array (..., 5)
        [L_w µm, L_o µm, P_c Pa, P_s Pa, Q_m mL/s] of the output model at ν_ref.
    platen_speed_mm_s : array (...) or float
        ν [mm/s] (broadcast against the outputs' leading shape).
    law : LineSpeedLaw
    """
    f_w, f_o = line_speed_factors(platen_speed_mm_s, law)
    return apply_line_factors(outputs, f_w, f_o)


def apply_line_factors(outputs, linewidth_factor, overspray_factor):
    """Outputs (..., 5) with L_w and L_o multiplied by the given factors (array-wise).

    The speed law's factors of :func:`line_speed_factors` at one speed, or what stands in for
    them when several camera measurements of one second printed at different speeds are
    combined (:mod:`ajtwin.estimation.print_time`): P_c, P_s and Q_m are unchanged.
    """
    y = jnp.asarray(outputs)
    f_w = jnp.broadcast_to(linewidth_factor, y.shape[:-1])
    f_o = jnp.broadcast_to(overspray_factor, y.shape[:-1])
    return jnp.concatenate(
        [(y[..., 0] * f_w)[..., None], (y[..., 1] * f_o)[..., None], y[..., 2:]], axis=-1
    )
