"""Render alignment-camera frames from height profiles (for tests, the demo and the CNN).

A height profile h(r) across the printed line becomes a top-down 8-bit grayscale frame:

1. brightness falls with the deposit's slope
   (:func:`~ajtwin.vision.profile.brightness_from_profile`, model reference §9), evaluated on a fine
   grid in line coordinates (s along the line, d across it);
   the two shoulders and the two overspray edges of that map are stretched independently
   along the line by smooth random fields (edge raggedness — the paper's random shoulder
   variation, App. A);
2. the map is put into the frame with :func:`cv2.remap` at a small tilt and offset and
   averaged over each pixel's width;
3. it multiplies the substrate background: gray level x uneven illumination (linear
   gradient + vignetting) x substrate texture (a smooth random field that moves with the
   platen along the line, so consecutive frames show the substrate sliding by);
4. optical blur (Gaussian PSF), sensor noise (Gaussian read noise + shot noise), 8-bit
   quantisation.

:func:`render_video` streams a whole print into a video (OpenCV) and writes a ground-truth
JSON (true profile per frame, its reference linewidth/overspray, pixel size, frame rate,
platen speed, nuisance settings).  :func:`render_columns` is the fast path for the CNN: many
1-D columns of ``n_px`` pixels straight across the line.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import scipy.fft
from scipy.ndimage import gaussian_filter1d
from tqdm import tqdm

from ajtwin.units import mm_per_s_to_um_per_s
from ajtwin.vision.profile import brightness_from_profile, optics, profile_features

SUBSAMPLES_PER_PX = 4  # across-line samples per pixel in the brightness map
S_STEP_PX = 2  # along-line sampling of the brightness map, pixels
SHOT_NOISE_GRAY = 0.03  # shot-noise variance per gray level (~33 e-/gray, 8.4k e- full well)


@dataclass(frozen=True)
class RenderSettings:
    """Camera and nuisance parameters of a rendered frame (defaults from ``optics.toml``).

    Attributes
    ----------
    um_per_px : float
        Pixel size on the substrate, µm.
    background_gray : float
        Substrate gray level at the frame centre (0–255).
    noise_sigma_gray : float
        Sensor read noise, gray levels (1 sigma); shot noise is added on top.
    blur_sigma_px : float
        Optical blur, Gaussian sigma in pixels (0 = none).
    texture_amplitude : float
        Substrate texture, relative 1-sigma brightness variation.
    texture_correlation_um : float
        Correlation length of the texture, µm.
    illumination_gradient : float
        Relative brightness change from the left to the right frame edge.
    vignetting : float
        Relative brightness loss in the frame corners.
    raggedness_um : float
        1-sigma random displacement of shoulders and overspray edges along the line, µm.
    raggedness_correlation_um : float
        Correlation length of that displacement along the line, µm.
    tilt_deg : float
        Angle of the line against the image x axis, degrees (counter-clockwise on screen).
    offset_px : float
        Perpendicular offset of the line from the frame centre, pixels.
    """

    um_per_px: float = 0.75
    background_gray: float = 170.0
    noise_sigma_gray: float = 2.0
    blur_sigma_px: float = 0.8
    texture_amplitude: float = 0.02
    texture_correlation_um: float = 6.0
    illumination_gradient: float = 0.06
    vignetting: float = 0.08
    raggedness_um: float = 1.0
    raggedness_correlation_um: float = 4.0
    tilt_deg: float = 0.0
    offset_px: float = 0.0

    @classmethod
    def from_defaults(cls, **overrides) -> RenderSettings:
        """Settings from ``optics.toml`` [render], with keyword overrides."""
        known = {f.name for f in dataclasses.fields(cls)}
        base = {k: v for k, v in optics()["render"].items() if k in known}
        unknown = set(overrides) - known
        if unknown:
            raise TypeError(f"unknown render settings: {sorted(unknown)}")
        return cls(**{**base, **overrides})

    def validate(self) -> None:
        """Raise ValueError for a setting out of its range (pixel size, gray levels, noise, blur
        ...)."""
        if not (np.isfinite(self.um_per_px) and self.um_per_px > 0):
            raise ValueError(f"um_per_px must be > 0, got {self.um_per_px}")
        if not 0 < self.background_gray <= 255:
            raise ValueError(f"background_gray must be in (0, 255], got {self.background_gray}")
        for name in (
            "noise_sigma_gray",
            "blur_sigma_px",
            "texture_amplitude",
            "raggedness_um",
            "vignetting",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


def _smooth_noise_1d(n: int, correlation_px: float, rng: np.random.Generator) -> np.ndarray:
    """Periodic smooth Gaussian noise of unit variance (FFT-filtered white noise)."""
    white = rng.standard_normal(n)
    if correlation_px <= 0.5:
        return white
    freq = np.fft.rfftfreq(n)
    spectrum = np.fft.rfft(white) * np.exp(-0.5 * (2 * np.pi * freq * correlation_px) ** 2)
    field = np.fft.irfft(spectrum, n)
    return field / max(field.std(), 1e-12)


def _smooth_noise_2d(shape, correlation_px: float, rng: np.random.Generator) -> np.ndarray:
    """Periodic smooth 2-D Gaussian noise of unit variance."""
    white = rng.standard_normal(shape, dtype=np.float32)
    if correlation_px <= 0.5:
        return white
    fy = np.fft.fftfreq(shape[0])[:, None].astype(np.float32)
    fx = np.fft.rfftfreq(shape[1])[None, :].astype(np.float32)
    kernel = np.exp(-0.5 * (2 * np.pi * correlation_px) ** 2 * (fx**2 + fy**2))
    field = scipy.fft.irfft2(scipy.fft.rfft2(white, workers=-1) * kernel, shape, workers=-1)
    return (field / max(field.std(), 1e-12)).astype(np.float32)


class Substrate:
    """The substrate under the camera: texture and edge raggedness that move with the platen.

    Both are periodic random fields in line coordinates (s along, d across), generated once
    and looked up at ``s + travelled distance`` so the same substrate slides through
    consecutive frames.
    """

    PERIOD_PX = 2048

    def __init__(self, shape, settings: RenderSettings, rng: np.random.Generator):
        height, width = shape
        px = settings.um_per_px
        self.half_diagonal = int(np.ceil(0.5 * np.hypot(height, width))) + 4
        self.texture = settings.texture_amplitude * _smooth_noise_2d(
            (2 * self.half_diagonal, self.PERIOD_PX), settings.texture_correlation_um / px, rng
        )
        corr = settings.raggedness_correlation_um / px
        # independent displacement (µm) of: left shoulder, right shoulder, left/right tail end
        self.raggedness_um = settings.raggedness_um * np.stack(
            [_smooth_noise_1d(self.PERIOD_PX, corr, rng) for _ in range(4)]
        )
        self._geometry: dict = {}

    def geometry(self, shape, settings: RenderSettings):
        """Per-pixel line coordinates (s along + half diagonal, d across) and illumination.

        Cached: consecutive frames of a video share them.
        """
        key = (
            tuple(shape),
            settings.tilt_deg,
            settings.offset_px,
            settings.illumination_gradient,
            settings.vignetting,
        )
        if key not in self._geometry:
            height, width = shape
            theta = np.deg2rad(settings.tilt_deg)
            along = np.array([np.cos(theta), -np.sin(theta)])  # image y points down
            normal = np.array([np.sin(theta), np.cos(theta)])
            xs = np.arange(width, dtype=np.float32) - 0.5 * (width - 1)
            ys = np.arange(height, dtype=np.float32) - 0.5 * (height - 1)
            gx, gy = np.meshgrid(xs, ys)
            s_px = (gx * along[0] + gy * along[1] + self.half_diagonal).astype(np.float32)
            d_px = (gx * normal[0] + gy * normal[1] - settings.offset_px).astype(np.float32)
            self._geometry = {key: (s_px, d_px, _illumination(shape, settings))}
        return self._geometry[key]


def _illumination(shape, settings: RenderSettings) -> np.ndarray:
    height, width = shape
    y = (np.arange(height) - 0.5 * (height - 1))[:, None] / (0.5 * height)
    x = (np.arange(width) - 0.5 * (width - 1))[None, :] / (0.5 * width)
    radius2 = (x**2 + y**2) / 2.0
    return (
        (1.0 + 0.5 * settings.illumination_gradient * x) * (1.0 - settings.vignetting * radius2)
    ).astype(np.float32)


def _landmarks(r_um: np.ndarray, h_um: np.ndarray):
    """Centre, half-widths of the body (shoulders) and outer ends of a profile, µm.

    Used only to place the raggedness warp; approximate on purpose (no feature extraction).
    """
    if not np.any(h_um > 0):
        return 0.0, (1.0, 1.0), (2.0, 2.0)
    top = int(np.argmax(h_um))
    center = float(r_um[top])
    slope = np.gradient(h_um, r_um)
    steep_left = float(r_um[: top + 1][np.argmax(slope[: top + 1])]) if top > 0 else center - 1
    steep_right = float(r_um[top:][np.argmin(slope[top:])])
    # the body's steepest point sits about half-way to the shoulder
    half = (max(2 * (center - steep_left), 1.0), max(2 * (steep_right - center), 1.0))
    nonzero = np.flatnonzero(h_um > 1e-6 * h_um.max())
    ends = (
        max(center - float(r_um[nonzero[0]]), half[0] + 1.0),
        max(float(r_um[nonzero[-1]]) - center, half[1] + 1.0),
    )
    return center, half, ends


def _warp_positions(d_um: np.ndarray, half, ends, shifts_um: np.ndarray) -> np.ndarray:
    """Map displayed positions d to profile positions so shoulders/ends move by ``shifts_um``.

    Piecewise-linear per side: centre fixed, shoulder w -> w + a, end e -> e + b.
    ``shifts_um`` is (4, n_s): left shoulder, right shoulder, left end, right end.
    Returns (n_s, n_d) profile positions.
    """
    out = np.empty((shifts_um.shape[1], d_um.size))
    for side, sign in ((0, -1.0), (1, 1.0)):
        mapped, _ = warp_side(
            sign * d_um[None, :],
            half[side],
            ends[side],
            shifts_um[side][:, None],
            shifts_um[2 + side][:, None],
        )
        mask = (d_um >= 0) if side == 1 else (d_um < 0)
        out[:, mask] = sign * mapped[:, mask]
    return out


def warp_side(u, w, e, a, b):
    """One side of the raggedness warp, elementwise (arrays broadcast).

    A displayed distance ``u >= 0`` from the line centre maps to the profile distance that
    is drawn there when the shoulder at ``w`` moves by ``a`` and the outer end at ``e`` by
    ``b`` (piecewise linear: centre fixed, shoulder ``w -> w + a``, end ``e -> e + b``).

    Returns
    -------
    mapped : array
        Profile distance, µm.
    stretch : array
        d(mapped)/du: the factor the profile's slope is multiplied by where it is drawn.
    """
    w_new = np.maximum(w + a, 0.25 * w)
    e_new = np.maximum(e + b, w_new + 0.25 * (e - w))
    inner_gain = w / w_new
    outer_gain = (e - w) / (e_new - w_new)
    inner = u * inner_gain
    outer = w + (u - w_new) * outer_gain
    beyond = e + (u - e_new)
    mapped = np.where(u <= w_new, inner, np.where(u <= e_new, outer, beyond))
    stretch = np.where(u <= w_new, inner_gain, np.where(u <= e_new, outer_gain, 1.0))
    return mapped, stretch


def render_frame(
    r_um,
    h_um,
    shape: tuple[int, int] = (1024, 1280),
    settings: RenderSettings | None = None,
    *,
    rng: np.random.Generator | None = None,
    substrate: Substrate | None = None,
    travel_um: float = 0.0,
) -> np.ndarray:
    """Render one top-down grayscale frame of a line with cross-section ``h(r)``.

    Parameters
    ----------
    r_um : (n,) array
        Positions across the line, µm, uniform and increasing (0 = line centre).
    h_um : (n,) array
        Deposit height, µm (zero outside the deposit).
    shape : (int, int)
        Frame (rows, columns) in pixels.
    settings : RenderSettings, optional
        Pixel size and nuisance parameters; defaults from ``optics.toml``.
    rng : numpy Generator, optional
        Noise source (sensor noise; substrate when ``substrate`` is not given).
    substrate : Substrate, optional
        Texture and raggedness fields shared by consecutive frames of one video.
    travel_um : float
        Distance the platen has moved (shifts texture and raggedness along the line).

    Returns
    -------
    frame : (rows, cols) uint8 array

    Examples
    --------
    >>> from ajtwin.vision.profile import line_profile
    >>> r = np.arange(-100, 100, 0.1)
    >>> frame = render_frame(r, line_profile(r, 43, 29, 15), shape=(240, 320),
    ...                      rng=np.random.default_rng(0))
    >>> frame.shape, frame.dtype.name
    ((240, 320), 'uint8')
    """
    settings = RenderSettings.from_defaults() if settings is None else settings
    settings.validate()
    rng = np.random.default_rng() if rng is None else rng
    height, width = int(shape[0]), int(shape[1])
    if height < 8 or width < 8:
        raise ValueError(f"frame shape must be at least 8x8, got {shape}")
    r_um = np.asarray(r_um, dtype=float)
    h_um = np.asarray(h_um, dtype=float)
    if r_um.shape != h_um.shape or r_um.ndim != 1:
        raise ValueError(
            f"r_um and h_um must be 1-D of equal length, got {r_um.shape}, {h_um.shape}"
        )
    if substrate is None:
        substrate = Substrate((height, width), settings, rng)
    px = settings.um_per_px

    # --- brightness map in line coordinates (rows: s along the line, cols: d across) ---
    center, half, ends = _landmarks(r_um, h_um)
    margin_um = 4.0 * settings.raggedness_um + 4.0 * px
    d_extent_um = max(ends) + margin_um
    step_um = px / SUBSAMPLES_PER_PX
    d_um = np.arange(-d_extent_um, d_extent_um + step_um, step_um)
    # the map is sampled every S_STEP_PX along the line (raggedness is smooth over 4 µm)
    s_count = 2 * substrate.half_diagonal // S_STEP_PX + 2
    s_index = (np.arange(s_count) * S_STEP_PX + int(round(travel_um / px))) % Substrate.PERIOD_PX
    shifts = substrate.raggedness_um[:, s_index]
    if settings.raggedness_um > 0:
        profile_r = _warp_positions(d_um, half, ends, shifts) + center
    else:
        profile_r = np.broadcast_to(d_um + center, (s_count, d_um.size))
    heights = np.interp(profile_r.ravel(), r_um, h_um, left=0.0, right=0.0).reshape(profile_r.shape)
    line_map = brightness_from_profile(d_um, heights).astype(np.float32)
    # average over each pixel's width (box of SUBSAMPLES_PER_PX samples across the line)
    line_map = cv2.blur(line_map, (SUBSAMPLES_PER_PX, 1), borderType=cv2.BORDER_REPLICATE)

    # --- pixel -> line coordinates (cached per frame geometry on the substrate) ---
    s_px, d_px, illumination = substrate.geometry((height, width), settings)
    map_d = (d_px * (px / step_um) + d_extent_um / step_um).astype(np.float32)
    line = cv2.remap(
        line_map,
        map_d,
        s_px * (1.0 / S_STEP_PX),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=1.0,
    )
    texture_s = (s_px + np.float32(travel_um / px)) % Substrate.PERIOD_PX
    texture = cv2.remap(
        substrate.texture,
        texture_s,
        d_px + np.float32(substrate.half_diagonal),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP,
    )

    return sensor_image(line, texture, illumination, settings, rng)


def sensor_image(line, texture, illumination, settings: RenderSettings, rng) -> np.ndarray:
    """Optics and sensor: relative brightness -> 8-bit frame.

    ``background_gray x illumination x (1 + texture) x line``, then the Gaussian blur of the
    optics, read and shot noise, and 8-bit quantisation.
    """
    image = settings.background_gray * illumination * (1.0 + texture) * line
    if settings.blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), settings.blur_sigma_px)
    variance = settings.noise_sigma_gray**2 + SHOT_NOISE_GRAY * np.maximum(image, 0)
    image = image + rng.standard_normal(image.shape, dtype=np.float32) * np.sqrt(variance)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def column_positions_um(n_px: int = 200, um_per_px: float = 0.75) -> np.ndarray:
    """Pixel-centre positions (µm) of a column of ``n_px`` pixels centred on the line."""
    return (np.arange(n_px) - 0.5 * (n_px - 1)) * um_per_px


def render_columns(
    r_um,
    h_um,
    *,
    n_px: int = 200,
    um_per_px: float = 0.75,
    rng: np.random.Generator | None = None,
    background_gray: float | tuple[float, float] = 170.0,
    noise_sigma_gray: float = 2.0,
    blur_sigma_px: float = 0.8,
    center_jitter_px: float = 0.0,
    shot_noise: float = SHOT_NOISE_GRAY,
    as_uint8: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Render many 1-D grayscale columns straight across the line (fast path for the CNN).

    The same optics as :func:`render_frame` (slope brightness, pixel-width averaging,
    Gaussian blur, read + shot noise), without tilt, texture and illumination.

    Parameters
    ----------
    r_um : (n,) array
        Uniform, increasing positions of the profiles, µm (0 = line centre).
    h_um : (n,) or (N, n) array
        One or ``N`` height profiles, µm.
    n_px : int
        Pixels per column.
    um_per_px : float
        Pixel size, µm.
    rng : numpy Generator, optional
    background_gray : float or (low, high)
        Substrate gray level, or a range to draw one per column from.
    noise_sigma_gray, blur_sigma_px : float
        Read noise (gray levels) and blur (pixels).
    center_jitter_px : float
        1-sigma random shift of the line centre per column, pixels.
    shot_noise : float
        Shot-noise variance per gray level (0 with ``noise_sigma_gray = 0`` = noiseless).
    as_uint8 : bool
        Quantise to uint8 (else float32 gray levels, still noisy).

    Returns
    -------
    columns : (N, n_px) array
        Gray levels.
    r_px_um : (n_px,) array
        Pixel-centre positions (µm) in profile coordinates, before jitter.

    Examples
    --------
    >>> from ajtwin.vision.profile import line_profile
    >>> r = np.arange(-100, 100, 0.1)
    >>> cols, pos = render_columns(r, line_profile(r, 43, 29, 15), rng=np.random.default_rng(1))
    >>> cols.shape, pos.shape
    ((1, 200), (200,))
    """
    rng = np.random.default_rng() if rng is None else rng
    r_um = np.asarray(r_um, dtype=float)
    profiles = np.atleast_2d(np.asarray(h_um, dtype=float))
    if profiles.shape[1] != r_um.size:
        raise ValueError(f"h_um has {profiles.shape[1]} samples per profile, r_um has {r_um.size}")
    dr = (r_um[-1] - r_um[0]) / (r_um.size - 1)
    if np.any(np.abs(np.diff(r_um) - dr) > 1e-6 * abs(dr)) or dr <= 0:
        raise ValueError("r_um must be uniform and increasing")
    count = profiles.shape[0]
    r_px = column_positions_um(n_px, um_per_px)
    sub = (np.arange(SUBSAMPLES_PER_PX) + 0.5) / SUBSAMPLES_PER_PX - 0.5
    r_sub = (r_px[:, None] + sub[None, :] * um_per_px).ravel()
    shift = (
        rng.normal(0.0, center_jitter_px * um_per_px, count)
        if center_jitter_px > 0
        else np.zeros(count)
    )
    # vectorised linear interpolation on the uniform grid
    pos = (r_sub[None, :] - shift[:, None] - r_um[0]) / dr
    inside = (pos >= 0) & (pos <= r_um.size - 1)
    base = np.clip(np.floor(pos).astype(np.int64), 0, r_um.size - 2)
    frac = pos - base
    lower = np.take_along_axis(profiles, base, axis=1)
    upper = np.take_along_axis(profiles, base + 1, axis=1)
    heights = np.where(inside, lower + frac * (upper - lower), 0.0)
    step = um_per_px / SUBSAMPLES_PER_PX
    sub_r = np.arange(r_sub.size) * step
    brightness = brightness_from_profile(sub_r, heights)
    pixels = brightness.reshape(count, n_px, SUBSAMPLES_PER_PX).mean(axis=2)
    if np.ndim(background_gray) == 0:
        gray = np.full((count, 1), float(background_gray))
    else:
        low, high = background_gray
        gray = rng.uniform(low, high, (count, 1))
    image = gray * pixels
    if blur_sigma_px > 0:
        image = gaussian_filter1d(image, blur_sigma_px, axis=1, mode="nearest")
    variance = noise_sigma_gray**2 + shot_noise * np.maximum(image, 0)
    image = image + rng.standard_normal(image.shape) * np.sqrt(variance)
    if as_uint8:
        return np.clip(np.rint(image), 0, 255).astype(np.uint8), r_px
    return image.astype(np.float32), r_px


