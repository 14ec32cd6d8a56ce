"""The actor-critic: a Gaussian policy and a value function, two tanh MLPs (Flax)."""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax.numpy as jnp
import numpy as np


class ActorCritic(nn.Module):
    """Policy mean, log standard deviation (state-independent) and value of a batch of observations.

    Attributes:
        action_dim: size of an action.
        hidden: widths of the hidden layers (the same for actor and critic).
        init_log_std: the policy's initial log standard deviation.
    """

    action_dim: int
    hidden: Sequence[int] = (128, 128)
    init_log_std: float = -0.5

    @nn.compact
    def __call__(self, obs):
        """Arguments: obs (..., obs_dim). Returns: (mean (..., A), log_std (A,), value (...))."""
        def mlp(x, out, scale):
            for width in self.hidden:
                x = nn.tanh(nn.Dense(width, kernel_init=nn.initializers.orthogonal(np.sqrt(2.0)))(x))
            return nn.Dense(out, kernel_init=nn.initializers.orthogonal(scale),
                            bias_init=nn.initializers.zeros)(x)

        mean = mlp(obs, self.action_dim, 0.01)  # a near-zero first policy: small actions everywhere
        log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (self.action_dim,))
        value = mlp(obs, 1, 1.0)[..., 0]
        return mean, log_std, value


def gaussian_log_prob(mean, log_std, action):
    """Log density of ``action`` under a diagonal Gaussian, summed over the last axis."""
    z = (action - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z * z - log_std - 0.5 * jnp.log(2.0 * jnp.pi), axis=-1)


def gaussian_entropy(log_std):
    """Entropy of a diagonal Gaussian with these log standard deviations."""
    return jnp.sum(log_std + 0.5 * jnp.log(2.0 * jnp.pi * jnp.e), axis=-1)
