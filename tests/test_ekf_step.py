"""ekf_step: the one EKF step that the batch filter scans and a streaming engine calls."""

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.estimation import (
    DEFAULT_SCALING,
    ModelSpec,
    Twin,
    ekf,
    ekf_fleet,
    ekf_fleet_threaded,
    ekf_init,
    ekf_step,
)
from ajtwin.estimation.filters import _is_valid_covariance
from ajtwin.model import DigitalModel
from ajtwin.simulation import simulate

MODEL = DigitalModel.default()
SPEC = ModelSpec(MODEL.params, jnp.asarray(MODEL.coefficient_matrix), DEFAULT_SCALING)
TWIN = Twin.default()


def test_step_by_step_equals_batch_filter():
    record = simulate("exp1", 3)
    u, y = record.inputs[:120].copy(), record.outputs[:120].copy()
    y[5, :] = np.nan  # a dropped sample
    y[17, 2] = np.nan  # one missing output
    start = TWIN.initial_state(u, y)
    theta = np.array([1e-6, 0.0, 0.0, 1e-5, 0.0])
    q, r = jnp.asarray(TWIN.process_cov), jnp.asarray(TWIN.measurement_var)
    batch = ekf(SPEC, start.mean, start.covariance, u, y, theta, q, r, 4.0)

    step = jax.jit(ekf_step)
    carry = ekf_init(SPEC, start.mean, start.covariance)
    rows = []
    for k in range(len(u)):
        carry, out = step(SPEC, carry, u[k], y[k], jnp.asarray(theta), q, r, 4.0)
        rows.append(out)
    for name, column in zip(batch._fields, batch):
        streamed = np.stack([np.asarray(getattr(o, f)) for o in rows for f in [_FIELD[name]]])
        np.testing.assert_allclose(streamed, np.asarray(column), rtol=1e-12, atol=0, err_msg=name)
    assert int(np.asarray(batch.n_measured)[5]) == 0
    assert int(np.asarray(batch.n_measured)[17]) == 4


def test_fleet_equals_one_filter_per_machine():
    """ekf_fleet (machines one after the other inside one compiled map) = ekf per machine."""
    record = simulate("exp1", 2)
    u, y = record.inputs[:50], record.outputs[:50].copy()
    start = TWIN.initial_state(u, y)
    rng = np.random.default_rng(1)
    machines = 3
    means = np.tile(start.mean, (machines, 1))
    means[:, 0] += rng.normal(0, 0.1, machines)
    covs = np.tile(start.covariance, (machines, 1, 1)) * rng.uniform(0.5, 2.0, (machines, 1, 1))
    us = np.tile(u, (machines, 1, 1)) * rng.uniform(0.95, 1.05, (machines, 1, 3))
    ys = np.tile(y, (machines, 1, 1)) + rng.normal(0, 0.3, (machines, len(u), 5)) * [1, 1, 1, 1, 0]
    ys[1, 10:13, :] = np.nan
    thetas = np.zeros((machines, 5))
    thetas[2, 0] = 1e-6
    q, r = jnp.asarray(TWIN.process_cov), jnp.asarray(TWIN.measurement_var)
    fleet = ekf_fleet(SPEC, means, covs, us, ys, thetas, q, r, 4.0)
    for m in range(machines):
        one = ekf(SPEC, means[m], covs[m], us[m], ys[m], thetas[m], q, r, 4.0)
        for name, column in zip(one._fields, one):
            np.testing.assert_allclose(
                np.asarray(getattr(fleet, name))[m],
                np.asarray(column),
                rtol=1e-12,
                atol=0,
                err_msg=f"{name}, machine {m}",
            )
    assert int(np.asarray(fleet.n_measured)[1, 11]) == 0
    # the same fleet split over threads (blocks of 2 and 1 machines): the same bits
    threaded = ekf_fleet_threaded(SPEC, means, covs, us, ys, thetas, q, r, 4.0, workers=2)
    for name, column in zip(fleet._fields, fleet):
        np.testing.assert_array_equal(np.asarray(getattr(threaded, name)), np.asarray(column))


_FIELD = {
    "means": "mean",
    "covariances": "covariance",
    "predicted_means": "predicted_mean",
    "predicted_covariances": "predicted_covariance",
    "transition_jacobians": "transition_jacobian",
    "predicted_outputs": "predicted_output",
    "innovation_variances": "innovation_variance",
    "log_likelihood": "log_likelihood",
    "nis": "nis",
    "n_measured": "n_measured",
    "reinitialised": "reinitialised",
}


def test_validity_check_matches_eigenvalue_definition():
    """The Cholesky test accepts exactly eig_min > −1e-9 · max|diag| (and diag > 0)."""
    rng = np.random.default_rng(0)
    for _ in range(300):
        a = rng.normal(size=(5, 5))
        p = a @ a.T
        eig, vec = np.linalg.eigh(p)
        # move the smallest eigenvalue across the threshold, either side by 10 %
        scale = np.max(np.abs(np.diag(p)))
        target = rng.choice([-1.1e-9, -0.9e-9, -1e-6, 1e-12]) * scale
        eig[0] = target
        p = (vec * eig) @ vec.T
        eig_min = np.linalg.eigvalsh(0.5 * (p + p.T)).min()
        expected = eig_min > -1e-9 * np.max(np.abs(np.diag(p))) and np.all(np.diag(p) > 0)
        assert bool(_is_valid_covariance(jnp.asarray(p))) == expected, (target / scale, eig_min)
    assert not bool(_is_valid_covariance(jnp.full((5, 5), jnp.nan)))
    assert not bool(_is_valid_covariance(-jnp.eye(5)))
