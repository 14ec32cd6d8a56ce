"""Ball and racket states as pytrees.

All quantities are SI and in the world frame: origin at the centre of the table's playing
surface, x along the table's length, y across it, z up.

Shapes are documented for one ball / one racket; any number of leading batch axes is allowed
(``(..., 3)``), and batching is done with ``jax.vmap``.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Ball:
    """State of one ball.

    Attributes:
        pos: (..., 3) centre position [m].
        vel: (..., 3) linear velocity [m/s].
        spin: (..., 3) angular velocity [rad/s].
    """

    pos: jnp.ndarray
    vel: jnp.ndarray
    spin: jnp.ndarray

    @classmethod
    def create(cls, pos, vel, spin=None, dtype=None) -> "Ball":
        """Builds a ball from array-likes; spin defaults to zero."""
        pos = jnp.asarray(pos, dtype)
        vel = jnp.asarray(vel, pos.dtype)
        spin = jnp.zeros_like(vel) if spin is None else jnp.asarray(spin, pos.dtype)
        pos, vel, spin = jnp.broadcast_arrays(pos, vel, spin)
        return cls(pos=pos, vel=vel, spin=spin)

    def as_array(self) -> jnp.ndarray:
        """(..., 9) array ``[pos, vel, spin]``."""
        return jnp.concatenate([self.pos, self.vel, self.spin], axis=-1)

    @classmethod
    def from_array(cls, x) -> "Ball":
        x = jnp.asarray(x)
        return cls(pos=x[..., 0:3], vel=x[..., 3:6], spin=x[..., 6:9])


@struct.dataclass
class Racket:
    """State of one racket (or of several, stacked on a leading axis).

    The racket frame: its x-axis is the face normal (the "forehand" face looks along +x), y and
    z are tangential, z points from the handle towards the tip. ``rot`` maps racket-frame
    vectors to the world frame, so its columns are the racket axes in world coordinates.

    Attributes:
        pos: (..., 3) centre of the face (blade mid-plane) [m].
        rot: (..., 3, 3) rotation racket frame -> world frame.
        vel: (..., 3) linear velocity of the face centre [m/s].
        ang_vel: (..., 3) angular velocity, world frame [rad/s].
        face: (..., 2) semi-axes of the elliptic face outline along racket y and z [m]; beyond it
            a ball meets only the rim (its centre within a radius of the outline).
    """

    pos: jnp.ndarray
    rot: jnp.ndarray
    vel: jnp.ndarray
    ang_vel: jnp.ndarray
    face: jnp.ndarray

    @classmethod
    def create(cls, pos, rot=None, vel=None, ang_vel=None, face=(0.0775, 0.0755), dtype=None) -> "Racket":
        """Builds a racket; defaults: identity orientation (face normal +x), at rest, ITTF-sized face."""
        pos = jnp.asarray(pos, dtype)
        batch = pos.shape[:-1]
        rot = jnp.broadcast_to(jnp.eye(3, dtype=pos.dtype), batch + (3, 3)) if rot is None else jnp.asarray(rot, pos.dtype)
        vel = jnp.zeros_like(pos) if vel is None else jnp.asarray(vel, pos.dtype)
        ang_vel = jnp.zeros_like(pos) if ang_vel is None else jnp.asarray(ang_vel, pos.dtype)
        face = jnp.broadcast_to(jnp.asarray(face, pos.dtype), batch + (2,))
        return cls(pos=pos, rot=rot, vel=vel, ang_vel=ang_vel, face=face)

    @property
    def normal(self) -> jnp.ndarray:
        """(..., 3) world-frame face normal (racket x-axis)."""
        return self.rot[..., :, 0]
