"""Table contact: Nakashima point contact, velocity-dependent restitution, local residual matrices.

The table's playing surface is the plane z = 0 (ITTF: 2.74 m x 1.525 m, net 15.25 cm high at x = 0,
its posts 15.25 cm outside each side line). Effects may tilt or warp it through the
``table_surface`` hook; the contact is then solved in the frame of the local surface normal.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from ttsim_jax.physics import hooks
from ttsim_jax.physics.contact import ContactCoefficients, apply_matrices, contact_matrices, sliding_alpha
from ttsim_jax.physics.numerics import safe_unit

_Z = jnp.array([0.0, 0.0, 1.0])


@struct.dataclass
class TableParams:
    """Table contact and geometry.

    Attributes:
        e0, e1: normal restitution e_n = e0 + e1 v_z^- (v_z^- < 0 at impact, so e1 > 0 lowers e_n
            as the impact gets faster: ball buckling); clipped to [e_min, e_max].
        e_min, e_max: clip range of e_n.
        mu: dynamic friction coefficient.
        kappa: m r^2 / I (3/2 for a thin spherical shell).
        alpha_roll: grip fraction of a rolling contact (2/5).
        residual: (4, 3, 3) local residual matrices (dA_vv, dA_vw, dA_wv, dA_ww), zeros for none.
        length, width: playing surface [m].
        net_height, net_overhang: net height above the surface and how far its posts stand
            outside the side lines [m].
        floor_z: floor height in the world frame [m] (the surface is 0.76 m above it).
    """

    e0: jnp.ndarray
    e1: jnp.ndarray
    e_min: jnp.ndarray
    e_max: jnp.ndarray
    mu: jnp.ndarray
    kappa: jnp.ndarray
    alpha_roll: jnp.ndarray
    residual: jnp.ndarray
    length: jnp.ndarray
    width: jnp.ndarray
    net_height: jnp.ndarray
    net_overhang: jnp.ndarray
    floor_z: jnp.ndarray


def surface(effects, pos):
    """(height, unit normal) of the playing surface under ``pos``; (0, z) without effects."""
    return hooks.apply(effects, "table_surface", (jnp.zeros_like(pos[2]), _Z.astype(pos.dtype)), pos=pos)


def on_table(table: TableParams, pos):
    """Whether the point's (x, y) lies over the playing surface."""
    return (jnp.abs(pos[0]) <= 0.5 * table.length) & (jnp.abs(pos[1]) <= 0.5 * table.width)


def residual_frame(vel):
    """R whose rows are (v_xy/|v_xy|, z x v_xy/|v_xy|, z): the paper's Eq. (table_rotation).

    The identity when the horizontal velocity vanishes (the frame is undefined there).
    """
    vh = safe_unit(jnp.stack([vel[0], vel[1], jnp.zeros_like(vel[0])]), jnp.array([1.0, 0.0, 0.0], vel.dtype))
    return jnp.stack([vh, jnp.cross(_Z.astype(vel.dtype), vh), _Z.astype(vel.dtype)])


def restitution(table: TableParams, vz, effects=()):
    """Normal restitution for a pre-contact normal velocity vz (< 0 at impact)."""
    e_n = jnp.clip(table.e0 + table.e1 * vz, table.e_min, table.e_max)
    return hooks.apply(effects, "table_restitution", e_n, vn=jnp.abs(vz))


def local_contact(table: TableParams, radius, vel, spin, effects=()):
    """Table contact in the surface frame (normal = z): returns (v+, w+).

    Implements v+ = Ã_vv v + Ã_vw w, w+ = Ã_wv v + Ã_ww w with Ã = A - R^T dA R.
    """
    e_n = restitution(table, vel[2], effects)
    alpha = sliding_alpha(table.mu, e_n, vel, spin, radius, table.alpha_roll)
    coef = ContactCoefficients(e_n=e_n, alpha=jnp.stack([alpha, alpha]), e_s=jnp.ones_like(e_n))
    mats = contact_matrices(coef, radius, table.kappa)
    rot = residual_frame(vel)
    mats = tuple(a - rot.T @ da @ rot for a, da in zip(mats, table.residual))
    return apply_matrices(mats, vel, spin)


def table_contact(table: TableParams, radius, pos, vel, spin, effects=()):
    """Post-contact (pos, vel, spin) of a ball touching the table at ``pos``.

    The position is put back on the surface (centre one radius above it along the normal) so
    that a ball at rest does not sink through the table step by step.
    """
    height, normal = surface(effects, pos)
    t1 = safe_unit(jnp.array([1.0, 0.0, 0.0], pos.dtype) - normal[0] * normal, jnp.array([1.0, 0.0, 0.0], pos.dtype))
    frame = jnp.stack([t1, jnp.cross(normal, t1), normal])  # world -> surface frame
    v_loc, w_loc = local_contact(table, radius, frame @ vel, frame @ spin, effects)
    pos_c = jnp.concatenate([pos[:2], jnp.maximum(pos[2:], height + radius)])
    return pos_c, frame.T @ v_loc, frame.T @ w_loc


def penetration(effects, radius, pos):
    """Signed gap (m) between the ball's lowest point and the surface below it (< 0: touching)."""
    height, _ = surface(effects, pos)
    return pos[2] - radius - height

