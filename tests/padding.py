"""Padding a small scenario up to a test module's one compiled batch size."""

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import Ball


def pad_balls(balls: Ball, n: int) -> Ball:
    """``balls`` filled up to ``n`` balls with balls at rest on the floor beside the table (they
    touch nothing the others touch), so every scenario of a module shares one compiled shape."""
    k = balls.pos.shape[0]
    filler = Ball.create(np.tile([[3.0, 0.0, -0.74]], (n - k, 1)), np.zeros((n - k, 3)), dtype=balls.pos.dtype)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), balls, filler)
