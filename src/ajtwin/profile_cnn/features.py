"""Linewidth and overspray from a predicted height profile, differentiably.

Stage-2 fine-tuning (paper §5) needs linewidth and overspray *computed from the
predicted profile* with gradients. The definitions are the project's reference,
:func:`ajtwin.vision.profile.profile_features` (model reference §9 applied to the noiseless
brightness of a profile through the optics model of ``vision/optics.toml``)::

    B(r)/B_bg = floor + (1 − floor) / (1 + |dh/dr| / slope_scale)

with slopes by forward differences (brightness at pixel midpoints), (ii) the
darkest point of each half, (iii) the first brightness peak outward (2 %
prominence), overspray from (iii) out to where B returns to ≥ 95 % of B_bg,
mean of both sides.

:func:`smooth_features` is that definition made differentiable:

* the *choice* of points — which pixel is (ii), which peak is (iii), which pixel
  pair brackets the threshold crossing — is made by the vision module's own
  :func:`~ajtwin.vision.features.find_edges` on the detached brightness; it is
  piecewise constant in ``h`` and needs no gradient;
* the *positions* are the sub-pixel refinements find_edges uses (parabola
  vertex through the peak pixel and its neighbours; linear interpolation of the
  threshold crossing), recomputed in torch from the brightness of the predicted
  profile. They are smooth functions of ``h``.

The value returned is exactly find_edges' value on the pixel grid
(straight-through: the torch formula supplies only the gradient), so on clean
profiles the result equals ``profile_features`` evaluated on the same pixel
grid, and differs from the fine-grid reference by the pixel discretization
(tested: within 0.75 µm for linewidth and overspray at 0.75 µm/px).
Profiles without a detectable shoulder or whose overspray leaves the column
give ``nan`` (as ``profile_features`` does); the stage-2 loss skips them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d

from ajtwin.profile_cnn.data import default_scan_smoothing_um
from ajtwin.vision.features import find_edges
from ajtwin.vision.profile import optics as vision_optics


@dataclass(frozen=True)
class Optics:
    """Brightness model parameters (read from ``ajtwin/vision/optics.toml``)."""

    slope_scale: float
    floor: float
    overspray_threshold: float

    @classmethod
    def from_package(cls) -> Optics:
        """The brightness constants of ``vision/optics.toml``."""
        b = vision_optics()["brightness"]
        return cls(float(b["slope_scale"]), float(b["floor"]), float(b["overspray_threshold"]))


_OPTICS: Optics | None = None


def optics() -> Optics:
    """The project's optics constants (cached)."""
    global _OPTICS
    if _OPTICS is None:
        _OPTICS = Optics.from_package()
    return _OPTICS


# ------------------------------------------------------------------ brightness


def brightness_ratio(h_um: torch.Tensor, um_per_px: float, opt: Optics | None = None):
    """B/B_bg at the pixel midpoints (forward differences), shape ``(..., n−1)``.

    Same formula as :func:`ajtwin.vision.profile.brightness_from_slope`, in torch.
    """
    opt = opt or optics()
    slope = (h_um[..., 1:] - h_um[..., :-1]) / um_per_px
    magnitude = torch.abs(slope)  # its gradient at exactly 0 is 0: harmless
    return opt.floor + (1 - opt.floor) / (1 + magnitude / opt.slope_scale)


def _gather(b: torch.Tensor, idx: np.ndarray) -> torch.Tensor:
    return torch.gather(b, 1, torch.as_tensor(np.clip(idx, 0, b.shape[1] - 1))[:, None])[:, 0]


def _peak_positions(b: torch.Tensor, pos: np.ndarray) -> torch.Tensor:
    """Differentiable parabola vertices at the peak pixels nearest ``pos`` (batch)."""
    n = b.shape[1]
    p = np.rint(np.nan_to_num(pos)).astype(np.int64)
    left, mid, right = _gather(b, p - 1), _gather(b, p), _gather(b, p + 1)
    denom = left - 2 * mid + right
    usable = torch.as_tensor((p > 0) & (p < n - 1)) & (denom.detach() < 0)
    safe = torch.where(usable, denom, -torch.ones_like(denom))
    vertex = torch.clamp(0.5 * (left - right) / safe, -0.5, 0.5)
    return torch.where(usable, torch.as_tensor(p, dtype=b.dtype) + vertex, mid * 0)


def _crossing_positions(b: torch.Tensor, pos: np.ndarray, direction: int, thr: float):
    """Differentiable threshold crossings next to ``pos`` (dark pixel, bright outward)."""
    n = b.shape[1]
    pos = np.nan_to_num(pos)
    dark = (np.floor(pos) if direction > 0 else np.ceil(pos)).astype(np.int64)
    bright = dark + direction
    lo, hi = _gather(b, dark) - thr, _gather(b, bright) - thr
    step = hi - lo
    usable = torch.as_tensor((dark >= 0) & (dark < n) & (bright >= 0) & (bright < n))
    usable = usable & (step.detach() != 0)
    safe = torch.where(usable, step, torch.ones_like(step))
    crossing = torch.as_tensor(dark, dtype=b.dtype) + direction * (-lo / safe)
    return torch.where(usable, crossing, lo * 0)


