"""The estimators on a 5,400-step (90-min) virtual print, after compilation, beside peers.

* :class:`Filter`: our EKF, its floor (the same filter with the model replaced by a linear
  one: what a step costs when f, g and their Jacobians are free), RTS, one EM iteration,
  the whole print's EKF + RTS + 10 EM iterations, the online twin run.
* :class:`Peers`: dynamax's ``extended_kalman_filter`` / ``extended_kalman_smoother`` and
  filterpy's ``ExtendedKalmanFilter`` on the same model (our f_d and g in the filter's
  scaled coordinates, jitted), same noise, same print: how many times faster ours is. The
  filtered (and smoothed) means must agree to 1e-8 relative, or the benchmark fails.
* :class:`Fleet`: machines filtered together: ``vmap``, ``ekf_fleet`` (one after the
  other, each scan one kernel), ``ekf_fleet_threaded`` (a block per core).

dynamax's convention differs from ours in one place: its step t → t+1 uses the input at t+1.
Ours uses u_t, so dynamax is given inputs [u_t, u_{t−1}] and its dynamics read the second
half. dynamax and filterpy are benchmark-only (``pip install -e '.[bench]'``).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

AGREEMENT = 1e-8  # relative, filtered/smoothed means against each peer
FLEET_STEPS = 60


def _best(fn, repeats=5):
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _relative(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))


def _check(name, err):
    if not err <= AGREEMENT:
        raise AssertionError(f"{name}: relative difference {err:.2e} > {AGREEMENT:g}")


class _Print:
    """The twin, its model spec and a 90-min exp1 print (seed 1), with the filter run."""

    def __init__(self):
        from ajtwin._jax import jax, jnp
        from ajtwin.estimation import DEFAULT_SCALING, ModelSpec, Twin, ekf, rts_smoother
        from ajtwin.simulation import simulate

        self.jax, self.jnp = jax, jnp
        self.record = simulate("exp1", 1)
        self.twin = Twin.default()
        model = self.twin.model
        self.spec = ModelSpec(model.params, jnp.asarray(model.coefficient_matrix), DEFAULT_SCALING)
        self.u, self.y = jnp.asarray(self.record.inputs), jnp.asarray(self.record.outputs)
        self.start = self.twin.initial_state(self.record.inputs, self.record.outputs)
        self.theta = np.zeros(5)
        self.q, self.r = self.twin.process_cov, self.twin.measurement_var
        self.scale = np.asarray(DEFAULT_SCALING.state)
        self.ekf, self.rts = ekf, rts_smoother
        self.filtered = self.run_ekf()
        self.smoothed = jax.block_until_ready(rts_smoother(self.spec, self.filtered))

    def run_ekf(self, functions=None):
        from ajtwin.estimation.filters import AJ_EULER

        result = self.ekf(
            self.spec,
            self.start.mean,
            self.start.covariance,
            self.u,
            self.y,
            self.theta,
            self.q,
            self.r,
            functions=functions or AJ_EULER,
        )
        return self.jax.block_until_ready(result)


class Filter:
    """Our EKF, RTS and EM on the whole print."""

    timeout = 600

    def setup(self):
        from ajtwin.estimation.em import EMSettings, e_step, m_step, run_em
        from ajtwin.estimation.filters import ModelFunctions

        p = self.p = _Print()
        jnp, s = p.jnp, p.scale
        a_lin = jnp.asarray(np.eye(5) * 0.999 + 1e-4)
        c_lin = jnp.asarray(np.diag(1.0 / np.asarray(p.spec.scaling.output)))
        self.linear = ModelFunctions(
            lambda x, uk, th, params, dt: (a_lin @ (x / s)) * s + th * x + 0.0 * uk[0],
            lambda x, uk, params, coefficients: c_lin @ (x / s) + 0.0 * uk[0],
        )
        p.run_ekf(self.linear)
        prec = jnp.asarray(p.twin.theta_prior_precision)
        win = 600
        args = (p.spec, p.start.mean, p.start.covariance, p.u[:win], p.y[:win], p.theta, p.q)
        args += (p.r, np.inf)

        def em_iteration():
            _, smoothed, _ = e_step(*args)
            p.jax.block_until_ready(m_step(p.spec, smoothed, p.u[:win], p.q, prec))

        def whole():
            em = run_em(
                p.spec,
                p.start.mean,
                p.start.covariance,
                p.u,
                p.y,
                p.theta,
                p.q,
                p.r,
                settings=EMSettings(prec, 10, 0.0),
            )
            assert em.iterations == 10
            return em

        self.em_iteration, self.whole = em_iteration, whole
        em_iteration()
        whole()
        p.twin.run(p.record)

    def time_ekf_5400_steps(self):
        self.p.run_ekf()

    def time_ekf_floor_model_free_5400_steps(self):
        """The same filter with f, g and their Jacobians free (linear maps)."""
        self.p.run_ekf(self.linear)

    def time_rts_5400_steps(self):
        self.p.jax.block_until_ready(self.p.rts(self.p.spec, self.p.filtered))

    def time_em_iteration_600s_window(self):
        self.em_iteration()

    def time_whole_print_ekf_rts_10_em_iterations(self):
        self.whole()

    def time_twin_run_online_em(self):
        """``Twin.run``: EM over a 600-s window every 300 s, the whole print."""
        self.p.twin.run(self.p.record)

    def track_ekf_steps_per_s(self):
        return len(self.p.u) / _best(self.p.run_ekf, 7)

    track_ekf_steps_per_s.unit = "steps/s"


class Peers:
    """How many times faster our filter (and filter + smoother) is than dynamax's and
    filterpy's on the same model and print; their means checked against ours."""

    timeout = 900
    FILTERPY_STEPS = 500  # filterpy is slow: the first 500 steps

    def setup_cache(self):
        p = _Print()
        jax, jnp, s = p.jax, p.jnp, p.scale
        from ajtwin.estimation.filters import AJ_EULER, _scaled_functions

        t_ekf = _best(p.run_ekf, 7)
        t_rts = _best(lambda: jax.block_until_ready(p.rts(p.spec, p.filtered)), 7)
        f_s, g_s = _scaled_functions(p.spec, AJ_EULER)
        output_scale = np.asarray(p.spec.scaling.output)
        z0 = jnp.asarray(p.start.mean) / s
        p0 = jnp.asarray(p.start.covariance) / np.outer(s, s)
        q_s = jnp.asarray(p.q) / np.outer(s, s)
        r_s = jnp.diag(jnp.asarray(p.r) / output_scale**2)
        eta = p.y / output_scale
        theta_j = jnp.zeros(5)
        figures = {}

        from dynamax.nonlinear_gaussian_ssm import (
            ParamsNLGSSM,
            extended_kalman_filter,
            extended_kalman_smoother,
        )

        shifted = jnp.concatenate([p.u, jnp.concatenate([p.u[:1], p.u[:-1]])], axis=1)
        # dynamax's smoother solves with P_{t+1|t} + 1e-9 I (psd_solve's diagonal boost); in
        # our scaled coordinates some predicted variances are ~1e-8, so the boost would bias
        # its gains. It runs on w = z / c instead, c putting every predicted variance ≥ 1e8.
        predicted = np.diagonal(p.filtered.predicted_covariances, 0, 1, 2)
        c = jnp.asarray(1e-4 * np.sqrt(np.min(predicted, 0)) / s)
        params = ParamsNLGSSM(
            initial_mean=z0 / c,
            initial_covariance=p0 / jnp.outer(c, c),
            dynamics_function=lambda w, inp: f_s(w * c, inp[3:], theta_j) / c,
            dynamics_covariance=q_s / jnp.outer(c, c),
            emission_function=lambda w, inp: g_s(w * c, inp[:3]),
            emission_covariance=r_s,
        )
        dx_filter = jax.jit(
            lambda e, i: extended_kalman_filter(params, e, inputs=i).filtered_means * c
        )
        dx_smoother = jax.jit(
            lambda e, i: extended_kalman_smoother(params, e, inputs=i).smoothed_means * c
        )
        means = jax.block_until_ready(dx_filter(eta, shifted))
        _check("dynamax filtered means", _relative(np.asarray(p.filtered.means) / s, means))
        smoothed = jax.block_until_ready(dx_smoother(eta, shifted))
        _check("dynamax smoothed means", _relative(np.asarray(p.smoothed.means) / s, smoothed))
        t_dx = _best(lambda: jax.block_until_ready(dx_filter(eta, shifted)), 7)
        t_dx_smooth = _best(lambda: jax.block_until_ready(dx_smoother(eta, shifted)), 5)
        figures["dynamax_filter"] = t_dx / t_ekf
        figures["dynamax_smoother"] = t_dx_smooth / (t_ekf + t_rts)

        from filterpy.kalman import ExtendedKalmanFilter

        f_j = jax.jit(lambda z, uk: f_s(z, uk, theta_j))
        jf_j = jax.jit(jax.jacfwd(lambda z, uk: f_s(z, uk, theta_j)))
        g_j = jax.jit(g_s)
        jg_j = jax.jit(jax.jacfwd(g_s))
        u_np, eta_np = np.asarray(p.u), np.asarray(eta)

        def run_filterpy():
            kf = ExtendedKalmanFilter(5, 5)
            kf.x, kf.P = np.asarray(z0).copy(), np.asarray(p0).copy()
            kf.Q, kf.R = np.asarray(q_s), np.asarray(r_s)
            out = []
            for k in range(self.FILTERPY_STEPS):
                kf.update(
                    eta_np[k],
                    lambda z, uk: np.asarray(jg_j(z, uk)),
                    lambda z, uk: np.asarray(g_j(z, uk)),
                    args=(u_np[k],),
                    hx_args=(u_np[k],),
                )
                out.append(kf.x.copy())
                fk = np.asarray(jf_j(kf.x, u_np[k]))
                kf.x = np.asarray(f_j(kf.x, u_np[k]))
                kf.P = fk @ kf.P @ fk.T + kf.Q
            return np.array(out)

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fp_means = run_filterpy()
            t_fp = _best(run_filterpy, 2) / self.FILTERPY_STEPS
        ours = np.asarray(p.filtered.means)[: self.FILTERPY_STEPS] / s
        _check("filterpy filtered means", _relative(ours, fp_means))
        figures["filterpy_filter"] = t_fp / (t_ekf / len(p.u))
        return figures

    def track_ekf_speed_vs_dynamax(self, figures):
        return figures["dynamax_filter"]

    def track_ekf_rts_speed_vs_dynamax_smoother(self, figures):
        return figures["dynamax_smoother"]

    def track_ekf_speed_vs_filterpy(self, figures):
        return figures["filterpy_filter"]

    for _method in (
        track_ekf_speed_vs_dynamax,
        track_ekf_rts_speed_vs_dynamax_smoother,
        track_ekf_speed_vs_filterpy,
    ):
        _method.unit = "x faster"
    del _method


