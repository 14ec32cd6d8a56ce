"""Gymnasium spaces of one environment (the vector environment batches them) and the names of the
observation's entries."""

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


def observation_fields(observation) -> tuple:
    """(name, unit) of each entry of a ReturnBall observation under the task's ``[observation]``
    settings (``spin``, ``plan``, ``target``), in order: e.g. ``("ball.vel.x", "10 m/s")``, the ball's x
    velocity in units of 10 m/s (divided by 10)."""
    def xyz(what, unit):
        return [(f"{what}.{a}", unit) for a in "xyz"]

    out = xyz("ball.pos", "m") + xyz("ball.vel", "10 m/s")
    if observation.spin:
        out += xyz("ball.spin", "300 rad/s")
    out += xyz("racket.pos", "m") + xyz("racket.vel", "10 m/s")
    out += [("racket.pitch", "rad"), ("racket.yaw", "rad"), ("racket.pitch_rate", "10 rad/s"),
            ("racket.yaw_rate", "10 rad/s")]
    out += xyz("ball_minus_racket", "m") + [("time", "s"), ("bounced", "0/1"), ("hit", "0/1")]
    if observation.plan:
        out += xyz("plan.hit_pos", "m") + xyz("plan.hit_vel", "10 m/s") + [("plan.time_to_hit", "s"),
                                                                            ("plan.exists", "0/1")]
    if observation.target:
        out += [("target.x", "m"), ("target.y", "m")]
    return tuple(out)
