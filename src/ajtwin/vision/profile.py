"""Synthetic line cross-sections and the reference linewidth/overspray definitions.

Three pieces that the renderer, the extractor's tests, the height-profile CNN and the
virtual printer share, so that they all mean the same thing by "linewidth" and "overspray":

* :func:`brightness_from_profile` — the camera's optical model (model reference §9: flat = bright,
  steep = dark): ``B = background * (floor + (1 - floor) / (1 + |dh/dr| / slope_scale))``.
  Its constants live in ``optics.toml`` next to this module.
* :func:`profile_features` — the paper's definitions (App. A) applied to the *noiseless*
  brightness of a true profile: minima (ii), first peaks outward (iii), linewidth between
  the (iii) points, overspray from (iii) outward to where brightness is back within 95 % of
  the background, one-sided = mean of both sides.  This is the truth the extractor is
  scored against.
* :func:`line_profile` — a deposit cross-section with a central body, two shoulders and a
  faint overspray tail (like the paper's profilometer scans, Fig. lw_def b), built in closed
  form so that :func:`profile_features` returns the requested linewidth and overspray and
  ``∫h dr`` equals the requested cross-section area.

Shape of :func:`line_profile`, per side (distance ``u`` from the centre, shoulder (iii) at
``w = L_w / 2``, flat terrace of width ``p`` centred on it, shoulder height ``h_s``, body
height ``H_b`` above it, body half-width ``w_b = w - p/2``)::

    body     0 <= u <= w_b          h = h_s + H_b (1 + cos(pi u / w_b)) / 2
    terrace  w_b < u <= w + p/2     h = h_s            (slope 0: the brightness peak (iii))
    tail     next T micrometres     slope ramps 0 -> P over `ramp`, stays P, falls to 0
                                    linearly over the last `foot` (= 0.25 L_o)
    substrate                       h = 0

* (ii), the steepest body slope, is at ``u = w_b / 2``; the body is kept at least
  ``min_flank_to_tail_slope`` times steeper than the tail so (ii) never lands in the tail.
* (iii) is the terrace centre ``u = w`` (a plateau of maximal brightness whose midpoint the
  definitions take), so linewidth = ``L_w`` exactly.
* The tail slope drops below ``s95`` (brightness back at 95 % of the background) at
  ``T - foot * s95 / P``; that point is placed at ``u = w + L_o``, so overspray = ``L_o``.
  ``P = tail_contrast * s95`` (2.5: a faint band ~11 % darker than the substrate).
* The tail's initial ramp is matched to the body's curvature at the terrace, so the
  brightness peak is symmetric and camera blur does not shift it.
* ``H_b`` takes whatever area is left:
  ``A = h_s (w_L + w_R + p) + H_b (w_bL + w_bR) / 2 + tail areas``.  Below
  :func:`minimum_area_um2` the shoulder and tail are thinned (with a warning).

Constants live in ``optics.toml`` ([brightness], [profile]).
"""

from __future__ import annotations

import functools
import warnings

import numpy as np
from scipy.interpolate import PchipInterpolator

from ajtwin.config import packaged_toml
from ajtwin.vision.features import EdgePoints, find_edges


@functools.cache
def optics() -> dict:
    """The optical/profile/render constants of ``optics.toml`` (with provenance comments)."""
    return packaged_toml("vision/optics.toml")


def _brightness_constants(slope_scale, floor):
    cfg = optics()["brightness"]
    return (
        cfg["slope_scale"] if slope_scale is None else float(slope_scale),
        cfg["floor"] if floor is None else float(floor),
    )


def brightness_from_slope(slope, *, background=1.0, slope_scale=None, floor=None):
    """Brightness seen by the alignment camera for a surface slope (model reference §9).

    Parameters
    ----------
    slope : float or array
        Surface slope dh/dr (µm/µm, dimensionless); its sign does not matter.
    background : float or array
        Brightness of flat substrate (any units, e.g. 8-bit gray).
    slope_scale, floor : float, optional
        Override the ``optics.toml`` constants.

    Returns
    -------
    brightness : float or array
        ``background * (floor + (1 - floor) / (1 + |slope| / slope_scale))``.

    Examples
    --------
    >>> float(brightness_from_slope(0.0, background=170.0))
    170.0
    """
    s0, fl = _brightness_constants(slope_scale, floor)
    return background * (fl + (1.0 - fl) / (1.0 + np.abs(slope) / s0))


