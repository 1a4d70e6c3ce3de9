"""JAX set-up shared by every JAX-using module: 64-bit floats on the CPU.

Import this module (``from ajtwin._jax import jax, jnp``) instead of ``jax``
directly so that x64 is enabled before any array is created.
"""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

jax.config.update("jax_enable_x64", True)

__all__ = ["jax", "jnp"]