def _fourcc_for(path: Path) -> int:
    suffix = path.suffix.lower()
    if suffix == ".mp4":
        return cv2.VideoWriter_fourcc(*"mp4v")
    if suffix in (".avi", ".mkv"):
        return cv2.VideoWriter_fourcc(*"FFV1")  # lossless
    raise ValueError(f"{path}: video must end in .mp4 (mp4v, lossy) or .avi/.mkv (FFV1, lossless)")


@dataclass(frozen=True)
class TruthFile:
    """A rendered video's ground truth: its JSON ``path`` (None: the video's path with
    ``.json``), ``extra`` keys for it (e.g. the print's scenario) and ``step_um``, the grid
    step of the profiles it stores [µm] (keeps a 90-min print's truth small; the reference
    linewidth and overspray are computed on the full grid)."""

    path: str | Path | None = None
    extra: dict = field(default_factory=dict)
    step_um: float = 0.25


def render_video(
    r_um,
    profiles: Sequence[np.ndarray] | np.ndarray,
    profile_times_s: Sequence[float] | np.ndarray,
    out_path: str | Path,
    *,
    fps: float = 1.0,
    duration_s: float | None = None,
    shape: tuple[int, int] = (1024, 1280),
    settings: RenderSettings | None = None,
    platen_speed_mm_s: float = 1.0,
    seed: int = 0,
    truth: TruthFile = TruthFile(),
    progress: bool = True,
) -> Path:
    """Render a video of a print from a sequence of cross-sections, plus ground truth.

    Frame ``k`` is taken at ``t = k / fps`` and shows the latest profile with
    ``profile_times_s <= t`` (profiles are held, not blended: a blend of two profiles would
    have two shoulders).  Frames are rendered and written one at a time.

    Parameters
    ----------
    r_um : (n,) array
        Common, uniform grid of the profiles, µm.
    profiles : (P, n) array or sequence of (n,) arrays
        Height profiles, µm.
    profile_times_s : (P,) array
        Print time of each profile, s, increasing; the first must be <= 0.
    out_path : path
        ``.mp4`` (mp4v, lossy) or ``.avi``/``.mkv`` (FFV1, lossless).
    fps : float
        Frame rate of the video.
    duration_s : float, optional
        Video length (default: last profile time + 1 / fps).
    shape : (int, int)
        Frame size (rows, cols).
    settings : RenderSettings, optional
    platen_speed_mm_s : float
        Platen speed (moves texture and raggedness; stored in the truth).
    seed : int
        Seeds substrate and noise.
    truth : TruthFile
        Where the ground-truth JSON goes and what more it holds.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    Path of the truth JSON.
    """
    settings = RenderSettings.from_defaults() if settings is None else settings
    settings.validate()
    out_path = Path(out_path)
    truth_path = out_path.with_suffix(".json") if truth.path is None else Path(truth.path)
    r_um = np.asarray(r_um, dtype=float)
    profile_times_s = np.asarray(profile_times_s, dtype=float)
    if len(profiles) != profile_times_s.size or profile_times_s.size == 0:
        raise ValueError(f"{len(profiles)} profiles but {profile_times_s.size} times")
    if np.any(np.diff(profile_times_s) < 0):
        raise ValueError("profile_times_s must be increasing")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be > 0, got {fps}")
    if duration_s is None:
        duration_s = float(profile_times_s[-1]) + 1.0 / fps
    n_frames = max(1, int(np.floor(duration_s * fps + 1e-9)))
    writer = cv2.VideoWriter(str(out_path), _fourcc_for(out_path), fps, (shape[1], shape[0]), False)
    if not writer.isOpened():
        raise OSError(f"{out_path}: OpenCV cannot open a video writer here")
    rng = np.random.default_rng(seed)
    substrate = Substrate(shape, settings, rng)
    speed_um_s = mm_per_s_to_um_per_s(platen_speed_mm_s)
    dr = float(r_um[1] - r_um[0]) if r_um.size > 1 else 1.0
    stored = _VideoTruth(r_um, profiles, profile_times_s, max(1, int(round(truth.step_um / dr))))
    try:
        for k in tqdm(
            range(n_frames), desc=f"render {out_path.name}", unit="frame", disable=not progress
        ):
            t = k / fps
            index = int(np.clip(np.searchsorted(profile_times_s, t, side="right") - 1, 0, None))
            h = np.asarray(profiles[index], dtype=float)
            frame = render_frame(
                r_um, h, shape, settings, rng=rng, substrate=substrate, travel_um=speed_um_s * t
            )
            writer.write(frame)
            stored.add_frame(k, t, index)
    finally:
        writer.release()
    document = {
        "video": out_path.name,
        "fps": fps,
        "n_frames": n_frames,
        "frame_shape": list(shape),
        "um_per_px": settings.um_per_px,
        "platen_speed_mm_s": platen_speed_mm_s,
        "seed": seed,
        "settings": dataclasses.asdict(settings),
        "definitions": "linewidth/overspray of the true profile: ajtwin.vision.profile_features",
        "r_um": np.round(r_um[:: stored.stride], 6).tolist(),
        "profiles": stored.profiles,
        "frames": stored.frames,
        **truth.extra,
    }
    truth_path.write_text(json.dumps(document, allow_nan=True))
    return truth_path


