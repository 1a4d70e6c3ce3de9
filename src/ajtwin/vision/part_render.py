"""Render the alignment camera's view of a printed part: video with known truth.

A frame at time ``t`` shows the part around ``p(t) + offset_mm`` (:mod:`ajtwin.vision.camera`)
with every trace printed before ``t`` (the job's segments with the shutter open, the one
being printed cut at ``t``). Each trace is drawn with the line printed at that moment: its
cross-section comes from the print's per-second truth (``true_linewidth_um``,
``true_overspray_um``, and the cross-section ``material_flow_mL_s / speed``) at the print
time of each point, through :func:`ajtwin.vision.profile.line_profile`.

Per pixel, for every trace piece within reach: the exact distance ``d`` to its centre line
and the point there (arclength ``s``, print time ``τ``) from the job's own geometry
(:func:`ajtwin.job.geometry.closest_point`); the profile of second ``⌊τ⌋`` gives the height
at ``|d|`` after the raggedness warp of that stroke at ``s``. Where traces overlap (a
crossing, a fill) the highest deposit is drawn and its slope sets the brightness (the upper
envelope of the heights); the ends of a stroke are round caps (the distance to the end
point). Brightness falls with the slope (:func:`ajtwin.vision.profile.brightness_from_slope`),
averaged over the pixel's width across the trace, on a substrate whose texture is fixed to
the part (it slides through the frames as the stage moves), under uneven illumination, then
blurred, with read and shot noise (:func:`ajtwin.vision.render.sensor_image`) — the optics
of :func:`ajtwin.vision.render.render_frame`, which this generalises from one straight line
to any part.

:class:`PrintTruth` is the truth a job print carries (record format version 2: per-second
``true_linewidth_um``/``true_overspray_um`` at the nozzle); :meth:`PrintTruth.features_at`
gives the reference linewidth/overspray (the paper's definitions on the noiseless profile,
:func:`ajtwin.vision.profile.profile_features`) of the line printed at any time, which is
what extracted values are scored against.
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from tqdm import tqdm

from ajtwin.io.records import LINE_TRUTH_COLUMNS
from ajtwin.job.geometry import SEGMENT_FIELDS, closest_point, point_at, segment_bbox, tangent_at
from ajtwin.job.program import KIND_ARC, KIND_DWELL
from ajtwin.units import cross_section_um2
from ajtwin.vision.camera import Camera
from ajtwin.vision.profile import (
    brightness_from_slope,
    line_profile,
    minimum_area_um2,
    profile_features,
)
from ajtwin.vision.render import (
    SUBSAMPLES_PER_PX,
    RenderSettings,
    _fourcc_for,
    _illumination,
    _landmarks,
    _smooth_noise_1d,
    _smooth_noise_2d,
    sensor_image,
    warp_side,
)

__all__ = ["PrintTruth", "PartRenderer", "render_part_video"]

#: Cross-section drawn where the print carries no material flow, µm² (the nominal line of
#: optics.toml's provenance: L_w 43 µm, L_o 29 µm, 15 µm²).
DEFAULT_AREA_UM2 = 15.0
PROFILE_STEP_UM = 0.05  # grid of the per-second profiles
CHUNK_MM = 0.12  # trace pieces drawn at a time (their boxes: about twice the band drawn)
RAGGED_PERIOD = 4096  # samples (one per pixel of arclength) of each stroke's raggedness
TEXTURE_PERIOD = 1024  # pixels of the part-fixed texture tile


@dataclasses.dataclass
class PrintTruth:
    """Per-second truth of a job print: the line printed during each second.

    Attributes
    ----------
    time_s : (n,) array
        Start of each second (the record's ``time_s``, 1 Hz, increasing).
    linewidth_um, overspray_um, area_um2 : (n,) arrays
        The line printed during that second (finite everywhere: seconds without a print
        hold the nearest printed one, so a stroke that starts inside a second whose row was
        sampled with the shutter closed still has a line).
    raised_area : int
        Seconds whose cross-section was raised to :func:`minimum_area_um2` (too little
        material for the requested overspray to be visible).
    """

    time_s: np.ndarray
    linewidth_um: np.ndarray
    overspray_um: np.ndarray
    area_um2: np.ndarray
    raised_area: int = 0

    @classmethod
    def from_table(cls, data: pd.DataFrame, job=None, default_area_um2: float = DEFAULT_AREA_UM2):
        """From a job print's table (``time_s``, ``true_linewidth_um``, ``true_overspray_um``,
        optionally ``material_flow_mL_s``).

        The cross-section is ``material_flow_mL_s`` over the platen speed at that second
        (from ``job``, else ``platen_speed_mm_s``), else ``default_area_um2``; raised to the
        least area for which the requested overspray is visible.

        Raises
        ------
        ValueError
            Missing columns, no finite truth at all, non-increasing times.
        """
        missing = [c for c in ("time_s", *LINE_TRUTH_COLUMNS) if c not in data.columns]
        if missing:
            raise ValueError(
                f"the print has no {missing}: rendering a part needs the truth of a job print "
                "(record format 2, written by the virtual printer on a job)"
            )
        time_s = data["time_s"].to_numpy(float)
        if time_s.size == 0 or np.any(np.diff(time_s) <= 0):
            raise ValueError("the print's time_s must be non-empty and increasing")
        lw = data["true_linewidth_um"].to_numpy(float)
        ov = data["true_overspray_um"].to_numpy(float)
        usable = np.isfinite(lw) & np.isfinite(ov) & (lw > 0) & (ov > 0)
        if not usable.any():
            raise ValueError(
                "the print's true_linewidth_um/true_overspray_um are NaN everywhere: no second "
                "with the shutter open"
            )
        lw, ov = _hold_nearest(lw, usable), _hold_nearest(ov, usable)
        area = np.full(time_s.size, float(default_area_um2))
        if "material_flow_mL_s" in data.columns:
            flow = data["material_flow_mL_s"].to_numpy(float)
            if job is not None:
                speed = job.state_at(time_s + 0.5).speed_mm_s
            elif "platen_speed_mm_s" in data.columns:
                speed = data["platen_speed_mm_s"].to_numpy(float)
            else:
                speed = np.full(time_s.size, np.nan)
            ok = np.isfinite(flow) & (flow > 0) & np.isfinite(speed) & (speed > 0)
            area[ok] = cross_section_um2(flow[ok], speed[ok])
        least = np.array([1.05 * minimum_area_um2(a, b) for a, b in zip(lw, ov, strict=True)])
        raised = area < least
        area = np.maximum(area, least)
        return cls(time_s, lw, ov, area, int(raised.sum()))

    @classmethod
    def constant(cls, duration_s: float, linewidth_um: float, overspray_um: float, area_um2=None):
        """A print whose line never changes (tests, demonstrations).

        The cross-section defaults to the nominal 15 µm² (raised to the least area for which
        the overspray is visible).
        """
        n = max(1, int(math.ceil(duration_s)) + 1)
        least = 1.05 * minimum_area_um2(linewidth_um, overspray_um)
        area = max(DEFAULT_AREA_UM2 if area_um2 is None else float(area_um2), least)
        return cls(
            np.arange(n, dtype=float),
            np.full(n, float(linewidth_um)),
            np.full(n, float(overspray_um)),
            np.full(n, float(area)),
        )

    def second_of(self, print_time_s) -> np.ndarray:
        """Row index of the second holding each print time (clipped to the table)."""
        k = np.searchsorted(self.time_s, np.asarray(print_time_s, dtype=float), side="right") - 1
        return np.clip(k, 0, self.time_s.size - 1)

    def features_at(self, print_time_s) -> tuple[np.ndarray, np.ndarray]:
        """Reference linewidth and overspray (µm) of the line printed at each time."""
        k = self.second_of(print_time_s)
        ref = self.reference()
        return ref[0][k], ref[1][k]

    def reference(self) -> tuple[np.ndarray, np.ndarray]:
        """Reference linewidth/overspray of every second (profile_features of its profile)."""
        if not hasattr(self, "_reference"):
            grid = _profile_grid(self)
            lw, ov = np.empty(self.time_s.size), np.empty(self.time_s.size)
            cache = {}
            for k in range(self.time_s.size):
                key = (self.linewidth_um[k], self.overspray_um[k], self.area_um2[k])
                if key not in cache:
                    cache[key] = profile_features(grid, _profile(self, k, grid))
                lw[k], ov[k] = cache[key]
            self._reference = (lw, ov)
        return self._reference

    def reach_um(self) -> float:
        """Largest distance from a centre line at which any second's deposit ends, µm."""
        return float(np.max(0.5 * self.linewidth_um + 1.6 * self.overspray_um)) + 10.0


