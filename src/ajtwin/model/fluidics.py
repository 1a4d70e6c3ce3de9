"""Fluidic resistance network of the AJ head and the MFC pressures (paper App. D).

Flows in m³/s, resistances in Pa·s/m³, pressures in Pa.

* :func:`tube_resistance` — Hagen–Poiseuille, R_T = 8 η_gas L_T / (π (r_T0 − ΔR_T)⁴).
* :func:`nozzle_tip_resistance` — R_3^N(ΔR_N) = Σ_{i=0..7} a_i ΔR_N^i, ΔR_N in µm.
* :func:`carrier_pressure` — P_c = Q_c (R_T + R_1 + R_2 + R_3) + (Q_c + Q_s) R_N.
* :func:`sheath_pressure` — P_s = Q_s (R_1^sh + R_2^sh + R_3^sh)/2 + (Q_c + Q_s) R_N,
  with R_N = R_1^N + R_2^N + R_3^N(ΔR_N).
"""

from __future__ import annotations

from ajtwin._jax import jnp


def tube_resistance(tube_deposition, params):
    """Carrier-tube resistance R_T [Pa·s/m³] for a deposit ΔR_T [m]."""
    radius = params.tube_radius - tube_deposition
    return 8.0 * params.gas_viscosity * params.tube_length / (jnp.pi * radius**4)


def nozzle_tip_resistance(nozzle_deposition_um, params):
    """Nozzle-tip resistance R_3^N [Pa·s/m³]; the paper's polynomial in ΔR_N [µm]."""
    coefficients = params.nozzle_tip_resistance_poly
    # Horner form, highest power first
    result = jnp.zeros_like(jnp.asarray(nozzle_deposition_um, dtype=float)) + coefficients[-1]
    for a in reversed(coefficients[:-1]):
        result = result * nozzle_deposition_um + a
    return result


def nozzle_resistance(nozzle_deposition_um, params):
    """Total nozzle resistance R_N = R_1^N + R_2^N + R_3^N(ΔR_N) [Pa·s/m³]."""
    return params.nozzle_r1 + params.nozzle_r2 + nozzle_tip_resistance(nozzle_deposition_um, params)


def carrier_pressure(carrier_flow, sheath_flow, tube_deposition, nozzle_deposition_um, params):
    """Carrier MFC pressure P_c [Pa].

    P_c = Q_c (R_T(ΔR_T) + R_1 + R_2 + R_3) + (Q_c + Q_s) R_N(ΔR_N).

    Parameters
    ----------
    carrier_flow, sheath_flow : Q_c, Q_s [m³/s]
    tube_deposition : ΔR_T [m]
    nozzle_deposition_um : ΔR_N [µm] (the published polynomial's unit)
    """
    carrier_line = (
        tube_resistance(tube_deposition, params)
        + params.carrier_inlet_r1
        + params.carrier_inlet_r2
        + params.carrier_inlet_r3
    )
    return carrier_flow * carrier_line + (carrier_flow + sheath_flow) * nozzle_resistance(
        nozzle_deposition_um, params
    )


def sheath_pressure(carrier_flow, sheath_flow, nozzle_deposition_um, params):
    """Sheath MFC pressure P_s [Pa].

    P_s = Q_s (R_1^sh + R_2^sh + R_3^sh)/2 + (Q_c + Q_s) R_N(ΔR_N); the two
    sheath branches run in parallel, hence the half.
    """
    sheath_line = 0.5 * (params.sheath_inlet_r1 + params.sheath_inlet_r2 + params.sheath_inlet_r3)
    return sheath_flow * sheath_line + (carrier_flow + sheath_flow) * nozzle_resistance(
        nozzle_deposition_um, params
    )
