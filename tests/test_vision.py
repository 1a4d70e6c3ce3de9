"""Vision core: profile model, reference definitions, renderer, extractor (model reference §9)."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ajtwin.units import cross_section_um2, material_flow_ml_s
from ajtwin.vision import features as F
from ajtwin.vision.extract import LineExtractor, annotate, to_gray
from ajtwin.vision.profile import (
    brightness_from_profile,
    brightness_from_slope,
    line_profile,
    minimum_area_um2,
    optics,
    profile_features,
    slope_at_threshold,
)
from ajtwin.vision.render import RenderSettings, Substrate, render_columns, render_frame

R_FINE = np.arange(-160.0, 160.0, 0.02)
R_RENDER = np.arange(-160.0, 160.0, 0.05)


# ---------------------------------------------------------------- optics and units
def test_brightness_hand_values():
    cfg = optics()["brightness"]
    s0, floor = cfg["slope_scale"], cfg["floor"]
    assert brightness_from_slope(0.0, background=170.0) == pytest.approx(170.0)
    # at |slope| = slope_scale the slope term is one half
    expected = 170.0 * (floor + (1 - floor) / 2)
    assert brightness_from_slope(-s0, background=170.0) == pytest.approx(expected)
    assert brightness_from_slope(1e9) == pytest.approx(floor, abs=1e-6)
    assert brightness_from_slope(slope_at_threshold()) == pytest.approx(0.95)


def test_brightness_from_profile_uses_slope_of_a_ramp():
    r = np.linspace(0.0, 10.0, 101)
    h = 0.03 * r  # constant slope
    b = brightness_from_profile(r, h, background=200.0)
    assert np.allclose(b, brightness_from_slope(0.03, background=200.0))


def test_cross_section_units():
    # nominal: Q_m 1.5e-8 mL/s at 1 mm/s -> 15 µm²  (1 µm³ = 1e-12 mL, 1 mm/s = 1000 µm/s)
    assert cross_section_um2(1.5e-8, 1.0) == pytest.approx(15.0)
    assert cross_section_um2(1.5e-8, 2.0) == pytest.approx(7.5)
    assert material_flow_ml_s(15.0, 1.0) == pytest.approx(1.5e-8)


# ---------------------------------------------------------------- reference definitions
def _piecewise_linear_line():
    """A line whose features follow by hand (slopes piecewise constant).

    |r| < 5 flat top, 5..20 slope 0.05 (dark flank, (ii)), 20..22 flat terrace (peak (iii)
    centred at 21), 22..40 slope giving brightness 0.9 (< 0.95: overspray), then substrate.
    Linewidth = 42, overspray = 40 - 21 = 19.
    """
    tail_slope = slope_at_threshold(0.9)
    u = np.abs(R_FINE)
    h = np.zeros_like(u)
    terrace = tail_slope * 18.0
    h = np.where(u <= 40, tail_slope * (40 - u), 0.0)
    h = np.where(u <= 22, terrace, h)
    h = np.where(u <= 20, terrace + 0.05 * (20 - u), h)
    h = np.where(u <= 5, terrace + 0.05 * 15, h)
    return h


def test_profile_features_hand_computed_line():
    lw, ov = profile_features(R_FINE, _piecewise_linear_line())
    assert lw == pytest.approx(42.0, abs=0.05)
    assert ov == pytest.approx(19.0, abs=0.05)


def test_profile_features_resamples_coarse_grid():
    coarse = np.arange(-160.0, 160.0, 0.1)
    h = line_profile(coarse, 43.0, 29.0, 15.0)
    lw, ov = profile_features(coarse, h)
    assert lw == pytest.approx(43.0, abs=0.15)
    assert ov == pytest.approx(29.0, abs=0.15)


@settings(max_examples=25, deadline=None)
@given(
    linewidth=st.floats(20.0, 90.0),
    overspray=st.floats(8.0, 60.0),
    extra_area=st.floats(1.0, 80.0),
)
def test_line_profile_meets_its_own_definitions(linewidth, overspray, extra_area):
    area = minimum_area_um2(linewidth, overspray) + extra_area
    h = line_profile(R_FINE, linewidth, overspray, area)
    assert np.all(h >= 0)
    assert np.trapezoid(h, R_FINE) == pytest.approx(area, rel=1e-3)
    lw, ov = profile_features(R_FINE, h)
    assert lw == pytest.approx(linewidth, abs=0.05)
    assert ov == pytest.approx(overspray, abs=0.05)


def test_line_profile_nominal_and_raggedness():
    h = line_profile(R_FINE, 43.0, 29.0, 15.0)
    assert h.max() == pytest.approx(h[np.argmin(np.abs(R_FINE))])  # peak at the centre
    rng = np.random.default_rng(3)
    ragged = [line_profile(R_FINE, 43.0, 29.0, 15.0, rng=rng, raggedness_um=2.0) for _ in range(30)]
    feats = np.array([profile_features(R_FINE, p) for p in ragged])
    # shoulders move independently by N(0, 2 µm): linewidth spread ~ 2.8 µm, mean unbiased
    assert 1.5 < feats[:, 0].std() < 4.5
    assert abs(feats[:, 0].mean() - 43.0) < 1.6
    for p in ragged:
        assert np.trapezoid(p, R_FINE) == pytest.approx(15.0, rel=1e-3)
    again = line_profile(R_FINE, 43.0, 29.0, 15.0, rng=np.random.default_rng(3), raggedness_um=2)
    assert np.array_equal(again, ragged[0])


def test_line_profile_small_area_warns_and_keeps_area():
    with pytest.warns(UserWarning, match="below"):
        h = line_profile(R_FINE, 43.0, 29.0, 2.0)
    assert np.trapezoid(h, R_FINE) == pytest.approx(2.0, rel=1e-3)


@pytest.mark.parametrize(
    "args", [(0.0, 29.0, 15.0), (43.0, -1.0, 15.0), (43.0, 29.0, np.nan), (43.0, 29.0, 0.0)]
)
def test_line_profile_rejects_bad_sizes(args):
    with pytest.raises(ValueError, match="line_profile"):
        line_profile(R_FINE, *args)


def test_profile_features_rejects_bad_grid():
    with pytest.raises(ValueError, match="increasing"):
        profile_features(R_FINE[::-1], np.zeros_like(R_FINE))
    with pytest.raises(ValueError, match="NaN"):
        profile_features(R_FINE, np.full_like(R_FINE, np.nan))


# ---------------------------------------------------------------- 1-D algorithm pieces
def test_std_fallback_when_no_brightness_peak():
    n = 200
    y = np.arange(n)
    # dark band, then brightness climbs monotonically back to background: no peak (iii)
    mean = 100.0 - 60.0 * np.exp(-0.5 * ((y - 100) / 25.0) ** 2)
    std = 1.0 + 8.0 * np.exp(-0.5 * ((np.abs(y - 100) - 40) / 2.0) ** 2)  # ragged shoulders
    pts = F.find_edges(mean, 100.0, std=std)
    assert pts.used_std == (True, True)
    assert pts.status == F.STD_FALLBACK
    assert pts.shoulders[0] == pytest.approx(60.0, abs=0.5)
    assert pts.shoulders[1] == pytest.approx(140.0, abs=0.5)
    no_std = F.find_edges(mean, 100.0)
    assert no_std.status == F.NO_SHOULDER and np.isnan(no_std.linewidth)


def test_overspray_end_ignores_a_short_bright_speck():
    seg = np.array([1.0, 0.9, 0.9, 0.97, 0.9, 0.9, 0.9, 1.0, 1.0, 1.0, 1.0])
    thr = np.full(seg.size, 0.95)
    assert F.overspray_end(seg, thr, hold=3) == pytest.approx(6.5)
    assert F.overspray_end(seg, thr, hold=1) == pytest.approx(2 + 0.05 / 0.07)
    assert F.overspray_end(np.ones(5), np.full(5, 0.95)) == 0.0
    assert np.isnan(F.overspray_end(np.array([1.0, 0.9, 0.9]), np.full(3, 0.95)))


def test_batch_version_equals_column_version():
    """Independent implementations: vectorised find_edges_batches vs per-column find_edges."""
    rng = np.random.default_rng(7)
    profiles = [
        line_profile(R_RENDER, lw, ov, area, rng=rng, raggedness_um=1.0)
        for lw, ov, area in [(43, 29, 15), (35, 20, 10), (55, 40, 30), (43, 29, 6)] * 6
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        columns, _ = render_columns(
            R_RENDER,
            np.stack(profiles),
            n_px=260,
            rng=rng,
            noise_sigma_gray=0.5,
            center_jitter_px=3.0,
            as_uint8=False,
        )
    mean = columns.T.astype(float)
    background = np.full_like(mean, 170.0)
    noise = np.full(mean.shape[1], 0.5)
    fast = F.find_edges_batches(mean, background, noise=noise)
    for b in range(mean.shape[1]):
        slow = F.find_edges(mean[:, b], background[:, b], noise=noise[b])
        assert fast.status[b] == slow.status
        np.testing.assert_allclose(fast.shoulders[b], slow.shoulders, atol=1e-9)
        np.testing.assert_allclose(fast.overspray_edges[b], slow.overspray_edges, atol=1e-9)
    assert fast.status.count(F.OK) >= 20


# ---------------------------------------------------------------- renderer
def _settings(**kw):
    return RenderSettings.from_defaults(**kw)


def test_render_frame_geometry_follows_tilt():
    """The darkest row per column must follow the requested tilt (no Hough involved)."""
    h = line_profile(R_RENDER, 43.0, 29.0, 15.0)
    for tilt in (-10.0, 0.0, 7.0):
        frame = render_frame(
            R_RENDER,
            h,
            (480, 640),
            _settings(
                tilt_deg=tilt, noise_sigma_gray=0.0, raggedness_um=0.0, texture_amplitude=0.0
            ),
            rng=np.random.default_rng(0),
        )
        cols = np.arange(100, 540, 20)
        image = frame[:, cols].astype(float)
        darkness = np.median(image, axis=0) - image
        weight = np.where(darkness > 0.5 * darkness.max(axis=0), darkness, 0.0)
        rows = (np.arange(480)[:, None] * weight).sum(axis=0) / weight.sum(axis=0)
        slope = np.polyfit(cols, rows, 1)[0]
        # image y points down: a line rising to the right has negative row slope
        assert np.rad2deg(np.arctan(-slope)) == pytest.approx(tilt, abs=0.5)


def test_render_frame_levels_and_determinism():
    h = line_profile(R_RENDER, 43.0, 29.0, 15.0)
    s = _settings(illumination_gradient=0.0, vignetting=0.0)
    a = render_frame(R_RENDER, h, (240, 320), s, rng=np.random.default_rng(1))
    b = render_frame(R_RENDER, h, (240, 320), s, rng=np.random.default_rng(1))
    assert a.dtype == np.uint8 and a.shape == (240, 320)
    assert np.array_equal(a, b)
    assert np.median(a[:20]) == pytest.approx(170.0, abs=4.0)  # substrate far from the line
    dark = a[100:140].min(axis=0).mean()
    assert dark < 0.6 * 170  # the steep flanks are dark


def test_render_columns_match_the_optical_model():
    h = line_profile(R_RENDER, 43.0, 29.0, 15.0)
    cols, r_px = render_columns(
        R_RENDER,
        h,
        rng=np.random.default_rng(0),
        noise_sigma_gray=0.0,
        blur_sigma_px=0.0,
        shot_noise=0.0,
        as_uint8=False,
    )
    assert cols.shape == (1, 200) and r_px.shape == (200,)
    # pixel value = mean brightness over the pixel width (brute force, 40 sub-samples)
    sub = (np.arange(40) + 0.5) / 40 - 0.5
    fine_r = (r_px[:, None] + sub[None, :] * 0.75).ravel()
    fine_h = np.interp(fine_r, R_RENDER, h)
    step = 0.75 / 40
    slope = np.gradient(fine_h, step)
    expected = brightness_from_slope(slope, background=170.0).reshape(200, 40).mean(axis=1)
    np.testing.assert_allclose(cols[0], expected, atol=2.0)


def test_render_columns_many_profiles_and_errors():
    hs = np.stack([line_profile(R_RENDER, 40 + i, 25, 15) for i in range(5)])
    cols, _ = render_columns(R_RENDER, hs, rng=np.random.default_rng(0), center_jitter_px=2)
    assert cols.shape == (5, 200) and cols.dtype == np.uint8
    with pytest.raises(ValueError, match="samples"):
        render_columns(R_RENDER[:-1], hs)


# ---------------------------------------------------------------- extraction accuracy
def _extract(tilt, noise, raggedness, seed=0, shape=(480, 640), lw=43.0, ov=29.0, area=15.0):
    h = line_profile(R_RENDER, lw, ov, area)
    truth = profile_features(R_FINE, line_profile(R_FINE, lw, ov, area))
    settings_ = _settings(tilt_deg=tilt, noise_sigma_gray=noise, raggedness_um=raggedness)
    frame = render_frame(R_RENDER, h, shape, settings_, rng=np.random.default_rng(seed))
    return LineExtractor(settings_.um_per_px).process(frame), truth


@pytest.mark.parametrize("tilt", [-10.0, -4.0, 0.0, 6.0, 10.0])
@pytest.mark.parametrize("noise", [2.0, 6.0])
def test_extraction_matches_truth_across_tilts(tilt, noise):
    """Linewidth within 1 µm, overspray within 3 µm, tilts up to ±10°."""
    result, (lw_true, ov_true) = _extract(tilt, noise, raggedness=0.5, seed=int(tilt) + 20)
    assert result.status == "ok"
    assert result.angle_deg == pytest.approx(tilt, abs=0.3)
    assert abs(result.linewidth_um - lw_true) <= 1.0
    assert abs(result.overspray_um - ov_true) <= 3.0


@pytest.mark.parametrize("lw,ov,area", [(30.0, 15.0, 8.0), (60.0, 45.0, 35.0)])
def test_extraction_other_line_sizes(lw, ov, area):
    result, (lw_true, ov_true) = _extract(3.0, 2.0, 0.5, lw=lw, ov=ov, area=area)
    assert abs(result.linewidth_um - lw_true) <= 1.0
    assert abs(result.overspray_um - ov_true) <= 3.0


def test_batch_statistics_match_numpy():
    """OpenCV INTER_AREA block means (the fast path) vs a plain NumPy reshape."""
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (64, 230), dtype=np.uint8)
    mean, std, n = LineExtractor(1.0, batch=50).batch_statistics(image)
    blocks = image[:, :200].astype(float).reshape(64, 4, 50)
    assert n == 4
    np.testing.assert_allclose(mean, blocks.mean(axis=2), atol=1e-3)
    np.testing.assert_allclose(std, blocks.std(axis=2), atol=1e-2)


def test_rotation_straightens_the_line():
    """After the extractor's rotation (cv2.warpAffine) the line must be horizontal."""
    h = line_profile(R_RENDER, 43.0, 29.0, 15.0)
    s = _settings(tilt_deg=8.0, raggedness_um=0.0)
    frame = render_frame(R_RENDER, h, (480, 640), s, rng=np.random.default_rng(2))
    result = LineExtractor(0.75).process(frame)
    centres = [0.5 * sum(b.shoulders) for b in result.batches if b.status == "ok"]
    assert len(centres) >= 10
    assert np.ptp(centres) < 2.0  # over 600 px: < 0.2° residual tilt


