"""The learning agent's racket: a kinematic body driven by acceleration commands at the control rate.

Each control period the policy commands an acceleration of the face centre (3) and of the face's
two angles (pitch: face opened upwards, yaw: face turned across the table), as fractions of their
limits. The racket moves at that constant acceleration over the period, reduced where it would
exceed the speed limits, inside its workspace (a coordinate driven into a wall stops there): a box
whose floor rises to the table's surface plus a clearance where the face centre is over the agent's
half of the table (x below the table's end), so that a box reaching over the table never lets the
face pass through it (:func:`clip_workspace`);
the period is cut into the kernel's physics steps, each a racket moving at constant velocity (the
kernel's racket model), so the schedule is the piecewise-linear interpolation of that motion.

Acceleration commands keep the policy's effect smooth and linear (a velocity command under an
acceleration limit saturates for most commands, which hides the action's effect from learning).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.state import Racket


@struct.dataclass
class RacketState:
    """One racket (fields (..., n)).

    Attributes:
        pos: (..., 3) face centre [m]; vel: (..., 3) its velocity [m/s].
        angle: (..., 2) pitch and yaw of the face [rad]; rate: (..., 2) their rates [rad/s].
    """

    pos: jnp.ndarray
    vel: jnp.ndarray
    angle: jnp.ndarray
    rate: jnp.ndarray


@struct.dataclass
class RacketLimits:
    """Kinematic limits (see ``[racket]`` of the task file); (3,) and (2,) arrays, scalars.

    ``lo``, ``hi`` are the workspace box; where the face centre's x is below ``table_x`` (the table's
    end) its z is also at least ``table_z`` (the playing surface plus ``[racket] table_clearance``).
    """

    lo: jnp.ndarray
    hi: jnp.ndarray
    max_speed: jnp.ndarray
    max_accel: jnp.ndarray
    angle_lo: jnp.ndarray
    angle_hi: jnp.ndarray
    max_rate: jnp.ndarray
    max_angle_accel: jnp.ndarray
    face: jnp.ndarray
    table_x: jnp.ndarray
    table_z: jnp.ndarray


def clip_workspace(limits: RacketLimits, pos):
    """Face centre positions (..., 3) clipped into the workspace: the box, then the raised floor over
    the table (a stepped box: z >= ``table_z`` where x < ``table_x``). Branch-free."""
    pos = jnp.clip(pos, limits.lo, limits.hi)
    over = pos[..., 0] < limits.table_x
    z = jnp.where(over, jnp.maximum(pos[..., 2], limits.table_z), pos[..., 2])
    return pos.at[..., 2].set(z)


def rotation(angle):
    """Racket frame -> world for face angles (pitch, yaw): at zero the face normal points along -x
    (towards the opponent), pitch turns it upwards, yaw about z.

    Arguments:
        angle: (..., 2) pitch, yaw [rad].

    Returns:
        (..., 3, 3) rotation whose first column is the face normal.
    """
    cp, sp = jnp.cos(angle[..., 0]), jnp.sin(angle[..., 0])
    cy, sy = jnp.cos(angle[..., 1]), jnp.sin(angle[..., 1])
    entries = (-cy * cp, sy, cy * sp, -sy * cp, -cy, sy * sp, sp, None, cp)
    # rz(yaw) @ ry(pitch) @ diag(-1, -1, 1) (normal -x, tip up), multiplied out, as a sum over the
    # unit matrices: a stack of the nine entries is a concatenation, which a CPU runs on one thread,
    # one element at a time
    return sum(e[..., None, None] * _UNIT[i] for i, e in enumerate(entries) if e is not None)


_UNIT = np.eye(9, dtype=np.float32).reshape(9, 3, 3)


def angular_velocity(angle, rate):
    """(..., 3) world angular velocity of :func:`rotation` for angles and their rates (pitch, yaw)
    (..., 2) [rad, rad/s]."""
    cy, sy = jnp.cos(angle[..., 1]), jnp.sin(angle[..., 1])
    pitch, yaw = rate[..., 0], rate[..., 1]
    return jnp.stack([-pitch * sy, pitch * cy, yaw], -1)


def _ramp(x, v, fraction, max_accel, max_speed, bound, period, n_sub):
    """Constant-acceleration motion of one group of coordinates over a control period.

    Arguments:
        x, v: (..., d) position and velocity; fraction: (..., d) commanded acceleration / its limit, in [-1, 1].
        bound: clips positions (..., d) into the allowed region.

    Returns:
        (positions at the n_sub step starts (n_sub, ..., d), mean velocities over each step
        (n_sub, ..., d), end position (..., d), end velocity (..., d), acceleration used / its
        limit (..., d)).
    """
    v = jnp.clip(v, -max_speed, max_speed)
    accel = jnp.clip(fraction * max_accel, (-max_speed - v) / period, (max_speed - v) / period)
    h = period / n_sub
    t = (jnp.arange(n_sub, dtype=x.dtype) * h).reshape((n_sub,) + (1,) * x.ndim)
    pos = bound(x + v * t + 0.5 * accel * t * t)
    end = x + v * period + 0.5 * accel * period * period
    held = bound(end)
    nxt = jnp.concatenate([pos[1:], held[None]])
    # a coordinate held at a wall stops there
    end_v = jnp.where(held != end, 0.0, v + accel * period)
    return pos, (nxt - pos) / h, held, end_v, accel / max_accel


def command(limits: RacketLimits, state: RacketState, action, period, n_sub: int):
    """Applies one control command to one racket, or to a batch of them.

    Arguments:
        limits: :class:`RacketLimits`; state: :class:`RacketState` with (..., 3) / (..., 2) fields.
        action: (..., 5) in [-1, 1]: acceleration of the face centre as fractions of ``max_accel`` (3),
            then the angles' accelerations as fractions of ``max_angle_accel`` (2); non-finite
            entries count as 0, others are clipped to [-1, 1].
        period: control period [s]; n_sub: physics steps in it (static).

    Returns:
        (new :class:`RacketState`, :class:`Racket` schedule with (n_sub, ..., 1, ...) fields (time
        first: the kernel's order, so that a batch's schedule needs no transposition), effort (...):
        mean squared acceleration as a fraction of its limit).
    """
    a = jnp.clip(jnp.where(jnp.isfinite(action), action, 0.0), -1.0, 1.0).astype(state.pos.dtype)
    pos, vel, end_p, end_v, eff_p = _ramp(state.pos, state.vel, a[..., :3], limits.max_accel, limits.max_speed,
                                          lambda p: clip_workspace(limits, p), period, n_sub)
    ang, rate, end_a, end_r, eff_a = _ramp(state.angle, state.rate, a[..., 3:5], limits.max_angle_accel,
                                           limits.max_rate, lambda a: jnp.clip(a, limits.angle_lo, limits.angle_hi),
                                           period, n_sub)
    face = jnp.broadcast_to(limits.face, ang.shape)
    schedule = Racket(pos=pos[..., None, :], rot=rotation(ang)[..., None, :, :], vel=vel[..., None, :],
                      ang_vel=angular_velocity(ang, rate)[..., None, :], face=face[..., None, :])
    effort = jnp.mean(jnp.concatenate([eff_p, eff_a], -1) ** 2, -1)
    return RacketState(pos=end_p, vel=end_v, angle=end_a, rate=end_r), schedule, effort
