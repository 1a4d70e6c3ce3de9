"""Where one EKF step's time goes: the step with parts taken out.

Every variant runs the real :func:`ajtwin.estimation.filters.ekf_step` algebra over the
5,400-step exp1 print as a ``lax.scan``; each leaves out one part, so the differences are
the parts' costs:

* ``all_parts`` — the step as the shipped filter does it (all outputs);
* ``no_transition_jacobian`` — F = I (f still evaluated): the cost of ∂f/∂x;
* ``no_guard`` — without the PSD/finite divergence guard;
* ``model_free`` — f and g replaced by linear maps (the algebra's floor).

CPU time (``time.process_time``) of the whole print, after compilation; a step's share is
the figure / 5,400.
"""

from __future__ import annotations

import time

import numpy as np

VARIANTS = {
    "shipped": None,
    "all_parts": {},
    "no_transition_jacobian": {"transition_jacobian": False},
    "no_guard": {"guard": False},
    "model_free": {"model": False},
}


def _variant(spec, start, u, y, q, r, transition_jacobian=True, guard=True, model=True):
    """A jitted scan of the EKF step with the named parts left out."""
    from ajtwin._jax import jax, jnp
    from ajtwin.estimation.filters import AJ_EULER, _is_valid_covariance, _scaled_functions

    s, r_scale = spec.scaling.state, spec.scaling.output
    f_s, g_s = _scaled_functions(spec, AJ_EULER)
    a_lin = jnp.asarray(np.eye(5) * 0.999 + 1e-4)
    theta = jnp.zeros(5)

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
    return lambda: jax.block_until_ready(run(z0, p0))


class EKFStepParts:
    """CPU time of the 5,400-step print through each variant of the step."""

    params = list(VARIANTS)
    param_names = ["variant"]
    timer = time.process_time
    timeout = 600

    def setup(self, variant):
        from ajtwin._jax import jax, jnp
        from ajtwin.estimation import DEFAULT_SCALING, ModelSpec, Twin, ekf
        from ajtwin.simulation import simulate

        record = simulate("exp1", 1)
        twin = Twin.default()
        model = twin.model
        spec = ModelSpec(model.params, jnp.asarray(model.coefficient_matrix), DEFAULT_SCALING)
        u, y = jnp.asarray(record.inputs), jnp.asarray(record.outputs)
        start = twin.initial_state(record.inputs, record.outputs)
        q, r = jnp.asarray(twin.process_cov), jnp.asarray(twin.measurement_var)
        if VARIANTS[variant] is None:
            theta = jnp.zeros(5)
            self.run = lambda: jax.block_until_ready(
                ekf(spec, start.mean, start.covariance, u, y, theta, q, r)
            )
        else:
            self.run = _variant(spec, start, u, y, q, r, **VARIANTS[variant])
        self.run()

    def time_print_5400_steps(self, variant):
        self.run()