def test_annotation_draws_the_three_colours():
    result, _ = _extract(5.0, 2.0, 0.5)
    h = line_profile(R_RENDER, 43.0, 29.0, 15.0)
    frame = render_frame(
        R_RENDER, h, (480, 640), _settings(tilt_deg=5.0), rng=np.random.default_rng(0)
    )
    canvas = annotate(frame, LineExtractor(0.75).process(frame))
    assert canvas.shape == (480, 640, 3)
    b, g, r = canvas[..., 0].astype(int), canvas[..., 1].astype(int), canvas[..., 2].astype(int)
    assert ((g > 150) & (r < 80) & (b < 80)).sum() > 300  # Hough fit
    assert ((r > 200) & (g < 80) & (b < 80)).sum() > 300  # linewidth edges
    assert ((b > 200) & (r < 80)).sum() > 300  # overspray edges


# ---------------------------------------------------------------- frames without a line
def test_dark_blank_and_lineless_frames_get_a_status():
    ex = LineExtractor(0.75)
    assert ex.process(np.zeros((240, 320), np.uint8)).status == "dark_frame"
    assert ex.process(np.full((240, 320), 128, np.uint8)).status == "blank_frame"
    noise = np.random.default_rng(0).normal(128, 10, (240, 320)).clip(0, 255).astype(np.uint8)
    assert ex.process(noise).status in ("no_line", "no_shoulder", "few_batches")


