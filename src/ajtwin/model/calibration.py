"""Per-machine calibration of the output model g (model reference §11).

No two printers share plumbing, gauges or camera optics. A machine's measured outputs
are the nominal model's outputs seen through its calibration:

    L_w = g_w · L_w^nom(x, u) + o_w                         (camera scale folded into g, o)
    L_o = g_o · L_o^nom(x, u) + o_o
    P_c = G_c · [k_c · Q_c (R_T + R_1 + R_2 + R_3) + (Q_c + Q_s) R_N(ΔR_N)] + O_c
    P_s = G_s · [k_s · Q_s (R_1^sh + R_2^sh + R_3^sh)/2 + (Q_c + Q_s) R_N(ΔR_N)] + O_s
    Q_m = g_m · Q_m^nom

with k the line-resistance factors, G and O the gauge gains and offsets [Pa]. The
identity calibration (gains and factors 1, offsets 0) gives the nominal numbers exactly.
The calibration is a pytree (:class:`Calibration`); pass
``CalibratedCoefficients(matrix, calibration)`` where the output function takes its
(2, 8) coefficient matrix and :func:`ajtwin.model.system.output_function` applies it.

Examples
--------
>>> import numpy as np
>>> cal = Calibration.identity()._replace(linewidth_offset_um=-30.0)
>>> vector = calibration_vector(cal)
>>> float(vector[CALIBRATION_NAMES.index("linewidth_offset_um")])
-30.0
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ajtwin import units
from ajtwin._jax import jnp
from ajtwin.config import read_toml
from ajtwin.model.fluidics import tube_resistance

#: Order of the calibration vector (display units: µm, Pa; the rest dimensionless).
CALIBRATION_NAMES = (
    "linewidth_gain",
    "linewidth_offset_um",
    "overspray_gain",
    "overspray_offset_um",
    "carrier_line_factor",
    "carrier_gauge_gain",
    "carrier_gauge_offset_Pa",
    "sheath_line_factor",
    "sheath_gauge_gain",
    "sheath_gauge_offset_Pa",
    "material_flow_gain",
)
IDENTITY = (1.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0)

#: Which output each calibration parameter acts on (index into y).
PARAMETER_OUTPUT = (0, 0, 1, 1, 2, 2, 2, 3, 3, 3, 4)


class Calibration(NamedTuple):
    """One machine's calibration (a pytree of scalars, display units)."""

    linewidth_gain: float = 1.0
    linewidth_offset_um: float = 0.0
    overspray_gain: float = 1.0
    overspray_offset_um: float = 0.0
    carrier_line_factor: float = 1.0
    carrier_gauge_gain: float = 1.0
    carrier_gauge_offset_Pa: float = 0.0
    sheath_line_factor: float = 1.0
    sheath_gauge_gain: float = 1.0
    sheath_gauge_offset_Pa: float = 0.0
    material_flow_gain: float = 1.0

    @classmethod
    def identity(cls) -> Calibration:
        """The nominal machine: gains 1, offsets 0."""
        return cls()

    def is_identity(self) -> bool:
        """Whether this is the nominal machine's calibration."""
        return all(float(a) == b for a, b in zip(self, IDENTITY, strict=True))


class CalibratedCoefficients(NamedTuple):
    """The (2, 8) line coefficients together with the machine's calibration (a pytree)."""

    line: object  # array (2, 8)
    calibration: Calibration


def calibration_vector(calibration: Calibration):
    """The calibration as an array (11,) in :data:`CALIBRATION_NAMES` order."""
    return jnp.stack([jnp.asarray(v, dtype=float) for v in calibration])


def calibration_from_vector(vector) -> Calibration:
    """Inverse of :func:`calibration_vector` (works on traced arrays)."""
    return Calibration(*(vector[i] for i in range(len(CALIBRATION_NAMES))))


def carrier_line_resistance(tube_deposition_um, params):
    """R_T(ΔR_T) + R_1 + R_2 + R_3 [Pa·s/m³]: the carrier path before the nozzle."""
    return (
        tube_resistance(units.um_to_m(tube_deposition_um), params)
        + params.carrier_inlet_r1
        + params.carrier_inlet_r2
        + params.carrier_inlet_r3
    )


def sheath_line_resistance(params):
    """(R_1^sh + R_2^sh + R_3^sh)/2 [Pa·s/m³]: the two parallel sheath branches."""
    return 0.5 * (params.sheath_inlet_r1 + params.sheath_inlet_r2 + params.sheath_inlet_r3)