def brightness_from_profile(r_um, h_um, *, background=1.0, slope_scale=None, floor=None):
    """Brightness across the line from a height profile (flat = bright, steep = dark).

    Parameters
    ----------
    r_um : (n,) array
        Position across the line, µm, increasing.
    h_um : (..., n) array
        Deposit height, µm (several profiles may be stacked on leading axes).
    background, slope_scale, floor
        See :func:`brightness_from_slope`.

    Returns
    -------
    brightness : (..., n) array

    Examples
    --------
    >>> r = np.linspace(-100, 100, 2001)
    >>> b = brightness_from_profile(r, line_profile(r, 43.0, 29.0, 15.0))
    >>> bool(b.min() < 0.5 and b.max() <= 1.0)
    True
    """
    r_um = np.asarray(r_um, dtype=float)
    h_um = np.asarray(h_um, dtype=float)
    slope = np.gradient(h_um, r_um, axis=-1)
    return brightness_from_slope(slope, background=background, slope_scale=slope_scale, floor=floor)


def slope_at_threshold(threshold=None, *, slope_scale=None, floor=None) -> float:
    """Slope (µm/µm) at which brightness is exactly ``threshold`` x background."""
    s0, fl = _brightness_constants(slope_scale, floor)
    if threshold is None:
        threshold = optics()["brightness"]["overspray_threshold"]
    y = (threshold - fl) / (1.0 - fl)
    return s0 * (1.0 / y - 1.0)


REFERENCE_STEP_UM = 0.02  # grid on which the reference definitions are evaluated


def _uniform(r_um, h_um):
    r_um = np.asarray(r_um, dtype=float)
    h_um = np.asarray(h_um, dtype=float)
    if r_um.ndim != 1 or r_um.size < 5 or h_um.shape != r_um.shape:
        raise ValueError(
            f"r_um and h_um must be 1-D arrays of the same length >= 5, got shapes "
            f"{r_um.shape} and {h_um.shape}"
        )
    if not (np.all(np.isfinite(r_um)) and np.all(np.isfinite(h_um))):
        raise ValueError("r_um/h_um contain NaN or inf")
    step = np.diff(r_um)
    if np.any(step <= 0):
        raise ValueError("r_um must be strictly increasing")
    if np.ptp(step) > 1e-6 * step.mean() or step.mean() > REFERENCE_STEP_UM * 1.0001:
        # PCHIP: shape-preserving (no overshoot, so no invented extrema or slopes)
        n = int(np.ceil((r_um[-1] - r_um[0]) / REFERENCE_STEP_UM)) + 1
        grid = np.linspace(r_um[0], r_um[-1], n)
        return grid, PchipInterpolator(r_um, h_um)(grid)
    return r_um, h_um


def profile_feature_points(r_um, h_um, *, threshold=None) -> tuple[EdgePoints, float, float]:
    """Like :func:`profile_features` but also returns the feature points.

    Returns
    -------
    points : EdgePoints
        Indices of (ii), (iii) and the overspray edges on the grid of interval midpoints
        of the (uniform) r grid, where the slopes are evaluated.
    r0_um, dr_um : float
        Origin and spacing of that grid, so ``r = r0_um + index * dr_um``.
    """
    r_um, h_um = _uniform(r_um, h_um)
    if threshold is None:
        threshold = optics()["brightness"]["overspray_threshold"]
    # slope by forward differences, brightness at the interval midpoints: a central
    # difference would smear the slope-free shoulder point with its steep neighbour and move
    # the (iii) peak by up to a full grid step
    dr = float(r_um[1] - r_um[0])
    brightness = brightness_from_slope(np.diff(h_um) / dr)
    # noiseless: the peak prominence rule reduces to 2 % of the (ii) contrast
    points = find_edges(brightness, 1.0, threshold=threshold, noise=0.0, refine=False)
    return points, float(r_um[0]) + 0.5 * dr, dr