class _VideoTruth:
    """The ground truth of a rendered video, grown frame by frame: each profile shown (its
    reference linewidth and overspray, area, the profile on a coarser grid) and, per frame,
    which profile it shows."""

    def __init__(self, r_um, profiles, profile_times_s, stride: int):
        self.r_um, self.source, self.times, self.stride = r_um, profiles, profile_times_s, stride
        self.profiles: list[dict] = []
        self.frames: list[dict] = []

    def add_frame(self, k: int, t: float, index: int) -> None:
        """Frame ``k`` at ``t`` [s] shows profile ``index`` (its truth added when new)."""
        while len(self.profiles) <= index:
            j = len(self.profiles)
            hj = np.asarray(self.source[j], dtype=float)
            lw, ov = profile_features(self.r_um, hj)
            self.profiles.append(
                {
                    "index": j,
                    "time_s": float(self.times[j]),
                    "linewidth_um": lw,
                    "overspray_um": ov,
                    "area_um2": float(np.trapezoid(hj, self.r_um)),
                    "h_um": np.round(hj[:: self.stride], 6).tolist(),
                }
            )
        self.frames.append(
            {
                "frame": k,
                "time_s": t,
                "profile": index,
                "linewidth_um": self.profiles[index]["linewidth_um"],
                "overspray_um": self.profiles[index]["overspray_um"],
            }
        )
