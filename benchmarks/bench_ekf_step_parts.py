"""Where one EKF step's time goes: the step with parts taken out.

All variants run the real :func:`ajtwin.estimation.filters.ekf_step` algebra
structure over the 5,400-step exp1 print as a ``lax.scan``; each leaves out one
part, so the differences are the parts' costs:

* ``ekf`` — the project's filter as shipped (all outputs);
* ``no_transition_jacobian`` — F = I (f still evaluated): the cost of ∂f/∂x;
* ``no_guard`` — without the PSD/finite divergence guard;
* ``model_free`` — f and g replaced by linear maps (the algebra's floor).

CPU time (``time.process_time``), best of several runs, after compilation.
"""

import os
import time

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.estimation import DEFAULT_SCALING, ModelSpec, Twin, ekf
from ajtwin.estimation.filters import AJ_EULER, _is_valid_covariance, _scaled_functions
from ajtwin.simulation import simulate


def _best_cpu(fn, repeats=7):
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def main() -> dict:
    record = simulate("exp1", 1)
    twin = Twin.default()
    spec = ModelSpec(twin.model.params, jnp.asarray(twin.model.coefficient_matrix), DEFAULT_SCALING)
    u, y = jnp.asarray(record.inputs), jnp.asarray(record.outputs)
    start = twin.initial_state(record.inputs, record.outputs)
    q, r = jnp.asarray(twin.process_cov), jnp.asarray(twin.measurement_var)
    theta = jnp.zeros(5)
    n = len(u)
    s, r_scale = spec.scaling.state, spec.scaling.output
    f_s, g_s = _scaled_functions(spec, AJ_EULER)
    a_lin = jnp.asarray(np.eye(5) * 0.999 + 1e-4)

    def variant(transition_jacobian=True, guard=True, model=True):
        @jax.jit
        def run(z0, p0):
            q_s = q / jnp.outer(s, s)
            r_diag = r / r_scale**2

            def body(carry, inputs):
                z, p = carry
                uk, yk = inputs
                if model:
                    h, y_hat = jax.jacfwd(lambda zz: (g_s(zz, uk), g_s(zz, uk)), has_aux=True)(z)
                else:
                    h, y_hat = jnp.eye(5), z
                innovation = yk / r_scale - y_hat
                for i in range(5):
                    ph = p @ h[i]
                    s_i = h[i] @ ph + r_diag[i]
                    k = ph / s_i
                    z = z + k * innovation[i]
                    m = p - jnp.outer(k, ph)
                    p = m - jnp.outer(m @ h[i], k) + r_diag[i] * jnp.outer(k, k)
                p = 0.5 * (p + p.T)
                if guard:
                    p = jnp.where(_is_valid_covariance(p), p, p0)
                if not model:
                    jac, z = a_lin, a_lin @ z
                elif transition_jacobian:
                    jac, z = jax.jacfwd(
                        lambda zz: (f_s(zz, uk, theta), f_s(zz, uk, theta)), has_aux=True
                    )(z)
                else:
                    jac, z = jnp.eye(5), f_s(z, uk, theta)
                p = jac @ p @ jac.T + q_s
                return (z, 0.5 * (p + p.T)), (z, p)

            return jax.lax.scan(body, (z0, p0), (u, y))[1]

        z0 = jnp.asarray(start.mean) / s
        p0 = jnp.asarray(start.covariance) / jnp.outer(s, s)
        return _best_cpu(lambda: jax.block_until_ready(run(z0, p0))) / n * 1e6

    shipped = _best_cpu(
        lambda: jax.block_until_ready(ekf(spec, start.mean, start.covariance, u, y, theta, q, r))
    )
    return {
        "load_average_1min": round(os.getloadavg()[0], 2),
        "ekf_step_cpu_us": round(shipped / n * 1e6, 2),
        "step_all_parts_cpu_us": round(variant(), 2),
        "step_no_transition_jacobian_cpu_us": round(variant(transition_jacobian=False), 2),
        "step_no_guard_cpu_us": round(variant(guard=False), 2),
        "step_model_free_cpu_us": round(variant(model=False), 2),
    }


if __name__ == "__main__":
    for key, value in main().items():
        print(f"{key}: {value}")