def profile_features(r_um, h_um, *, threshold=None) -> tuple[float, float]:
    """Linewidth and one-sided overspray of a true height profile (the reference values).

    The paper's image definitions (model reference §9, App. A) applied to the noiseless brightness
    of the profile (no pixels, no blur, no noise).  The profile is first resampled with a
    shape-preserving PCHIP interpolant onto a uniform 0.02 µm grid (unless already that
    fine); slopes are forward differences, and points are taken at the sample (no sub-sample
    fit: the noiseless shoulder peak is a cusp), so positions are exact to ~0.01 µm plus the
    interpolation error of a coarse input grid: (ii) = darkest point of each half,
    (iii) = first brightness peak outward from each (ii) (prominence >= 2 % of the (ii)
    contrast), linewidth = distance between the (iii) points, overspray = from each (iii)
    outward to where brightness is back at or above 95 % of the background, mean of left and right.

    Parameters
    ----------
    r_um : (n,) array
        Positions across the line, µm (resampled to a uniform grid if needed).
    h_um : (n,) array
        Heights, µm.
    threshold : float, optional
        Overspray threshold (default 0.95 from ``optics.toml``).

    Returns
    -------
    linewidth_um, overspray_um : float
        ``nan`` when a definition cannot be applied (no shoulder peak, tail reaching the
        end of ``r_um``).

    Examples
    --------
    >>> r = np.arange(-120.0, 120.0, 0.02)
    >>> lw, ov = profile_features(r, line_profile(r, 43.0, 29.0, 15.0))
    >>> round(lw, 1), round(ov, 1)
    (43.0, 29.0)
    """
    points, _, dr = profile_feature_points(r_um, h_um, threshold=threshold)
    return float(points.linewidth * dr), float(points.overspray * dr)


def _tail_geometry(overspray_um, shoulder_height_um, ramp_um, foot_um, s95):
    """Peak slope P and length T of a tail whose visible part ends ``overspray_um`` out.

    The tail's slope magnitude ramps from 0 to P over ``ramp_um``, stays at P, and falls
    linearly to 0 over the last ``foot_um``.  It drops below ``s95`` (brightness back within
    the threshold) at ``T - foot * s95 / P``, which must equal the overspray; its integral
    ``P (T - ramp/2 - foot/2)`` must equal the shoulder height.  Both are linear in T, so
    ``P = (h_s - foot s95) / (overspray - ramp/2 - foot/2)``.
    """
    denom = overspray_um - 0.5 * ramp_um - 0.5 * foot_um
    peak = (shoulder_height_um - foot_um * s95) / denom
    return peak, overspray_um + foot_um * s95 / peak


def _tail_height(x, shoulder_height, peak, length, ramp, foot):
    """Height of the tail at distance ``x`` (0..length) past the shoulder."""
    knee = length - foot
    drop = np.where(
        x <= ramp,
        0.5 * peak * x * x / ramp,
        np.where(
            x <= knee,
            peak * (0.5 * ramp + (x - ramp)),
            peak * (0.5 * ramp + (knee - ramp) + (x - knee) - (x - knee) ** 2 / (2 * foot)),
        ),
    )
    return shoulder_height - drop


def _tail_area(peak, length, ramp, foot):
    """∫ tail height dx = ∫ x |slope| dx (integration by parts)."""
    knee = length - foot
    return peak * (ramp**2 / 3 + (knee**2 - ramp**2) / 2 + length * foot / 2 - foot**2 / 3)


def _shape_constants(overspray_um, tail_contrast):
    cfg = optics()["profile"]
    c = cfg["tail_contrast"] if tail_contrast is None else float(tail_contrast)
    if c <= 1.0:
        raise ValueError(f"line_profile: tail_contrast must be > 1, got {c}")
    s95 = slope_at_threshold()
    foot = cfg["foot_fraction"] * overspray_um
    return c, s95, foot, cfg


def minimum_area_um2(linewidth_um, overspray_um, *, tail_contrast=None) -> float:
    """Smallest cross-section area (µm²) for which :func:`line_profile` is exact.

    Below it the overspray tail cannot be both as long and as visible as requested while the
    body still rises above the shoulders; :func:`line_profile` then thins the tail (with a
    warning) and the visible overspray comes out shorter.
    """
    c, s95, foot, cfg = _shape_constants(overspray_um, tail_contrast)
    ramp = cfg["ramp_min_um"]
    terrace = min(cfg["terrace_um"], 0.25 * linewidth_um, 0.5 * overspray_um)
    visible = overspray_um - 0.5 * terrace
    peak = c * s95
    h_s = peak * (visible - 0.5 * ramp - 0.5 * foot) + foot * s95
    length = visible + foot * s95 / peak
    w = 0.5 * linewidth_um
    tail = _tail_area(peak, length, ramp, foot)
    body_min = _min_body_height(h_s, peak, w - 0.5 * terrace, cfg) * (w - 0.5 * terrace)
    return float(h_s * (2 * w + terrace) + 2 * tail + body_min)