def _straight_through(values: np.ndarray, formula: torch.Tensor) -> torch.Tensor:
    """``values`` exactly; the gradient of ``formula`` where it reproduces them.

    Elsewhere (plateau peaks, clamped vertices, overspray clipped to the
    shoulder) the value is kept with no gradient.
    """
    target = torch.as_tensor(values, dtype=formula.dtype)
    agrees = (formula.detach() - target).abs() <= 1e-6
    return torch.where(agrees, formula + (target - formula.detach()), target)


def smooth_features(h_um: torch.Tensor, um_per_px: float, *, opt: Optics | None = None):
    """Differentiable linewidth and one-sided overspray of height profiles.

    Parameters
    ----------
    h_um : tensor (batch, n_pixels) or (n_pixels,)
        Height profiles on the camera column's pixel grid, µm.
    um_per_px : float
        Pixel size, µm.
    opt : Optics, optional
        Brightness model (default: ``ajtwin/vision/optics.toml``).

    Returns
    -------
    linewidth_um, overspray_um : tensors (batch,), scalars for 1-D input
        ``nan`` where the definition cannot be applied.

    Examples
    --------
    >>> from ajtwin.vision.profile import line_profile
    >>> r = (np.arange(200) - 99.5) * 0.75
    >>> h = torch.tensor(line_profile(r, 43.0, 29.0, 15.0))
    >>> lw, ov = smooth_features(h, 0.75)
    >>> round(float(lw), 1), round(float(ov), 1)
    (43.5, 28.7)
    """
    opt = opt or optics()
    if h_um.dim() == 1:
        lw, ov = smooth_features(h_um[None], um_per_px, opt=opt)
        return lw[0], ov[0]
    b = brightness_ratio(h_um, um_per_px, opt)
    b_np = b.detach().cpu().numpy().astype(np.float64)
    thr = opt.overspray_threshold
    points = np.array(
        [
            (*p.shoulders, *p.overspray_edges)
            for p in (find_edges(row, 1.0, threshold=thr, noise=0.0) for row in b_np)
        ],
        dtype=np.float64,
    ).reshape(-1, 4)
    sl, sr, el, er = points.T
    shoulder_l = _straight_through(sl, _peak_positions(b, sl))
    shoulder_r = _straight_through(sr, _peak_positions(b, sr))
    edge_l = _straight_through(el, _crossing_positions(b, el, -1, thr))
    edge_r = _straight_through(er, _crossing_positions(b, er, 1, thr))
    linewidth = (shoulder_r - shoulder_l) * um_per_px
    overspray = 0.5 * ((shoulder_l - edge_l) + (edge_r - shoulder_r)) * um_per_px
    return linewidth, overspray


def features_numpy(h_um, um_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Linewidth and overspray (µm) of many profiles, no gradients (evaluation)."""
    with torch.no_grad():
        lw, ov = smooth_features(
            torch.as_tensor(np.atleast_2d(h_um), dtype=torch.float64), um_per_px
        )
    return lw.numpy(), ov.numpy()


def read_features(h_um, um_per_px: float, *, sigma_um: float | None = None, tries: int = 3):
    """Linewidth and overspray of predicted profiles, defined on every profile if possible.

    The model reference §9 definitions react to sub-nm slopes, so a profile with a small
    ripple on its tail may have no clean threshold crossing or shoulder peak
    (``nan``). Those profiles — and only those — are read again after a
    Gaussian smoothing of σ = ``sigma_um`` (default: the scan smoothing the
    stage-1 targets were made with, ``data/profile_cnn.toml``), doubling σ up
    to ``tries`` times. Profiles that are defined as they are keep their value.

    Returns
    -------
    linewidth_um, overspray_um : ndarray (N,)
    fallback : ndarray (N,) bool
        Profiles read through the smoothing fallback.
    """

    h = np.atleast_2d(np.asarray(h_um, dtype=np.float64))
    lw, ov = features_numpy(h, um_per_px)
    bad = ~(np.isfinite(lw) & np.isfinite(ov))
    fallback = bad.copy()
    sigma = default_scan_smoothing_um() if sigma_um is None else float(sigma_um)
    for _ in range(tries):
        if not bad.any() or sigma <= 0:
            break
        smooth = gaussian_filter1d(h[bad], sigma / um_per_px, axis=1, mode="nearest")
        lw_s, ov_s = features_numpy(smooth, um_per_px)
        lw[bad], ov[bad] = lw_s, ov_s
        bad = ~(np.isfinite(lw) & np.isfinite(ov))
        sigma *= 2
    return lw, ov, fallback
