"""Material flow from a height profile: Q_m = ν ∫ h dr (paper eq. for Q_m, model reference §9).

Units: h and r in µm, ν (platen speed) in mm/s, Q_m in mL/s of deposited
volume. Conversions go through :mod:`ajtwin.units` (1 µm³ = 1e-12 mL).
"""

from __future__ import annotations

import numpy as np

from ajtwin.units import mm_per_s_to_um_per_s, um3_per_s_to_ml_per_s


def cross_section_area_um2(h_um, um_per_px: float):
    """Area under a height profile sampled on a pixel grid, in µm².

    Each sample is the mean height over its pixel (that is how
    :func:`ajtwin.profile_cnn.data.register_profile` builds them), so the
    area is exactly ``Σ h · Δr``.

    Parameters
    ----------
    h_um : array (..., n_pixels)
        Heights in µm; the last axis runs across the line.
    um_per_px : float
        Pixel size across the line in µm.

    Returns
    -------
    area_um2 : float or array (...)

    Examples
    --------
    >>> float(cross_section_area_um2(np.ones(10), 2.0))
    20.0
    """
    if not um_per_px > 0:
        raise ValueError(f"um_per_px must be > 0, got {um_per_px}")
    return np.sum(np.asarray(h_um, dtype=float), axis=-1) * um_per_px


def material_flow_ml_s(h_um, um_per_px: float, platen_speed_mm_s):
    """Deposited material flow Q_m = ν ∫ h dr in mL/s.

    Parameters
    ----------
    h_um : array (..., n_pixels)
        Height profile(s) across the line, µm.
    um_per_px : float
        Pixel size across the line, µm.
    platen_speed_mm_s : float or array (...)
        Platen (print) speed ν, mm/s.

    Returns
    -------
    q_m_ml_s : float or array (...)

    Examples
    --------
    A 40 µm × 2 µm rectangle printed at 2 mm/s: 80 µm² × 2000 µm/s = 1.6e5 µm³/s.

    >>> h = np.zeros(200); h[80:120] = 2.0
    >>> float(material_flow_ml_s(h, 1.0, 2.0))
    1.6e-07
    """
    speed = np.asarray(platen_speed_mm_s, dtype=float)
    if np.any(~np.isfinite(speed)) or np.any(speed < 0):
        raise ValueError(f"platen speed must be finite and >= 0 mm/s, got {platen_speed_mm_s}")
    area = cross_section_area_um2(h_um, um_per_px)
    return um3_per_s_to_ml_per_s(area * mm_per_s_to_um_per_s(speed))