def _min_body_height(shoulder_height, tail_peak_slope, body_half_width, cfg) -> float:
    """Lowest body (above the shoulders) that keeps (ii) on the body's flank.

    The body must rise clearly above the shoulders, and its steepest slope
    ``H_b pi / (2 w_b)`` must exceed the tail's by ``min_flank_to_tail_slope``, or the
    darkest point of a half would sit in the overspray band.
    """
    by_height = cfg["min_body_to_shoulder"] * shoulder_height
    by_slope = cfg["min_flank_to_tail_slope"] * tail_peak_slope * 2.0 * body_half_width / np.pi
    return max(by_height, by_slope)


def line_profile(
    r_um,
    linewidth_um: float,
    overspray_um: float,
    area_um2: float,
    *,
    rng: np.random.Generator | None = None,
    raggedness_um: float = 0.0,
    center_um: float = 0.0,
    tail_contrast: float | None = None,
) -> np.ndarray:
    """A deposit cross-section with the requested linewidth, overspray and area.

    Parameters
    ----------
    r_um : array
        Positions across the line, µm (any shape; the profile is evaluated pointwise).
    linewidth_um : float
        Distance between the shoulders (iii), µm, > 0.
    overspray_um : float
        One-sided overspray (mean of the left and right extents), µm, > 0.
    area_um2 : float
        Cross-section area ``∫h dr``, µm².  From a material flow Q_m [mL/s] at platen speed
        ν: :func:`ajtwin.units.cross_section_um2`.
    rng : numpy Generator, optional
        Source of the raggedness perturbation.
    raggedness_um : float
        Standard deviation (µm) of independent random shifts of the two shoulders and of the
        two overspray edges (paper App. A: shoulder positions vary randomly).  With 0 the
        profile is symmetric and :func:`profile_features` returns the requested values.
    center_um : float
        Line centre, µm.
    tail_contrast : float, optional
        Peak slope of the overspray tail as a multiple of the 95 %-threshold slope (default
        from ``optics.toml``; must be > 1 for the overspray to be visible).

    Returns
    -------
    h_um : array
        Heights, µm, same shape as ``r_um``.

    Raises
    ------
    ValueError
        For non-finite or non-positive sizes.

    Warns
    -----
    UserWarning
        When ``area_um2`` is below :func:`minimum_area_um2`: the tail is thinned and the
        visible overspray will be shorter than requested.

    Examples
    --------
    >>> r = np.arange(-120.0, 120.0, 0.05)
    >>> h = line_profile(r, 43.0, 29.0, 15.0)
    >>> round(float(np.trapezoid(h, r)), 3)
    15.0
    """
    for name, value in (
        ("linewidth_um", linewidth_um),
        ("overspray_um", overspray_um),
        ("area_um2", area_um2),
    ):
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"line_profile: {name} must be finite and > 0, got {value!r}")
    if not np.isfinite(raggedness_um) or raggedness_um < 0:
        raise ValueError(f"line_profile: raggedness_um must be >= 0, got {raggedness_um!r}")
    c, s95, foot, cfg = _shape_constants(overspray_um, tail_contrast)
    half = np.full(2, 0.5 * linewidth_um)
    ovs = np.full(2, float(overspray_um))
    if raggedness_um > 0:
        rng = np.random.default_rng() if rng is None else rng
        half = np.maximum(half + rng.normal(0.0, raggedness_um, 2), 0.25 * half)
        ovs = np.maximum(ovs + rng.normal(0.0, raggedness_um, 2), 0.5 * ovs)
    shape = _fit_shape(half, ovs, area_um2, c * s95, s95, foot, cfg)
    if shape["thinned"]:
        warnings.warn(
            f"line_profile: area {area_um2:.3g} µm² is below the "
            f"{minimum_area_um2(linewidth_um, overspray_um, tail_contrast=c):.3g} µm² needed "
            f"for a visible {overspray_um:.3g} µm overspray with a {linewidth_um:.3g} µm "
            "line; thinning the tail (the visible overspray will be shorter)",
            stacklevel=2,
        )
    return _draw_profile(np.asarray(r_um, dtype=float) - center_um, shape, foot)


