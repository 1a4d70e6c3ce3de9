"""Speed of the estimators on a 5,400-step (90 min) virtual print.

Figures: our EKF steps/s vs filterpy's EKF on the same model (same process, same
run); RTS; one EM iteration (600 s window and whole print); whole-print
EKF + RTS + 10 EM iterations; a vmap batch of 1,000 machines filtered together.
"""

import time

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.estimation import DEFAULT_SCALING, ModelSpec, Twin, ekf, rts_smoother
from ajtwin.estimation.em import e_step, m_step, run_em
from ajtwin.model import euler_step, output_function
from ajtwin.simulation import simulate


def _best(fn, repeats=3):
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> dict:
    record = simulate("exp1", 1)
    twin = Twin.default()
    spec = ModelSpec(twin.model.params, jnp.asarray(twin.model.coefficient_matrix), DEFAULT_SCALING)
    u, y = record.inputs, record.outputs
    start = twin.initial_state(u, y)
    theta = np.zeros(5)
    q, r = twin.process_cov, twin.measurement_var
    n = len(u)

    def run_ekf():
        return jax.block_until_ready(ekf(spec, start.mean, start.covariance, u, y, theta, q, r))

    run_ekf()
    t_ekf = _best(run_ekf)
    filt = run_ekf()
    jax.block_until_ready(rts_smoother(spec, filt))
    t_rts = _best(lambda: jax.block_until_ready(rts_smoother(spec, filt)))

    # filterpy on the same model (jitted JAX f, g and Jacobians), 500 steps
    from filterpy.kalman import ExtendedKalmanFilter

    coeff = jnp.asarray(twin.model.coefficient_matrix)
    step = jax.jit(lambda x, uk: euler_step(x, uk, theta, twin.model.params))
    jf = jax.jit(jax.jacfwd(lambda x, uk: euler_step(x, uk, theta, twin.model.params)))
    g = jax.jit(lambda x, uk: output_function(x, uk, twin.model.params, coeff))
    jg = jax.jit(jax.jacfwd(lambda x, uk: output_function(x, uk, twin.model.params, coeff)))
    m_fp = 500

    def run_filterpy():
        f = ExtendedKalmanFilter(5, 5)
        f.x, f.P, f.Q, f.R = start.mean.copy(), start.covariance.copy(), q, np.diag(r)
        for k in range(m_fp):
            f.update(
                y[k],
                lambda x, uk: np.asarray(jg(x, uk)),
                lambda x, uk: np.asarray(g(x, uk)),
                args=(u[k],),
                hx_args=(u[k],),
            )
            fk = np.asarray(jf(f.x, u[k]))
            f.x = np.asarray(step(f.x, u[k]))
            f.P = fk @ f.P @ fk.T + f.Q

    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_filterpy()
        t_fp = _best(run_filterpy, 2) / m_fp

    # EM iterations
    prec = jnp.asarray(twin.theta_prior_precision)
    win = 600
    args_w = (spec, start.mean, start.covariance, u[:win], y[:win], theta, q, r, np.inf)
    filt_w, sm_w, _ = e_step(*args_w)
    jax.block_until_ready(m_step(spec, sm_w, u[:win], q, prec))

    def em_iter_window():
        f_, s_, _ = e_step(*args_w)
        jax.block_until_ready(m_step(spec, s_, u[:win], q, prec))

    t_em_window = _best(em_iter_window)
    args_full = (spec, start.mean, start.covariance, u, y, theta, q, r, np.inf)
    f_full, s_full, _ = e_step(*args_full)
    jax.block_until_ready(m_step(spec, s_full, u, q, prec))

    def em_iter_full():
        f_, s_, _ = e_step(*args_full)
        jax.block_until_ready(m_step(spec, s_full, u, q, prec))

    t_em_full = _best(em_iter_full)

    def whole():
        run_em(
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

    whole()
    t_whole = _best(whole, 2)

    # twin run with online EM (600 s window every 300 s), warm
    twin.run(record)
    t0 = time.perf_counter()
    twin.run(record)
    t_twin = time.perf_counter() - t0

    # 1,000 machines filtered together with vmap (60 steps each)
    machines, steps = 1000, 60
    rng = np.random.default_rng(0)
    means0 = np.tile(start.mean, (machines, 1))
    means0[:, 0] += rng.normal(0, 0.1, machines)
    covs0 = np.tile(start.covariance, (machines, 1, 1))
    us = np.tile(u[:steps], (machines, 1, 1))
    ys = np.tile(y[:steps], (machines, 1, 1)) + rng.normal(0, 0.5, (machines, steps, 5)) * [
        1,
        1,
        1,
        1,
        0,
    ]
    batched = jax.jit(
        jax.vmap(lambda m0, p0, uu, yy: ekf(spec, m0, p0, uu, yy, theta, q, r).means[-1])
    )
    jax.block_until_ready(batched(means0, covs0, us, ys))
    t_batch = _best(lambda: jax.block_until_ready(batched(means0, covs0, us, ys)), 2)

    return {
        "print_steps": n,
        "ekf_steps_per_s": round(n / t_ekf),
        "ekf_whole_print_ms": round(t_ekf * 1e3, 1),
        "filterpy_ekf_steps_per_s": round(1 / t_fp),
        "ekf_speedup_vs_filterpy": round(t_fp / (t_ekf / n), 1),
        "rts_whole_print_ms": round(t_rts * 1e3, 1),
        "em_iteration_600s_window_ms": round(t_em_window * 1e3, 1),
        "em_iteration_whole_print_ms": round(t_em_full * 1e3, 1),
        "whole_print_ekf_rts_plus_10_em_iterations_s": round(t_whole, 2),
        "twin_run_online_em_whole_print_s": round(t_twin, 2),
        "vmap_1000_machines_machine_steps_per_s": round(machines * steps / t_batch),
    }


if __name__ == "__main__":
    print(main())