class Fleet:
    """1,000 and 10,000 machines × 60 steps: vmap, ``ekf_fleet``, ``ekf_fleet_threaded``."""

    params = [1000, 10000]
    param_names = ["machines"]
    timeout = 600

    def setup(self, machines):
        from ajtwin.estimation import ekf, ekf_fleet, ekf_fleet_threaded

        p = _Print()
        jax = p.jax
        rng = np.random.default_rng(0)
        means0 = np.tile(p.start.mean, (machines, 1))
        means0[:, 0] += rng.normal(0, 0.1, machines)
        covs0 = np.tile(p.start.covariance, (machines, 1, 1))
        us = np.tile(np.asarray(p.u[:FLEET_STEPS]), (machines, 1, 1))
        noise = rng.normal(0, 0.5, (machines, FLEET_STEPS, 5)) * [1, 1, 1, 1, 0]
        ys = np.tile(np.asarray(p.y[:FLEET_STEPS]), (machines, 1, 1)) + noise
        fleet, thetas = (means0, covs0, us, ys), np.zeros((machines, 5))
        theta, q, r, spec = p.theta, p.q, p.r, p.spec
        batched = jax.jit(
            jax.vmap(lambda m0, p0_, uu, yy: ekf(spec, m0, p0_, uu, yy, theta, q, r).means[-1])
        )
        self.vmap = lambda: jax.block_until_ready(batched(*fleet))
        self.fleet = lambda: jax.block_until_ready(
            ekf_fleet(spec, *fleet, thetas, q, r).means[:, -1]
        )
        self.threaded = lambda: ekf_fleet_threaded(spec, *fleet, thetas, q, r).means[:, -1]
        if machines == 1000:
            _check("ekf_fleet vs vmap", _relative(self.fleet(), self.vmap()))
            assert np.array_equal(self.threaded(), np.asarray(self.fleet()))
        for run in (self.vmap, self.fleet, self.threaded):
            run()

    def time_vmap(self, machines):
        self.vmap()

    def time_ekf_fleet(self, machines):
        self.fleet()

    def time_ekf_fleet_threaded(self, machines):
        self.threaded()

    def track_ekf_fleet_threaded_machine_steps_per_s(self, machines):
        return machines * FLEET_STEPS / _best(self.threaded, 3)

    track_ekf_fleet_threaded_machine_steps_per_s.unit = "machine-steps/s"
