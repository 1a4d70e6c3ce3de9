"""Does the video show what the program prints? Its frames compared with the program's.

Program-guided extraction (:mod:`ajtwin.vision.part_extract`) measures only where the
program puts a trace. Another program whose path near the camera looks like the video's
(a straight trace seen by a trailing camera looks the same on any program) would have every
window read and attributed to the wrong strokes and print times. What tells them apart is
the rest of each frame: the program also says where *nothing* is printed. This module looks
there.

**Lines where the program prints nothing** (:func:`lines_off_program`). The frame is
averaged down to pixels of ``reach / grid_per_reach`` (a line's core stays darker than its
overspray; two traces a reach apart stay apart), the substrate is estimated by a
morphological closing over ``2 reach`` (it removes every dark band narrower than a trace's
deposit) and the darkness is the substrate minus the image. A pixel is dark when darker
than half of the frame's 99th percentile of darkness (the core of the darkest line in view,
not its overspray), at least :data:`~ajtwin.vision.extract.MIN_LINE_CONTRAST` below the bare
substrate, and six robust standard deviations (1.4826 MAD) above the frame's median darkness
(the substrate's texture, vignetting and noise: a frame filled by a fill area has no line to
go by). Each dark pixel's point on the part is looked up among the traces the program
has printed by the frame's time (:meth:`ajtwin.job.Job.locate`, exact on lines and arcs);
those farther than ``reach`` from every one of them, and outside the fiducial marks, are
grouped into connected patches. A patch is a line when its principal axis is at least
``min_length_reach × reach`` long (length ``√(12 λ₁)`` of the second moments, exact for a
uniform bar) and it is no thicker than ``max_thickness_reach × reach`` (area / length): a
speck, a blob or the substrate's texture is none. A frame with such lines is compared again
with the program up to ``clock_tolerance_s`` earlier and later, and the comparison that
leaves the fewest counts: a clock a frame or two off is not a mismatch.

**No line where the program prints one** comes from the windows themselves: a frame whose
measured windows mostly found no line, or found it away from the path (``no_line``,
``off_program``).

**The verdict** (:class:`ProgramMatch`). A frame disagrees when it shows a line where the
program prints nothing, or no line where it prints one. The video *does not match* the
program when at least ``refuse_frames`` frames show lines where it prints nothing and the
frames that disagree are at least ``refuse_share`` of the frames where a trace is seen or
expected (a blank frame where the program prints nothing in view says nothing); it is
*doubtful* when any frame shows such a line. A trace missing alone is never a mismatch: a
clogged nozzle or an empty vial prints nothing where the program says (the extraction
warns about it). The numbers live in ``vision/part.toml [match]`` with their reasons.

Examples
--------
>>> from ajtwin.job import read_program_text
>>> from ajtwin.vision.camera import Camera
>>> from ajtwin.vision.part_render import PartRenderer, PrintTruth
>>> printed = read_program_text("ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),1,0\\nOUT0.0=0",
...                             process_speed_mm_s=2)
>>> other = read_program_text("ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),0,1\\nOUT0.0=0",
...                           process_speed_mm_s=2)  # the same speed, towards +y
>>> cam = Camera(um_per_px=0.75, width_px=480, height_px=360, offset_mm=(-0.3, 0.0))
>>> frame = PartRenderer(printed, cam, PrintTruth.constant(2, 43, 29)).frame(0.4)
>>> settings = MatchSettings.from_defaults()
>>> lines_off_program(frame, printed, cam, 0.4, 75.0, settings)
[]
>>> [(round(line.angle_deg), round(line.y_mm, 2), round(line.length_um, -1)) for line in
...  lines_off_program(frame, other, cam, 0.4, 75.0, settings)]
[(0, 0.8, 360.0)]
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ajtwin.config import packaged_toml, settings_from_table
from ajtwin.vision.errors import VisionInputError
from ajtwin.vision.extract import MIN_LINE_CONTRAST, to_gray

__all__ = [
    "MISPLACED_SHARE",
    "ForeignLine",
    "MatchSettings",
    "ProgramMatch",
    "ProgramMismatchError",
    "lines_off_program",
]

#: share of a frame's measured windows that found no line where the program put it, above
#: which the frame shows no trace where the program prints one (and, over the whole video,
#: the camera's geometry or the clock is suspect)
MISPLACED_SHARE = 0.5
#: the darkest line in view: this percentile of the frame's darkness
DARKEST_PERCENTILE = 99.0
#: a pixel belongs to a line's core when darker than this share of the darkest line's
CORE_SHARE = 0.5
#: the bare substrate's brightness: this percentile of the substrate estimate
BARE_PERCENTILE = 90.0
#: a line's core is darker than the frame's median darkness by this many robust standard
#: deviations of it (the substrate's texture, vignetting and noise)
TEXTURE_SIGMAS = 6.0


class ProgramMismatchError(VisionInputError):
    """The video does not show what the program prints (or its clock is off)."""


@functools.cache
def _defaults() -> dict:
    return packaged_toml("vision/part.toml")["match"]


@dataclass(frozen=True)
class MatchSettings:
    """How frames are compared with the program (defaults: ``vision/part.toml [match]``).

    Attributes
    ----------
    grid_per_reach : float
        The comparison grid's pixel is ``reach / grid_per_reach``.
    clock_tolerance_s : float
        A frame is also compared with the program this much earlier and later, s.
    min_length_reach, max_thickness_reach : float
        A line is at least this many reaches long and at most this many thick.
    refuse_frames : int
        Frames with a line where the program prints nothing needed for a mismatch.
    refuse_share : float
        Share of the frames where a trace is seen or expected that must disagree for a
        mismatch.
    """

    grid_per_reach: float = 4.0
    clock_tolerance_s: float = 0.1
    min_length_reach: float = 2.0
    max_thickness_reach: float = 1.0
    refuse_frames: int = 3
    refuse_share: float = 0.25

    @classmethod
    def from_defaults(cls, **overrides) -> MatchSettings:
        """Settings from ``part.toml [match]`` with keyword overrides."""
        return settings_from_table(cls, _defaults(), overrides, "match")


@dataclass(frozen=True)
class ForeignLine:
    """A line a frame shows where the program prints nothing.

    Attributes
    ----------
    length_um, thickness_um : float
        Along its principal axis, and its area over that length, µm.
    x_mm, y_mm : float
        Its centre on the part (where the program puts the frame), mm.
    angle_deg : float
        Its direction on the part, degrees in [-90, 90) from +x.
    """

    length_um: float
    thickness_um: float
    x_mm: float
    y_mm: float
    angle_deg: float


def lines_off_program(
    frame: np.ndarray,
    job,
    camera,
    time_s: float,
    reach_um: float,
    settings: MatchSettings,
    fiducials=(),
) -> list[ForeignLine]:
    """The lines a frame shows farther than ``reach_um`` from every trace printed by then.

    The frame is compared with the program at its time; where lines are off it, also at
    times up to ``clock_tolerance_s`` earlier and later (a clock that far off moves the view
    along the path), and the comparison with the least length of lines off the program
    counts.

    Parameters
    ----------
    frame : (H, W) or (H, W, 3) array
        The frame.
    job : ajtwin.job.Job
        The program (its path, traces and their print times).
    camera : ajtwin.vision.camera.Camera
    time_s : float
        Job time of the frame, s.
    reach_um : float
        A trace's deposit ends within this distance of its centre line, µm.
    settings : MatchSettings
    fiducials : sequence of (x_mm, y_mm, radius_mm)
        Marks on the part that are not traces.

    Returns
    -------
    list of ForeignLine, longest first (placed on the part as the comparison that counts
    puts the frame).
    """
    dark = _dark_pixels(to_gray(frame), camera, reach_um, settings)
    if dark is None:
        return []
    best = _lines_at(dark, job, camera, time_s, reach_um, settings, fiducials)
    if not best:
        return best
    for shift in _clock_shifts(job, time_s, reach_um, settings.clock_tolerance_s)[1:]:
        lines = _lines_at(dark, job, camera, time_s + shift, reach_um, settings, fiducials)
        if sum(line.length_um for line in lines) < sum(line.length_um for line in best):
            best = lines
        if not best:
            break
    return best


@dataclass(frozen=True)
class _Dark:
    """A frame's dark pixels on the comparison grid."""

    rows: np.ndarray
    cols: np.ndarray
    step: int  # frame pixels per grid pixel
    shape: tuple[int, int]


