"""The fast model against a 64-node, fully converged reference.

The transition f uses an 8-node Gauss–Hermite rule for the droplet integrals
and 3 Newton steps for the critical radius x_c. These tests prove, over the
whole operating box of model reference §3 (states and inputs, corners included), that
this changes f and its Jacobian by ≤ 1e-6 relative against the same physics
at 64 nodes and 12 Newton steps, and that x_c matches the root of the quartic
found independently by NumPy's companion-matrix solver. The droplet integrals'
closed-form derivatives (their custom JVP rules) equal JAX's automatic ones. g has no quadrature
or iteration (a polynomial and the resistance network): it is compared with
the model before the speed work through the values pinned in test_model.py.
"""

import itertools

import numpy as np
import pytest

from ajtwin import units
from ajtwin._jax import jax, jnp
from ajtwin.model import load_parameters, transition_rates, transport
from ajtwin.model.droplets import (
    QUADRATURE_ORDER,
    cunningham_slip_correction,
    lognormal_quadrature,
    slip_log_slope,
)
from ajtwin.model.transport import CRITICAL_RADIUS_NEWTON_STEPS, critical_radius

PARAMS = load_parameters()
# 12 Newton steps: converged to rounding from any start in (0, 1] (the quartic test below)
REFERENCE = {"quadrature_order": 64, "newton_steps": 12}

# model reference §3 typical ranges; flows: the span of every scenario (15–35, 30–80 sccm) widened
STATE_BOX = [(2.5, 4.0), (0.5, 1.5), (0.0, 1e-3), (0.0, 0.1), (1e-7, 1e-6)]
INPUT_BOX = [(300.0, 440.0), (10.0, 50.0), (20.0, 120.0)]


def _box_points(n_random, state_box=STATE_BOX, input_box=INPUT_BOX, seed=0):
    """All 2⁸ corners of the (x, u) box plus uniform random points inside it."""
    box = np.array(state_box + input_box)
    corners = np.array(list(itertools.product(*box)))
    rng = np.random.default_rng(seed)
    inside = box[:, 0] + rng.random((n_random, len(box))) * (box[:, 1] - box[:, 0])
    points = np.concatenate([corners, inside])
    return jnp.asarray(points[:, :5]), jnp.asarray(points[:, 5:])


def _relative_error(fast, reference):
    fast, reference = np.asarray(fast), np.asarray(reference)
    scale = np.abs(reference)
    # exact zeros (θ = 0 rows) must be exactly zero in both
    return np.where(scale > 0, np.abs(fast - reference) / np.where(scale > 0, scale, 1.0), fast)


def _rates(resolution):
    return jax.jit(lambda x, u, th: transition_rates(x, u, th, PARAMS, **resolution))


def test_defaults_are_the_fast_ones():
    assert QUADRATURE_ORDER == 8
    assert CRITICAL_RADIUS_NEWTON_STEPS == 3
    _, w = lognormal_quadrature(3.0, 0.25)
    assert w.shape == (QUADRATURE_ORDER,)
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-14)


@pytest.mark.parametrize("with_theta", [False, True])
def test_transition_matches_64_node_reference_over_operating_box(with_theta):
    x, u = _box_points(2000)
    rng = np.random.default_rng(1)
    theta = jnp.asarray(rng.normal(0, 1e-4, (len(x), 5))) if with_theta else jnp.zeros(5)
    fast = _rates({})(x, u, theta)
    reference = _rates(REFERENCE)(x, u, theta)
    err = _relative_error(fast, reference)
    assert np.all(np.isfinite(np.asarray(fast)))
    worst = err.max(axis=0)
    assert np.all(worst <= 1e-6), f"worst relative error per component: {worst}"
    if not with_theta:  # (with θ, θ ⊙ x may nearly cancel the deposit rate)
        # the deposit rates (the integrals) are in fact far tighter than required
        assert worst[2] < 1e-10 and worst[3] < 1e-10, worst


def test_transition_jacobian_matches_reference_over_operating_box():
    x, u = _box_points(300, seed=2)
    theta = jnp.zeros(5)

    def jacobian(resolution):
        jac = jax.jacfwd(lambda xx, uu: transition_rates(xx, uu, theta, PARAMS, **resolution))
        return jax.jit(jax.vmap(jac))(x, u)

    fast, reference = np.asarray(jacobian({})), np.asarray(jacobian(REFERENCE))
    # relative to each row's largest entry: a row's tiny entries are rounding-level terms
    row_scale = np.abs(reference).max(axis=-1, keepdims=True)
    err = np.abs(fast - reference) / np.where(row_scale > 0, row_scale, 1.0)
    assert err.max() <= 1e-6, err.max(axis=0)


def test_transition_wide_box_still_close():
    """Beyond the operating box (d_a 0.5–15 µm, wide flows) the error stays ≤ 1e-8."""
    state_box = [(0.5, 15.0), (0.5, 1.5), (0.0, 1e-2), (0.0, 1.0), (1e-8, 1e-5)]
    input_box = [(100.0, 900.0), (5.0, 100.0), (5.0, 200.0)]
    x, u = _box_points(2000, state_box, input_box, seed=3)
    theta = jnp.zeros(5)
    err = _relative_error(_rates({})(x, u, theta), _rates(REFERENCE)(x, u, theta))
    assert err.max() <= 1e-8, err.max(axis=0)


