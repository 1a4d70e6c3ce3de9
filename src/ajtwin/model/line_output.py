"""Printed-line outputs: linewidth, overspray and material flow (paper §6.2).

* :func:`line_feature` — the paper's output polynomial (eqs. linewidth/overspray
  output model): L = α^da d_a + α^φ φ_A + α^N1 ΔR_N + α^N2 ΔR_N² + α^N3 ΔR_N³
  + β^c Q_c + β^s Q_s + γ, coefficients from the CFD macro-model file.
* :func:`linewidth`, :func:`overspray` — that polynomial with each set.
* :func:`material_flow` — Q_m = φ_m φ_A Q_c (silver volume flow, mL/s).

These are the line at the reference platen speed (2 mm/s); how L_w and L_o change with
the speed is :mod:`ajtwin.model.line_speed` (Q_m does not depend on it).

Display units: d_a, ΔR_N, L in µm, Q in sccm (coefficients are per those units).
"""

from __future__ import annotations

from ajtwin._jax import jnp


def line_feature(
    coefficients,
    droplet_diameter_um,
    aerosol_fraction,
    nozzle_deposition_um,
    carrier_flow_sccm,
    sheath_flow_sccm,
):
    """Evaluate the output polynomial with a coefficient vector.

    Parameters
    ----------
    coefficients : array (8,)
        [α^da, α^φ, α^N1, α^N2, α^N3, β^c, β^s, γ] (order of
        :class:`ajtwin.model.parameters.Coefficients`).

    Returns
    -------
    array
        The feature in µm.
    """
    c = jnp.asarray(coefficients)
    n = nozzle_deposition_um
    return (
        c[0] * droplet_diameter_um
        + c[1] * aerosol_fraction
        + n * (c[2] + n * (c[3] + n * c[4]))
        + c[5] * carrier_flow_sccm
        + c[6] * sheath_flow_sccm
        + c[7]
    )


def linewidth(
    linewidth_coefficients,
    droplet_diameter_um,
    aerosol_fraction,
    nozzle_deposition_um,
    carrier_flow_sccm,
    sheath_flow_sccm,
):
    """Linewidth L_w [µm]."""
    return line_feature(
        linewidth_coefficients,
        droplet_diameter_um,
        aerosol_fraction,
        nozzle_deposition_um,
        carrier_flow_sccm,
        sheath_flow_sccm,
    )


def overspray(
    overspray_coefficients,
    droplet_diameter_um,
    aerosol_fraction,
    nozzle_deposition_um,
    carrier_flow_sccm,
    sheath_flow_sccm,
):
    """One-sided overspray L_o [µm] (mean of the left and right extents)."""
    return line_feature(
        overspray_coefficients,
        droplet_diameter_um,
        aerosol_fraction,
        nozzle_deposition_um,
        carrier_flow_sccm,
        sheath_flow_sccm,
    )


def material_flow(aerosol_fraction, carrier_flow_ml_s, silver_volume_fraction):
    """Deposited silver volume flow Q_m = φ_m φ_A Q_c [mL/s]."""
    return silver_volume_fraction * aerosol_fraction * carrier_flow_ml_s
