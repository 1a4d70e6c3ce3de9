"""An alignment-camera video of a print record: each second's line becomes a cross-section.

Each second's ``linewidth_um``, ``overspray_um`` and ``material_flow_mL_s`` of a print
record become a line cross-section (cross-section area = Q_m / platen speed,
:func:`ajtwin.units.cross_section_um2`; shape :func:`ajtwin.vision.profile.line_profile`),
rendered frame by frame (:func:`ajtwin.vision.render.render_video`). Seconds without a
usable line hold the previous one. Without a record, a constant line is rendered.

Examples
--------
>>> from ajtwin.simulation import simulate
>>> record = simulate("exp1", seed=1, duration_min=0.1)            # 6 s: 6 frames at 1 fps
>>> done = render_record_video(record, "p.mp4", progress=False)
>>> done.truth_path.name, done.held_seconds                            # the truth beside it
('p.json', 0)
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ajtwin.units import cross_section_um2
from ajtwin.vision.profile import line_profile, minimum_area_um2
from ajtwin.vision.render import RenderSettings, TruthFile, render_video


@dataclass(frozen=True)
class ConstantLine:
    """The line drawn where a record has none (or when there is no record).

    Attributes
    ----------
    linewidth_um, overspray_um : float
        Linewidth and one-sided overspray [µm].
    area_um2 : float
        Cross-section [µm²] (also where the record's material flow is NaN).
    """

    linewidth_um: float = 43.0
    overspray_um: float = 29.0
    area_um2: float = 15.0


@dataclass
class RenderedVideo:
    """What :func:`render_record_video` wrote and what it had to make up.

    Attributes
    ----------
    truth_path : Path
        The ground-truth JSON beside the video.
    held_seconds : int
        Seconds without a usable line (the previous one held).
    thin_seconds : int
        Seconds with too little material for the requested overspray (its visible part
        is shorter).
    notes : list of str
        Those two counts as sentences for the user (empty when both are 0).
    """

    truth_path: Path
    held_seconds: int = 0
    thin_seconds: int = 0
    notes: list = field(default_factory=list)


class LazyProfiles:
    """A sequence of profiles computed on demand (a 90-min print never sits in memory).

    Parameters
    ----------
    rows : array (P,) of int
        For each profile time, the row of the line it shows (−1: the constant line).
    make : callable(int) -> array (n,)
        The profile of a row [µm], cached for the last few rows.
    """

    def __init__(self, rows: np.ndarray, make):
        self.rows = rows
        self.make = functools.lru_cache(maxsize=8)(make)

    def __len__(self) -> int:
        return int(self.rows.size)

    def __getitem__(self, index: int) -> np.ndarray:
        return self.make(int(self.rows[index]))


def record_lines(record, start_s: float = 0.0, duration_s: float | None = None):
    """Times [s from ``start_s``], linewidth, overspray [µm] and material flow [mL/s] of the
    record's seconds in [start_s, start_s + duration_s).

    Raises
    ------
    ValueError
        The window holds no row of the record.
    """
    data = record.data
    data = data[data["time_s"] >= start_s]
    if duration_s is not None:
        data = data[data["time_s"] < start_s + duration_s]
    if data.empty:
        raise ValueError("no rows in the requested time window")
    return (
        data["time_s"].to_numpy(float) - start_s,
        data["linewidth_um"].to_numpy(float),
        data["overspray_um"].to_numpy(float),
        data["material_flow_mL_s"].to_numpy(float),
    )


def render_record_video(
    record,
    out,
    *,
    fps: float = 1.0,
    shape: tuple[int, int] = (1024, 1280),
    settings: RenderSettings | None = None,
    start_s: float = 0.0,
    duration_s: float | None = None,
    platen_speed_mm_s: float | None = None,
    constant: ConstantLine = ConstantLine(),
    seed: int = 0,
    truth: TruthFile | None = None,
    progress: bool = True,
) -> RenderedVideo:
    """Render the alignment-camera video of a print (or of a constant line).

    Parameters
    ----------
    record : PrintRecord or None
        The print; None renders ``constant`` for ``duration_s`` (default 10 s).
    out : str or Path
        Video to write (``.mp4`` lossy, ``.avi``/``.mkv`` lossless).
    fps : float
        Frame rate [1/s].
    shape : (int, int)
        Frame size (rows, columns) [px].
    settings : RenderSettings, optional
        Optics and noise (default ``vision/optics.toml``).
    start_s, duration_s : float
        The print's time window to render [s].
    platen_speed_mm_s : float, optional
        Platen speed [mm/s] (default: the record's, else 1).
    constant : ConstantLine
        The line where the record has none.
    seed : int
        Seed of the frames' noise.
    truth : TruthFile, optional
        Where the ground-truth JSON goes (default: beside the video, ``.json``) and more
        keys for it.
    progress : bool
        A progress bar while frames are written.
    """
    truth = truth or TruthFile()
    extra = dict(truth.extra)
    if record is not None:
        speed = platen_speed_mm_s or float(record.meta.get("platen_speed_mm_s", 1.0))
        times, lw, ov, flow = record_lines(record, start_s, duration_s)
        extra.update(scenario=record.meta.get("scenario"), machine_id=record.meta.get("machine_id"))
    else:
        speed = platen_speed_mm_s or 1.0
        times = np.arange(0.0, 10.0 if duration_s is None else duration_s, 1.0)
        lw = np.full(times.size, constant.linewidth_um)
        ov = np.full(times.size, constant.overspray_um)
        flow = np.full(times.size, np.nan)
    area = np.where(np.isfinite(flow), cross_section_um2(flow, speed), constant.area_um2)
    reach = float(np.nanmax(0.5 * lw + 1.6 * ov)) if np.isfinite(lw).any() else 100.0
    r_um = np.arange(-reach - 20.0, reach + 20.0, 0.05)
    # rows without a usable line hold the previous one (the first falls back to `constant`)
    usable = np.isfinite(lw) & np.isfinite(ov) & (lw > 0) & (ov > 0) & np.isfinite(area)
    source_row = np.maximum.accumulate(np.where(usable, np.arange(lw.size), -1))
    minimum = [minimum_area_um2(a, b) for a, b in zip(lw[usable], ov[usable], strict=True)]
    result = RenderedVideo(
        truth_path=Path(out), held_seconds=int((~usable).sum()),
        thin_seconds=int(np.sum(area[usable] < minimum)),
    )  # fmt: skip
    if result.held_seconds:
        result.notes.append(
            f"{result.held_seconds} seconds without linewidth/overspray: previous line held"
        )
    if result.thin_seconds:
        result.notes.append(
            f"{result.thin_seconds} seconds with too little material for the requested "
            "overspray (its visible part will be shorter)"
        )

    def profile_for(row: int) -> np.ndarray:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # counted above
            if row < 0:
                return line_profile(
                    r_um, constant.linewidth_um, constant.overspray_um, constant.area_um2
                )
            return line_profile(r_um, lw[row], ov[row], area[row])

    result.truth_path = render_video(
        r_um,
        LazyProfiles(source_row, profile_for),
        times,
        out,
        fps=fps,
        duration_s=float(times[-1]) + 1.0,
        shape=shape,
        settings=settings,
        platen_speed_mm_s=speed,
        seed=seed,
        truth=replace(truth, extra={**extra, "print_start_s": start_s}),
        progress=progress,
    )
    return result