def _fit_shape(half, ovs, area_um2, peak_nominal, s95, foot, cfg) -> dict:
    """Shoulder height, body height, tail geometry and ramp that give the area.

    Parameters
    ----------
    half, ovs : array (2,)
        Half linewidth and overspray of the left and right side [µm].
    area_um2 : float
        The cross-section [µm²].
    peak_nominal : float
        The tail's peak slope at the nominal contrast.
    s95, foot : float
        The 95 %-threshold slope and the tail's foot [µm].
    cfg : dict
        ``optics.toml``'s profile constants.

    Returns
    -------
    dict
        ``h_s`` shoulder height, ``body`` body height above it [µm], ``geometry`` (peak,
        length) of each tail, ``ramp``, ``terrace``, ``body_half`` (2,) [µm] and
        ``thinned`` (too little material: shoulder, tail and body scaled down together).
    """
    body_span = half.sum()
    ramp = cfg["ramp_min_um"]
    thinned = False
    terrace = min(cfg["terrace_um"], 0.5 * half.min(), 0.5 * ovs.min())
    visible = ovs - 0.5 * terrace  # visible tail length past the terrace
    body_half = half - 0.5 * terrace
    for _ in range(4):
        # shoulder height from the mean overspray at the nominal tail contrast
        h_s = peak_nominal * (visible.mean() - 0.5 * ramp - 0.5 * foot) + foot * s95
        geometry = [_tail_geometry(o, h_s, ramp, foot, s95) for o in visible]
        tails = sum(_tail_area(p, t, ramp, foot) for p, t in geometry)
        body = 2.0 * (area_um2 - h_s * (body_span + terrace) - tails) / (body_span - terrace)
        body_min = _min_body_height(h_s, max(p for p, _ in geometry), body_half.mean(), cfg)
        if body < body_min:
            # too little material: scale shoulder, tail and minimum body down together
            scale = area_um2 / (
                h_s * (body_span + terrace) + tails + 0.5 * body_min * (body_span - terrace)
            )
            h_s *= scale
            geometry = [(p * scale, t) for p, t in geometry]
            body = body_min * scale
            thinned = True
            break
        # match the tail's initial slope rise to the body's curvature at the shoulder, so
        # the brightness peak at (iii) is not lopsided (blur would then move it outward)
        curvature = body * np.pi**2 / (2.0 * body_half.mean() ** 2)
        new_ramp = float(np.clip(peak_nominal / curvature, cfg["ramp_min_um"], 0.25 * ovs.min()))
        if abs(new_ramp - ramp) < 1e-3:
            break
        ramp = new_ramp
    return {
        "h_s": h_s,
        "body": body,
        "geometry": geometry,
        "ramp": ramp,
        "terrace": terrace,
        "body_half": body_half,
        "thinned": thinned,
    }


def _draw_profile(r: np.ndarray, shape: dict, foot: float) -> np.ndarray:
    """Heights [µm] at positions ``r`` [µm from the centre]: a cosine body between the
    shoulders, a flat terrace, then each side's tail (:func:`_fit_shape`'s ``shape``)."""
    h_s, body, ramp, terrace = shape["h_s"], shape["body"], shape["ramp"], shape["terrace"]
    h = np.zeros_like(r)
    for side, sign in ((0, -1.0), (1, 1.0)):
        u = sign * r
        mask = (u >= 0) if side == 1 else (u > 0)
        w = shape["body_half"][side]
        start = w + terrace  # tail starts after the flat shoulder terrace
        peak, length = shape["geometry"][side]
        in_body = mask & (u <= w)
        h[in_body] = h_s + body * 0.5 * (1.0 + np.cos(np.pi * u[in_body] / w))
        h[mask & (u > w) & (u <= start)] = h_s
        in_tail = mask & (u > start) & (u < start + length)
        h[in_tail] = _tail_height(u[in_tail] - start, h_s, peak, length, ramp, foot)
    return np.maximum(h, 0.0)
