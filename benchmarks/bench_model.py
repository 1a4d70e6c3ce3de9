"""Speed of the digital model: jitted derivative+outputs, single and batched."""

import time

import numpy as np

from ajtwin._jax import jax, jnp
from ajtwin.model import DigitalModel, output_function, simulate_open_loop, transition_rates


def _best_time(fn, repeats):
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> dict:
    m = DigitalModel.default()
    params, coeffs = m.params, jnp.asarray(m.coefficient_matrix)
    theta = jnp.zeros(5)

    @jax.jit
    def both(x, u):
        return transition_rates(x, u, theta, params), output_function(x, u, params, coeffs)

    x = jnp.asarray([3.5, 1.0, 0.0, 0.0, 4.6e-7])
    u = jnp.asarray([375.0, 23.0, 50.0])
    jax.block_until_ready(both(x, u))
    n = 2000
    single = _best_time(lambda: [jax.block_until_ready(both(x, u)) for _ in range(n)], 3) / n

    rng = np.random.default_rng(0)
    batch = 10_000
    xs = jnp.asarray(
        np.column_stack(
            [
                rng.uniform(2.5, 4, batch),
                rng.uniform(0.5, 1.5, batch),
                rng.uniform(0, 1e-3, batch),
                rng.uniform(0, 0.1, batch),
                rng.uniform(1e-7, 1e-6, batch),
            ]
        )
    )
    us = jnp.asarray(
        np.column_stack(
            [rng.uniform(300, 440, batch), rng.uniform(15, 35, batch), rng.uniform(30, 70, batch)]
        )
    )
    jax.block_until_ready(both(xs, us))
    batched = _best_time(lambda: jax.block_until_ready(both(xs, us)), 10)

    inputs = jnp.tile(u, (5400, 1))
    jax.block_until_ready(simulate_open_loop(x, inputs, theta, params))
    scan = _best_time(
        lambda: jax.block_until_ready(simulate_open_loop(x, inputs, theta, params)), 5
    )
    return {
        "derivative_plus_outputs_single_us": round(single * 1e6, 2),
        "derivative_plus_outputs_batch10000_ms": round(batched * 1e3, 3),
        "derivative_plus_outputs_batch10000_per_state_us": round(batched / batch * 1e6, 4),
        "open_loop_5400_steps_ms": round(scan * 1e3, 2),
    }


if __name__ == "__main__":
    print(main())
