"""Racket states that make a wanted shot: the plain contact model inverted, then corrected through the truth.

A player of the reality generator picks the ball it wants to play (velocity and spin) and needs
the racket state that gives it. :func:`invert_contact` solves for that state under the *plain*
contact model of the model the player believes (exact for it); :func:`true_contact` then corrects
the racket velocity through the *true* contact, with the truth model's effects, so that the ball
leaves at the aimed velocity (the players know their equipment). :func:`invert_batch` and
:func:`true_contact_batch` are their compiled batches.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ttsim_jax.kernel import ball_properties
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.numerics import safe_norm, safe_unit
from ttsim_jax.state import Racket


def _normal_for(dv, dw, k):
    """(n, a): unit normal and a = Dv . n with Dv = a n + k n x Dw (Newton from n = Dv / |Dv|)."""
    dtype = dv.dtype

    def residual(x):
        n, a = x[:3], x[3]
        return jnp.concatenate([a * n + k * jnp.cross(n, dw) - dv, (jnp.dot(n, n) - 1.0)[None]])

    x = jnp.concatenate([safe_unit(dv, jnp.array([1.0, 0.0, 0.0], dtype)), safe_norm(dv)[None]])
    for _ in range(8):
        jac = jax.jacfwd(residual)(x)
        ok = jnp.abs(jnp.linalg.det(jac)) > 1e-12
        x = x - jnp.where(ok, jnp.linalg.solve(jnp.where(ok, jac, jnp.eye(4, dtype=dtype)), residual(x)), 0.0)
    n = safe_unit(x[:3], jnp.array([1.0, 0.0, 0.0], dtype))
    return n, jnp.dot(dv, n), safe_norm(residual(x)[:3])


def invert_contact(params, radius, mass, pos, v_in, w_in, v_out, w_out, d, roll, ang_vel, max_spin_ratio=0.8):
    """A racket state that turns (v_in, w_in) into (v_out, w_out) under the plain contact model.

    Arguments:
        params: :class:`~ttsim_jax.physics.racket.RacketParams` of the model the player believes.
        radius, mass: ball radius [m] and mass [kg] of that model.
        pos: (3,) ball centre at the contact.
        v_in, w_in: (3,) incoming velocity and spin.
        v_out, w_out: (3,) wanted outgoing velocity and spin. Only the spin's tangential part can
            be chosen, and only as much of its change as a point contact can give
            (|Dw| r / kappa <= max_spin_ratio |Dv|; less if that has no solution).
        d: (2,) contact point on the face (d_y, d_z) [m].
        roll: angle [rad] of the racket's z-axis (handle -> tip) about the normal, from "up".
        ang_vel: (3,) racket angular velocity [rad/s].

    Returns:
        dict with ``pos``, ``rot`` (columns: normal, y, z), ``vel``, ``ang_vel`` of the racket.

    The point contact changes the spin by (kappa / r) Dv_t x n, so the tangential velocity change
    fixes the normal: Dv = a n + (r / kappa) n x Dw with a > 0 (Newton). The normal racket speed
    then follows from v_n+ = -e_n v_n- and the tangential one from Dv_t = -alpha u- (u: slip
    velocity of the contact point), with e_n(|v_n|) and alpha(|u|) solved in closed form (they are
    linear laws, clipped). The outgoing velocity is then exact for the plain model.
    """
    dtype = pos.dtype
    kappa = params.kappa
    k = radius / kappa
    dv = v_out - v_in
    dw = w_out - w_in
    ndv = safe_norm(dv)
    cap = jnp.minimum(1.0, max_spin_ratio * ndv / jnp.maximum(k * safe_norm(dw), 1e-9))
    # the full (capped) spin change, half of it, or none: the first whose solution has the ball
    # arriving at the face (a well above 0) is used
    sols = [_normal_for(dv, dw * cap * f, k) for f in (1.0, 0.5, 0.0)]
    n, a = sols[2][0], sols[2][1]
    for cand_n, cand_a, res in reversed(sols[:2]):
        good = (cand_a > 0.3 * ndv) & (res < 1e-3 * (1.0 + ndv))
        n, a = jnp.where(good, cand_n, n), jnp.where(good, cand_a, a)

    up = jnp.array([0.0, 0.0, 1.0], dtype)
    ref = jnp.where(jnp.abs(n[2]) > 0.95, jnp.array([1.0, 0.0, 0.0], dtype), up)
    z0 = safe_unit(ref - jnp.dot(ref, n) * n, up)
    y0 = jnp.cross(z0, n)
    z_axis = jnp.cos(roll) * z0 + jnp.sin(roll) * y0
    y_axis = jnp.cross(z_axis, n)
    rot = jnp.stack([n, y_axis, z_axis], axis=1)
    offset = d[0] * y_axis + d[1] * z_axis
    racket_pos = pos - radius * n - offset

    # e = e0 + e1 |v_n-| with |v_n-| = a / (1 + e): e^2 + (1 - e0) e - (e0 + e1 a) = 0, clipped
    disc = (1.0 - params.e0) ** 2 + 4.0 * (params.e0 + params.e1 * a)
    e = jnp.clip(0.5 * (-(1.0 - params.e0) + jnp.sqrt(jnp.maximum(disc, 0.0))), 0.0, params.e_max)
    vs_n = jnp.dot(v_in, n) + a / (1.0 + e)

    w_surf = ang_vel if racket_stage.uses_racket_spin(params) else jnp.zeros_like(ang_vel)
    w_rel = w_in - w_surf
    dv_t = dv - a * n
    ndv_t = safe_norm(dv_t)
    if params.kind == "updated":
        # alpha = (1 + e_t) / (1 + kappa), e_t = et0 + et1 |u|, |u| = |Dv_t| / alpha: a quadratic in |u|
        c = ndv_t * (1.0 + kappa)
        b = 1.0 + params.et0
        small = jnp.abs(params.et1) < 1e-12
        disc = b * b + 4.0 * params.et1 * c
        s = jnp.where(small, c / b, (-b + jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.where(small, 1.0, 2.0 * params.et1))
        e_t = jnp.clip(params.et0 + params.et1 * s, 0.0, 1.0)
        alpha = (1.0 + e_t) / (1.0 + kappa)
    else:
        alpha = params.k_p / mass
    u = -dv_t / alpha
    v_in_t = v_in - jnp.dot(v_in, n) * n
    vs = v_in_t + radius * jnp.cross(n, w_rel) - u + vs_n * n
    vel = vs - jnp.cross(w_surf, offset)
    return dict(pos=racket_pos, rot=rot, vel=vel, ang_vel=ang_vel)


@jax.jit
def invert_batch(params, radius, mass, pos, v_in, w_in, v_out, w_out, d, roll, ang_vel):
    """:func:`invert_contact` of a batch: every argument from ``pos`` on has a leading batch axis."""
    return jax.vmap(invert_contact, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0, 0, 0))(
        params, radius, mass, pos, v_in, w_in, v_out, w_out, d, roll, ang_vel)


def true_contact(model, rpos, rrot, rvel, rang, face, pos, vel, spin, v_target, iters):
    """The truth model's racket contact, after ``iters`` Newton steps on the racket velocity.

    The players know their equipment: the racket velocity from the plain-model inversion is
    corrected through the true contact (with the model's effects) until the outgoing velocity is
    ``v_target`` (the face orientation, and so the spin, is left as inverted).

    Returns:
        (racket velocity, outgoing velocity, outgoing spin, contact point d (2,)).
    """
    radius, mass = ball_properties(model)

    def contact(rv):
        racket = Racket(pos=rpos, rot=rrot, vel=rv, ang_vel=rang, face=face)
        return racket_stage.racket_contact(model.racket, racket, radius, mass, pos, vel, spin, model.effects)

    def newton(_, rv):
        jac = jax.jacfwd(lambda r: contact(r)[0])(rv)
        ok = jnp.abs(jnp.linalg.det(jac)) > 1e-9
        step = jnp.linalg.solve(jnp.where(ok, jac, jnp.eye(3, dtype=rv.dtype)), contact(rv)[0] - v_target)
        return rv - jnp.where(ok, jnp.clip(step, -5.0, 5.0), 0.0)

    rvel = jax.lax.fori_loop(0, iters, newton, rvel)
    v, w, state = contact(rvel)
    return rvel, v, w, state["d"]


@jax.jit
def true_contact_batch(models, rpos, rrot, rvel, rang, face, pos, vel, spin, v_target, iters):
    """:func:`true_contact` of a batch: ``models`` and every argument but ``face`` and ``iters`` are batched."""
    return jax.vmap(true_contact, in_axes=(0, 0, 0, 0, 0, None, 0, 0, 0, 0, None))(
        models, rpos, rrot, rvel, rang, face, pos, vel, spin, v_target, iters)
