"""Gymnasium spaces of one environment (the vector environment batches them)."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

# Observations are clipped to this magnitude (``ReturnBall.observe``).
OBS_BOUND = 1e3


def observation_space(env) -> spaces.Box:
    """Box (obs_dim,) float32 in [-1e3, 1e3] of a :class:`~ttsim_jax.env.return_ball.ReturnBall`."""
    return spaces.Box(-OBS_BOUND, OBS_BOUND, (env.obs_dim,), np.float32)


def action_space(env) -> spaces.Box:
    """Box (5,) float32 in [-1, 1]: face-centre acceleration, then face-angle accelerations, as fractions
    of their limits."""
    return spaces.Box(-1.0, 1.0, (env.action_dim,), np.float32)
