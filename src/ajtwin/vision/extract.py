"""Linewidth and overspray from alignment-camera frames (paper App. A, model reference §9).

Per frame:

1. **Canny** edge map (:func:`cv2.Canny`) of the frame, on a 2x area-downscaled copy for
   frames wider than 800 px (edges of a line hundreds of pixels long survive; Canny and
   Hough cost drop 4x); thresholds follow the frame's contrast.
2. **Hough** transform (:func:`cv2.HoughLines`, 0.25° steps): the strongest line gives the
   line's angle (the mean angle of the strongest lines within 2° of it, which are the
   parallel edges of the same printed line).
3. **Rotate** the frame so the line is horizontal (:func:`cv2.getRotationMatrix2D` +
   :func:`cv2.warpAffine`, bilinear, reflected borders).
4. **Batches** of ``n = 50`` columns: per-row mean and standard deviation of each batch
   (block means by :func:`cv2.resize` with ``INTER_AREA``, which averages exact blocks).
5. Per batch: substrate background per row (quadratic fit in the row index to the rows
   outside the line, so uneven illumination does not move the 95 % threshold), then the
   paper's definitions on the batch mean (:func:`ajtwin.vision.features.find_edges`):
   minima (ii), first peaks outward (iii) with the std-profile fallback, linewidth, and
   overspray out to where brightness is back within 95 % of the background.
6. Frame value = median over the batches that succeeded (robust to a batch whose shoulder
   hid in ragged edges); the standard deviation over batches is reported too.

Frames are processed one at a time (videos are streamed, never loaded whole);
:meth:`FrameSource.prefetched` decodes them in a background thread, at most a few frames
ahead, so decoding and extraction use two cores.
"""

from __future__ import annotations

import queue
import threading
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ajtwin.config import InputFileError, check_regular_file
from ajtwin.vision import features as F
from ajtwin.vision.errors import VisionInputError

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v")

DARK_MEAN_GRAY = 8.0  # a frame darker than this on average has no usable light
BLANK_RANGE_GRAY = 4.0  # p99 - p1 below this: nothing in the frame
HOUGH_THETA_RAD = np.pi / 720  # 0.25°
PARALLEL_TOLERANCE_DEG = 2.0
DOWNSCALE_ABOVE_PX = 800
LINE_FILLS_FRAME = "line_fills_frame"
STEEP_LINE = "steep_line"  # the strongest line is beyond ±45° of the image's horizontal
MAX_LINE_ANGLE_DEG = 45.0  # the documented range of the paper's algorithm here
TRACK_WINDOW_DEG = 3.0
MIN_LINE_CONTRAST = 0.08  # a line's dark streak is at least this much below the substrate


class TruncatedVideoWarning(UserWarning):
    """A video decoded fewer frames than its container announces (a cut-off file)."""


@dataclass
class BatchResult:
    """Feature points of one batch of columns, in rotated-frame pixel rows."""

    col_start: int
    col_end: int
    shoulders: tuple[float, float]
    overspray_edges: tuple[float, float]
    linewidth_um: float
    overspray_um: float
    status: str


@dataclass
class FrameResult:
    """Linewidth/overspray of one frame (medians and spreads over its batches)."""

    frame: int
    time_s: float
    linewidth_um: float = np.nan
    overspray_um: float = np.nan
    linewidth_std_um: float = np.nan
    overspray_std_um: float = np.nan
    n_batches: int = 0
    status: str = F.NO_LINE
    angle_deg: float = np.nan  # line angle to the image x axis, counter-clockwise on screen
    batches: list[BatchResult] = field(default_factory=list)
    rotation: np.ndarray | None = None  # 2x3 affine: original -> rotated pixels

    def row(self) -> dict:
        """The CSV row (columns of ``ajtwin extract``)."""
        return {
            "frame": self.frame,
            "time_s": self.time_s,
            "linewidth_um": self.linewidth_um,
            "overspray_um": self.overspray_um,
            "linewidth_std_um": self.linewidth_std_um,
            "overspray_std_um": self.overspray_std_um,
            "n_batches": self.n_batches,
            "status": self.status,
        }


