"""The state of a rally between steps, and how a rally starts.

Time is kept as an integer step count plus a start time, so that it does not drift: a float32 clock
incremented by 1 ms reads 4.99982 s after 5,000 steps; ``t0 + step * dt`` reads 5.0.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from ttsim_jax.state import Ball

# Why a ball stopped (``RallyState.status``); the same codes as the event kinds of
# ``physics.events`` (FLOOR, OUT, INVALID, REST), 0 while alive.


@struct.dataclass
class RallyState:
    """State of a batch of balls between steps; everything a rollout needs to resume.

    Attributes:
        ball: :class:`~ttsim_jax.state.Ball` with (B, 3) fields.
        alive: (B,) False once the ball hit the floor, left play, came to rest on the table or
            became invalid (then frozen).
        status: (B,) why it stopped (``FLOOR``, ``OUT``, ``REST``, ``INVALID``), 0 while alive.
        ball_id: (B,) int32 identity of each ball; random draws (the residual network's sampled
            correction) depend on it and on the step, never on where the ball sits in a buffer, a
            block or a shard.
        step: () int32 steps taken since ``t0``.
        t0: () start time [s].
        dt: () step length of the steps counted in ``step`` [s] (0 before the first rollout).
    """

    ball: Ball
    alive: jnp.ndarray
    status: jnp.ndarray
    ball_id: jnp.ndarray
    step: jnp.ndarray
    t0: jnp.ndarray
    dt: jnp.ndarray

    @property
    def batch(self) -> int:
        return self.alive.shape[0]

    @property
    def time(self) -> jnp.ndarray:
        """() current time [s]."""
        return self.t0 + self.step.astype(self.t0.dtype) * self.dt


def init_state(ball: Ball, t0=0.0, ball_id=None) -> RallyState:
    """The state of a rally about to start.

    Arguments:
        ball: :class:`~ttsim_jax.state.Ball` with (B, 3) fields.
        t0: start time [s].
        ball_id: (B,) int identities (default ``arange(B)``); give distinct ids to balls that must
            draw independent noise across separate rollouts.

    Returns:
        A :class:`RallyState` with every ball alive. Balls whose state is not finite are flagged
        invalid by the first step.
    """
    if ball.pos.ndim != 2 or ball.pos.shape[-1] != 3:
        raise ValueError(f"ball fields must be (B, 3); got pos {ball.pos.shape}")
    b = ball.pos.shape[0]
    dtype = ball.pos.dtype
    ids = jnp.arange(b, dtype=jnp.int32) if ball_id is None else jnp.asarray(ball_id, jnp.int32)
    if ids.shape != (b,):
        raise ValueError(f"ball_id must have shape ({b},), got {ids.shape}")
    return RallyState(ball=ball, alive=jnp.ones(b, bool), status=jnp.zeros(b, jnp.int32), ball_id=ids,
                      step=jnp.zeros((), jnp.int32), t0=jnp.asarray(t0, dtype), dt=jnp.zeros((), dtype))
