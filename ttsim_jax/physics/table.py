"""Table contact: Nakashima point contact, velocity-dependent restitution, local residual matrices.

The table's playing surface is the plane z = 0 (ITTF: 2.74 m x 1.525 m, net 15.25 cm high at x = 0,
its posts 15.25 cm outside each side line). Effects may tilt or warp it through the
``table_surface`` hook; the contact is then solved in the frame of the local surface normal.

Geometry: the table is a box, the playing surface on top and ``THICKNESS`` (2.5 cm, a usual
ITTF top; the paper does not give it) deep, the ball a sphere. A ball touches the table where its
centre comes within one radius of the box; the contact normal points from the nearest point of
the box to the ball centre, so a ball reaching an end or a side below the surface height meets
the edge (the normal turns from z towards x or y), the corner, or the side face, and the same
contact model responds in that normal's frame. Over the playing surface the normal is the
surface's (effects included).

Residual matrices (conti2026): the paper fitted them on bounces of rally balls, and they are
applied with two bounds so that outside that data they cannot create motion:

- faded with the horizontal speed (full above ``RESIDUAL_FADE_SPEED`` = 1 m/s, a smoothstep
  below it, none for a vertical drop): their frame (velocity heading) is undefined for a
  vertical drop, and the fitted bounces all travel several m/s along the table;
- scaled by the largest factor in [0, 1] for which the contact creates no kinetic energy
  (translational + rotational, I = m r^2 / kappa). On the public measured bounces and the
  generator's games the factor is 1 (``benchmarks/table_bound.py``); for grazing balls, where
  the raw matrices would add up to 1.75 % of energy per bounce, it is less.

The normal speed is not bounded: the law's normal row, v_z+ = |v_z| (e_n - 0.02717) +
0.02344 |v_xy| (+ spin terms, at most 2.3 mm/s per 100 rad/s), gives a normal restitution above
1 for flat impacts (impact angles below 17, 12 and 11 degrees at 5, 15 and 20 m/s), as oblique
impacts can (Louge and Adams 2002 measured it; Kuninaka and Hayakawa 2004,
arXiv:cond-mat/0310058, explain it). A ball skimming the table at a few m/s therefore hops
higher over its first bounces, taking the normal speed from its horizontal speed and spin, and
lower once friction has slowed it.

Sustained contact: a contact that leaves less than ``REST_SPEED`` of normal speed (a bounce under
0.5 mm) is perfectly inelastic: the ball stays on the surface (normal speed zero). A ball that
starts a step touching the table (within ``CONTACT_SLOP`` of it, normal speed below
``REST_SPEED``) flies freely over the step and is then put back onto the surface by
:func:`slide`: the same contact model with e_n = 0 and no residual, i.e. a normal impulse that
cancels the normal velocity gravity added over the step and Coulomb friction (mu) with that
impulse. A sliding ball thus decelerates by about mu g until it rolls, a rolling ball rolls on
(drag and Magnus act as in flight), the same at every dt. It leaves contact where the surface
ends (rolling over the edge, it pivots about it until it falls away) or where lift exceeds
gravity, and comes to rest (REST) once its velocity and its contact point's velocity are both
below ``REST_SPEED``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.physics import hooks
from ttsim_jax.physics.contact import (ContactCoefficients, apply_matrices, contact_matrices, sliding_alpha,
                                       surface_velocity)
from ttsim_jax.physics.numerics import dot3, matmul, matvec, safe_norm, safe_unit, transpose

_Z = np.array([0.0, 0.0, 1.0])  # numpy: no device array at import; cast to the state's dtype at use

# Depth of the table top [m] (not in the paper; ITTF tops are usually about 2.5 cm).
THICKNESS = 0.025
# A contact leaving less normal speed than this [m/s] is perfectly inelastic, and a ball touching
# the table whose velocity and contact-point velocity are both below it is at rest.
REST_SPEED = 0.1
# A ball this close to the table [m] at the start of a step, with normal speed below REST_SPEED,
# is in sustained contact (above the g dt^2 / 2 a step of free flight sinks it, 20 um at 2 ms).
CONTACT_SLOP = 1e-4
# Horizontal speed [m/s] above which the residual matrices act fully.
RESIDUAL_FADE_SPEED = 1.0


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
    return hooks.apply(effects, "table_surface", (jnp.zeros_like(pos[2]), jnp.asarray(_Z, pos.dtype)), pos=pos)


def box_distance(table: TableParams, effects, pos):
    """Signed distance from a point to the table box and the outward unit normal there.

    Over the playing surface (and above the box's mid-plane) it is the height above the surface
    and the surface normal; elsewhere the distance to the nearest point of the box (negative
    inside) and the direction from that point to ``pos``.

    Arguments:
        table: table parameters; effects: the model's effects (hook ``table_surface``);
        pos: (3,) point, world frame.

    Returns:
        (distance [m], normal (3,)).
    """
    height, top_normal = surface(effects, pos)
    rel = pos - jnp.stack([jnp.zeros_like(height), jnp.zeros_like(height), height - 0.5 * THICKNESS])
    half = jnp.stack([0.5 * table.length, 0.5 * table.width, jnp.full_like(height, 0.5 * THICKNESS)])
    d = jnp.abs(rel) - half  # > 0 beyond the face pair of that axis
    sign = jnp.where(rel >= 0.0, 1.0, -1.0).astype(pos.dtype)
    beyond = jnp.maximum(d, 0.0)
    outside = safe_norm(beyond)
    # the largest component and its axis (the first of equals) without a reduction: over a short
    # axis a reduction is a pass over the batch of its own
    d0, d1, d2 = jnp.unstack(d, axis=-1)
    first, second = (d0 >= d1) & (d0 >= d2), (d0 < d1) & (d1 >= d2)
    n_in = sign * jnp.stack([first, second, ~first & ~second], axis=-1).astype(pos.dtype)
    normal = safe_unit(beyond * sign, n_in)
    dist = outside + jnp.minimum(jnp.maximum(jnp.maximum(d0, d1), d2), 0.0)
    top = (d[0] <= 0.0) & (d[1] <= 0.0) & (rel[2] >= 0.0)
    return jnp.where(top, pos[2] - height, dist), jnp.where(top, top_normal, normal)


def gap(table: TableParams, effects, radius, pos):
    """Signed gap [m] between the ball's surface and the table (< 0: touching)."""
    return box_distance(table, effects, pos)[0] - radius


def residual_frame(vel):
    """R whose rows are (v_xy/|v_xy|, z x v_xy/|v_xy|, z): the paper's Eq. (table_rotation).

    The identity when the horizontal velocity vanishes (the frame is undefined there; the
    residual is faded out there, see :func:`residual_fade`).
    """
    vh = safe_unit(jnp.stack([vel[0], vel[1], jnp.zeros_like(vel[0])]), jnp.array([1.0, 0.0, 0.0], vel.dtype))
    return jnp.stack([vh, jnp.cross(jnp.asarray(_Z, vel.dtype), vh), jnp.asarray(_Z, vel.dtype)])


def residual_fade(vel):
    """Weight of the residual correction: smoothstep of |v_xy| / RESIDUAL_FADE_SPEED (0 to 1)."""
    s = jnp.clip(safe_norm(vel[:2]) / RESIDUAL_FADE_SPEED, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def restitution(table: TableParams, vz, effects=()):
    """Normal restitution for a pre-contact normal velocity vz (< 0 at impact)."""
    e_n = jnp.clip(table.e0 + table.e1 * vz, table.e_min, table.e_max)
    return hooks.apply(effects, "table_restitution", e_n, vn=jnp.abs(vz))


def friction(table: TableParams, vn, effects=()):
    """Friction coefficient mu of a contact with normal speed ``vn`` (>= 0)."""
    return hooks.apply(effects, "table_friction", table.mu, vn=vn)


def kinetic_energy(kappa, radius, vel, spin):
    """Kinetic energy per unit mass [J/kg]: |v|^2 / 2 + (r^2 / kappa) |w|^2 / 2 (I = m r^2 / kappa)."""
    return 0.5 * dot3(vel, vel) + 0.5 * radius * radius / kappa * dot3(spin, spin)


def residual_bound(kappa, radius, vel, spin, base_v, base_w, dv, dw):
    """Largest lam in [0, 1] for which (base + lam d) has no more kinetic energy than (vel, spin).

    The energy is quadratic in lam, E(lam) = E_b + b lam + a lam^2; E_b <= E_in (the base model
    dissipates), so its root above 0 exists and is taken in a cancellation-free form.

    Arguments:
        kappa, radius: m r^2 / I and the ball radius [m];
        vel, spin: (3,) incoming velocity [m/s] and spin [rad/s];
        base_v, base_w: (3,) outgoing state of the base model;
        dv, dw: (3,) the (faded) residual correction.

    Returns:
        lam, a scalar in [0, 1]; 1 where the full correction creates no energy.
    """
    w2 = radius * radius / kappa
    a = 0.5 * (jnp.sum(dv * dv) + w2 * jnp.sum(dw * dw))
    b = jnp.sum(base_v * dv) + w2 * jnp.sum(base_w * dw)
    c = jnp.maximum(kinetic_energy(kappa, radius, vel, spin) - kinetic_energy(kappa, radius, base_v, base_w), 0.0)
    grows = a + b > c  # E(1) > E_in
    disc = jnp.sqrt(jnp.where(grows, b * b + 4.0 * a * c, 1.0))
    den = jnp.where(b >= 0.0, b + disc, 2.0 * a)
    num = jnp.where(b >= 0.0, 2.0 * c, disc - b)
    lam = jnp.where(grows & (den > 0.0), num / jnp.where(den > 0.0, den, 1.0), 1.0)
    return jnp.clip(lam, 0.0, 1.0)


def residual_terms(table: TableParams, radius, vel, spin, effects=()):
    """The base contact and the faded residual correction, in the surface frame (normal = z).

    The paper's law is v+ = Ã_vv v + Ã_vw w, w+ = Ã_wv v + Ã_ww w with Ã = A - R^T dA R: the
    base part A (Nakashima's point contact with e_n = e0 + e1 v_z) and the residual part
    -R^T dA R, here faded with the horizontal speed (:func:`residual_fade`) but not bounded.

    Arguments:
        table, radius: table parameters and ball radius [m];
        vel, spin: (3,) incoming velocity and spin, surface frame; effects: the model's effects.

    Returns:
        (base_v, base_w, dv, dw): the law's outgoing state is (base_v + dv, base_w + dw).
    """
    e_n = restitution(table, vel[2], effects)
    alpha = sliding_alpha(friction(table, jnp.abs(vel[2]), effects), e_n, vel, spin, radius, table.alpha_roll)
    coef = ContactCoefficients(e_n=e_n, alpha=jnp.stack([alpha, alpha]), e_s=jnp.ones_like(e_n))
    base_v, base_w = apply_matrices(contact_matrices(coef, radius, table.kappa), vel, spin)
    rot = residual_frame(vel)
    dv, dw = apply_matrices(tuple(-matmul(transpose(rot), matmul(da, rot)) for da in table.residual), vel, spin)
    fade = residual_fade(vel)
    return base_v, base_w, fade * dv, fade * dw


def local_contact(table: TableParams, radius, vel, spin, effects=()):
    """Table contact in the surface frame (normal = z): returns (v+, w+).

    The paper's law (:func:`residual_terms`) with its residual part faded with the horizontal
    speed and scaled down where it would create kinetic energy (:func:`residual_bound`; see the
    module docstring).
    """
    base_v, base_w, dv, dw = residual_terms(table, radius, vel, spin, effects)
    lam = residual_bound(table.kappa, radius, vel, spin, base_v, base_w, dv, dw)
    return base_v + lam * dv, base_w + lam * dw


def _frame(normal):
    """World -> contact frame whose third axis is ``normal``."""
    x = jnp.array([1.0, 0.0, 0.0], normal.dtype)
    alt = jnp.array([0.0, 1.0, 0.0], normal.dtype)
    t1 = safe_unit(x - normal[0] * normal, safe_unit(alt - normal[1] * normal, x))
    return jnp.stack([t1, jnp.cross(normal, t1), normal])


def _geometry(table, effects, radius, pos, edges):
    """(normal, position pushed out to touch) of a contact at ``pos``."""
    if edges:
        dist, normal = box_distance(table, effects, pos)
        return normal, pos + jnp.maximum(radius - dist, 0.0) * normal
    height, normal = surface(effects, pos)
    return normal, jnp.concatenate([pos[:2], jnp.maximum(pos[2:], height + radius)])


def table_contact(table: TableParams, radius, pos, vel, spin, effects=(), edges=True):
    """Post-contact (pos, vel, spin) of a ball touching the table at ``pos``.

    The position is put back on the table (centre one radius from it along the normal) so that a
    ball at rest does not sink through the table step by step. A contact leaving less than
    ``REST_SPEED`` of normal speed is perfectly inelastic (sustained contact).

    Arguments:
        table, radius: table parameters and ball radius; pos, vel, spin: the ball at the contact;
        effects: the model's effects;
        edges: the table is the box (ends, sides, edges); False: the playing surface extended
            as an unbounded plane (for aiming).

    Returns:
        (pos, vel, spin) after the contact.
    """
    normal, pos_c = _geometry(table, effects, radius, pos, edges)
    frame = _frame(normal)
    v_loc, w_loc = local_contact(table, radius, matvec(frame, vel), matvec(frame, spin), effects)
    v_loc = v_loc.at[2].set(jnp.where(v_loc[2] < REST_SPEED, 0.0, v_loc[2]))
    return pos_c, matvec(transpose(frame), v_loc), matvec(transpose(frame), w_loc)


def touching(table: TableParams, effects, radius, pos, vel):
    """Whether a ball is in sustained contact: within CONTACT_SLOP of the table, normal speed
    below REST_SPEED."""
    dist, normal = box_distance(table, effects, pos)
    return (jnp.abs(dist - radius) <= CONTACT_SLOP) & (jnp.abs(dot3(vel, normal)) < REST_SPEED)


def slide(table: TableParams, radius, pos, vel, spin, effects=()):
    """Puts a ball in sustained contact back onto the table after a step of free flight.

    A perfectly inelastic contact (e_n = 0, no residual, no restitution effects; friction effects
    act) in the frame of the contact normal, applied only where the ball has sunk into the table
    moving inwards; a ball that has moved away from the table (over the edge, lifted) is left as
    it is.

    Returns:
        (pos, vel, spin).
    """
    normal, pos_c = _geometry(table, effects, radius, pos, True)
    frame = _frame(normal)
    v_loc, w_loc = matvec(frame, vel), matvec(frame, spin)
    zero = jnp.zeros_like(v_loc[2])
    alpha = sliding_alpha(friction(table, jnp.abs(v_loc[2]), effects), zero, v_loc, w_loc, radius, table.alpha_roll)
    coef = ContactCoefficients(e_n=zero, alpha=jnp.stack([alpha, alpha]), e_s=jnp.ones_like(zero))
    v_c, w_c = apply_matrices(contact_matrices(coef, radius, table.kappa), v_loc, w_loc)
    press = (gap(table, effects, radius, pos) < 0.0) & (v_loc[2] < 0.0)
    return (jnp.where(press, pos_c, pos), jnp.where(press, matvec(transpose(frame), v_c), vel),
            jnp.where(press, matvec(transpose(frame), w_c), spin))


def at_rest(table: TableParams, effects, radius, pos, vel, spin):
    """Whether a ball touching the table has its velocity and its contact point's velocity below
    REST_SPEED."""
    _, normal = box_distance(table, effects, pos)
    frame = _frame(normal)
    u = surface_velocity(matvec(frame, vel), matvec(frame, spin), radius)
    return touching(table, effects, radius, pos, vel) & (safe_norm(vel) < REST_SPEED) & (safe_norm(u) < REST_SPEED)
