"""The digital model: the jitted transition rates and outputs, one state and 10,000 at once,
and a 5,400-step open-loop run (90 min at 1 Hz), after compilation."""

from __future__ import annotations

import numpy as np

BATCH = 10_000


class Model:
    """f (transition rates) and g (outputs) of :class:`ajtwin.model.DigitalModel`."""

    def setup(self):
        from ajtwin._jax import jax, jnp
        from ajtwin.model import (
            DigitalModel,
            output_function,
            simulate_open_loop,
            transition_rates,
        )

        self.jax = jax
        m = DigitalModel.default()
        params, coeffs = m.params, jnp.asarray(m.coefficient_matrix)
        theta = jnp.zeros(5)

        @jax.jit
        def both(x, u):
            return transition_rates(x, u, theta, params), output_function(x, u, params, coeffs)

        self.both = both
        self.x = jnp.asarray([3.5, 1.0, 0.0, 0.0, 4.6e-7])
        self.u = jnp.asarray([375.0, 23.0, 50.0])
        rng = np.random.default_rng(0)
        low, high = [2.5, 0.5, 0, 0, 1e-7], [4, 1.5, 1e-3, 0.1, 1e-6]
        self.xs = jnp.asarray(rng.uniform(low, high, (BATCH, 5)))
        self.us = jnp.asarray(rng.uniform([300, 15, 30], [440, 35, 70], (BATCH, 3)))
        inputs = jnp.tile(self.u, (5400, 1))
        self.open_loop = lambda: simulate_open_loop(self.x, inputs, theta, params)
        for run in (self.time_rates_and_outputs_one_state, self.time_rates_and_outputs_batch):
            run()  # compiled here, not in the timing
        jax.block_until_ready(self.open_loop())

    def time_rates_and_outputs_one_state(self):
        self.jax.block_until_ready(self.both(self.x, self.u))

    def time_rates_and_outputs_batch(self):
        """10,000 states in one call."""
        self.jax.block_until_ready(self.both(self.xs, self.us))

    def time_open_loop_5400_steps(self):
        self.jax.block_until_ready(self.open_loop())
