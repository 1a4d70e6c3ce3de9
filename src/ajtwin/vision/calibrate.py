"""Fit the camera's geometry (µm per pixel, rotation, offset) to frames of known strokes.

The program says where every trace is on the part and when it was printed; the job says
where the nozzle is when each frame is taken. A frame therefore shows the traces where the
camera's geometry puts them (:mod:`ajtwin.vision.camera`): the part point under pixel
``(col, row)`` is ``p(t) + o + (s/1000) · R(θ) · (col − col₀, row − row₀)``. Calibration
finds ``s`` (µm per pixel), ``θ`` (rotation) and ``o`` (offset) that put the lines seen in
the frames onto the program's traces.

1. **Line centres in the frames.** Each frame is reduced and smoothed at a scale of
   about a third of the trace's reach, where a trace (dark flanks, bright top, faint
   overspray) becomes one dark valley; the valley's centre line is found with sub-pixel
   precision from the Hessian of the smoothed image (C. Steger, "An unbiased detector of
   curvilinear structures", IEEE PAMI 20(2), 1998: the second derivative across the line
   is large and positive, and the first derivative crosses zero within the pixel). One
   point is kept per 8 x 8 block of the reduced frame, so neighbouring points do not share
   the same noise.
2. **Search.** From the starting camera (a file, or the nominal values), rotations over
   the whole turn and pixel sizes within ±25 % are scored by the share of points that land
   within ``gate_um`` of a trace printed before their frame
   (:meth:`ajtwin.job.Job.locate`); the offset must be known to about the gate (the
   machine's nominal offset).
3. **Least squares.** The signed distance of every point to its nearest trace is the
   residual; Gauss-Newton over (θ, s, o_x, o_y) with the exact derivatives of the mapping,
   points re-associated with their nearest trace at every step, robust Tukey weights
   (points on texture or a detached speck get weight 0) and a gate that shrinks to
   4.685 robust sigmas. Points near other traces (fills, crossings, neighbours: an
   association there could pick the wrong trace) are left out.
4. **Standard errors** from the weighted normal equations, ``σ² (JᵀWJ)⁻¹`` with σ the
   residuals' weighted spread; they assume independent points (points are ≥ 8 reduced
   pixels apart, several times the edges' correlation length).

A fit is **refused**, with the reason, when the frames cannot determine it: too few
points on clean traces, traces of one direction only (the offset along them and the scale
are then free: the weak combination of parameters is named), standard errors beyond
``MAX_SE`` or residuals larger than a trace's position can be off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from ajtwin.vision.camera import Camera
from ajtwin.vision.errors import VisionInputError
from ajtwin.vision.extract import area_downscale
from ajtwin.vision.part_extract import PartSettings, Windows
from ajtwin.vision.part_video import check_video_duration

__all__ = [
    "CalibrationError",
    "CalibrationResult",
    "line_centre_points",
    "calibrate_camera",
    "calibrate_video",
]

#: Largest standard errors of a fit that is kept: (µm/px relative, degrees, µm).
MAX_SE = {"um_per_px_relative": 0.01, "rotation_deg": 0.5, "offset_um": 5.0}
#: Residuals (robust sigma) above this mean the frames are not the program's traces.
MAX_RESIDUAL_UM = 6.0
MIN_POINTS = 30
TUKEY_C = 4.685
BLOCK = 4  # reduced pixels per kept point
SCALE_STEPS = (0.8, 0.9, 1.0, 1.1, 1.25)
ROTATION_STEP_DEG = 5.0


class CalibrationError(ValueError):
    """Frames that cannot determine the camera's geometry; the message says why."""


@dataclass(frozen=True)
class CalibrationResult:
    """A fitted camera with its standard errors and how well the frames fit it."""

    camera: Camera
    points: int
    frames: int
    residual_um: float  # robust sigma of the point-to-trace distances
    correlation: np.ndarray  # of (rotation, scale, offset x, offset y)