def test_line_wider_than_frame_gets_status():
    h = line_profile(R_RENDER, 43.0, 29.0, 15.0)
    frame = render_frame(
        R_RENDER, h, (240, 320), _settings(um_per_px=0.12), rng=np.random.default_rng(0)
    )
    assert LineExtractor(0.12).process(frame).status == "line_fills_frame"


def test_to_gray_handles_colour_and_16_bit():
    bgr = np.zeros((10, 12, 3), np.uint8)
    bgr[..., 1] = 200
    assert to_gray(bgr).shape == (10, 12)
    assert to_gray(np.full((4, 4), 65535, np.uint16)).max() == 255
    with pytest.raises(ValueError):
        to_gray(np.zeros((0,), np.uint8))


def test_substrate_moves_with_the_platen():
    s = _settings(noise_sigma_gray=0.0, raggedness_um=0.0)
    rng = np.random.default_rng(0)
    sub = Substrate((120, 400), s, rng)
    h = np.zeros_like(R_RENDER)
    a = render_frame(R_RENDER, h, (120, 400), s, rng=rng, substrate=sub, travel_um=0.0)
    b = render_frame(R_RENDER, h, (120, 400), s, rng=rng, substrate=sub, travel_um=30 * 0.75)
    # texture seen 30 px further along the line after the platen moved 30 px
    ia = _flat(a)
    ib = _flat(b)
    corr_shifted = np.corrcoef(ia[:, 30:].ravel(), ib[:, :-30].ravel())[0, 1]
    corr_same = np.corrcoef(ia.ravel(), ib.ravel())[0, 1]
    assert corr_shifted > 0.9 > corr_same


def _flat(frame):
    """Remove illumination and pixel noise so only the (smooth) texture remains."""
    f = frame.astype(float)
    return cv2.GaussianBlur(f, (0, 0), 2.0) / cv2.GaussianBlur(f, (0, 0), 40)