def test_critical_radius_matches_quartic_root():
    # (1 − x)²(1 − x²) = μ  ⇔  ε⁴ − 2ε³ + μ = 0 with ε = 1 − x; the root in [0, 1]
    mus = np.logspace(-12, -0.01, 400)
    fast = np.asarray(critical_radius(jnp.asarray(mus)))
    for mu, x_fast in zip(mus, fast):
        roots = np.roots([1.0, -2.0, 0.0, 0.0, mu])
        real = roots[np.abs(roots.imag) < 1e-9].real
        eps = real[(real >= -1e-12) & (real <= 1 + 1e-12)].min()
        # compare ε = 1 − x (the small quantity that carries the loss), not x
        assert (1.0 - x_fast) == pytest.approx(eps, rel=1e-9), mu
    assert float(critical_radius(2.0)) == 0.0  # μ ≥ 1: no survivors


def _integral_arguments():
    """(d_a, R, Q_c, Q_c + Q_s) in SI over the operating box (corners and inside)."""
    x, u = _box_points(300, seed=4)
    d_a = units.um_to_m(x[:, 0])
    radius = PARAMS.tube_radius - units.um_to_m(x[:, 2])
    carrier = units.sccm_to_m3_per_s(u[:, 1])
    total = units.sccm_to_m3_per_s(u[:, 1] + u[:, 2])
    return d_a, radius, carrier, total


@pytest.mark.parametrize("which", ["settled", "diffused"])
def test_droplet_integrals_closed_form_derivatives_equal_automatic_ones(which):
    """The custom JVP rules (closed forms, implicit x_c) against JAX differentiating the
    plain integrals operation by operation — through the arcsine, the cube roots and
    the three Newton steps — in every argument the state and the inputs reach."""
    d_a, radius, carrier, total = _integral_arguments()
    if which == "settled":
        args = (d_a, radius, carrier)
        fast = lambda *a: transport.settled_fraction(QUADRATURE_ORDER, *a, PARAMS)  # noqa: E731
        plain = lambda *a: transport._settling_terms(QUADRATURE_ORDER, *a, PARAMS)[0]  # noqa: E731
    else:
        args = (d_a, total)
        fast = lambda *a: transport.diffused_fraction(  # noqa: E731
            QUADRATURE_ORDER, CRITICAL_RADIUS_NEWTON_STEPS, *a, PARAMS
        )
        plain = lambda *a: transport._diffusion_terms(  # noqa: E731
            QUADRATURE_ORDER, CRITICAL_RADIUS_NEWTON_STEPS, *a, PARAMS
        )[0]
    for i in range(len(args)):
        tangents = tuple(a * (1e-3 if j == i else 0.0) for j, a in enumerate(args))
        value, tangent = jax.jvp(fast, args, tangents)
        value_ref, tangent_ref = jax.jvp(plain, args, tangents)
        np.testing.assert_allclose(value, value_ref, rtol=1e-12, atol=0)
        np.testing.assert_allclose(tangent, tangent_ref, rtol=1e-10, atol=0)
    # a 1 % step in d_a: the derivative predicts the change to second order
    step = 1e-4 * d_a
    central = (fast(d_a + step, *args[1:]) - fast(d_a - step, *args[1:])) / (2 * step)
    _, slope = jax.jvp(
        fast, args, (jnp.ones_like(d_a),) + tuple(jnp.zeros_like(a) for a in args[1:])
    )
    np.testing.assert_allclose(slope, central, rtol=1e-6)


def test_droplet_integrals_reverse_mode_and_parameter_derivatives():
    """Reverse mode transposes the rules; derivatives in the parameters take the
    automatic path and equal the plain integrals'."""
    x = jnp.asarray([3.2, 1.0, 4e-4, 0.03, 3e-7])
    u = jnp.asarray([380.0, 25.0, 60.0])
    theta = jnp.zeros(5)
    forward = jax.jacfwd(lambda xx: transition_rates(xx, u, theta, PARAMS))(x)
    reverse = jax.jacrev(lambda xx: transition_rates(xx, u, theta, PARAMS))(x)
    np.testing.assert_allclose(reverse, forward, rtol=1e-12, atol=1e-300)

    params = jax.tree.map(lambda v: jnp.asarray(v, dtype=float), PARAMS)
    d_a, radius, carrier, total = (a[0] for a in _integral_arguments())

    def through(fn):
        return jax.grad(lambda p: fn(p))(params)

    for fast, plain in [
        (
            lambda p: transport.settled_fraction(QUADRATURE_ORDER, d_a, radius, carrier, p),
            lambda p: transport._settling_terms(QUADRATURE_ORDER, d_a, radius, carrier, p)[0],
        ),
        (
            lambda p: transport.diffused_fraction(
                QUADRATURE_ORDER, CRITICAL_RADIUS_NEWTON_STEPS, d_a, total, p
            ),
            lambda p: transport._diffusion_terms(
                QUADRATURE_ORDER, CRITICAL_RADIUS_NEWTON_STEPS, d_a, total, p
            )[0],
        ),
    ]:
        for got, want in zip(jax.tree.leaves(through(fast)), jax.tree.leaves(through(plain))):
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    assert float(jnp.abs(through(fast).droplet_cv)) > 0  # a parameter the integral reads


def test_slip_log_slope_is_the_derivative_of_log_slip():
    diameters = jnp.logspace(-8, -4, 50)  # 10 nm … 100 µm
    lam = PARAMS.mean_free_path
    auto = jax.vmap(
        jax.grad(lambda log_d: jnp.log(cunningham_slip_correction(jnp.exp(log_d), lam)))
    )(jnp.log(diameters))
    np.testing.assert_allclose(slip_log_slope(diameters, lam), auto, rtol=1e-12, atol=1e-15)
