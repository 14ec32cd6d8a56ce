"""Simple racket policies for rallies without a learned agent (benchmarks, tests, baselines).

A policy is a :class:`~ttsim_jax.kernel.plans.RacketPolicy`: a pure function of (params, ball, t)
evaluated inside the rally scan, returning the rackets' states.
"""

from __future__ import annotations

import jax.numpy as jnp

from ttsim_jax.kernel.plans import RacketPolicy, face_boxes
from ttsim_jax.state import Racket

# The tracking rackets' face semi-axis [m], and the ranges their centres follow the ball over.
_FACE = 0.077
_Y_RANGE = (-1.0, 1.0)
_Z_RANGE = (0.05, 1.5)
# Height [m] of the racket parked out of reach.
_PARKED_Z = -10.0


def _facing(sign, tilt):
    """Rotation whose x-axis (face normal) points along -sign * x, tilted up by ``tilt`` [rad]."""
    c, s = jnp.cos(tilt), jnp.sin(tilt)
    n = jnp.array([-sign * c, 0.0, s])
    z = jnp.array([sign * s, 0.0, c])
    y = jnp.cross(z, n)
    return jnp.stack([n, y, z], axis=-1)


def tracking_rackets_fn(params, ball, t):
    """Two rackets, one behind each end line, that follow the ball in y and z and swing forward.

    Only the racket the ball is flying towards is in play; the other is parked out of reach, so a
    ball leaving one racket cannot catch its back face.

    Returns:
        :class:`Racket` with (2, ...) fields: index 0 at x = -params["x"], index 1 at +params["x"].
    """
    x, swing, lift, tilt = params["x"], params["swing"], params["lift"], params["tilt"]
    signs = jnp.array([-1.0, 1.0])
    y = jnp.clip(ball.pos[1], *_Y_RANGE)
    z = jnp.clip(ball.pos[2], *_Z_RANGE)
    heading = jnp.where(ball.vel[0] >= 0.0, 1.0, -1.0)
    parked = signs != heading
    pos = jnp.stack([signs * x, jnp.full(2, y), jnp.where(parked, _PARKED_Z, z)], -1)
    rot = jnp.stack([_facing(s, tilt) for s in (-1.0, 1.0)])
    vel = jnp.stack([-signs * swing, jnp.zeros(2), jnp.full(2, lift)], -1)
    return Racket(pos=pos, rot=rot, vel=vel, ang_vel=jnp.zeros((2, 3)), face=jnp.full((2, 2), _FACE))


def tracking_rackets_reach(params, dt):
    """:attr:`RacketPolicy.reach` of :func:`tracking_rackets_fn`: each racket's face over a step,
    from the corners of the range its centre follows the ball over (and its parked height), (2, 2, 3)."""
    signs = jnp.array([-1.0, 1.0])
    dtype = jnp.result_type(params["x"], dt)
    # the centre's extreme positions: y and z at either end of their ranges, z also parked
    lo = jnp.stack([signs * params["x"], jnp.full(2, _Y_RANGE[0]), jnp.full(2, _PARKED_Z)], -1)
    hi = jnp.stack([signs * params["x"], jnp.full(2, _Y_RANGE[1]), jnp.full(2, _Z_RANGE[1])], -1)
    vel = jnp.stack([-signs * params["swing"], jnp.zeros(2), jnp.full(2, params["lift"])], -1)
    face = jnp.full((2, 2), _FACE)
    corners = [face_boxes(c.astype(dtype), vel, face, dt) for c in (lo, hi)]
    return jnp.stack([jnp.minimum(corners[0][:, 0], corners[1][:, 0]),
                      jnp.maximum(corners[0][:, 1], corners[1][:, 1])], axis=-2)


def tracking_rackets(x: float = 1.9, swing: float = 4.0, lift: float = 1.0, tilt: float = -0.3) -> RacketPolicy:
    """A :class:`RacketPolicy` of :func:`tracking_rackets_fn`: a crude baseline opponent, not a good player.

    With the defaults about one ball in four survives 3 s of rally (~1.5 racket contacts per ball):
    enough contacts to exercise racket contact and the residual network in benchmarks.

    Arguments:
        x: distance of each racket behind the table centre along x [m].
        swing: forward racket speed towards the table [m/s].
        lift: upward racket speed [m/s].
        tilt: how far the face is opened upwards [rad].
    """
    params = {k: jnp.asarray(v, jnp.float32) for k, v in dict(x=x, swing=swing, lift=lift, tilt=tilt).items()}
    return RacketPolicy(params=params, fn=tracking_rackets_fn, reach=tracking_rackets_reach)
