"""The physics model against hand-computed values, limits, conservation and autodiff."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ajtwin import units
from ajtwin._jax import jax, jnp
from ajtwin.model import (
    DigitalModel,
    euler_step,
    ink_flows,
    load_parameters,
    output_function,
    simulate_open_loop,
    transition_rates,
)
from ajtwin.model.atomizer import net_droplet_generation
from ajtwin.model.droplets import (
    cunningham_slip_correction,
    diffusion_coefficient,
    lognormal_quadrature,
    lognormal_sigma,
    settling_velocity,
)
from ajtwin.model.fluidics import nozzle_tip_resistance, tube_resistance
from ajtwin.model.transport import critical_radius, diffusion_survival, settling_survival

MODEL = DigitalModel.default()
P = MODEL.params
U_EXP1 = np.array([375.0, 23.0, 50.0])
X_CLEAN = np.array([3.5, 1.0, 0.0, 0.0, 4.6192e-7])


# --------------------------------------------------------------------------- #
# Hand values from model reference §5 and §4
# --------------------------------------------------------------------------- #
def test_pressures_match_spec_hand_values():
    y = MODEL.outputs(X_CLEAN, U_EXP1)
    assert y[2] == pytest.approx(5661.0, rel=0.005)
    assert y[3] == pytest.approx(5641.0, rel=0.005)


def test_pressures_recomputed_by_hand():
    # Hagen–Poiseuille and the network written out independently of the code
    qc, qs = 23 / 60 * 1e-6, 50 / 60 * 1e-6
    r_t = 8 * 1.76e-5 * 0.4572 / (math.pi * 7.89e-4**4)
    r_n = 5.36e6 + 6.07e7 + 4.57e9
    p_c = qc * (r_t + 1.1972e4 + 5.6305e4 + 6.9590e5) + (qc + qs) * r_n
    p_s = qs * (2.185e5 + 175.66 + 1.28e6) / 2 + (qc + qs) * r_n
    y = MODEL.outputs(X_CLEAN, U_EXP1)
    assert y[2] == pytest.approx(p_c, rel=1e-12)
    assert y[3] == pytest.approx(p_s, rel=1e-12)


def test_carrier_pressure_sensitivity_to_nozzle_deposition():
    g = jax.jacfwd(output_function)(
        jnp.asarray(X_CLEAN), jnp.asarray(U_EXP1), P, MODEL.coefficient_matrix
    )
    dpc_dn = float(g[2, 3])  # Pa per µm
    assert dpc_dn == pytest.approx(3.3e3, rel=0.02)
    # and exactly (Q_c + Q_s)·a_1 at a clean nozzle
    assert dpc_dn == pytest.approx(73 / 60 * 1e-6 * 2.75e9, rel=1e-9)


def test_nozzle_tip_polynomial_coefficients():
    assert nozzle_tip_resistance(0.0, P) == pytest.approx(4.57e9)
    a = [4.57e9, 2.75e9, -7.96e8, 9.73e7, -5.81e6, 1.83e5, -2.92e3, 18.67]
    for dn in (0.03, 1.0, 7.5, 30.0):
        expected = sum(c * dn**i for i, c in enumerate(a))
        assert float(nozzle_tip_resistance(dn, P)) == pytest.approx(expected, rel=1e-12)


def test_generation_at_box_behnken_points():
    fit = P.generation_fit
    # centre point of the design: Q_c 25 sccm, V_l 1 mL, I_A 370 mA
    h = (
        3.3e2 * 25**2
        + 2.7e4 * 1 * 25
        + 66 * 25 * 370
        + 2.1e2 * 370 * 1
        - 5.2e5 * 1
        - 4.8e4 * 25
        - 1.1e3 * 370
        + 7.7e5
    )
    assert h == pytest.approx(212_450.0)  # 206250+675000+610500+77700-520000-1200000-407000+770000
    assert float(net_droplet_generation(25.0, 1.0, 370.0, fit)) == pytest.approx(h * 1e-12)
    # an edge midpoint of the design: Q_c 15, V_l 0.5, I_A 370
    h2 = (
        3.3e2 * 225
        + 2.7e4 * 0.5 * 15
        + 66 * 15 * 370
        + 2.1e2 * 370 * 0.5
        - 5.2e5 * 0.5
        - 4.8e4 * 15
        - 1.1e3 * 370
        + 7.7e5
    )
    assert float(net_droplet_generation(15.0, 0.5, 370.0, fit)) == pytest.approx(h2 * 1e-12)


def test_units_conversion_sccm():
    assert units.sccm_to_m3_per_s(1.0) == pytest.approx(1.6667e-8, rel=1e-4)
    assert units.sccm_to_ml_per_s(60.0) == pytest.approx(1.0)


def test_slip_and_diffusion_hand_values():
    d = 3.5e-6
    kn = 2 * 0.066e-6 / d
    cc = 1 + kn * (1.257 + 0.4 * math.exp(-1.1 / kn))
    assert float(cunningham_slip_correction(d, 0.066e-6)) == pytest.approx(cc, rel=1e-12)
    diff = 1.380649e-23 * 293.15 * cc / (3 * math.pi * 1.76e-5 * d)  # 3π, not the paper's 2π
    assert float(diffusion_coefficient(d, 293.15, 1.76e-5, 0.066e-6, 1.380649e-23)) == (
        pytest.approx(diff, rel=1e-12)
    )
    v = 5804 * d**2 * 9.81 * cc / (18 * 72e-3)
    assert float(settling_velocity(d, 5804, 9.81, 72e-3, 0.066e-6)) == pytest.approx(v, rel=1e-12)


# --------------------------------------------------------------------------- #
# Limits
# --------------------------------------------------------------------------- #
def test_settling_survival_limits():
    u_bar, length, radius = 0.2, 0.4572, 7.89e-4
    # vanishing droplets: survival → 1 like 1 − (16/3π) α³
    tiny = float(settling_survival(1e-15, u_bar, length, radius))
    assert tiny == pytest.approx(1.0, abs=1e-11)
    small_v = 1e-7
    alpha = (3 * length * small_v / (8 * u_bar * radius)) ** (1 / 3)
    assert 1 - float(settling_survival(small_v, u_bar, length, radius)) == pytest.approx(
        16 / (3 * math.pi) * alpha**3, rel=1e-3
    )
    # α ≥ 1: nobody survives; and the gradient stays finite there
    v_at_alpha_one = 8 * u_bar * radius / (3 * length)
    for factor in (1.0, 1.5, 10.0):
        assert float(settling_survival(v_at_alpha_one * factor, u_bar, length, radius)) == (
            pytest.approx(0.0, abs=1e-12)
        )
    grad = jax.grad(lambda v: settling_survival(v, u_bar, length, radius))(v_at_alpha_one * 2)
    assert np.isfinite(float(grad))
    # monotone decreasing in settling speed
    speeds = np.geomspace(1e-9, v_at_alpha_one, 200)
    surv = np.asarray(settling_survival(jnp.asarray(speeds), u_bar, length, radius))
    assert np.all(np.diff(surv) <= 1e-15)


@settings(max_examples=200, deadline=None)
@given(st.floats(min_value=1e-14, max_value=50.0, allow_nan=False))
def test_critical_radius_solves_its_equation(mu):
    x = float(critical_radius(mu))
    assert 0.0 <= x <= 1.0
    if mu < 1.0:
        # residual relative to μ: the fixed Newton steps converge for every μ
        assert (1 - x) ** 2 * (1 - x**2) == pytest.approx(mu, rel=1e-9, abs=1e-300)
    else:
        assert x == 0.0


@settings(max_examples=100, deadline=None)
@given(
    st.floats(min_value=1e-14, max_value=1e-6),  # D m²/s
    st.floats(min_value=1e-9, max_value=1e-4),  # Q m³/s
)
def test_diffusion_survival_in_unit_interval(diffusivity, flow):
    p = float(diffusion_survival(diffusivity, flow, 0.01))
    assert 0.0 < p <= 1.0 or (p == 0.0 and math.pi * 0.01 * diffusivity / flow >= 1)


def test_diffusion_survival_small_loss_asymptote():
    # for μ ≪ 1: ε ≈ (μ/2)^{1/3} and 1 − P ≈ 4ε²
    mu = 1e-7
    diffusivity, flow, length = mu / math.pi, 1.0, 1.0
    eps = (mu / 2) ** (1 / 3)
    loss = 1 - float(diffusion_survival(diffusivity, flow, length))
    assert loss == pytest.approx(4 * eps**2, rel=1e-2)


def test_quadrature_weights_and_lognormal_mean():
    d, w = lognormal_quadrature(3.5, 0.25)
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-14)
    sigma = float(lognormal_sigma(0.25))
    assert sigma == pytest.approx(math.sqrt(math.log(1 + 0.0625)))
    mean = float((w * d).sum())
    assert mean == pytest.approx(3.5 * math.exp(sigma**2 / 2), rel=1e-12)
    # the coefficient of variation is the stated 25 %
    var = float((w * d**2).sum()) - mean**2
    assert math.sqrt(var) / mean == pytest.approx(0.25, rel=1e-10)
    # median: half the probability mass below d_a
    assert float(w[d < 3.5].sum()) == pytest.approx(0.5, abs=1e-12)


def test_tube_resistance_scales_with_fourth_power():
    r0 = float(tube_resistance(0.0, P))
    half = float(tube_resistance(P.tube_radius / 2, P))
    assert half / r0 == pytest.approx(16.0, rel=1e-12)


# --------------------------------------------------------------------------- #
# Dynamics
# --------------------------------------------------------------------------- #
def test_steady_aerosol_fraction_is_a_fixed_point():
    phi = float(MODEL.steady_aerosol_fraction(U_EXP1, 1.0))
    assert phi == pytest.approx(177_070e-12 / (23 / 60), rel=1e-3)
    x = X_CLEAN.copy()
    x[4] = phi
    rate = MODEL.derivative(x, U_EXP1)[4]
    # relative to φ/τ with τ = (V_v − V_l)/Q_c ≈ 5 s, the residual rate is the tiny φ² term
    assert abs(rate) < 1e-6 * phi / 5.0


def test_aerosol_level_theta_std_moves_the_steady_fraction_by_its_relative_std():
    """σ_θ = w Q_c/(V_v − V_l): by hand (V_v = 3 mL, Q_c 23 sccm), and a θ_φA of that size
    shifts the steady φ_A by ≈ w (first order)."""
    from ajtwin.model.system import aerosol_level_theta_std, steady_aerosol_fraction

    std = float(aerosol_level_theta_std(U_EXP1, 1.0, P, 0.01))
    assert std == pytest.approx(0.01 * (23 / 60) / (3.0 - 1.0), rel=1e-12)
    base = float(steady_aerosol_fraction(U_EXP1, 1.0, P))
    moved = float(steady_aerosol_fraction(U_EXP1, 1.0, P, theta_aerosol=std))
    assert moved / base - 1 == pytest.approx(0.01, rel=0.02)


def test_theta_enters_linearly():
    theta = np.array([-1e-5, 2e-6, 1e-3, 5e-4, -3e-5])
    x = np.array([3.4, 0.9, 2e-4, 0.02, 4.0e-7])
    diff = MODEL.derivative(x, U_EXP1, theta) - MODEL.derivative(x, U_EXP1)
    # dφ/dt picks up θ_Vl V_l through the φ dV_l/dt term too
    expected = theta * x
    expected[4] += x[4] * theta[1] * x[1] / (3.0 - x[1])
    np.testing.assert_allclose(diff, expected, rtol=1e-10, atol=1e-22)


def test_ink_conservation_over_a_run():
    """Ink leaving the vial = ink in the tube + nozzle deposits + on the substrate."""
    x0 = X_CLEAN.copy()
    x0[4] = float(MODEL.steady_aerosol_fraction(U_EXP1, 1.0))
    inputs = np.tile(U_EXP1, (5400, 1))
    xs = MODEL.simulate(x0, inputs)
    # with θ = 0 the vial loses exactly what the carrier takes out
    carried = np.sum(xs[:-1, 4] * units.sccm_to_ml_per_s(inputs[:, 1]))
    assert x0[1] - xs[-1, 1] == pytest.approx(carried, rel=1e-10)
    # where it went: deposits from the radius change (annulus volumes) + substrate
    flows = [np.asarray(f) for f in ink_flows(xs[:-1], inputs, P)]
    substrate = np.sum(flows[3])
    r_t, r_n = P.tube_radius, P.nozzle_radius
    dr_t, dr_n = units.um_to_m(xs[-1, 2]), units.um_to_m(xs[-1, 3])
    tube_ml = units.m3_to_ml(math.pi * (r_t**2 - (r_t - dr_t) ** 2) * P.tube_length)
    nozzle_ml = units.m3_to_ml(math.pi * (r_n**2 - (r_n - dr_n) ** 2) * P.nozzle_length)
    assert carried == pytest.approx(tube_ml + nozzle_ml + substrate, rel=1e-6)
    # and the deposits are a real, non-negligible share
    assert nozzle_ml / carried > 1e-6


def test_open_loop_exp1_states_are_physical():
    x0 = X_CLEAN.copy()
    x0[4] = float(MODEL.steady_aerosol_fraction(U_EXP1, 1.0))
    xs = MODEL.simulate(x0, np.tile(U_EXP1, (5400, 1)))
    assert np.all(np.diff(xs[:, 1]) < 0)  # vial drains
    assert np.all(np.diff(xs[:, 2]) > 0) and np.all(np.diff(xs[:, 3]) > 0)  # deposits grow
    assert 1e-4 < xs[-1, 2] < 1e-3  # tube: typical 0–1e-3 µm (model reference §3)
    assert 5e-3 < xs[-1, 3] < 0.1  # nozzle: tens of nm at most over 90 min
    assert xs[-1, 1] == pytest.approx(1.0 - 5400 * 1.77e-7, rel=1e-3)


def test_rk4_and_euler_converge_to_the_same_trajectory():
    x = X_CLEAN.copy()
    x[4] = 3e-7  # off balance: φ relaxes in ~5 s, the stiffest part of f
    euler = MODEL.simulate(x, np.tile(U_EXP1, (2000, 1)), dt=1e-3)[-1]
    rk4 = MODEL.simulate(x, np.tile(U_EXP1, (20, 1)), dt=0.1, method="rk4")[-1]
    # compare what changed over the 2 s (the states themselves barely move)
    np.testing.assert_allclose(euler - x, rk4 - x, rtol=5e-4, atol=1e-20)


# --------------------------------------------------------------------------- #
# Autodiff, jit, vmap
# --------------------------------------------------------------------------- #
def _central_difference(fun, x, rel=1e-4):
    x = np.asarray(x, dtype=float)
    # floors keep the step above round-off where an output is large (P_c ~ 5e3 Pa)
    floors = np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-11])
    cols = []
    for i in range(x.size):
        h = max(rel * abs(x[i]), floors[i])
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        cols.append((np.asarray(fun(xp)) - np.asarray(fun(xm))) / (2 * h))
    return np.stack(cols, axis=-1)


def test_jacobians_match_finite_differences():
    x = np.array([3.3, 0.95, 3e-4, 0.04, 4.4e-7])
    u = np.array([360.0, 24.0, 48.0])
    theta = np.array([-2e-5, 1e-6, 1e-4, 2e-4, 1e-5])
    # the rates, not the step: the step's identity part would hide small entries
    f = lambda xx: transition_rates(jnp.asarray(xx), u, theta, P)  # noqa: E731
    g = lambda xx: output_function(jnp.asarray(xx), u, P, MODEL.coefficient_matrix)  # noqa: E731
    for fun in (f, g):
        auto = np.asarray(jax.jacfwd(fun)(jnp.asarray(x)))
        fd = _central_difference(fun, x)
        assert np.count_nonzero(auto) >= 10  # the coupling is really exercised
        scale = np.abs(auto).max(axis=1, keepdims=True) + 1e-300
        np.testing.assert_allclose(auto / scale, fd / scale, rtol=1e-5, atol=1e-9)


def test_jit_and_vmap_equal_plain_call():
    rng = np.random.default_rng(0)
    xs = np.column_stack(
        [
            rng.uniform(2.5, 4.0, 64),
            rng.uniform(0.5, 1.5, 64),
            rng.uniform(0, 1e-3, 64),
            rng.uniform(0, 0.1, 64),
            rng.uniform(1e-7, 1e-6, 64),
        ]
    )
    us = np.column_stack(
        [rng.uniform(300, 440, 64), rng.uniform(15, 35, 64), rng.uniform(30, 70, 64)]
    )
    theta = jnp.zeros(5)
    plain = np.stack([np.asarray(transition_rates(x, u, theta, P)) for x, u in zip(xs, us)])
    jitted = np.asarray(jax.jit(transition_rates)(xs, us, theta, P))
    vmapped = np.asarray(jax.vmap(transition_rates, in_axes=(0, 0, None, None))(xs, us, theta, P))
    np.testing.assert_allclose(jitted, plain, rtol=1e-12, atol=0)
    np.testing.assert_allclose(vmapped, plain, rtol=1e-12, atol=0)
    out_plain = np.stack([MODEL.outputs(x, u) for x, u in zip(xs, us)])
    np.testing.assert_allclose(MODEL.outputs(xs, us), out_plain, rtol=1e-12)


def test_scan_matches_python_loop():
    x0 = X_CLEAN.copy()
    inputs = np.tile(U_EXP1, (50, 1))
    xs = np.asarray(simulate_open_loop(x0, inputs, jnp.zeros(5), P))
    x = x0
    for k in range(50):
        x = np.asarray(euler_step(x, inputs[k], jnp.zeros(5), P))
    np.testing.assert_allclose(xs[-1], x, rtol=1e-13)


# --------------------------------------------------------------------------- #
# Bad input
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize(
    "x, u, match",
    [
        ([3.5, 1.0, 0, 0, 4e-7], [375, -23, 50], "carrier_flow_sccm = -23"),
        ([3.5, 1.0, 0, 0, 4e-7], [375, 23, 0], "sheath_flow_sccm = 0"),
        ([3.5, 1.0, 0, 0, 4e-7], [0.375, 23, 50], "375 mA"),
        ([3.5, 0.0, 0, 0, 4e-7], [375, 23, 50], "vial_volume_mL = 0"),
        ([3.5, 3.2, 0, 0, 4e-7], [375, 23, 50], "vial_volume_mL = 3.2"),
        ([3.5, 1.0, 800.0, 0, 4e-7], [375, 23, 50], "tube_deposition_um = 800"),
        ([3.5, 1.0, 0, 75.0, 4e-7], [375, 23, 50], "nozzle_deposition_um = 75"),
        ([-1.0, 1.0, 0, 0, 4e-7], [375, 23, 50], "droplet_diameter_um = -1"),
        ([np.nan, 1.0, 0, 0, 4e-7], [375, 23, 50], "droplet_diameter_um contains NaN"),
        ([3.5, 1.0, 0, 0, 4e-7], [375, np.inf, 50], "carrier_flow_sccm contains NaN/inf"),
        ([3.5, 1.0, 0, 0], [375, 23, 50], r"shape \(5,\)"),
        ([3.5, 1.0, 0, 0, 4e-7], [375, 23], r"shape \(3,\)"),
    ],
)
def test_bad_input_raises_clear_error(x, u, match):
    with pytest.raises(ValueError, match=match):
        MODEL.outputs(np.array(x, dtype=float), np.array(u, dtype=float))


def test_bad_dt_and_method():
    with pytest.raises(ValueError, match="dt"):
        MODEL.step(X_CLEAN, U_EXP1, dt=-1)
    with pytest.raises(ValueError, match="method"):
        MODEL.step(X_CLEAN, U_EXP1, method="euler2")


def test_from_files_round_trip_and_errors(tmp_path):
    import tomllib
    from importlib import resources

    text = (resources.files("ajtwin") / "data" / "parameters.toml").read_text()
    custom = tmp_path / "params.toml"
    custom.write_text(text.replace('value = 10.0\nunit = "mm"', 'value = 20.0\nunit = "mm"'))
    m = DigitalModel.from_files(parameters=custom)
    assert m.params.nozzle_length == pytest.approx(0.02)
    assert tomllib.loads(custom.read_text())["nozzle_length"]["value"] == 20.0
    broken = tmp_path / "broken.toml"
    broken.write_text(text.replace('unit = "mm"', 'unit = "furlong"'))
    with pytest.raises(ValueError, match="unknown unit 'furlong'"):
        DigitalModel.from_files(parameters=broken)
    with pytest.raises(FileNotFoundError):
        DigitalModel.from_files(parameters=tmp_path / "nope.toml")


def test_parameter_file_has_provenance_for_everything():
    from ajtwin.model.parameters import parameter_records

    records = parameter_records()
    assert len(records) >= 25
    for r in records:
        assert r.provenance in {
            "paper",
            "corrected",
            "assumed",
            "physics",
        } or r.provenance.startswith("fitted-cfd"), r
        assert r.unit
    assert load_parameters().gas_viscosity == pytest.approx(1.76e-5)


def test_a_packaged_setting_changed_by_one_caller_does_not_reach_the_next():
    from ajtwin.config import packaged_toml

    first = packaged_toml("data/parameters.toml")
    key = next(iter(first))
    first[key] = "changed"
    assert packaged_toml("data/parameters.toml")[key] != "changed"
