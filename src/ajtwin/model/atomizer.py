"""Ultrasonic atomizer: net droplet generation and aerosol-fraction dynamics.

* :func:`net_droplet_generation` — the paper's Box–Behnken quadratic fit H
  (App. B.3), µm³/s from Q_c [sccm], V_l [mL], I_A [mA].
* :func:`aerosol_fraction_rate` — paper eq. (dAd_dt_def):
  dφ_A/dt = (H − φ_A Q_c + φ_A dV_l/dt)/(V_v − V_l) + θ_φA φ_A.
* :func:`vial_volume_rate` — dV_l/dt = −φ_A Q_c + θ_Vl V_l.
"""

from __future__ import annotations

from ajtwin import units


def net_droplet_generation(carrier_flow_sccm, vial_volume_ml, atomizer_current_ma, fit):
    """Net droplet generation rate H = G − B in mL/s (paper App. B.3).

    H[µm³/s] = 3.3e2 Q_c² + 2.7e4 V_l Q_c + 66 Q_c I_A + 2.1e2 I_A V_l
               − 5.2e5 V_l − 4.8e4 Q_c − 1.1e3 I_A + 7.7e5,
    with Q_c in sccm, V_l in mL, I_A in mA; converted to mL/s (1 µm³ = 1e-12 mL).
    ``fit`` is the 8 coefficients in that order (``PhysicalParameters.generation_fit``).

    Examples
    --------
    >>> from ajtwin.model.parameters import load_parameters
    >>> fit = load_parameters().generation_fit
    >>> round(float(net_droplet_generation(23.0, 1.0, 375.0, fit)) * 1e12)   # µm³/s
    177070
    """
    q, v, i = carrier_flow_sccm, vial_volume_ml, atomizer_current_ma
    h_um3 = (
        fit[0] * q**2
        + fit[1] * v * q
        + fit[2] * q * i
        + fit[3] * i * v
        + fit[4] * v
        + fit[5] * q
        + fit[6] * i
        + fit[7]
    )
    return units.um3_per_s_to_ml_per_s(h_um3)


def vial_volume_rate(aerosol_fraction, carrier_flow_ml_s, vial_volume_ml, theta_vial=0.0):
    """dV_l/dt [mL/s] = −φ_A Q_c + θ_Vl V_l (ink carried out of the vial)."""
    return -aerosol_fraction * carrier_flow_ml_s + theta_vial * vial_volume_ml


def aerosol_fraction_rate(
    aerosol_fraction,
    generation_ml_s,
    carrier_flow_ml_s,
    vial_volume_ml,
    vial_volume_rate_ml_s,
    vial_capacity_ml,
    theta_aerosol=0.0,
):
    """dφ_A/dt [1/s] from mass balance of the aerosol in the vial's head space.

    dφ_A/dt = (H − φ_A Q_c + φ_A dV_l/dt)/(V_v − V_l) + θ_φA φ_A.
    """
    headspace = vial_capacity_ml - vial_volume_ml
    balance = (
        generation_ml_s
        - aerosol_fraction * carrier_flow_ml_s
        + aerosol_fraction * vial_volume_rate_ml_s
    )
    return balance / headspace + theta_aerosol * aerosol_fraction
