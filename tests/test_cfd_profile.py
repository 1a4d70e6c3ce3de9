"""CFD post-processing (model reference §8) on hand-made landing distributions with known
answers."""

import numpy as np
import pytest

from ajtwin.cfd.profile import _semicircle_cdf, height_profile, line_metrics

# Gaussian line profile N(0, σ): h > 0.8 h_max for |y| < σ sqrt(2 ln 1.25)
GAUSS_HALF_B = np.sqrt(2 * np.log(1.25))


def test_single_droplet_chord_kernel_gives_b_of_0_6_footprint():
    # one droplet at the centre: disc of D = 3.8 d summed along the line → sqrt(R² − y²);
    # above 80 % where sqrt(1 − u²) > 0.8, i.e. |u| < 0.6 → b = 1.2 R = 0.6 · 3.8 d
    y, h = height_profile(
        np.zeros(1),
        np.full(1, 10.0),
        spread_factor=3.8,
        bin_um=0.01,
        half_width_um=25.0,
        azimuths=1,
    )
    m = line_metrics(y, h)
    assert m["b_um"] == pytest.approx(0.6 * 38.0, abs=0.02)
    assert m["linewidth_um"] == pytest.approx(2.1 * 22.8, abs=0.05)
    # the deposit ends at ±19 µm, inside the linewidth edges at ±23.94 µm: no overspray
    assert np.isnan(m["overspray_um"])


def test_profile_conserves_droplet_volume():
    rng = np.random.default_rng(1)
    r = rng.uniform(0, 40, 500)
    d = rng.uniform(1, 5, 500)
    y, h = height_profile(r, d, bin_um=0.5, azimuths=4)
    total = np.sum(h) * 0.5
    assert total == pytest.approx(np.sum(np.pi * d**3 / 6), rel=1e-10)


def test_semicircle_cdf_is_a_cdf():
    u = np.linspace(-1, 1, 2001)
    f = _semicircle_cdf(u)
    assert f[0] == 0.0 and f[-1] == pytest.approx(1.0)
    assert np.all(np.diff(f) >= 0)
    # density (2/π) sqrt(1-u²) at 0 is 2/π
    assert (f[1001] - f[999]) / (u[1001] - u[999]) == pytest.approx(2 / np.pi, rel=1e-5)


def test_gaussian_landing_gives_analytic_linewidth_and_overspray():
    # landing points 2-D normal (σ = 10 µm) → radii Rayleigh; random azimuth + line
    # summation must give back a normal profile across the line
    sigma = 10.0
    rng = np.random.default_rng(7)
    radii = sigma * np.sqrt(-2 * np.log(rng.uniform(size=200_000)))
    d = np.full(radii.size, 0.01)  # negligible footprint
    y, h = height_profile(radii, d, bin_um=0.25, azimuths=4, seed=3)
    m = line_metrics(y, h)
    b = 2 * GAUSS_HALF_B * sigma  # 13.36 µm
    assert m["b_um"] == pytest.approx(b, rel=0.03)
    assert m["linewidth_um"] == pytest.approx(2.1 * b, rel=0.03)
    # edges at ±1.403σ where h = exp(−1.403²/2) h_max; 1 % of that is reached at
    # |y| = sqrt(edge² + 2σ² ln 100)
    edge = 1.05 * b
    y_end = sigma * np.sqrt(edge**2 / sigma**2 + 2 * np.log(100.0))
    assert m["overspray_um"] == pytest.approx(y_end - edge, rel=0.04)
    assert abs(m["centre_um"]) < 0.3


def test_uniform_disc_landing_gives_semicircle_profile():
    # landing uniform over a disc of radius R: the projection is ∝ sqrt(R² − y²) → b = 1.2 R
    # (stratified radii; the azimuths stay random. h_max of a noisy histogram is biased
    # high, which narrows b, so the sample must be large: 3.2 M points in 1 µm bins)
    radius = 30.0
    n = 100_000
    radii = radius * np.sqrt((np.arange(n) + 0.5) / n)
    y, h = height_profile(radii, np.full(n, 0.01), bin_um=1.0, azimuths=32)
    assert line_metrics(y, h)["b_um"] == pytest.approx(1.2 * radius, rel=0.03)


def test_line_metrics_on_an_exact_triangle():
    # h = 1 − |y|/W: b = 0.4 W; L_w = 0.84 W; edges ±0.42 W with h 0.58;
    # 1 % of 0.58 reached at |y| = W (1 − 0.0058) → overspray 0.5742 W
    w = 50.0
    y = np.linspace(-80, 80, 160001)
    h = np.clip(1 - np.abs(y) / w, 0, None)
    m = line_metrics(y, h)
    assert m["b_um"] == pytest.approx(0.4 * w, abs=1e-3)
    assert m["linewidth_um"] == pytest.approx(0.84 * w, abs=2e-3)
    assert m["overspray_um"] == pytest.approx(0.5742 * w, abs=2e-3)
    assert m["overspray_left_um"] == pytest.approx(m["overspray_right_um"], abs=1e-3)


def test_longest_run_above_80_percent_is_chosen():
    # two plateaus above 80 %: a narrow tall spike and a wide shoulder → b is the wide one
    y = np.linspace(-50, 50, 10001)
    h = np.where(np.abs(y - 20) < 1, 1.0, 0.0) + np.where(np.abs(y + 10) < 15, 0.85, 0.0)
    m = line_metrics(y, h)
    assert m["b_um"] == pytest.approx(30.0, abs=0.05)
    assert m["centre_um"] == pytest.approx(-10.0, abs=0.05)


def test_overspray_sides_are_measured_separately():
    # asymmetric exponential tails: right tail twice as long as the left one
    y = np.linspace(-200, 200, 40001)
    h = np.where(
        np.abs(y) <= 10, 1.0, np.where(y > 0, np.exp(-(y - 10) / 20), np.exp((y + 10) / 10))
    )
    m = line_metrics(y, h, width_ratio=1.0)  # edges exactly at ±10, h_edge = 1
    assert m["overspray_right_um"] == pytest.approx(20 * np.log(100), rel=1e-3)
    assert m["overspray_left_um"] == pytest.approx(10 * np.log(100), rel=1e-3)
    assert m["overspray_um"] == pytest.approx(15 * np.log(100), rel=1e-3)


@pytest.mark.parametrize("bad", [np.nan, -1.0])
def test_bad_landing_radius_is_rejected(bad):
    with pytest.raises(ValueError, match="landing radii"):
        height_profile(np.array([1.0, bad]), np.array([1.0, 1.0]))


def test_empty_and_nan_profiles_are_rejected():
    with pytest.raises(ValueError, match="no landed droplets"):
        height_profile(np.array([]), np.array([]))
    with pytest.raises(ValueError, match="NaN"):
        line_metrics(np.arange(5.0), np.array([0, 1, np.nan, 1, 0]))
    with pytest.raises(ValueError, match="empty"):
        line_metrics(np.arange(5.0), np.zeros(5))