def _dark_pixels(gray: np.ndarray, camera, reach_um: float, settings) -> _Dark | None:
    """The cores of the lines a frame shows, on a grid of ``reach / grid_per_reach``."""
    step = max(1, int(reach_um / settings.grid_per_reach // camera.um_per_px))
    height, width = gray.shape[0] // step, gray.shape[1] // step
    if min(height, width) < 3:
        return None
    # every few pixels averaged, not all of them: a 25-fold area mean of a full HD frame costs
    # as much as the rest of the comparison, and 6 x 6 samples already average the noise away
    sub = max(1, step // 4)
    sampled = np.ascontiguousarray(gray[: height * step : sub, : width * step : sub])
    small = cv2.resize(sampled, (width, height), interpolation=cv2.INTER_AREA).astype(np.float32)
    size = 2 * int(math.ceil(reach_um / (step * camera.um_per_px))) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (size, size))
    substrate = cv2.morphologyEx(small, cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_REPLICATE)
    darkness = substrate - small
    # a line's core: half the darkest line's darkness, a line's least contrast below the bare
    # substrate (its bright pixels: a fill can cover most of the frame), and well out of the
    # substrate's own texture, vignetting and noise (a fill's frame has no line to go by)
    middle = float(np.median(darkness))
    spread = 1.4826 * float(np.median(np.abs(darkness - middle)))
    level = max(
        CORE_SHARE * float(np.percentile(darkness, DARKEST_PERCENTILE)),
        MIN_LINE_CONTRAST * float(np.percentile(substrate, BARE_PERCENTILE)),
        middle + TEXTURE_SIGMAS * spread,
    )
    rows, cols = np.nonzero(darkness > level)
    if rows.size == 0:
        return None
    return _Dark(rows, cols, step, (height, width))


#: clock errors tried on each side of a frame's time, at most
MAX_SHIFTS_PER_SIDE = 5


def _clock_shifts(job, time_s: float, reach_um: float, tolerance_s: float) -> np.ndarray:
    """Clock errors to try, 0 first then nearest first: within ±``tolerance_s``, close
    enough that the view moves by at most a reach from one to the next (up to
    :data:`MAX_SHIFTS_PER_SIDE` a side)."""
    if tolerance_s <= 0:
        return np.zeros(1)
    state = job.state_at(time_s + np.linspace(-tolerance_s, tolerance_s, 21))
    path_mm = float(np.hypot(np.diff(state.x_mm), np.diff(state.y_mm)).sum())
    per_side = int(np.clip(math.ceil(0.5 * path_mm / (reach_um * 1e-3)), 1, MAX_SHIFTS_PER_SIDE))
    shifts = np.linspace(-tolerance_s, tolerance_s, 2 * per_side + 1)
    return shifts[np.argsort(np.abs(shifts), kind="stable")]


def _lines_at(dark: _Dark, job, camera, time_s, reach_um, settings, fiducials) -> list:
    """The dark pixels' lines off the program, the frame placed as the program puts it at
    ``time_s``."""
    state = job.state_at(time_s)
    nozzle = (float(state.x_mm), float(state.y_mm))
    step = dark.step
    # the grid pixel's centre in the frame's pixels
    x, y = camera.pixel_to_part(
        (dark.cols + 0.5) * step - 0.5, (dark.rows + 0.5) * step - 0.5, nozzle
    )
    off = ~job.locate(x, y, reach_um * 1e-3, before_s=time_s).found
    for fx, fy, radius in fiducials:
        off &= np.hypot(x - fx, y - fy) > radius + reach_um * 1e-3
    if not off.any():
        return []
    mask = np.zeros(dark.shape, dtype=np.uint8)
    mask[dark.rows[off], dark.cols[off]] = 1
    count, labels = cv2.connectedComponents(mask, connectivity=8)
    pixel_um = step * camera.um_per_px
    min_length = settings.min_length_reach * reach_um
    lines = []
    for label in range(1, count):
        r, c = np.nonzero(labels == label)
        if r.size < min_length / pixel_um:  # shorter than a line even one pixel thick
            continue
        eigenvalues, vectors = np.linalg.eigh(np.cov(np.vstack([c, r]).astype(float)))
        length = math.sqrt(12.0 * max(float(eigenvalues[1]), 0.0)) * pixel_um
        thickness = r.size * pixel_um * pixel_um / max(length, 1e-9)
        if length < min_length or thickness > settings.max_thickness_reach * reach_um:
            continue
        dcol, drow = vectors[0, 1], vectors[1, 1]
        (ax, ay), (bx, by) = camera.axes
        angle = math.degrees(math.atan2(dcol * ay + drow * by, dcol * ax + drow * bx))
        angle = (angle + 90.0) % 180.0 - 90.0  # a line near +x reads about 0°, not 179°
        cx, cy = camera.pixel_to_part(
            (c.mean() + 0.5) * step - 0.5, (r.mean() + 0.5) * step - 0.5, nozzle
        )
        lines.append(ForeignLine(length, thickness, float(cx), float(cy), angle))
    return sorted(lines, key=lambda line: -line.length_um)


@dataclass
class _Run:
    """Consecutive frames that disagree the same way."""

    first: int
    last: int
    t_first: float
    t_last: float
    example: ForeignLine | None = None
    windows: int = 0


@dataclass
class ProgramMatch:
    """The frames of a video compared with the program, one frame at a time.

    Attributes
    ----------
    settings : MatchSettings
    frames : int
        Frames compared where a trace is seen or expected (a window of the program inside
        the frame, or a line off it).
    foreign_frames, missing_frames, disagreeing : int
        Frames showing a line where the program prints nothing; frames with no line where
        it prints one; frames with either.
    """

    settings: MatchSettings = field(default_factory=MatchSettings.from_defaults)
    frames: int = 0
    foreign_frames: int = 0
    missing_frames: int = 0
    disagreeing: int = 0
    foreign_runs: list = field(default_factory=list)
    missing_runs: list = field(default_factory=list)

    #: runs kept for the message (the counts go on beyond)
    MAX_RUNS = 1000

    def add(
        self, frame: int, time_s: float, lines, missing: int, measured: int, in_view: int
    ) -> None:
        """One frame with light: the lines it shows off the program, its measured windows
        (those that found no line or found it off the path, and all) and the program's
        windows in view."""
        if not (lines or in_view):
            return
        self.frames += 1
        lost = measured > 0 and missing > MISPLACED_SHARE * measured
        if lines:
            self.foreign_frames += 1
            self._extend(self.foreign_runs, frame, time_s, example=lines[0])
        if lost:
            self.missing_frames += 1
            self._extend(self.missing_runs, frame, time_s, windows=missing)
        self.disagreeing += bool(lines) or lost

    def add_frame(self, result) -> None:
        """One frame as the extractor left it (:class:`~ajtwin.vision.part_extract.PartFrame`);
        a frame without light is not compared."""
        if not result.lit:
            return
        missing = result.failed.get("no_line", 0) + result.failed.get("off_program", 0)
        measured = result.n_readings + sum(result.failed.values())
        # a window at the frame's border may show no more than substrate: not expected seen
        in_view = result.windows_in_view - result.skipped.get("border", 0)
        self.add(result.frame, result.time_s, result.foreign, missing, measured, in_view)

    def _extend(self, runs, frame, time_s, example=None, windows=0) -> None:
        if runs and runs[-1].last == frame - 1:
            run = runs[-1]
            run.last, run.t_last = frame, time_s
        elif len(runs) < self.MAX_RUNS:
            run = _Run(frame, frame, time_s, time_s)
            runs.append(run)
        else:
            return
        run.windows += windows
        if example is not None and (
            run.example is None or example.length_um > run.example.length_um
        ):
            run.example = example

    @property
    def verdict(self) -> str:
        """``"agree"``, ``"doubtful"`` (a line off the program in some frame) or
        ``"mismatch"``."""
        s = self.settings
        if self.foreign_frames == 0:
            return "agree"
        if (
            self.foreign_frames >= s.refuse_frames
            and self.disagreeing >= s.refuse_share * self.frames
        ):
            return "mismatch"
        return "doubtful"

    def explain(self, source, program: str) -> str:
        """What disagrees, in which frames, and what to check."""
        verb = "does not show" if self.verdict == "mismatch" else "may not show"
        parts = [
            f"{self.foreign_frames} show a line where {program} prints nothing "
            f"({_runs(self.foreign_runs, _line_words)})"
        ]
        if self.missing_frames:
            parts.append(
                f"{self.missing_frames} show no line where it prints one "
                f"({_runs(self.missing_runs, _missing_words)})"
            )
        return (
            f"{source} {verb} what {program} prints: {self.disagreeing} of the "
            f"{self.frames} frames where a trace is seen or expected disagree — "
            + "; ".join(parts)
            + ". --job may not be the program this video was filmed over, or --start-offset "
            "is wrong (frame k is at job time S + k / fps); marks on the substrate that are "
            "not traces can be left out with --fiducial X,Y,R."
        )


def _line_words(run: _Run) -> str:
    line = run.example
    angle = round(line.angle_deg)
    return (
        f"{line.length_um:.0f} µm long at {90 if angle == -90 else angle}° around "
        f"x {line.x_mm:.3f}, y {line.y_mm:.3f} mm"
    )


def _missing_words(run: _Run) -> str:
    return f"{run.windows} windows without their trace"


def _runs(runs, words, shown: int = 3) -> str:
    text = []
    for run in runs[:shown]:
        frames = f"frame {run.first}" if run.first == run.last else f"frames {run.first}–{run.last}"
        times = (
            f"{run.t_first:.2f} s"
            if run.first == run.last
            else f"{run.t_first:.2f}–{run.t_last:.2f} s"
        )
        text.append(f"{frames}, job time {times}: {words(run)}")
    if len(runs) > shown:
        text.append(f"{len(runs) - shown} more stretches")
    return "; ".join(text)
