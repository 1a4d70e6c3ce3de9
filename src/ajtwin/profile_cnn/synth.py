"""Synthetic training data from the project's renderer, mirroring the paper's two sets.

* :func:`synthetic_pairs` — stage 1, "profilometer" pairs (paper: 125 scans).
  For each pair a line with random linewidth, overspray and area
  (:func:`ajtwin.vision.profile.line_profile`, ragged shoulders) is rendered
  as an alignment-camera frame (:func:`ajtwin.vision.render.render_frame`: tilt,
  offset, uneven light, texture, blur, sensor noise), and the input column is
  cut out exactly as at inference (:mod:`ajtwin.profile_cnn.frames`). The
  frame's edges are as ragged along the line as the stage-2 frames' (a batch
  column averages 50 rows of a ragged edge), and the scan stands for the mean
  cross-section under the batch (what several scans across the batch average
  to). The "profilometer scan" of that profile is sampled at 0.5 µm with 3 nm
  height noise and a random tilt, and goes through the real-data path:
  levelling, Gaussian smoothing (``scan_smoothing_um``), centring and
  area-preserving resampling
  (:func:`ajtwin.profile_cnn.data.register_profile`).
* :func:`synthetic_labelled` — stage 2, thousands of batch columns labelled
  only by the computer-vision extractor (the "CV labels"), from frames of
  random lines. The hidden truth (profile on the column grid, true
  linewidth/overspray) is kept in ``extra``/``profiles_um`` for evaluation
  only; training never reads it.

Ranges: linewidth 32–52 µm, overspray 16–34 µm (paper App. A: 43 ± 6, 29),
area 1.3–3× the smallest area that gives a visible tail at that size.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from tqdm.auto import tqdm

from ajtwin.profile_cnn.data import ColumnDataset, default_scan_smoothing_um, register_profile
from ajtwin.vision.extract import LineExtractor
from ajtwin.vision.profile import line_profile, minimum_area_um2, profile_features
from ajtwin.vision.render import RenderSettings, Substrate, render_frame

from .frames import frame_columns

FINE_STEP_UM = 0.05
PROFILOMETER_STEP_UM = 0.5
PROFILOMETER_NOISE_UM = 0.003
FRAME_SHAPE = (320, 800)  # rows, cols: 16 batches of 50 columns per frame


@dataclasses.dataclass(frozen=True)
class LineRanges:
    """Ranges the synthetic lines are drawn from.

    Attributes
    ----------
    linewidth_um, overspray_um : (float, float)
        Uniform ranges [µm].
    area_factor : (float, float)
        Cross-section as a multiple of the least area that shows the overspray.
    raggedness_um : float
        σ of the edges' random shifts [µm].
    """

    linewidth_um: tuple[float, float] = (32.0, 52.0)
    overspray_um: tuple[float, float] = (16.0, 34.0)
    area_factor: tuple[float, float] = (1.3, 3.0)
    raggedness_um: float = 1.0


def _random_line(rng: np.random.Generator, ranges: LineRanges):
    lw = rng.uniform(*ranges.linewidth_um)
    ov = rng.uniform(*ranges.overspray_um)
    area = minimum_area_um2(lw, ov) * rng.uniform(*ranges.area_factor)
    r = np.arange(-110.0, 110.0 + FINE_STEP_UM / 2, FINE_STEP_UM)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the area is above the minimum by construction
        h = line_profile(r, lw, ov, area, rng=rng, raggedness_um=ranges.raggedness_um)
    return r, h


def _frame_settings(rng, base: RenderSettings) -> RenderSettings:
    return dataclasses.replace(
        base,
        tilt_deg=float(rng.uniform(-3.0, 3.0)),
        offset_px=float(rng.uniform(-12.0, 12.0)),
        background_gray=float(rng.uniform(140.0, 200.0)),
    )


def _truth_on_grid(r, h, um_per_px, n_pixels):
    """Box-averaged true profile on the column grid (centred on the area centroid)."""
    return register_profile(
        h, FINE_STEP_UM, um_per_px, n_pixels=n_pixels, level=False
    ), profile_features(r, h)


def synthetic_pairs(
    n_pairs: int = 125,
    *,
    seed: int = 0,
    um_per_px: float = 0.75,
    n_pixels: int = 200,
    batch: int = 50,
    ranges: LineRanges = LineRanges(),
    progress: bool = True,
    scan_smoothing_um: float | None = None,
    edge_raggedness_um: float | None = None,
) -> ColumnDataset:
    """Stage-1 pairs: (batch-mean column of a rendered frame, registered scan profile).

    ``scan_smoothing_um`` (default: the packaged setting) smooths each scan
    before registration, as for real scans. ``edge_raggedness_um`` (default: the
    renderer's, the same as the stage-2 frames of :func:`synthetic_labelled`) is
    the along-line raggedness of the rendered frame. Why not straight lines
    (0): a batch column of a ragged edge is smeared, and a
    network trained on straight pairs read the stage-2 columns' area 1.1–2.5 %
    low (stage 1, training seeds 0–3, held-out seed 11: Q_m error 3.0–3.6 % on
    ragged columns, 1.8–2.2 % on straight ones; trained on ragged pairs 2.4–2.8 %,
    bias +0.1…+1.1 %; docs/explanation/profile-cnn.md). The warp that makes the raggedness
    moves each row's shoulders by zero-mean shifts, so the mean cross-section
    under a batch is the straight profile to first order: the scan's target.

    Returns
    -------
    ColumnDataset
        ``columns``, ``profiles_um`` (registered synthetic profilometer scans),
        ``extra['true_linewidth_um' / 'true_overspray_um']``; one group per pair.
    """
    if scan_smoothing_um is None:
        scan_smoothing_um = default_scan_smoothing_um()
    rng = np.random.default_rng([seed, 1])
    ragged = {} if edge_raggedness_um is None else {"raggedness_um": edge_raggedness_um}
    base = RenderSettings.from_defaults(um_per_px=um_per_px, **ragged)
    substrate = Substrate(FRAME_SHAPE, base, rng)
    extractor = LineExtractor(um_per_px, batch=batch)
    columns, profiles, true_lw, true_ov = [], [], [], []
    bar = tqdm(total=n_pairs, desc="stage-1 pairs", disable=not progress)
    attempts = 0
    while len(columns) < n_pairs:
        attempts += 1
        if attempts > 5 * n_pairs + 20:
            raise RuntimeError("the extractor found no line in too many rendered frames")
        r, h = _random_line(rng, ranges)
        settings = _frame_settings(rng, base)
        frame = render_frame(
            r, h, FRAME_SHAPE, settings, rng=rng, substrate=substrate, travel_um=attempts * 600.0
        )
        fc = frame_columns(frame, extractor, n_pixels=n_pixels)
        if len(fc.columns) == 0:
            continue
        column = fc.columns[len(fc.columns) // 2]
        # the synthetic profilometer: coarser sampling, noise, tilted stage, offset
        x = np.arange(r[0], r[-1], PROFILOMETER_STEP_UM)
        scan = np.interp(x, r, h)
        scan = scan + rng.normal(0.0, PROFILOMETER_NOISE_UM, x.size)
        scan = scan + rng.uniform(-2e-3, 2e-3) * (x - x[0]) + rng.uniform(-0.5, 0.5)
        profile = register_profile(
            scan,
            PROFILOMETER_STEP_UM,
            um_per_px,
            n_pixels=n_pixels,
            smoothing_um=scan_smoothing_um,
        )
        lw, ov = profile_features(r, h)
        columns.append(column)
        profiles.append(profile)
        true_lw.append(lw)
        true_ov.append(ov)
        bar.update(1)
    bar.close()
    return ColumnDataset(
        columns=np.array(columns),
        um_per_px=um_per_px,
        profiles_um=np.array(profiles),
        group=np.arange(n_pairs),
        extra={
            "true_linewidth_um": np.array(true_lw),
            "true_overspray_um": np.array(true_ov),
        },
    )


def synthetic_labelled(
    n_columns: int = 4000,
    *,
    seed: int = 0,
    um_per_px: float = 0.75,
    n_pixels: int = 200,
    batch: int = 50,
    ranges: LineRanges = LineRanges(),
    progress: bool = True,
) -> ColumnDataset:
    """Stage-2 columns with CV labels (from the extractor on rendered frames).

    Each frame shows one random line (ragged along the line); its batches
    whose CV measurement succeeded become labelled columns (one group per
    frame, so a frame never straddles two CV folds).

    Returns
    -------
    ColumnDataset
        ``columns``, ``linewidth_um``/``overspray_um`` (CV labels),
        ``profiles_um`` (hidden truth, for evaluation only),
        ``extra['true_linewidth_um' / 'true_overspray_um']``, ``group`` = frame.
    """
    rng = np.random.default_rng([seed, 2])
    base = RenderSettings.from_defaults(um_per_px=um_per_px)
    substrate = Substrate(FRAME_SHAPE, base, rng)
    extractor = LineExtractor(um_per_px, batch=batch)
    cols, lws, ovs, truth, t_lw, t_ov, groups = [], [], [], [], [], [], []
    bar = tqdm(total=n_columns, desc="stage-2 columns", disable=not progress)
    frame_no = 0
    count = 0
    while count < n_columns:
        frame_no += 1
        if frame_no > 5 * n_columns // max(1, FRAME_SHAPE[1] // batch) + 20:
            raise RuntimeError("the extractor labelled too few batches of the rendered frames")
        r, h = _random_line(rng, ranges)
        settings = _frame_settings(rng, base)
        frame = render_frame(
            r, h, FRAME_SHAPE, settings, rng=rng, substrate=substrate, travel_um=frame_no * 600.0
        )
        fc = frame_columns(frame, extractor, n_pixels=n_pixels, index=frame_no)
        if len(fc.columns) == 0:
            continue
        ok = fc.cv_ok & np.isfinite(fc.cv_linewidth_um) & np.isfinite(fc.cv_overspray_um)
        if not ok.any():
            continue
        true_profile, (lw, ov) = _truth_on_grid(r, h, um_per_px, n_pixels)
        take = np.flatnonzero(ok)[: n_columns - count]
        cols.append(fc.columns[take])
        lws.append(fc.cv_linewidth_um[take])
        ovs.append(fc.cv_overspray_um[take])
        truth.append(np.repeat(true_profile[None], take.size, axis=0))
        t_lw.append(np.full(take.size, lw))
        t_ov.append(np.full(take.size, ov))
        groups.append(np.full(take.size, frame_no))
        count += take.size
        bar.update(take.size)
    bar.close()
    return ColumnDataset(
        columns=np.concatenate(cols),
        um_per_px=um_per_px,
        profiles_um=np.concatenate(truth),
        linewidth_um=np.concatenate(lws),
        overspray_um=np.concatenate(ovs),
        group=np.concatenate(groups),
        extra={
            "true_linewidth_um": np.concatenate(t_lw),
            "true_overspray_um": np.concatenate(t_ov),
        },
    )