def _hold_nearest(values: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Unusable entries take the next usable one (else the previous)."""
    out = pd.Series(np.where(usable, values, np.nan)).bfill().ffill()
    return out.to_numpy(float)


def _profile_grid(truth: PrintTruth) -> np.ndarray:
    reach = truth.reach_um() + 10.0
    return np.arange(-reach, reach + PROFILE_STEP_UM, PROFILE_STEP_UM)


def _profile(truth: PrintTruth, k: int, grid: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # areas were raised above the least area
        return line_profile(grid, truth.linewidth_um[k], truth.overspray_um[k], truth.area_um2[k])


class _ProfileTable:
    """Heights and slopes of the per-second profiles on one grid, built on first use."""

    def __init__(self, truth: PrintTruth):
        self.truth = truth
        self.grid = _profile_grid(truth)
        self.r0 = float(self.grid[0])
        self.step = float(self.grid[1] - self.grid[0])
        self.rows: dict[tuple, int] = {}
        self.row_of_second = np.full(truth.time_s.size, -1, dtype=np.int64)
        self.height = np.zeros((0, self.grid.size), dtype=np.float32)
        self.slope = np.zeros((0, self.grid.size), dtype=np.float32)
        self.half = np.zeros((0, 2))
        self.ends = np.zeros((0, 2))
        self.centre = np.zeros(0)

    def rows_for(self, seconds: np.ndarray) -> np.ndarray:
        """Table rows of the profiles of these seconds (computing the missing ones)."""
        need = np.unique(seconds[self.row_of_second[seconds] < 0])
        if need.size:
            t = self.truth
            new_h, new_s, new_half, new_ends, new_c = [], [], [], [], []
            for k in need.tolist():
                key = (t.linewidth_um[k], t.overspray_um[k], t.area_um2[k])
                if key not in self.rows:
                    h = _profile(t, k, self.grid)
                    centre, half, ends = _landmarks(self.grid, h)
                    self.rows[key] = self.height.shape[0] + len(new_h)
                    new_h.append(h)
                    new_s.append(np.gradient(h, self.grid))
                    new_half.append(half)
                    new_ends.append(ends)
                    new_c.append(centre)
                self.row_of_second[k] = self.rows[key]
            if new_h:
                self.height = np.vstack([self.height, np.asarray(new_h, dtype=np.float32)])
                self.slope = np.vstack([self.slope, np.asarray(new_s, dtype=np.float32)])
                self.half = np.vstack([self.half, new_half])
                self.ends = np.vstack([self.ends, new_ends])
                self.centre = np.concatenate([self.centre, new_c])
        return self.row_of_second[seconds]

    def lookup(self, table: np.ndarray, row: np.ndarray, r_um: np.ndarray) -> np.ndarray:
        """Linear interpolation of ``table[row]`` at ``r_um`` (0 outside the grid)."""
        x = (r_um - self.r0) / self.step
        i = np.floor(x).astype(np.int64)
        inside = (i >= 0) & (i < self.grid.size - 1)
        i = np.clip(i, 0, self.grid.size - 2)
        frac = (x - i).astype(np.float32)
        lo = table[row, i]
        return np.where(inside, lo + frac * (table[row, i + 1] - lo), 0.0)


_FIELDS = ("kind", "x0_mm", "y0_mm", "x1_mm", "y1_mm", "cx_mm", "cy_mm", "radius_mm", "a0_rad")


class PartRenderer:
    """Frames of a job's part under a camera, with the line printed at each moment.

    Parameters
    ----------
    job : ajtwin.job.Job
    camera : Camera
        Pixel size, rotation, offset and frame size.
    truth : PrintTruth
        The line printed during each second of the job (same clock as the job).
    settings : RenderSettings, optional
        Noise, blur, texture, illumination and raggedness (``um_per_px``, ``tilt_deg`` and
        ``offset_px`` are ignored: the camera sets the geometry). Defaults: ``optics.toml``.
    seed : int
        Seeds the substrate, the raggedness of every stroke and the sensor noise.

    Examples
    --------
    >>> from ajtwin.job import read_program_text
    >>> job = read_program_text("ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),1,0\\nOUT0.0=0\\n"
    ...                         "ptp/e (X,Y),0,0", process_speed_mm_s=2)
    >>> cam = Camera(um_per_px=0.75, width_px=320, height_px=240)
    >>> frame = PartRenderer(job, cam, PrintTruth.constant(2, 43, 29)).frame(0.75)
    >>> frame.shape, frame.dtype.name
    ((240, 320), 'uint8')
    """

    def __init__(
        self,
        job,
        camera: Camera,
        truth: PrintTruth,
        settings: RenderSettings | None = None,
        seed: int = 0,
    ):
        base = RenderSettings.from_defaults() if settings is None else settings
        self.settings = dataclasses.replace(base, um_per_px=camera.um_per_px)
        self.settings.validate()
        self.job = job
        self.camera = camera
        self.truth = truth
        self.seed = int(seed)
        self.rng = np.random.default_rng([self.seed, 1])
        self.profiles = _ProfileTable(truth)
        self.reach_mm = 1e-3 * (truth.reach_um() + 4.0 * self.settings.raggedness_um)
        px = camera.um_per_px
        self.texture = self.settings.texture_amplitude * _smooth_noise_2d(
            (TEXTURE_PERIOD, TEXTURE_PERIOD),
            self.settings.texture_correlation_um / px,
            np.random.default_rng([self.seed, 2]),
        )
        self.illumination = _illumination((camera.height_px, camera.width_px), self.settings)
        self._ragged: dict[int, np.ndarray] = {}
        s = job.segments
        self._printed = np.flatnonzero(
            s["shutter_open"] & (s["kind"] != KIND_DWELL) & (s["length_mm"] > 0)
        )
        g = {k: s[k][self._printed] for k in _FIELDS}
        self._bbox = np.stack(segment_bbox(*g.values(), s["sweep_rad"][self._printed]))
        rows = np.arange(camera.height_px, dtype=np.float64)
        cols = np.arange(camera.width_px, dtype=np.float64)
        self._cols, self._rows = np.meshgrid(cols, rows)

    # -- raggedness of a stroke --------------------------------------------------------
    def _raggedness(self, stroke: int) -> np.ndarray:
        """(4, RAGGED_PERIOD) shoulder/end displacements (µm) of a stroke along its length."""
        if stroke not in self._ragged:
            rng = np.random.default_rng([self.seed, 3, int(stroke)])
            corr = self.settings.raggedness_correlation_um / self.camera.um_per_px
            self._ragged[stroke] = self.settings.raggedness_um * np.stack(
                [_smooth_noise_1d(RAGGED_PERIOD, corr, rng) for _ in range(4)]
            )
        return self._ragged[stroke]

    # -- the traces under the camera ---------------------------------------------------
    def _chunks(self, t: float, nozzle) -> dict | None:
        """Printed trace pieces (cut at ``t``) within reach of the frame at time ``t``."""
        cam = self.camera
        s = self.job.segments
        corners_c = np.array([0, cam.width_px - 1, 0, cam.width_px - 1], dtype=float)
        corners_r = np.array([0, 0, cam.height_px - 1, cam.height_px - 1], dtype=float)
        xs, ys = cam.pixel_to_part(corners_c, corners_r, nozzle)
        margin = self.reach_mm
        box = (xs.min() - margin, ys.min() - margin, xs.max() + margin, ys.max() + margin)
        b = self._bbox
        seg = self._printed
        near = (
            (b[0] <= box[2])
            & (b[2] >= box[0])
            & (b[1] <= box[3])
            & (b[3] >= box[1])
            & (s["t0_s"][seg] < t)
        )
        seg = seg[near]
        if seg.size == 0:
            return None
        t0, t1 = s["t0_s"][seg], s["t1_s"][seg]
        f_end = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
        length = s["length_mm"][seg] * f_end
        count = np.maximum(1, np.ceil(length / CHUNK_MM)).astype(np.int64)
        parent = np.repeat(np.arange(seg.size), count)
        within = np.arange(parent.size) - np.repeat(np.cumsum(count) - count, count)
        fa = within / count[parent] * f_end[parent]
        fb = (within + 1) / count[parent] * f_end[parent]
        sg = seg[parent]
        g = {k: s[k][sg] for k in _FIELDS}
        sweep = s["sweep_rad"][sg]
        x0, y0 = point_at(*g.values(), sweep, fa)
        x1, y1 = point_at(*g.values(), sweep, fb)
        arc = g["kind"] == KIND_ARC
        a0 = np.where(arc, g["a0_rad"] + fa * sweep, g["a0_rad"])
        chunk = {
            "kind": g["kind"],
            "x0": x0,
            "y0": y0,
            "x1": x1,
            "y1": y1,
            "cx": g["cx_mm"],
            "cy": g["cy_mm"],
            "r": g["radius_mm"],
            "a0": a0,
            "sweep": sweep * (fb - fa),
            "length": s["length_mm"][sg] * (fb - fa),
            "s0": s["s0_mm"][sg] + fa * s["length_mm"][sg],
            "t0": t0[parent] + fa * (t1 - t0)[parent],
            "dt": (fb - fa) * (t1 - t0)[parent],
            "stroke": s["stroke"][sg],
        }
        bx = segment_bbox(
            chunk["kind"], x0, y0, x1, y1, chunk["cx"], chunk["cy"], chunk["r"], a0, chunk["sweep"]
        )
        chunk["bbox"] = np.stack(bx)
        return chunk

    def line_brightness(self, t: float) -> np.ndarray:
        """Relative brightness of the part (1 = bare substrate) in the frame at time ``t``."""
        cam = self.camera
        height, width = cam.height_px, cam.width_px
        nozzle = self.job.state_at(t)
        nozzle = (float(nozzle.x_mm), float(nozzle.y_mm))
        out = np.ones((height, width), dtype=np.float32)
        chunks = self._chunks(t, nozzle)
        if chunks is None:
            return out
        top = np.zeros((height, width), dtype=np.float32)
        reach = self.reach_mm
        px_um = cam.um_per_px
        sub = ((np.arange(SUBSAMPLES_PER_PX) + 0.5) / SUBSAMPLES_PER_PX - 0.5) * px_um
        xmin, ymin, xmax, ymax = chunks["bbox"]
        corner_x = np.stack([xmin - reach, xmax + reach, xmin - reach, xmax + reach])
        corner_y = np.stack([ymin - reach, ymin - reach, ymax + reach, ymax + reach])
        cc, rr = cam.part_to_pixel(corner_x, corner_y, nozzle)
        c_lo = np.clip(np.floor(cc.min(axis=0)), 0, width).astype(int)
        c_hi = np.clip(np.ceil(cc.max(axis=0)) + 1, 0, width).astype(int)
        r_lo = np.clip(np.floor(rr.min(axis=0)), 0, height).astype(int)
        r_hi = np.clip(np.ceil(rr.max(axis=0)) + 1, 0, height).astype(int)
        table = self.profiles
        for j in np.flatnonzero((c_hi > c_lo) & (r_hi > r_lo)).tolist():
            rows, cols = slice(r_lo[j], r_hi[j]), slice(c_lo[j], c_hi[j])
            px, py = cam.pixel_to_part(self._cols[rows, cols], self._rows[rows, cols], nozzle)
            px, py = px.ravel(), py.ravel()
            n = px.size

            def one(name, j=j, n=n):
                return np.full(n, chunks[name][j])

            kind = one("kind")
            x0, y0, x1, y1 = one("x0"), one("y0"), one("x1"), one("y1")
            a0, sweep, length = one("a0"), one("sweep"), one("length")
            dist, f = closest_point(px, py, {k: one(k) for k in SEGMENT_FIELDS})
            close = dist <= reach
            if not close.any():
                continue
            idx = np.flatnonzero(close)
            f = f[idx]
            qx, qy = point_at(
                kind[idx],
                x0[idx],
                y0[idx],
                x1[idx],
                y1[idx],
                one("cx")[idx],
                one("cy")[idx],
                one("r")[idx],
                a0[idx],
                sweep[idx],
                f,
            )
            ux, uy = tangent_at(
                kind[idx], x0[idx], y0[idx], x1[idx], y1[idx], a0[idx], sweep[idx], length[idx], f
            )
            # left of the direction of travel is side 1 (d > 0)
            left = (ux * (py[idx] - qy) - uy * (px[idx] - qx)) >= 0
            u_um = 1e3 * dist[idx]
            along_px = (1e3 * (chunks["s0"][j] + f * chunks["length"][j]) / px_um).astype(
                np.int64
            ) % RAGGED_PERIOD
            seconds = self.truth.second_of(chunks["t0"][j] + f * chunks["dt"][j])
            row = table.rows_for(seconds)
            fields = self._raggedness(int(chunks["stroke"][j]))
            side = left.astype(np.int64)
            w = table.half[row, side]
            e = table.ends[row, side]
            shoulder = fields[side, along_px]
            end = fields[2 + side, along_px]
            sign = np.where(left, 1.0, -1.0)
            centre = table.centre[row]
            mapped, _ = warp_side(u_um, w, e, shoulder, end)
            h = table.lookup(table.height, row, centre + sign * mapped)
            block_top = top[rows, cols].reshape(-1)
            block_out = out[rows, cols].reshape(-1)
            higher = h > block_top[idx]
            if not higher.any():
                continue
            # brightness averaged over the pixel's width across the trace, where this
            # trace is the top one
            u_um, w, e, row = u_um[higher], w[higher], e[higher], row[higher]
            shoulder, end, sign, centre = (
                shoulder[higher],
                end[higher],
                sign[higher],
                centre[higher],
            )
            bright = np.zeros(u_um.shape, dtype=np.float32)
            for offset in sub:
                m, st = warp_side(np.abs(u_um + offset), w, e, shoulder, end)
                slope = table.lookup(table.slope, row, centre + sign * m) * st
                bright += brightness_from_slope(slope).astype(np.float32)
            bright /= SUBSAMPLES_PER_PX
            hit = idx[higher]
            block_top[hit] = h[higher]
            block_out[hit] = bright
            top[rows, cols] = block_top.reshape(r_hi[j] - r_lo[j], c_hi[j] - c_lo[j])
            out[rows, cols] = block_out.reshape(r_hi[j] - r_lo[j], c_hi[j] - c_lo[j])
        return out

    def substrate(self, t: float) -> np.ndarray:
        """Relative texture (zero mean) of the substrate under the frame at time ``t``."""
        cam = self.camera
        nozzle = self.job.state_at(t)
        matrix = cam.part_to_pixel_matrix((float(nozzle.x_mm), float(nozzle.y_mm)))
        # pixel -> part µm / pixel size: the texture tile is indexed in part pixels
        inverse = cv2.invertAffineTransform(matrix)
        scale = 1.0 / cam.mm_per_px
        map_x = (inverse[0, 0] * self._cols + inverse[0, 1] * self._rows + inverse[0, 2]) * scale
        map_y = (inverse[1, 0] * self._cols + inverse[1, 1] * self._rows + inverse[1, 2]) * scale
        map_x = np.mod(map_x, TEXTURE_PERIOD).astype(np.float32)
        map_y = np.mod(map_y, TEXTURE_PERIOD).astype(np.float32)
        return cv2.remap(self.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def frame(self, t: float) -> np.ndarray:
        """The 8-bit grayscale frame at job time ``t`` (s)."""
        line = self.line_brightness(t)
        return sensor_image(line, self.substrate(t), self.illumination, self.settings, self.rng)


def render_part_video(
    job,
    camera: Camera,
    truth: PrintTruth,
    out_path: str | Path,
    *,
    fps: float = 10.0,
    start_s: float = 0.0,
    duration_s: float | None = None,
    settings: RenderSettings | None = None,
    seed: int = 0,
    truth_path: str | Path | None = None,
    extra_truth: dict | None = None,
    progress: bool = True,
) -> Path:
    """Render the camera's video of a job print (frame k at job time ``start_s + k / fps``).

    Writes the video (``.mp4`` mp4v lossy, ``.avi``/``.mkv`` FFV1 lossless) and a truth JSON
    (default: the video's name with ``.json``): the camera, the render settings, the
    frame clock, and per second of the print the line drawn and its reference
    linewidth/overspray (what an extraction is scored against through each reading's
    print time).

    Returns
    -------
    Path of the truth JSON.
    """
    out_path = Path(out_path)
    truth_path = out_path.with_suffix(".json") if truth_path is None else Path(truth_path)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be > 0, got {fps}")
    if duration_s is None:
        duration_s = job.duration_s - start_s
    if not duration_s > 0:
        raise ValueError(
            f"nothing to render: the job lasts {job.duration_s:.3f} s and the video would start "
            f"at {start_s:g} s"
        )
    n_frames = max(1, int(math.floor(duration_s * fps + 1e-9)))
    renderer = PartRenderer(job, camera, truth, settings, seed)
    size = (camera.width_px, camera.height_px)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(out_path), _fourcc_for(out_path), fps, size, False)
    if not writer.isOpened():
        raise OSError(f"{out_path}: OpenCV cannot open a video writer here")
    try:
        for k in tqdm(
            range(n_frames), desc=f"render {out_path.name}", unit="frame", disable=not progress
        ):
            writer.write(renderer.frame(start_s + k / fps))
    finally:
        writer.release()
    lw_ref, ov_ref = truth.reference()
    record = {
        "video": out_path.name,
        "fps": fps,
        "n_frames": n_frames,
        "start_offset_s": start_s,
        "frame_time": "job time of frame k = start_offset_s + k / fps",
        "camera": json.loads(json.dumps(dataclasses.asdict(camera), default=str)),
        "settings": dataclasses.asdict(renderer.settings),
        "seed": seed,
        "job": {"program": Path(job.path).name, "duration_s": job.duration_s},
        "definitions": "reference linewidth/overspray of the line printed in each second: "
        "ajtwin.vision.profile_features of its noiseless profile",
        "seconds": {
            "time_s": truth.time_s.tolist(),
            "linewidth_um": np.round(lw_ref, 6).tolist(),
            "overspray_um": np.round(ov_ref, 6).tolist(),
            "area_um2": np.round(truth.area_um2, 6).tolist(),
        },
        **(extra_truth or {}),
    }
    truth_path.write_text(json.dumps(record))
    return truth_path