def line_centre_points(gray: np.ndarray, um_per_px: float, reach_um: float = 75.0):
    """Sub-pixel centre points of the dark lines of a frame.

    Parameters
    ----------
    gray : (rows, cols) uint8
    um_per_px : float
        Pixel size (sets the smoothing scale to the trace's size).
    reach_um : float
        Reach of a trace's deposit from its centre line, µm.

    Returns
    -------
    col, row : (n,) arrays
        Full-resolution pixel positions of valley centre points.
    strength : (n,) array
        Second derivative across the valley (gray levels per reduced pixel²).
    """
    sigma_full = max(1.5, reach_um / 3.0 / um_per_px)
    q = max(1, int(sigma_full // 4))
    small = area_downscale(gray, q).astype(np.float32)
    sigma = sigma_full / q
    smooth = cv2.GaussianBlur(small, (0, 0), sigma).astype(np.float64)
    # uneven illumination tilts the valley's sides and moves its centre (vignetting would
    # move every point away from the middle: a false scale): divide it out first
    smooth /= _illumination_surface(smooth, int(2 * reach_um / um_per_px / q) | 1)
    gy, gx = np.gradient(smooth)
    gyy, gyx = np.gradient(gy)
    _, gxx = np.gradient(gx)
    half_trace = 0.5 * (gxx + gyy)
    root = np.sqrt(0.25 * (gxx - gyy) ** 2 + gyx**2)
    lam = half_trace + root  # the larger eigenvalue: curvature across a dark valley
    nx, ny = gyx, lam - gxx
    norm = np.hypot(nx, ny)
    flat = norm < 1e-12
    nx = np.where(flat, 1.0, nx / np.where(flat, 1.0, norm))
    ny = np.where(flat, 0.0, ny / np.where(flat, 1.0, norm))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(gx * nx + gy * ny) / lam
    strong = lam > 0.3 * np.percentile(lam, 99.5)
    strong &= lam > 0
    centre = strong & (np.abs(t * nx) <= 0.5) & (np.abs(t * ny) <= 0.5)
    edge = max(2, int(math.ceil(3 * sigma)))  # blur reflected at the border moves lines
    centre[:edge], centre[-edge:], centre[:, :edge], centre[:, -edge:] = False, False, False, False
    rows, cols = np.nonzero(centre)
    if rows.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    sub_c = cols + t[rows, cols] * nx[rows, cols]
    sub_r = rows + t[rows, cols] * ny[rows, cols]
    strength = lam[rows, cols]
    # one point per block: the strongest
    block = (rows // BLOCK) * (small.shape[1] // BLOCK + 1) + cols // BLOCK
    order = np.lexsort((-strength, block))
    first = order[np.r_[True, block[order][1:] != block[order][:-1]]]
    col = (sub_c[first] + 0.5) * q - 0.5
    row = (sub_r[first] + 0.5) * q - 0.5
    return col, row, strength[first]


def _illumination_surface(image: np.ndarray, window: int) -> np.ndarray:
    """Quadratic surface fitted to the substrate: the pixels within 2 % of the brightest
    around them (``window`` pixels wide: wider than a trace), so traces are left out
    wherever they are, also in the darker corners."""
    rows, cols = np.indices(image.shape, dtype=float)
    y = rows / image.shape[0] - 0.5
    x = cols / image.shape[1] - 0.5
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1).reshape(-1, 6)
    values = image.reshape(-1)
    local = cv2.dilate(image.astype(np.float32), np.ones((window, window), np.uint8))
    bright = values >= 0.98 * local.reshape(-1)
    if bright.sum() < 50:
        bright = values >= np.median(values)
    coef, *_ = np.linalg.lstsq(design[bright], values[bright], rcond=None)
    surface = (design @ coef).reshape(image.shape)
    return np.maximum(surface, 1e-6 * max(float(values.max()), 1.0))


SPOT_MM = 0.05  # points on the same 50 µm of a trace share its edges' raggedness


def _cluster_covariance(jac, r, stroke, s_mm, sigma) -> np.ndarray:
    """Covariance of the least-squares fit, allowing for points that are not independent.

    Points that look at the same spot of a trace (the same stroke within ``SPOT_MM``, in
    any frame) share the raggedness of its edges and the substrate there: they count as
    one. ``σ² (JᵀJ)⁻¹`` is inflated by the number of points per spot (the design effect
    of fully correlated clusters).
    """
    spot = np.floor(s_mm / SPOT_MM).astype(np.int64)
    n_spots = np.unique(np.stack([stroke, spot]), axis=1).shape[1]
    return np.linalg.inv(jac.T @ jac) * sigma**2 * (r.size / max(n_spots, 1))


def _axes(theta):
    c, s = math.cos(theta), math.sin(theta)
    return np.array([c, s]), np.array([s, -c]), np.array([-s, c]), np.array([c, s])


def _project(params, u, v, nozzle):
    """Part points of pixel offsets (u, v) from the centre, and their derivatives."""
    theta, scale, ox, oy = params
    ex, ey, dex, dey = _axes(theta)
    k = scale * 1e-3
    x = nozzle[:, 0] + ox + k * (u * ex[0] + v * ey[0])
    y = nozzle[:, 1] + oy + k * (u * ex[1] + v * ey[1])
    d_theta = np.stack([k * (u * dex[0] + v * dey[0]), k * (u * dex[1] + v * dey[1])])
    d_scale = np.stack([1e-3 * (u * ex[0] + v * ey[0]), 1e-3 * (u * ex[1] + v * ey[1])])
    return x, y, d_theta, d_scale


def _residuals(job, params, u, v, nozzle, times, gate_mm):
    """Signed distance (mm) of each point to its nearest trace, its normal, and found."""
    x, y, d_theta, d_scale = _project(params, u, v, nozzle)
    hits = job.locate(x, y, radius_mm=gate_mm, before_s=times)
    nx, ny = -hits.uy, hits.ux
    r = (x - hits.x_mm) * nx + (y - hits.y_mm) * ny
    jac = np.stack(
        [
            d_theta[0] * nx + d_theta[1] * ny,
            d_scale[0] * nx + d_scale[1] * ny,
            nx,
            ny,
        ],
        axis=1,
    )
    return np.where(hits.found, r, np.nan), jac, hits


def _robust_sigma(r):
    r = r[np.isfinite(r)]
    return 1.4826 * float(np.median(np.abs(r))) if r.size else np.inf


def calibrate_camera(
    job,
    frames,
    initial: Camera,
    *,
    reach_um: float = 75.0,
    gate_um: float = 60.0,
    search: bool = True,
    clean=None,
) -> CalibrationResult:
    """Fit ``um_per_px``, ``rotation_deg`` and ``offset_mm`` to frames of a job's part.

    Parameters
    ----------
    job : ajtwin.job.Job
    frames : sequence of (time_s, gray)
        Frames taken at these job times (at least two, over printed traces).
    initial : Camera
        Starting geometry (frame size must match the frames).
    reach_um : float
        A trace's reach (sets the line-finding scale).
    gate_um : float
        A point further than this from every trace is not used (the starting offset
        should be this good).
    search : bool
        Search rotations over the whole turn and pixel sizes within ±25 % first.
    clean : callable, optional
        ``clean(stroke, s_mm, time_s) -> bool array``: points on traces that may be used
        (e.g. not in fills or crossings).

    Raises
    ------
    CalibrationError
        Naming why the frames cannot determine the geometry.
    """
    box = getattr(job, "program", job).summary()["bbox_mm"]
    extent_um = 0.0 if box is None else 1e3 * math.hypot(box[2] - box[0], box[3] - box[1])
    if not 0 < gate_um <= max(extent_um, reach_um):
        # a gate wider than the whole part admits every trace: it gates nothing, and asks
        # the trace index for cells the size of the gate
        raise CalibrationError(
            f"gate_um = {gate_um:g} µm is wider than the whole printed part ({extent_um:.0f} µm "
            "corner to corner): give the starting offset to within a gate smaller than the part"
        )
    cols, rows, times, nozzles = [], [], [], []
    for time_s, gray in frames:
        if gray.shape != (initial.height_px, initial.width_px):
            raise CalibrationError(
                f"frames are {gray.shape[1]}x{gray.shape[0]} px but the starting camera says "
                f"{initial.width_px}x{initial.height_px}"
            )
        c, r, _ = line_centre_points(gray, initial.um_per_px, reach_um)
        state = job.state_at(time_s)
        cols.append(c)
        rows.append(r)
        times.append(np.full(c.size, float(time_s)))
        nozzles.append(np.tile([float(state.x_mm), float(state.y_mm)], (c.size, 1)))
    n_frames = len(frames)
    if n_frames == 0:
        raise CalibrationError("no frame to calibrate from")
    col0, row0 = initial.centre_px
    u = np.concatenate(cols) - col0
    v = np.concatenate(rows) - row0
    times = np.concatenate(times)
    nozzle = np.concatenate(nozzles) if nozzles else np.zeros((0, 2))
    if u.size < MIN_POINTS:
        raise CalibrationError(
            f"only {u.size} line points in {n_frames} frames: the frames show too little of "
            "the printed traces (pick frames over printed strokes)"
        )
    params = np.array(
        [math.radians(initial.rotation_deg), initial.um_per_px, *initial.offset_mm], dtype=float
    )
    gate = gate_um * 1e-3
    if search:
        params = _search(job, params, u, v, nozzle, times, gate)
    found_any = False
    for gate_now in (gate, 0.5 * gate, None):
        for _ in range(12):
            r, jac, hits = _residuals(job, params, u, v, nozzle, times, gate)
            use = np.isfinite(r)
            if clean is not None and use.any():
                use[use] = clean(hits.stroke[use], hits.s_mm[use], times[use])
            if use.sum() < MIN_POINTS:
                break
            found_any = True
            if gate_now is not None:  # first plain least squares inside a shrinking gate
                w = (use & (np.abs(np.nan_to_num(r, nan=np.inf)) < gate_now)).astype(float)
            else:  # then Tukey's biweight at 4.685 robust sigmas
                sigma = max(_robust_sigma(r[use]), 1e-6)
                z = np.where(use, np.nan_to_num(r, nan=np.inf) / sigma, np.inf)
                w = np.where(np.abs(z) < TUKEY_C, (1 - (z / TUKEY_C) ** 2) ** 2, 0.0)
            if (w > 0).sum() < MIN_POINTS:
                break
            a = jac[w > 0] * np.sqrt(w[w > 0])[:, None]
            b = r[w > 0] * np.sqrt(w[w > 0])
            step, *_ = np.linalg.lstsq(a, -b, rcond=None)
            params = params + step
            if abs(step[0]) < 1e-8 and abs(step[1]) < 1e-7 and np.all(np.abs(step[2:]) < 1e-7):
                break
    if not found_any:
        raise CalibrationError(
            f"no line point lies within {gate_um:g} µm of a printed trace under the starting "
            "camera: the starting offset_mm (or --start-offset, or the program) is wrong by "
            "more than that"
        )
    return _result(job, params, u, v, nozzle, times, initial, n_frames, clean)


def _search(job, params, u, v, nozzle, times, gate):
    """Best rotation (5° steps over the turn) and scale (±25 %) at the starting offset."""
    rng = np.random.default_rng(0)
    pick = rng.choice(u.size, size=min(u.size, 400), replace=False)
    best, best_score = params, -1.0
    start_theta = params[0]
    for turn in np.radians(np.arange(0.0, 360.0, ROTATION_STEP_DEG)):
        for factor in SCALE_STEPS:
            trial = params.copy()
            trial[0] = start_theta + turn
            trial[1] = params[1] * factor
            x, y, _, _ = _project(trial, u[pick], v[pick], nozzle[pick])
            hits = job.locate(x, y, radius_mm=0.5 * gate, before_s=times[pick])
            score = float(hits.found.mean())
            if score > best_score + 1e-9:
                best, best_score = trial, score
    best[0] = (best[0] + math.pi) % (2 * math.pi) - math.pi
    return best


def _result(job, params, u, v, nozzle, times, initial, n_frames, clean) -> CalibrationResult:
    r, jac, hits = _residuals(job, params, u, v, nozzle, times, 0.05)
    use = np.isfinite(r)
    if clean is not None and use.any():
        use[use] = clean(hits.stroke[use], hits.s_mm[use], times[use])
    sigma = _robust_sigma(r[use])
    keep = use & (np.abs(r) < TUKEY_C * sigma)
    n = int(keep.sum())
    if n < MIN_POINTS:
        raise CalibrationError(
            f"only {n} line points fit the program's traces: too few to calibrate (frames over "
            "more printed strokes, or a better starting camera)"
        )
    sigma_um = 1e3 * sigma
    if sigma_um > MAX_RESIDUAL_UM:
        raise CalibrationError(
            f"the lines seen lie {sigma_um:.1f} µm (robust sigma) from the program's traces "
            f"after the fit (expected a few µm): the video and the program do not match, or "
            "the clock (--start-offset) is off"
        )
    a = jac[keep]
    # parameters in comparable units (µm at the frame's corner) to judge what is determined
    half_diag_px = 0.5 * math.hypot(initial.width_px, initial.height_px)
    units = np.array(
        [half_diag_px * params[1], half_diag_px, 1e3, 1e3]
    )  # µm per (rad, µm/px, mm, mm)
    scaled = (a * 1e3) / units  # residual µm per unit of µm-equivalent
    info = scaled.T @ scaled
    eigval, eigvec = np.linalg.eigh(info)
    names = ("rotation", "pixel size", "offset x", "offset y")
    if eigval[0] <= 1e-9 * eigval[-1]:
        weak = eigvec[:, 0]
        involved = [names[k] for k in np.argsort(-np.abs(weak)) if abs(weak[k]) > 0.3]
        raise CalibrationError(
            "the frames cannot determine the camera's "
            + " and ".join(involved)
            + ": the traces seen run in one direction only (or too few are seen); add frames "
            "over a corner, a stroke end or traces at another angle"
        )
    cov = _cluster_covariance(a, r[keep], hits.stroke[keep], hits.s_mm[keep], sigma)
    se = np.sqrt(np.diag(cov))
    checks = {
        "pixel size": se[1] / params[1] > MAX_SE["um_per_px_relative"],
        "rotation": math.degrees(se[0]) > MAX_SE["rotation_deg"],
        "offset": max(se[2], se[3]) * 1e3 > MAX_SE["offset_um"],
    }
    loose = [k for k, bad in checks.items() if bad]
    if loose:
        raise CalibrationError(
            f"the frames determine the camera's {' and '.join(loose)} too loosely (standard "
            f"errors: pixel size {100 * se[1] / params[1]:.2g} %, rotation "
            f"{math.degrees(se[0]):.2g}°, offset {1e3 * se[2]:.2g}/{1e3 * se[3]:.2g} µm): add "
            "frames over more traces, in other directions"
        )
    corr = cov / np.outer(se, se)
    rotation = (math.degrees(params[0]) + 180.0) % 360.0 - 180.0
    camera = replace(
        initial,
        um_per_px=float(params[1]),
        rotation_deg=float(rotation),
        offset_mm=(float(params[2]), float(params[3])),
        um_per_px_se=float(se[1]),
        rotation_deg_se=float(math.degrees(se[0])),
        offset_mm_se=(float(se[2]), float(se[3])),
        calibration={
            "points": n,
            "frames": n_frames,
            "residual_um": round(sigma_um, 4),
        },
    )
    return CalibrationResult(camera, n, n_frames, sigma_um, corr)


def frames_over_traces(job, frames, start: Camera, windows: Windows, start_offset_s, n_frames):
    """Up to ``n_frames`` frames spread over the video where the starting camera shows a
    printed trace: a list of (job time [s], gray frame).

    Raises
    ------
    VisionInputError
        A video that does not state its frame count, or fewer than two frames over traces.
    """
    if not frames.count:
        raise VisionInputError(f"{frames.path}: the video does not state its frame count")
    times = start_offset_s + np.arange(frames.count) / frames.fps
    radius = start.half_diagonal_mm
    state = job.state_at(times)
    centre = np.column_stack([state.x_mm, state.y_mm]) + np.asarray(start.offset_mm)
    seen = np.array(
        [
            np.any(windows.t_to[windows.near(x, y, radius)] < t)
            for (x, y), t in zip(centre, times, strict=True)
        ]
    )
    candidates = np.flatnonzero(seen)
    if candidates.size < 2:
        raise VisionInputError(
            f"{frames.path}: under the starting camera only {candidates.size} frame(s) show a "
            "printed trace: give a starting --offset-mm (or --camera) closer to the machine's, "
            "and the right --start-offset"
        )
    chosen = set(candidates[np.linspace(0, candidates.size - 1, n_frames).round().astype(int)])
    picked = []
    with frames.prefetched() as decoded:
        for index, video_time, gray in decoded:
            if index in chosen:
                picked.append((start_offset_s + video_time, gray))
            if len(picked) == len(chosen):
                break
    return picked


def calibrate_video(
    frames,
    job,
    start: Camera,
    *,
    start_offset_s: float = 0.0,
    n_frames: int = 12,
    gate_um: float = 60.0,
    search: bool = True,
    program_name: str | None = None,
) -> CalibrationResult:
    """Fit the camera's geometry to a video of a job's part (:func:`calibrate_camera` on
    frames spread over the video where traces are in view).

    Parameters
    ----------
    frames : FrameSource
        The opened video (:func:`ajtwin.vision.extract.open_source`).
    job : ajtwin.job.Job
        The program as the print ran it.
    start : Camera
        Starting geometry (its offset right to within about ``gate_um``).
    start_offset_s : float
        Job time of the video's first frame [s].
    n_frames, gate_um, search
        Frames used; the gate and the search of :func:`calibrate_camera`.
    program_name : str, optional
        The program, for the messages.

    Raises
    ------
    VisionInputError
        A video beyond the job's end, without a frame count, or without two frames over
        printed traces under the starting camera.
    CalibrationError
        Frames that cannot determine the geometry (:func:`calibrate_camera`).
    """
    name = program_name or Path(job.path).name
    check_video_duration(frames, start_offset_s, job, frames.path, name)
    settings = PartSettings.from_defaults()
    windows = Windows(job, start, settings)
    picked = frames_over_traces(job, frames, start, windows, start_offset_s, n_frames)
    return calibrate_camera(
        job,
        picked,
        start,
        reach_um=settings.reach_um,
        gate_um=gate_um,
        search=search,
        clean=windows.usable,
    )
