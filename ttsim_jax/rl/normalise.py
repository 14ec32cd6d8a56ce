"""Running mean and variance of observations (merged batch by batch, Chan et al.'s parallel update)."""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

# normalised observations are clipped to this many standard deviations
CLIP = 10.0


@struct.dataclass
class RunningStats:
    """Attributes: mean (D,), var (D,), count () of the observations seen."""

    mean: jnp.ndarray
    var: jnp.ndarray
    count: jnp.ndarray

    @classmethod
    def create(cls, dim: int) -> "RunningStats":
        return cls(mean=jnp.zeros(dim, jnp.float32), var=jnp.ones(dim, jnp.float32),
                   count=jnp.asarray(1e-4, jnp.float32))

    def update(self, batch) -> "RunningStats":
        """The statistics with a batch (..., D) merged in."""
        x = batch.reshape(-1, batch.shape[-1]).astype(jnp.float32)
        n = jnp.asarray(x.shape[0], jnp.float32)
        mean, var = jnp.mean(x, 0), jnp.var(x, 0)
        total = self.count + n
        delta = mean - self.mean
        new_mean = self.mean + delta * n / total
        m2 = self.var * self.count + var * n + delta * delta * self.count * n / total
        return RunningStats(mean=new_mean, var=m2 / total, count=total)

    def normalise(self, obs):
        """(obs - mean) / std, clipped to +-CLIP."""
        return jnp.clip((obs - self.mean) / jnp.sqrt(self.var + 1e-8), -CLIP, CLIP)