def to_gray(frame: np.ndarray, where: str = "frame") -> np.ndarray:
    """8-bit single-channel view of a frame (BGR/BGRA converted, 16-bit scaled)."""
    if frame is None or frame.size == 0:
        raise VisionInputError(f"{where}: empty image")
    if frame.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if frame.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        frame = cv2.cvtColor(frame, code) if frame.shape[2] in (3, 4) else frame[..., 0]
    if frame.ndim != 2:
        raise VisionInputError(f"{where}: expected a 2-D image, got shape {frame.shape}")
    if frame.dtype == np.uint16:
        frame = (frame >> 8).astype(np.uint8)
    elif frame.dtype != np.uint8:
        finite = np.nan_to_num(frame.astype(np.float32))
        top = float(finite.max()) or 1.0
        frame = np.clip(finite * (255.0 / top), 0, 255).astype(np.uint8)
    return frame


class LineExtractor:
    """The paper's linewidth/overspray algorithm for one camera set-up.

    Parameters
    ----------
    um_per_px : float
        Pixel size on the substrate, µm.
    batch : int
        Columns per batch (paper: n = 50).
    threshold : float
        Overspray ends where brightness is back at ``threshold`` x background (0.95).

    Examples
    --------
    >>> from ajtwin.vision.profile import line_profile
    >>> from ajtwin.vision.render import render_frame, RenderSettings
    >>> r = np.arange(-150, 150, 0.05)
    >>> frame = render_frame(r, line_profile(r, 43, 29, 15), shape=(480, 640),
    ...                      rng=np.random.default_rng(0))
    >>> result = LineExtractor(0.75).process(frame)
    >>> result.status, abs(result.linewidth_um - 43) < 2
    ('ok', True)
    """

    def __init__(
        self, um_per_px: float, batch: int = 50, threshold: float = 0.95, track: bool = True
    ):
        if not (np.isfinite(um_per_px) and um_per_px > 0):
            raise VisionInputError(f"--um-per-px must be a positive number, got {um_per_px}")
        if int(batch) < 1:
            raise VisionInputError(f"--batch must be >= 1, got {batch}")
        if not 0 < threshold < 1:
            raise VisionInputError(f"threshold must be in (0, 1), got {threshold}")
        self.um_per_px = float(um_per_px)
        self.batch = int(batch)
        self.threshold = float(threshold)
        self.track = bool(track)
        #: seconds spent per stage over all processed frames (for profiling/benchmarks)
        self.stage_seconds: dict[str, float] = {}
        self._last_theta: float | None = None

    # -- steps 1-3: Canny -> Hough -> rotation ------------------------------------------
    @staticmethod
    def coarse_scale(shape) -> int:
        """Downscale factor of the coarse copy used for Canny/Hough and the background."""
        width = shape[1]
        return 4 if width > 2 * DOWNSCALE_ABOVE_PX else 2 if width > DOWNSCALE_ABOVE_PX // 2 else 1

    def line_angle(self, small: np.ndarray, contrast: float | None = None) -> float | None:
        """Angle (degrees, counter-clockwise on screen) of the strongest straight line.

        Canny on the (coarse) frame, then the standard Hough transform over all directions
        (the caller refuses lines beyond ±45° of horizontal: searching only within ±45°
        would take the edge of a steeper line at the range's end for a line at 45°).  In a
        video the search is first limited to ±3° around the previous frame's angle (30x
        fewer Hough bins; the full range is searched when that finds nothing).  Returns
        ``None`` without a line; the angle is in (-90°, 90°].
        """
        blurred = cv2.GaussianBlur(small, (5, 5), 1.0)
        if contrast is None:
            low_p, high_p = np.percentile(blurred[::4, ::4], (1, 99))
            contrast = float(high_p - low_p)
        high = max(10.0, 0.35 * contrast)
        edges = cv2.Canny(blurred, 0.4 * high, high, L2gradient=True)
        votes = max(15, int(0.3 * small.shape[1]))
        # (theta range, lowest vote count tried): the tracked window must find the line at
        # full strength, or a weaker spurious line inside it would be taken
        ranges = [(0.0, np.pi, 15)]
        if self.track and self._last_theta is not None:
            window = np.deg2rad(TRACK_WINDOW_DEG)
            low, high = max(0.0, self._last_theta - window), min(np.pi, self._last_theta + window)
            ranges.insert(0, (low, high, votes))
        lines = None
        for theta_min, theta_max, lowest in ranges:
            level = votes
            while lines is None and level >= lowest:
                lines = cv2.HoughLines(
                    edges, 1, HOUGH_THETA_RAD, level, min_theta=theta_min, max_theta=theta_max
                )
                level //= 2
            if lines is not None:
                break
        if lines is None:
            self._last_theta = None
            return None
        self._last_theta = float(lines[0, 0, 1])
        theta = lines[:10, 0, 1]
        # a near-vertical line's normal wraps from 180° to 0°: bring its parallels along
        theta = np.where(theta - theta[0] > np.pi / 2, theta - np.pi, theta)
        theta = np.where(theta[0] - theta > np.pi / 2, theta + np.pi, theta)
        near = np.abs(theta - theta[0]) <= np.deg2rad(PARALLEL_TOLERANCE_DEG)
        # HoughLines' theta is the angle of the normal (x axis -> y axis, y pointing down);
        # a horizontal line has theta = 90°, and a line rising to the right has theta < 90°
        angle = float(90.0 - np.rad2deg(theta[near].mean()))
        return angle - 180.0 if angle > 90.0 else angle + 180.0 if angle <= -90.0 else angle

    @staticmethod
    def rotation_matrix(shape, angle_deg: float) -> np.ndarray:
        """Affine (2x3) turning a line at ``angle_deg`` horizontal about the frame centre."""
        height, width = shape
        return cv2.getRotationMatrix2D(((width - 1) / 2.0, (height - 1) / 2.0), -angle_deg, 1.0)

    # -- steps 4-6 ----------------------------------------------------------------------
    def batch_statistics(self, rotated: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Per-row mean and std of each batch of columns: two (rows, n_batches) arrays."""
        height, width = rotated.shape
        n_batches = width // self.batch
        if n_batches == 0:
            raise VisionInputError(
                f"frame is {width} px wide, narrower than one batch of {self.batch} columns"
            )
        used = rotated[:, : n_batches * self.batch].astype(np.float32)
        mean = cv2.resize(used, (n_batches, height), interpolation=cv2.INTER_AREA)
        mean_sq = cv2.resize(used * used, (n_batches, height), interpolation=cv2.INTER_AREA)
        std = np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))
        return mean.astype(np.float64), std.astype(np.float64), n_batches

    def process(self, frame: np.ndarray, index: int = 0, time_s: float = 0.0) -> FrameResult:
        """Extract linewidth/overspray from one frame (any 8/16-bit gray or BGR image).

        Coarse to fine: Canny, Hough, the line's position and the substrate background come
        from a 2-4x area-downscaled copy; only a band of rows around the line is rotated at
        full resolution for the batch statistics and the feature points.
        """
        clock = _StageClock(self.stage_seconds)
        gray = to_gray(frame, f"frame {index}")
        result = FrameResult(frame=index, time_s=time_s)
        height, width = gray.shape
        if width < self.batch or height < 16:
            raise VisionInputError(
                f"frame {index}: {width}x{height} px is too small (batch of {self.batch} columns)"
            )
        q = self.coarse_scale(gray.shape)
        small = area_downscale(gray, q)
        if float(small.mean()) < DARK_MEAN_GRAY:
            result.status = "dark_frame"
            return result
        low, high = np.percentile(small[::4, ::4], (1, 99))
        if high - low < BLANK_RANGE_GRAY:
            result.status = "blank_frame"
            return result
        clock.lap("1 downscale + checks")
        angle = self.line_angle(small, contrast=float(high - low))
        clock.lap("2 Canny + Hough (coarse)")
        if angle is None:
            result.status = F.NO_LINE
            return result
        result.angle_deg = angle
        if abs(angle) > MAX_LINE_ANGLE_DEG:
            result.status = STEEP_LINE
            return result
        n_batches = width // self.batch

        # coarse pass: line position, extent and background on the rotated small copy
        small_rot = cv2.warpAffine(
            small,
            self.rotation_matrix(small.shape, angle),
            (small.shape[1], small.shape[0]),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT_101,
        )
        used_cols = max(1, int(round(n_batches * self.batch / q)))
        coarse = cv2.resize(
            small_rot[:, :used_cols].astype(np.float32),
            (n_batches, small.shape[0]),
            interpolation=cv2.INTER_AREA,
        ).astype(np.float64)
        profile = coarse.mean(axis=1)
        # substrate level: a high percentile, so a line covering many rows does not pull it
        bg0 = float(np.percentile(profile, 90))
        depth = bg0 - float(profile.min())
        noise_c = _noise(profile)
        if depth < max(MIN_LINE_CONTRAST * bg0, 6.0 * noise_c):
            result.status = F.NO_LINE  # Hough found edges, but there is no dark streak
            return result
        center_c = F.dark_band_center(profile, bg0)
        if not np.isfinite(center_c):
            result.status = F.NO_LINE
            return result
        first = F.find_edges(profile, bg0, threshold=self.threshold, noise=noise_c)
        if np.all(np.isfinite(first.overspray_edges)):
            extent_c = max(center_c - first.overspray_edges[0], first.overspray_edges[1] - center_c)
        elif np.mean(profile < self.threshold * bg0) > 0.5:
            result.status = LINE_FILLS_FRAME
            return result
        else:
            extent_c = 0.25 * small.shape[0]
        y_c = (np.arange(small.shape[0]) + 0.5) * (height / small.shape[0]) - 0.5
        center = (center_c + 0.5) * (height / small.shape[0]) - 0.5
        extent = max(extent_c * q, 4.0)
        exclude = 1.3 * extent + 10.0
        outside = np.abs(y_c - center) > exclude
        if outside.sum() < max(4, small.shape[0] // 10):
            result.status = LINE_FILLS_FRAME
            return result

        # quadratic background per batch in the full-resolution row coordinate
        def design(y):
            yn = (y - 0.5 * height) / height
            return np.stack([np.ones_like(yn), yn, yn * yn], axis=1)

        a_out = design(y_c[outside])
        coef = np.linalg.solve(a_out.T @ a_out, a_out.T @ coarse[outside])
        clock.lap("3 coarse rotate + line position + background fit")

        # fine pass: rotate only the band of rows around the line, at full resolution
        half_band = 1.6 * extent + 20.0
        lo = int(max(0, np.floor(center - half_band)))
        hi = int(min(height, np.ceil(center + half_band) + 1))
        matrix = self.rotation_matrix(gray.shape, angle)
        result.rotation = matrix
        band_matrix = matrix.copy()
        band_matrix[1, 2] -= lo
        band = cv2.warpAffine(
            gray,
            band_matrix,
            (width, hi - lo),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT_101,
        )
        clock.lap("4 rotate band (warpAffine, full res)")
        mean, std, _ = self.batch_statistics(band)
        clock.lap("5 batch mean/std (50 columns)")
        rows = np.arange(lo, hi, dtype=float)
        background = design(rows) @ coef
        margin = np.abs(rows - center) > exclude
        if margin.sum() >= 4:
            noise = (mean[margin] - background[margin]).std(axis=0)
        else:
            noise = np.full(n_batches, _noise(mean.mean(axis=1)))
        self._measure(mean, std, background, noise, lo, result)
        clock.lap("6 feature points (ii)/(iii)/overspray")
        return result

    def _measure(self, mean, std, background, noise, row0: int, result: FrameResult) -> None:
        px = self.um_per_px
        found = F.find_edges_batches(
            mean, background, std=std, threshold=self.threshold, noise=noise
        )
        shoulders = found.shoulders + row0
        edges = found.overspray_edges + row0
        widths = found.linewidth * px
        oversprays = found.overspray * px
        good = np.array([s in (F.OK, F.STD_FALLBACK) for s in found.status])
        for b in range(mean.shape[1]):
            result.batches.append(
                BatchResult(
                    b * self.batch,
                    (b + 1) * self.batch,
                    tuple(shoulders[b]),
                    tuple(edges[b]),
                    float(widths[b]),
                    float(oversprays[b]),
                    found.status[b],
                )
            )
        result.n_batches = int(good.sum())
        if not good.any():
            result.status = max(set(found.status), key=found.status.count)
            return
        widths_a, ovs_a = widths[good], oversprays[good]
        # the median over batches: one batch whose shoulder hid in ragged edges would pull a
        # mean by (its error) / (number of batches)
        result.linewidth_um = float(np.median(widths_a))
        result.overspray_um = float(np.median(ovs_a))
        result.linewidth_std_um = float(widths_a.std(ddof=1)) if widths_a.size > 1 else 0.0
        result.overspray_std_um = float(ovs_a.std(ddof=1)) if ovs_a.size > 1 else 0.0
        result.status = F.OK if 2 * good.sum() >= mean.shape[1] else "few_batches"


class _StageClock:
    """Accumulates wall time per named stage into a dict (negligible overhead)."""

    def __init__(self, store: dict[str, float]):
        self.store = store
        self.last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.store[name] = self.store.get(name, 0.0) + now - self.last
        self.last = now


def area_downscale(gray: np.ndarray, q: int) -> np.ndarray:
    """``q``-fold block mean of an 8-bit image, rounded: ``cv2.resize(..., INTER_AREA)``.

    For ``q = 4`` on a frame divisible by 4 the same result comes from two 2x steps that
    keep exact sums (16-bit sums of 2x2 blocks, then a float 2x mean), 1.5-2x faster than
    OpenCV's generic 4x area path; rounding is the same (half to even), so the output is
    bit-identical (tested).
    """
    if q == 1:
        return gray
    height, width = gray.shape
    if q == 4 and height % 4 == 0 and width % 4 == 0 and gray.dtype == np.uint8:
        wide = gray.astype(np.uint16)
        wide <<= 2  # 4x the values: the 2x area mean is then the exact 2x2 sum
        sums = cv2.resize(wide, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
        sixteenth = cv2.resize(
            sums.astype(np.float32), (width // 4, height // 4), interpolation=cv2.INTER_AREA
        )  # = (4x4 sum) / 4, exact in float32
        return np.rint(sixteenth * 0.25).astype(np.uint8)
    return cv2.resize(gray, (width // q, height // q), interpolation=cv2.INTER_AREA)


def _noise(profile: np.ndarray) -> float:
    """Robust noise sigma of a 1-D profile from its first differences."""
    diff = np.diff(profile)
    return float(1.4826 * np.median(np.abs(diff - np.median(diff))) / np.sqrt(2.0))


# -- inputs -------------------------------------------------------------------------------
@dataclass
class FrameSource:
    """Frames of a video, an image folder or a single image, read one at a time."""

    path: Path
    fps: float
    count: int | None
    kind: str

    def __iter__(self) -> Iterator[tuple[int, float, np.ndarray]]:
        count = yield from self._produce()
        self._finish(count, stacklevel=3)

    def prefetched(self, depth: int = 4) -> PrefetchedFrames:
        """The same frames, decoded up to ``depth`` frames ahead in a background thread.

        Decoding (``VideoCapture.read``, ``imread``, the gray conversion) releases the GIL, so
        it runs on a second core beside the caller's feature extraction.  Use it as a context
        manager (or call ``close``) so the thread stops when the caller stops early.
        """
        return PrefetchedFrames(self, depth)

    def _produce(self, decoder_threads: int | None = None):
        """Yield (index, time_s, gray) and return the number of frames read.

        ``decoder_threads`` caps FFmpeg's own decoding threads (``None``: its default).
        """
        if self.kind == "video":
            capture = _open_capture(self.path, decoder_threads)
            index = 0
            try:
                while True:
                    ok, frame = capture.read()
                    if not ok:
                        break
                    yield index, index / self.fps, to_gray(frame, f"{self.path} frame {index}")
                    index += 1
            finally:
                capture.release()
            return index
        files = [self.path] if self.kind == "image" else _image_files(self.path)
        for index, file in enumerate(files):
            image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise VisionInputError(f"{file}: not a readable image")
            yield index, index / self.fps, to_gray(image, str(file))
        return len(files)

    def _finish(self, index: int, stacklevel: int) -> None:
        """After the last frame: an empty video is an error, a short one a warning."""
        if self.kind != "video":
            return
        if index == 0:
            raise VisionInputError(f"{self.path}: no frame could be decoded")
        if self.count and index < self.count:
            # the container announced more frames than decode: a cut-off file
            warnings.warn(
                f"{self.path}: decoded {index} of the {self.count} frames the video "
                "header announces; the file looks truncated (frames after "
                f"{index / self.fps:.3g} s are missing)",
                TruncatedVideoWarning,
                stacklevel=stacklevel,
            )


@dataclass
class _End:
    count: int


@dataclass
class _Failed:
    error: BaseException


class PrefetchedFrames:
    """Iterator over a :class:`FrameSource`'s frames, decoded ahead in a worker thread.

    Yields exactly what iterating the source yields, in order; an error while decoding is
    raised here at the frame where it happened, and the truncated-video warning is issued
    in the caller's thread after the last frame.  At most ``depth`` decoded frames wait in
    the bounded queue, so memory stays bounded for any video length.  The thread ends at
    the last frame, on an error, or on :meth:`close` (also called by ``with`` and on
    garbage collection).

    Examples
    --------
    >>> extractor = LineExtractor(0.75)                   # µm per pixel
    >>> with open_source("print.mp4").prefetched() as frames:
    ...     results = [extractor.process(gray, index, time_s) for index, time_s, gray in frames]
    >>> len(results), results[0].status
    (6, 'ok')
    """

    POLL_S = 0.05  # how often a blocked queue operation re-checks the stop flag

    def __init__(self, source: FrameSource, depth: int = 4):
        if int(depth) < 1:
            raise ValueError(f"prefetch depth must be >= 1, got {depth}")
        self.source = source
        self._queue: queue.Queue = queue.Queue(maxsize=int(depth))
        self._stop = threading.Event()
        self._closed = False
        # the worker holds no reference to self, so an abandoned reader can be collected
        # (and its __del__ stops the thread)
        self._thread = threading.Thread(
            target=_decode_ahead,
            args=(source, self._queue, self._stop),
            name=f"ajtwin-decode {source.path.name}",
            daemon=True,
        )
        self._thread.start()

    # consumer --------------------------------------------------------------------------
    def __iter__(self) -> PrefetchedFrames:
        return self

    def __next__(self) -> tuple[int, float, np.ndarray]:
        if self._closed:
            raise StopIteration
        while True:
            try:
                item = self._queue.get(timeout=self.POLL_S)
                break
            except queue.Empty:
                if not self._thread.is_alive() and self._queue.empty():
                    self.close()
                    raise RuntimeError(
                        f"{self.source.path}: the decoder thread ended early"
                    ) from None
        if isinstance(item, _End):
            self.close()
            self.source._finish(item.count, stacklevel=3)
            raise StopIteration
        if isinstance(item, _Failed):
            self.close()
            raise item.error
        return item

    def close(self) -> None:
        """Stop the decoder thread and wait for it (at most one frame's decode)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join()
        while not self._queue.empty():  # drop decoded frames now, not at collection
            self._queue.get_nowait()

    @property
    def running(self) -> bool:
        """Whether the decoder thread is still alive."""
        return self._thread.is_alive()

    def __enter__(self) -> PrefetchedFrames:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        if not getattr(self, "_closed", True):
            self.close()


def _decode_ahead(source: FrameSource, out: queue.Queue, stop: threading.Event) -> None:
    """Worker of :class:`PrefetchedFrames`: frames, then an end marker or the error."""

    def put(item) -> bool:
        while not stop.is_set():
            try:
                out.put(item, timeout=PrefetchedFrames.POLL_S)
                return True
            except queue.Full:
                continue
        return False

    # one FFmpeg thread: this thread already decodes beside the consumer, and FFmpeg's
    # frame threads on top cost ~10 % more CPU per frame for nothing on 2 cores
    frames = source._produce(decoder_threads=1)
    try:
        while not stop.is_set():
            try:
                item = next(frames)
            except StopIteration as end:
                put(_End(end.value))
                return
            except BaseException as exc:  # handed to the consumer, raised there
                put(_Failed(exc))
                return
            if not put(item):
                return
    finally:
        frames.close()  # releases the VideoCapture in this thread


def _open_capture(path: Path, decoder_threads: int | None) -> cv2.VideoCapture:
    """``cv2.VideoCapture`` of a file, with FFmpeg's thread count if asked and supported."""
    if decoder_threads is not None and hasattr(cv2, "CAP_PROP_N_THREADS"):
        capture = cv2.VideoCapture(
            str(path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, int(decoder_threads)]
        )
        if capture.isOpened():
            return capture
        capture.release()  # a backend that refuses the property: open it plainly
    return cv2.VideoCapture(str(path))


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def open_source(path: str | Path, fps: float | None = None) -> FrameSource:
    """Open a video (mp4/avi/...), an image folder or a single PNG/TIFF for streaming.

    Raises
    ------
    VisionInputError
        Missing path, unreadable or empty video, folder without images, unknown frame rate.
    """
    path = Path(path)
    if not path.exists():
        raise VisionInputError(f"{path}: no such file or folder")
    if not path.is_dir():
        try:  # a FIFO or device would block OpenCV's open forever
            check_regular_file(path, "video or image")
        except InputFileError as exc:
            raise VisionInputError(str(exc)) from None
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise VisionInputError(f"--fps must be > 0, got {fps}")
    if path.is_dir():
        files = _image_files(path)
        if not files:
            raise VisionInputError(f"{path}: folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
        return FrameSource(path, fps or 1.0, len(files), "folder")
    suffix = path.suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        return FrameSource(path, fps or 1.0, 1, "image")
    if suffix not in VIDEO_SUFFIXES:
        raise VisionInputError(
            f"{path}: unknown input type {suffix!r}; give a video "
            f"({', '.join(VIDEO_SUFFIXES)}), an image folder or a PNG/TIFF"
        )
    if path.stat().st_size == 0:
        raise VisionInputError(f"{path}: empty file")
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise VisionInputError(f"{path}: OpenCV cannot open this video (corrupt or codec?)")
        ok, _ = capture.read()
        if not ok:
            raise VisionInputError(f"{path}: video has no decodable frame (empty or corrupt)")
        video_fps = capture.get(cv2.CAP_PROP_FPS)
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    finally:
        capture.release()
    if fps is None:
        if not (np.isfinite(video_fps) and video_fps > 0):
            raise VisionInputError(f"{path}: the video does not state its frame rate; pass --fps")
        fps = float(video_fps)
    return FrameSource(path, float(fps), count, "video")


# -- annotation -----------------------------------------------------------------------------
GREEN, RED, BLUE = (0, 200, 0), (0, 0, 255), (255, 80, 0)


def annotate(frame: np.ndarray, result: FrameResult) -> np.ndarray:
    """The paper's annotated frame: Hough fit (green), linewidth (red), overspray (blue)."""
    gray = to_gray(frame)
    canvas = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    label = f"t={result.time_s:.1f}s  "
    if result.rotation is None:
        cv2.putText(canvas, label + result.status, (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, RED, 2)
        return canvas
    inverse = cv2.invertAffineTransform(result.rotation)

    def back(points):
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.transform(pts, inverse).reshape(-1, 2)

    height, width = gray.shape
    centres = [
        0.5 * (b.shoulders[0] + b.shoulders[1])
        for b in result.batches
        if np.all(np.isfinite(b.shoulders))
    ]
    if centres:
        row = float(np.median(centres))
        ends = back([(0.0, row), (width - 1.0, row)])
        cv2.line(canvas, _pt(ends[0]), _pt(ends[1]), GREEN, 1, cv2.LINE_AA)
    for b in result.batches:
        for rows, colour in ((b.shoulders, RED), (b.overspray_edges, BLUE)):
            for r in rows:
                if np.isfinite(r):
                    seg = back([(b.col_start, r), (b.col_end - 1, r)])
                    cv2.line(canvas, _pt(seg[0]), _pt(seg[1]), colour, 2, cv2.LINE_AA)
    text = label + (
        f"Lw={result.linewidth_um:.1f}um  Lo={result.overspray_um:.1f}um"
        if np.isfinite(result.linewidth_um)
        else result.status
    )
    cv2.putText(canvas, text, (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 255, 255), 2)
    return canvas


def _pt(xy) -> tuple[int, int]:
    return int(round(float(xy[0]))), int(round(float(xy[1])))
