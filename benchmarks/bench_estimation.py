"""Speed of the estimators on a 5,400-step (90 min) virtual print, beside their peers.

Figures (wall time, best of several runs, after compilation):

* our EKF (steps/s) and the floor: the same filter with the model replaced by
  a linear one (what a step costs when f, g and their Jacobians are free);
* dynamax's ``extended_kalman_filter`` / ``extended_kalman_smoother`` and
  filterpy's ``ExtendedKalmanFilter`` on the same model (our f_d and g in the
  filter's scaled coordinates, jitted), same noise, same print; the filtered
  (and smoothed) means must agree to 1e-8 relative or the bench fails;
* RTS, one EM iteration, whole-print EKF + RTS + 10 EM iterations, the online
  twin run, and a vmap fleet of machines filtered together.

dynamax's convention differs from ours in one place: its step t → t+1 uses the
input at t+1. Ours uses u_t, so dynamax is given inputs [u_t, u_{t−1}] and its
dynamics read the second half. dynamax and filterpy are bench-only.
"""

import os
import time
import warnings

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.estimation import (
    DEFAULT_SCALING,
    ModelSpec,
    Twin,
    ekf,
    ekf_fleet,
    ekf_fleet_threaded,
    rts_smoother,
)
from ajtwin.estimation.em import e_step, m_step, run_em
from ajtwin.estimation.filters import AJ_EULER, ModelFunctions, _scaled_functions
from ajtwin.simulation import simulate

AGREEMENT = 1e-8  # relative, filtered/smoothed means against each peer


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
    return float(f"{err:.2e}")


