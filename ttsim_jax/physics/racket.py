"""Racket contact: the Nakashima base model, its "refined" variant and the paper's updated model.

Racket frame (one convention everywhere, as in the authors' code): x is the face normal, y and z
are tangential, so the contact position on the face is d = (d_y, d_z). The paper writes the base
model with the normal along z; we solve it in the contact frame (y, z, x) (a cyclic permutation of
the racket axes, so still right-handed), where the normal is last as in the table model.

A ball that arrives at the back face (n . (p_ball - p_racket) < 0) sees the frame turned 180 degrees
about the racket z-axis: x -> -x, y -> -y.

Models (``RacketParams.kind``, static):
    nakashima: alpha = k_p / m, constant e_n, racket angular velocity ignored, no spin damping.
    refined:   the same coefficients, with the racket's angular velocity: the surface moves with
               v_R + w_R x r at the contact point and spin is taken relative to w_R.
    updated:   the paper's: e_n = e0 + e1 |v_n|, alpha = (1 + e_t) / (1 + kappa) with
               e_t = et0 + et1 |u_T|, normal spin damping e_s; racket angular velocity included.

The contact point is the point of the face under the ball centre (p_ball - r n). The face is a flat
ellipse: a ball that meets its rim (its centre beyond the outline) has the contact normal from the
rim to its centre, and the contact is solved in the racket frame turned onto that normal
(:func:`facing`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.physics import hooks
from ttsim_jax.physics.contact import ContactCoefficients, apply_matrices, contact_matrices, surface_velocity
from ttsim_jax.physics.numerics import component_norm, dot3, matvec, rotate, safe_divide, safe_norm, transpose

RACKET_KINDS = ("nakashima", "refined", "updated")

# racket frame (x=normal, y, z) -> contact frame (y, z, x) and back; numpy, so that importing the
# module creates no device array (whose integer width would follow jax_enable_x64 at import time)
_TO_CONTACT = np.array([1, 2, 0], dtype=np.int32)
_FROM_CONTACT = np.array([2, 0, 1], dtype=np.int32)


@struct.dataclass
class RacketParams:
    """Racket contact parameters.

    Attributes:
        e0, e1: normal restitution e_n = e0 + e1 |v_n| (e1 = 0 for the baselines), clipped to
            [0, e_max].
        et0, et1: tangential restitution e_t = et0 + et1 |u_T| ("updated"), clipped to [0, 1].
        e_s: factor on the normal spin component ("updated"; 1 = no damping).
        k_p: tangential impulse coefficient [kg] of the base model: alpha = k_p / m.
        kappa: m r^2 / I of the ball.
        e_max: upper clip of e_n.
        kind: ``"nakashima"``, ``"refined"`` or ``"updated"`` (static).
    """

    e0: jnp.ndarray
    e1: jnp.ndarray
    et0: jnp.ndarray
    et1: jnp.ndarray
    e_s: jnp.ndarray
    k_p: jnp.ndarray
    kappa: jnp.ndarray
    e_max: jnp.ndarray
    kind: str = struct.field(pytree_node=False, default="updated")


def uses_racket_spin(params: RacketParams) -> bool:
    return params.kind != "nakashima"


def advance(racket, elapsed):
    """The racket ``elapsed`` seconds on, its face centre moving at ``vel`` and its frame turning at
    ``ang_vel`` about the face centre (``elapsed`` 0 gives the racket exactly)."""
    axes = rotate(elapsed * racket.ang_vel[..., None, :], jnp.swapaxes(racket.rot, -1, -2))  # turned columns
    return racket.replace(pos=racket.pos + elapsed * racket.vel, rot=jnp.swapaxes(axes, -1, -2))


def to_face(racket, vec, elapsed=0.0):
    """A world-frame vector in the racket frame of the racket ``elapsed`` seconds on
    (:func:`advance`; no turn for a Python 0), without forming its rotation matrix (elementwise
    arithmetic only)."""
    no_turn = isinstance(elapsed, (int, float)) and elapsed == 0
    turned, rot = (vec if no_turn else rotate(-elapsed * racket.ang_vel, vec)), racket.rot
    return rot[0] * turned[0] + rot[1] * turned[1] + rot[2] * turned[2]  # rot.T @ turned


def relative_motion(racket, pos, vel, elapsed=0.0):
    """A ball centre's position and velocity in the frame of the face of the racket ``elapsed``
    seconds on (racket frame, relative to the face centre; the frame moves and turns with the face,
    so the velocity is relative to the point of the face frame the ball passes)."""
    rel = pos - racket.pos - elapsed * racket.vel
    v_rel = vel - racket.vel - jnp.cross(racket.ang_vel, rel)
    return to_face(racket, rel, elapsed), to_face(racket, v_rel, elapsed)


def face_offset(local, face):
    """(3,) racket-frame vector from the nearest point of the face to the point ``local`` (racket
    frame, relative to the face centre); its length is the point's distance from the face.

    The face is a flat ellipse of semi-axes ``face`` (along racket y, z). Beyond the outline the
    in-plane distance is Sampson's first-order estimate (f - 1) / |grad f| of the ellipse norm f:
    exact for a circular face and near the rim of an elliptic one, where contacts are. Written in
    components (no reductions), since it runs many times in each contact search.
    """
    sy, sz = local[1] / face[0], local[2] / face[1]
    gy, gz = sy / face[0], sz / face[1]  # f grad f
    f, g = component_norm(sy, sz), component_norm(gy, gz)
    scale = jnp.maximum(safe_divide((f - 1.0) * f, g * g, 0.0), 0.0)  # beyond / |f grad f|
    return jnp.stack([local[0], scale * gy, scale * gz])


def facing(racket, pos):
    """The racket with its frame turned so that its normal (on ``pos``'s side) points from the
    nearest point of the face to ``pos``: unchanged over the face; beyond the outline tilted by the
    angle t = atan(beyond / height) towards the rim, about the rim's tangent, so that a ball meeting
    the rim gets a face contact along the rim's normal.

    The turn T (racket frame), for the outward unit direction (g_y, g_z) and s = +-1 the side:
    T x = (cos t, s g_y sin t, s g_z sin t), T y = (-s g_y sin t, cos t + g_z^2 (1 - cos t),
    -g_y g_z (1 - cos t)), T z = (-s g_z sin t, -g_y g_z (1 - cos t), cos t + g_y^2 (1 - cos t)):
    the identity exactly over the face.
    """
    h, ry, rz = face_offset(to_face(racket, pos - racket.pos), racket.face)
    s = jnp.where(h >= 0.0, 1.0, -1.0).astype(pos.dtype)
    beyond = component_norm(ry, rz)
    dist = component_norm(h, beyond)
    cos, sin = safe_divide(jnp.abs(h), dist, 1.0), safe_divide(beyond, dist, 0.0)
    gy, gz = safe_divide(ry, beyond, 0.0), safe_divide(rz, beyond, 0.0)
    ver = 1.0 - cos
    turn = jnp.stack([jnp.stack([cos, -s * gy * sin, -s * gz * sin]),
                      jnp.stack([s * gy * sin, cos + gz * gz * ver, -gy * gz * ver]),
                      jnp.stack([s * gz * sin, -gy * gz * ver, cos + gy * gy * ver])])
    rot = racket.rot
    return racket.replace(rot=rot[:, :1] * turn[0] + rot[:, 1:2] * turn[1] + rot[:, 2:] * turn[2])  # rot @ turn


def contact_frame(racket, pos):
    """(rot, side): the racket frame turned to face the ball, and +1 / -1 for front / back face."""
    n = racket.rot[:, 0]
    side = jnp.where(dot3(n, pos - racket.pos) >= 0.0, 1.0, -1.0).astype(pos.dtype)
    flip = jnp.stack([side, side, jnp.ones_like(side)])
    return racket.rot * flip[None, :], side


def racket_frame_state(params: RacketParams, racket, radius, pos, vel, spin):
    """The ball's pre-contact state in the racket frame.

    Returns:
        dict with ``v`` (3,) velocity relative to the face at the contact point, ``w`` (3,) spin
        relative to the racket, ``d`` (2,) contact position on the face, ``rot`` (3, 3) the
        (possibly turned) racket frame, ``v_surf`` and ``w_surf`` (3,) the face's world-frame
        velocity at the contact point and the racket spin used (zero for "nakashima").
    """
    rot, side = contact_frame(racket, pos)
    n = rot[:, 0]
    offset = pos - radius * n - racket.pos  # contact point relative to the face centre
    w_surf = racket.ang_vel if uses_racket_spin(params) else jnp.zeros_like(racket.ang_vel)
    v_surf = racket.vel + jnp.cross(w_surf, offset)
    local = matvec(transpose(rot), offset)
    return dict(v=matvec(transpose(rot), vel - v_surf), w=matvec(transpose(rot), spin - w_surf), d=local[1:3], rot=rot,
                v_surf=v_surf, w_surf=w_surf)


def coefficients(params: RacketParams, v_c, w_c, radius, mass, d, effects=()):
    """Contact coefficients for a contact-frame pre-contact state (normal last)."""
    u = surface_velocity(v_c, w_c, radius)
    vn = jnp.abs(v_c[2])
    e_n = jnp.clip(params.e0 + params.e1 * vn, 0.0, params.e_max)
    if params.kind == "updated":
        e_t = jnp.clip(params.et0 + params.et1 * safe_norm(u), 0.0, 1.0)
        alpha = (1.0 + e_t) / (1.0 + params.kappa)
        e_s = params.e_s
    else:
        alpha = params.k_p / mass
        e_s = jnp.ones_like(e_n)
    coef = ContactCoefficients(e_n=e_n, alpha=jnp.stack([alpha, alpha]), e_s=e_s)
    return hooks.apply(effects, "racket_coefficients", coef, d=d, vn=vn, ut=u[:2])


def base_response(params: RacketParams, v_tilde, w_tilde, d, radius, mass, effects=()):
    """Post-contact racket-frame (v, w) predicted by the base model (no residual network).

    Arguments:
        params: racket parameters.
        v_tilde, w_tilde: (3,) pre-contact velocity and spin in the racket frame, relative to the
            face (x = normal; v_tilde[0] < 0 for a ball arriving at the face).
        d: (2,) contact position on the face [m] (used by effects only).
        radius, mass: ball radius [m] and mass [kg].
        effects: tuple of effects (hook ``racket_coefficients``).

    Returns:
        (v_plus, w_plus) in the racket frame.
    """
    v_c, w_c = v_tilde[_TO_CONTACT], w_tilde[_TO_CONTACT]
    coef = coefficients(params, v_c, w_c, radius, mass, d, effects)
    v_p, w_p = apply_matrices(contact_matrices(coef, radius, params.kappa), v_c, w_c)
    return v_p[_FROM_CONTACT], w_p[_FROM_CONTACT]


def network_input(state):
    """The residual network's input x = (v~, w~, d) (8,) from :func:`racket_frame_state`.

    A 6-input network (durr2026) takes the first six entries.
    """
    return jnp.concatenate([state["v"], state["w"], state["d"]])


def racket_contact(params: RacketParams, racket, radius, mass, pos, vel, spin, effects=()):
    """Base-model racket contact in the world frame.

    Returns:
        (vel+, spin+, state) with ``state`` from :func:`racket_frame_state`, which the rally
        kernel uses to add the residual network's racket-frame correction.
    """
    state = racket_frame_state(params, racket, radius, pos, vel, spin)
    v_p, w_p = base_response(params, state["v"], state["w"], state["d"], radius, mass, effects)
    rot = state["rot"]
    return matvec(rot, v_p) + state["v_surf"], matvec(rot, w_p) + state["w_surf"], state