def apply_calibration(y, x, u, params, calibration: Calibration):
    """Measured outputs (..., 5) from nominal outputs ``y`` (..., 5) of state x, input u.

    See the module docstring for the equations; x, u in display units.
    """
    c = calibration
    y = jnp.asarray(y)
    x = jnp.asarray(x)
    u = jnp.asarray(u)
    carrier_m3_s = units.sccm_to_m3_per_s(u[..., 1])
    sheath_m3_s = units.sccm_to_m3_per_s(u[..., 2])
    # the nominal P_c already holds 1 × the line term; add (k − 1) × it
    carrier_line = carrier_m3_s * carrier_line_resistance(x[..., 2], params)
    sheath_line = sheath_m3_s * sheath_line_resistance(params)
    p_carrier = c.carrier_gauge_gain * (y[..., 2] + (c.carrier_line_factor - 1.0) * carrier_line)
    p_sheath = c.sheath_gauge_gain * (y[..., 3] + (c.sheath_line_factor - 1.0) * sheath_line)
    return jnp.stack(
        [
            c.linewidth_gain * y[..., 0] + c.linewidth_offset_um,
            c.overspray_gain * y[..., 1] + c.overspray_offset_um,
            p_carrier + c.carrier_gauge_offset_Pa,
            p_sheath + c.sheath_gauge_offset_Pa,
            c.material_flow_gain * y[..., 4],
        ],
        axis=-1,
    )


# --------------------------------------------------------------------------- #
# Files: a calibration with its provenance (TOML)
# --------------------------------------------------------------------------- #


def calibration_to_dict(calibration: Calibration) -> dict:
    """{parameter name: value} (display units)."""
    return {name: float(v) for name, v in zip(CALIBRATION_NAMES, calibration, strict=True)}


def calibration_from_dict(values: dict, where: str = "calibration") -> Calibration:
    """A Calibration from {parameter name: value}; missing parameters are the identity's.

    Raises ValueError naming ``where`` and the parameter for unknown names or non-numbers.
    """
    unknown = sorted(set(values) - set(CALIBRATION_NAMES))
    if unknown:
        raise ValueError(f"{where}: unknown calibration parameter(s) {unknown}")
    out = {}
    for name, value in values.items():
        try:
            out[name] = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: {name} = {value!r} is not a number") from None
        if not np.isfinite(out[name]):
            raise ValueError(f"{where}: {name} = {value!r} is not finite")
    for name in CALIBRATION_NAMES:
        if (name.endswith("_gain") or name.endswith("_factor")) and name in out:
            if out[name] <= 0:
                raise ValueError(f"{where}: {name} = {out[name]} must be positive")
    return Calibration(**out)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(float(value)) if isinstance(value, float) else str(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    text = str(value).replace("\\", "\\\\").replace('"', '\\"')
    return f'"{text}"'


def write_calibration_file(
    path,
    calibration: Calibration,
    std: dict | None = None,
    provenance: dict | None = None,
    *,
    covariance=None,
    noise_factors: dict | None = None,
    aerosol_level: dict | None = None,
) -> Path:
    """Write a calibration TOML: ``[calibration]``, ``[standard_error]``, ``[provenance]``,
    and optionally ``covariance`` (11 × 11, :data:`CALIBRATION_NAMES` order),
    ``[noise_factor]`` (output name → σ_w factor) and ``[aerosol_level]`` (φ_A's level
    relative to the generation model: ``relative``, ``relative_std``, ``pinned_by``,
    ``theta_per_s``)."""
    path = Path(path)
    lines = ["format_version = 1", ""]
    prov = {"written": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}
    prov.update(provenance or {})
    lines.append("[provenance]")
    for key, value in prov.items():
        if isinstance(value, dict):
            continue
        lines.append(f"{key} = {_toml_value(value)}")
    for key, value in prov.items():
        if isinstance(value, dict):
            lines += ["", f"[provenance.{key}]"]
            lines += [f'"{k}" = {_toml_value(v)}' for k, v in value.items()]
    lines += ["", "[calibration]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in calibration_to_dict(calibration).items()]
    if std:
        lines += ["", "[standard_error]"]
        lines += [f"{k} = {_toml_value(float(v))}" for k, v in std.items()]
    if noise_factors:
        lines += ["", "[noise_factor]"]
        lines += [f"{k} = {_toml_value(float(v))}" for k, v in noise_factors.items()]
    if aerosol_level:
        lines += ["", "[aerosol_level]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in aerosol_level.items()]
    if covariance is not None:
        rows = [[float(v) for v in row] for row in np.asarray(covariance, dtype=float)]
        lines += ["", "[covariance]", f"order = {_toml_value(list(CALIBRATION_NAMES))}"]
        lines += ["matrix = [", *[f"    {_toml_value(r)}," for r in rows], "]"]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def read_calibration_file(path) -> tuple[Calibration, dict]:
    """(Calibration, the whole file as a dict) from a calibration TOML."""
    path = Path(path)
    try:
        data = read_toml(path, what="calibration")
    except FileNotFoundError:
        raise ValueError(f"{path}: no such calibration file") from None
    if "calibration" not in data:
        raise ValueError(f"{path}: no [calibration] table")
    return calibration_from_dict(data["calibration"], str(path)), data