def main() -> dict:
    record = simulate("exp1", 1)
    twin = Twin.default()
    spec = ModelSpec(twin.model.params, jnp.asarray(twin.model.coefficient_matrix), DEFAULT_SCALING)
    u, y = jnp.asarray(record.inputs), jnp.asarray(record.outputs)
    start = twin.initial_state(record.inputs, record.outputs)
    theta = np.zeros(5)
    q, r = twin.process_cov, twin.measurement_var
    n = len(u)
    s = np.asarray(DEFAULT_SCALING.state)
    out = {"print_steps": n, "load_average_1min": round(os.getloadavg()[0], 2)}

    # ---- our EKF, RTS, and the floor --------------------------------------------------
    def run_ekf(functions=AJ_EULER):
        result = ekf(spec, start.mean, start.covariance, u, y, theta, q, r, functions=functions)
        return jax.block_until_ready(result)

    filt = run_ekf()
    t_ekf = _best(run_ekf, 7)
    smooth = jax.block_until_ready(rts_smoother(spec, filt))
    t_rts = _best(lambda: jax.block_until_ready(rts_smoother(spec, filt)), 7)
    a_lin = jnp.asarray(np.eye(5) * 0.999 + 1e-4)
    c_lin = jnp.asarray(np.diag(1.0 / np.asarray(DEFAULT_SCALING.output)))
    linear = ModelFunctions(
        lambda x, uk, th, params, dt: (a_lin @ (x / s)) * s + th * x + 0.0 * uk[0],
        lambda x, uk, params, coefficients: c_lin @ (x / s) + 0.0 * uk[0],
    )
    run_ekf(linear)
    t_floor = _best(lambda: run_ekf(linear), 7)
    out.update(
        ekf_steps_per_s=round(n / t_ekf),
        ekf_step_us=round(t_ekf / n * 1e6, 2),
        ekf_whole_print_ms=round(t_ekf * 1e3, 1),
        ekf_floor_step_us_model_free=round(t_floor / n * 1e6, 2),
        rts_whole_print_ms=round(t_rts * 1e3, 1),
        ekf_plus_rts_whole_print_ms=round((t_ekf + t_rts) * 1e3, 1),
    )

    # ---- the same model for the peers: scaled coordinates, jitted ----------------------
    f_s, g_s = _scaled_functions(spec, AJ_EULER)
    z0 = jnp.asarray(start.mean) / s
    p0 = jnp.asarray(start.covariance) / np.outer(s, s)
    q_s = jnp.asarray(q) / np.outer(s, s)
    r_s = jnp.diag(jnp.asarray(r) / np.asarray(DEFAULT_SCALING.output) ** 2)
    eta = y / np.asarray(DEFAULT_SCALING.output)
    theta_j = jnp.zeros(5)

    # ---- dynamax -------------------------------------------------------------------------
    from dynamax.nonlinear_gaussian_ssm import (
        ParamsNLGSSM,
        extended_kalman_filter,
        extended_kalman_smoother,
    )

    shifted = jnp.concatenate([u, jnp.concatenate([u[:1], u[:-1]])], axis=1)  # [u_t, u_{t−1}]
    # dynamax's smoother solves with P_{t+1|t} + 1e-9 I (psd_solve's diagonal boost); in our
    # scaled coordinates some predicted variances are ~1e-8, so the boost would bias its
    # gains. It runs on w = z / c instead, with c putting every predicted variance ≥ 1e8.
    c = jnp.asarray(1e-4 * np.sqrt(np.min(np.diagonal(filt.predicted_covariances, 0, 1, 2), 0)) / s)
    params_dx = ParamsNLGSSM(
        initial_mean=z0 / c,
        initial_covariance=p0 / jnp.outer(c, c),
        dynamics_function=lambda w, inp: f_s(w * c, inp[3:], theta_j) / c,
        dynamics_covariance=q_s / jnp.outer(c, c),
        emission_function=lambda w, inp: g_s(w * c, inp[:3]),
        emission_covariance=r_s,
    )
    dx_filter = jax.jit(
        lambda e, i: extended_kalman_filter(params_dx, e, inputs=i).filtered_means * c
    )
    dx_smoother = jax.jit(
        lambda e, i: extended_kalman_smoother(params_dx, e, inputs=i).smoothed_means * c
    )
    dx_means = jax.block_until_ready(dx_filter(eta, shifted))
    t_dx = _best(lambda: jax.block_until_ready(dx_filter(eta, shifted)), 7)
    dx_smoothed = jax.block_until_ready(dx_smoother(eta, shifted))
    t_dx_smooth = _best(lambda: jax.block_until_ready(dx_smoother(eta, shifted)), 5)
    out.update(
        dynamax_ekf_steps_per_s=round(n / t_dx),
        ekf_speed_vs_dynamax=round(t_dx / t_ekf, 2),
        dynamax_filtered_means_max_rel_diff=_check(
            "dynamax filtered means", _relative(np.asarray(filt.means) / s, dx_means)
        ),
        dynamax_ekf_plus_smoother_ms=round(t_dx_smooth * 1e3, 1),
        ekf_plus_rts_speed_vs_dynamax_smoother=round(t_dx_smooth / (t_ekf + t_rts), 2),
        dynamax_smoothed_means_max_rel_diff=_check(
            "dynamax smoothed means", _relative(np.asarray(smooth.means) / s, dx_smoothed)
        ),
    )

    # ---- filterpy (first 500 steps: it is slow) --------------------------------------------
    from filterpy.kalman import ExtendedKalmanFilter

    f_j = jax.jit(lambda z, uk: f_s(z, uk, theta_j))
    jf_j = jax.jit(jax.jacfwd(lambda z, uk: f_s(z, uk, theta_j)))
    g_j = jax.jit(g_s)
    jg_j = jax.jit(jax.jacfwd(g_s))
    m_fp = 500
    u_np, eta_np = np.asarray(u), np.asarray(eta)

    def run_filterpy():
        kf = ExtendedKalmanFilter(5, 5)
        kf.x, kf.P = np.asarray(z0).copy(), np.asarray(p0).copy()
        kf.Q, kf.R = np.asarray(q_s), np.asarray(r_s)
        means = []
        for k in range(m_fp):
            kf.update(
                eta_np[k],
                lambda z, uk: np.asarray(jg_j(z, uk)),
                lambda z, uk: np.asarray(g_j(z, uk)),
                args=(u_np[k],),
                hx_args=(u_np[k],),
            )
            means.append(kf.x.copy())
            fk = np.asarray(jf_j(kf.x, u_np[k]))
            kf.x = np.asarray(f_j(kf.x, u_np[k]))
            kf.P = fk @ kf.P @ fk.T + kf.Q
        return np.array(means)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fp_means = run_filterpy()
        t_fp = _best(run_filterpy, 2) / m_fp
    out.update(
        filterpy_ekf_steps_per_s=round(1 / t_fp),
        ekf_speed_vs_filterpy=round(t_fp / (t_ekf / n), 1),
        filterpy_filtered_means_max_rel_diff=_check(
            "filterpy filtered means", _relative(np.asarray(filt.means)[:m_fp] / s, fp_means)
        ),
    )

    # ---- EM --------------------------------------------------------------------------------
    prec = jnp.asarray(twin.theta_prior_precision)
    win = 600
    args_w = (spec, start.mean, start.covariance, u[:win], y[:win], theta, q, r, np.inf)
    _, sm_w, _ = e_step(*args_w)
    jax.block_until_ready(m_step(spec, sm_w, u[:win], q, prec))

    def em_iter_window():
        _, s_, _ = e_step(*args_w)
        jax.block_until_ready(m_step(spec, s_, u[:win], q, prec))

    t_em_window = _best(em_iter_window)

    def whole():
        em = run_em(
            spec,
            start.mean,
            start.covariance,
            u,
            y,
            theta,
            q,
            r,
            theta_prior_precision=prec,
            max_iterations=10,
            tolerance=0.0,
        )
        assert em.iterations == 10
        return em

    whole()
    t_whole = _best(whole, 3)

    twin.run(record)  # online EM, 600 s window every 300 s
    t_twin = _best(lambda: twin.run(record), 2)
    out.update(
        em_iteration_600s_window_ms=round(t_em_window * 1e3, 1),
        whole_print_ekf_rts_plus_10_em_iterations_s=round(t_whole, 3),
        twin_run_online_em_whole_print_s=round(t_twin, 2),
    )

    # ---- fleets: machines filtered together with vmap (60 steps each) ---------------------
    steps = 60
    rng = np.random.default_rng(0)
    batched = jax.jit(
        jax.vmap(lambda m0, p0_, uu, yy: ekf(spec, m0, p0_, uu, yy, theta, q, r).means[-1])
    )
    for machines in (1000, 10000):
        means0 = np.tile(start.mean, (machines, 1))
        means0[:, 0] += rng.normal(0, 0.1, machines)
        covs0 = np.tile(start.covariance, (machines, 1, 1))
        us = np.tile(np.asarray(u[:steps]), (machines, 1, 1))
        noise = rng.normal(0, 0.5, (machines, steps, 5)) * [1, 1, 1, 1, 0]
        ys = np.tile(np.asarray(y[:steps]), (machines, 1, 1)) + noise
        fleet = (means0, covs0, us, ys)
        jax.block_until_ready(batched(*fleet))
        t_batch = _best(lambda fleet=fleet: jax.block_until_ready(batched(*fleet)), 3)
        out[f"vmap_{machines}_machines_machine_steps_per_s"] = round(machines * steps / t_batch)
        # ekf_fleet: the machines one after the other, each scan one XLA kernel
        thetas = np.zeros((machines, 5))

        def run_fleet(fleet=fleet, thetas=thetas):
            return jax.block_until_ready(ekf_fleet(spec, *fleet, thetas, q, r).means[:, -1])

        if machines == 1000:
            out["ekf_fleet_vs_vmap_max_rel_diff"] = _check(
                "ekf_fleet vs vmap", _relative(run_fleet(), batched(*fleet))
            )
        run_fleet()
        t_fleet = _best(run_fleet, 3)
        key = f"ekf_fleet_{machines}_machines_machine_steps_per_s"
        out[key] = round(machines * steps / t_fleet)

        # the same on every core: blocks of machines, one thread each
        def run_threaded(fleet=fleet, thetas=thetas):
            return ekf_fleet_threaded(spec, *fleet, thetas, q, r).means[:, -1]

        if machines == 1000:
            out["ekf_fleet_threaded_vs_ekf_fleet_max_abs_diff"] = float(
                np.max(np.abs(run_threaded() - np.asarray(run_fleet())))
            )
        run_threaded()
        t_threaded = _best(run_threaded, 3)
        key = f"ekf_fleet_threaded_{machines}_machines_machine_steps_per_s"
        out[key] = round(machines * steps / t_threaded)
    out["cpu_count"] = os.cpu_count()
    out["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    return out


if __name__ == "__main__":
    for key, value in main().items():
        print(f"{key}: {value}")
