"""The "intercept" action mode of ReturnBall: a scripted tracker moves the racket to the ball, the
policy chooses the stroke.

As in robot table tennis systems (a hitting-point predictor plus a stroke), each control step

1. :func:`predict` extrapolates the observed ball to its hit point (``[intercept]`` of the task
   file): flight to the table, a bounce with the task model's nominal ``table.e0`` (horizontal
   velocity kept; a bounce on the opponent's half, a serve's first, is followed to the next one),
   then flight to the hitting plane ``x = x_hit``, or, for a short ball that would sink below
   ``min_height`` above the playing surface before that plane (bouncing a second time on the
   agent's half), to where it sinks through ``min_height`` (its apex if it never rises that high),
   but not before the workspace's near end ``x_min`` (over the table). Each flight is closed-form at
   a constant acceleration: gravity alone, or with ``air = true`` gravity plus the model's drag and
   Magnus force at its velocity a third of the way through (two passes; the spin is held). The
   bounce's friction is left out unless ``bounce = "model"`` (then the model's table contact with
   the observed spin).
   Re-predicting every 10 ms from the current ball makes the remaining errors shrink as the ball
   nears, and after the bounce on the agent's half only the short last flight is extrapolated;
2. :func:`mirror` gives the stroke that sends that ball to the task's target point: the face
   normal and normal speed that turn the predicted incoming velocity (and the observed spin) into
   the arc of a chosen flight time (with the ball's drag and, with ``magnus = true``, the Magnus
   force of the spin the stroke gives it), through the kernel's racket contact model with the
   nominal ``racket.e0`` / ``et0`` (the "mirror law" of robot table tennis, with the face's grip);
   :func:`stroke` maps the policy's action (5,) in [-1, 1] linearly onto adjustments of it: the
   return's flight time (``flight_time`` range: short is fast and flat), offsets of the hit point
   in y and z (``offset_y``, ``offset_z``), and offsets of the face's pitch and yaw (``pitch``,
   ``yaw``). Action 0 is the mirror law's stroke with the middle flight time;
3. :func:`track` turns that stroke into the acceleration command of the kinematic racket
   (:mod:`.racket`, whose speed, acceleration and workspace limits still apply): a critically
   damped PD (natural frequency ``omega``) with velocity feed-forward on a reference that waits
   ``swing_time`` of the stroke's velocity behind the hit point and, in the last ``swing_time``
   before the predicted hit, moves through it at that velocity (so the racket arrives at the
   predicted time moving with the stroke); the face angles are driven by the same PD to the
   stroke's angles. Before a prediction exists, when the ball has passed the plane, and after the
   contact, the racket returns to its start position with a level face.

Everything is elementwise over the batch, branch-free and closed-form (a fixed number
of fixed-point steps; no data-dependent loop).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.env.racket import clip_workspace, rotation
from ttsim_jax.physics import aero as aero_stage
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics import table as table_stage
from ttsim_jax.physics.numerics import component_norm, safe_norm, safe_sqrt
from ttsim_jax.state import Racket

if TYPE_CHECKING:
    from ttsim_jax.env.config import TaskConfig
    from ttsim_jax.params import Model

# Fixed-point steps of the mirror law's normal (each shrinks its error about threefold).
MIRROR_STEPS = 8
# Passes of the mirror law with the return's spin acceleration (each re-plans the arc with the
# spin its previous stroke gives the ball).
SPIN_STEPS = 3
# Slowest ball (towards the agent, [m/s]) for which a crossing of the hitting plane is predicted.
MIN_SPEED = 0.2
# The least downward acceleration of a predicted flight with air, as a fraction of gravity.
MIN_FALL = 0.25


@struct.dataclass
class InterceptParams:
    """The tracker's settings (``[intercept]`` of the task file, arrays).

    Attributes:
        x_hit: hitting plane [m]; flight: (2,) range of the return's flight time [s]; offset: (2,)
        largest y and z offsets of the hit point [m]; angle: (2,) largest pitch and yaw offsets
        [rad]; swing_time: [s]; omega: the tracking loop's natural frequency [rad/s]; min_height: a
        short ball is met before it sinks below this height [m]; x_min: the workspace's near end
        [m] (the earliest hit point along x); drag: the ball's drag deceleration per squared speed
        [1/m] (:func:`arc_velocity`); e_table,
        e_racket: restitutions of the predicted bounce and stroke (e0 of the racket's); e_slope: the
        racket's e1 [s/m]; grip, grip_slope: the face's tangential grip (1 + et0) / (1 + kappa) and
        et1 / (1 + kappa) [s/m] (:func:`mirror`); gravity: [m/s^2] (positive);
        radius: ball [m]; table: the model's :class:`~ttsim_jax.physics.table.TableParams` to
        predict each bounce with its contact model (spin, friction and residual matrices), or None
        for the plain bounce (vertical speed times ``e_table``, horizontal velocity and spin kept);
        aero, contact, mass, face: the model's :class:`~ttsim_jax.physics.aero.AeroParams` and
        :class:`~ttsim_jax.physics.racket.RacketParams`, the ball's mass [kg] and the face's
        semi-axes [m], to plan the return's arc with the Magnus force of the spin the stroke gives it
        (:func:`mirror`), or None (aero) to leave it out; air: the model's
        :class:`~ttsim_jax.physics.aero.AeroParams` to predict the incoming ball's flight with its
        drag and Magnus force (:func:`predict`), or None for drag-free flight.
    """

    x_hit: jnp.ndarray
    flight: jnp.ndarray
    offset: jnp.ndarray
    angle: jnp.ndarray
    swing_time: jnp.ndarray
    omega: jnp.ndarray
    min_height: jnp.ndarray
    x_min: jnp.ndarray
    drag: jnp.ndarray
    e_table: jnp.ndarray
    e_racket: jnp.ndarray
    e_slope: jnp.ndarray
    grip: jnp.ndarray
    grip_slope: jnp.ndarray
    gravity: jnp.ndarray
    radius: jnp.ndarray
    table: object = None
    aero: object = None
    contact: object = None
    mass: jnp.ndarray = None
    face: jnp.ndarray = None
    air: object = None


def _accel(p: InterceptParams, vel, spin):
    """(B, 3) the constant acceleration a predicted flight at velocity ``vel`` is given: gravity, and
    with ``p.air`` the model's whole aerodynamic acceleration (drag, Magnus) at that velocity, its
    vertical part held at least ``MIN_FALL`` downwards (a backspin ball whose lift nearly cancels
    gravity still comes down: its drag slows it and its lift with it)."""
    if p.air is None:
        return jnp.broadcast_to(jnp.array([0.0, 0.0, -1.0], vel.dtype) * p.gravity, vel.shape)
    zero = jnp.zeros(3, vel.dtype)
    acc = jax.vmap(lambda v, w: aero_stage.acceleration(p.air, p.radius, p.mass, zero, v, w, 0.0))(vel, spin)
    return acc.at[:, 2].set(jnp.minimum(acc[:, 2], -MIN_FALL * p.gravity))


def _fall(pos, vel, acc, z):
    """(time until the centre falls to height z, position, velocity then) of flight at the constant
    acceleration ``acc`` (B, 3) (its z part negative); (B,), (B, 3), (B, 3). A ball already below z
    lands at once; one that never rises to z is taken to its apex."""
    down = -acc[:, 2]
    t = jnp.maximum((vel[:, 2] + safe_sqrt(vel[:, 2] ** 2 + 2.0 * down * (pos[:, 2] - z))) / down, 0.0)
    return t, _fly(pos, vel, acc, t)


def _reach(pos, vel, acc, x):
    """(B,) time until the ball reaches x = ``x`` along the table at constant acceleration (negative
    if it is past it; a ball that stops short is given the time a constant speed would take)."""
    gap = x - pos[:, 0]
    speed = jnp.where(vel[:, 0] > MIN_SPEED, vel[:, 0], 1.0)
    disc = speed ** 2 + 2.0 * acc[:, 0] * gap
    root = jnp.where(disc > 0.0, safe_sqrt(disc), speed)
    return 2.0 * gap / (speed + root)


def _fly(pos, vel, acc, t):
    """(position, velocity) after flight at the constant acceleration ``acc`` (B, 3) for times t (B,)."""
    tt = t[:, None]
    return pos + vel * tt + 0.5 * acc * tt * tt, vel + acc * tt


def _flight(p: InterceptParams, pos, vel, spin, when):
    """(time, position, velocity, acceleration) of a predicted flight that lasts ``when(acc)``
    (B,): one pass with gravity alone, or with ``p.air`` two, the second at the aerodynamic
    acceleration of the first pass's velocity a third of the way through the flight. An
    acceleration a(s) changing linearly over a flight of duration T moves the ball as its value at
    T / 3 would (the position weighs a(s) by T - s): so the vertical drag, downwards while the ball
    rises and upwards as it falls, is not averaged away (2 cm of height over a 0.25 s flight)."""
    acc = _accel(p, vel, spin)
    t = when(acc)
    if p.air is not None:
        _, v_end = _fly(pos, vel, acc, t)
        acc = _accel(p, vel + (v_end - vel) / 3.0, spin)
        t = when(acc)
    return (t,) + _fly(pos, vel, acc, t) + (acc,)


def _bounce(p: InterceptParams, pos, vel, spin):
    """(velocity, spin) (B, 3) just after a bounce at ``pos``."""
    if p.table is None:
        keep, up = jnp.array([1.0, 1.0, 0.0], vel.dtype), jnp.array([0.0, 0.0, 1.0], vel.dtype)
        return vel * keep - p.e_table * vel * up, spin

    def one(x, v, w):
        # the playing surface as an unbounded plane: a bounce predicted just past an edge still comes back up
        return table_stage.table_contact(p.table, p.radius, x, v, w, edges=False)[1:]

    return jax.vmap(one)(pos, vel, spin)


def predict(p: InterceptParams, pos, vel, bounced, spin=None):
    """Where and when the racket should meet the ball after its bounce on the agent's half: where it
    crosses the hitting plane ``x_hit``, or earlier where it sinks through ``min_height`` (at its
    apex if it never rises that high), but not before ``x_min``.

    The hit comes at ``min(t_plane, max(t_low, t_min))`` after the bounce: t_plane, t_min the times
    the ball reaches x = x_hit and x = x_min, t_low the time it sinks through min_height. A long
    ball (still above min_height at the plane) is met at the plane; a short one, whose second bounce
    on the agent's half would come before the plane, above the table before that bounce.

    Arguments:
        p: :class:`InterceptParams`; pos, vel: (B, 3) ball state; bounced: (B,) the ball already
            bounced on the agent's half; spin: (B, 3) (zero if None; flight keeps it; the flight
            with ``p.air`` and the bounce with ``p.table`` read it).

    Returns:
        (point (B, 3) [m], velocity there (B, 3) [m/s], time from now (B,) [s], valid (B,): the ball
        flies towards the agent and has not passed the plane; elsewhere the others are finite but
        meaningless).
    """
    z = p.radius
    spin = jnp.zeros_like(vel) if spin is None else spin
    t1, p1, v1, _ = _flight(p, pos, vel, spin, lambda a: _fall(pos, vel, a, z)[0])
    v1, w1 = _bounce(p, p1, v1, spin)
    # a bounce on the opponent's half (a serve's first) is followed to the next one, on the agent's
    t2, p2, v2, _ = _flight(p, p1, v1, w1, lambda a: _fall(p1, v1, a, z)[0])
    v2, w2 = _bounce(p, p2, v2, w1)
    serve = (p1[:, 0] < 0.0)[:, None]
    pb, vb, tb = jnp.where(serve, p2, p1), jnp.where(serve, v2, v1), jnp.where(serve[:, 0], t1 + t2, t1)
    wb = jnp.where(serve, w2, w1)
    after = bounced[:, None]
    pb, vb, tb = jnp.where(after, pos, pb), jnp.where(after, vel, vb), jnp.where(bounced, 0.0, tb)
    wb = jnp.where(after, spin, wb)

    def when(acc):
        # _fall's clamped root is the apex for a ball that never rises to min_height, 0 for one below it and falling
        t_low, _ = _fall(pb, vb, acc, p.min_height)
        return jnp.minimum(_reach(pb, vb, acc, p.x_hit), jnp.maximum(t_low, _reach(pb, vb, acc, p.x_min)))

    th, point, v_hit, acc = _flight(p, pb, vb, wb, when)
    t_plane = _reach(pb, vb, acc, p.x_hit)
    valid = (vb[:, 0] > MIN_SPEED) & (t_plane >= 0.0) & jnp.isfinite(t_plane + tb + th)
    keep = valid[:, None]
    return jnp.where(keep, point, pos), jnp.where(keep, v_hit, vel), jnp.where(valid, tb + th, 0.0), valid


def stroke(p: InterceptParams, action):
    """The stroke settings of a policy action.

    Arguments:
        p: :class:`InterceptParams`; action: (B, 5) in [-1, 1] (non-finite entries count as 0).

    Returns:
        (return flight time (B,) [s], hit point offset (B, 3) [m] (x offset 0), face angle offsets
        (B, 2) [rad] from the mirror law's).
    """
    a = jnp.clip(jnp.where(jnp.isfinite(action), action, 0.0), -1.0, 1.0)
    flight = p.flight[0] + 0.5 * (a[:, 0] + 1.0) * (p.flight[1] - p.flight[0])
    offset = jnp.stack([jnp.zeros_like(a[:, 1]), a[:, 1] * p.offset[0], a[:, 2] * p.offset[1]], -1)
    return flight, offset, a[:, 3:5] * p.angle


def arc_velocity(d, tau, g, drag, extra=None):
    """Start velocity (B, 3) of the arc that covers the displacement ``d`` (B, 3) in ``tau`` (B, 1)
    seconds under gravity ``g`` (down), a constant acceleration ``extra`` (B, 3) (none if None) and
    a linear drag ``-c v`` standing for the quadratic one, ``c = drag * |d| / tau`` (drag [1/m]
    times the mean speed).

    With x = c tau and A the constant acceleration: ``d = v0 tau f1 - A tau^2 f2`` where
    ``f1 = (1 - e^-x) / x`` and ``f2 = (f1 - 1) / x``
    (Taylor series below x = 0.01, where the closed forms lose digits); drag 0 gives the parabola's
    ``d / tau + (0, 0, g tau / 2)``.
    """
    x = drag * safe_norm(d, keepdims=True)
    small = x < 1e-2
    xs = jnp.where(small, 1.0, x)
    f1 = jnp.where(small, 1.0 - x / 2.0 + x * x / 6.0, -jnp.expm1(-xs) / xs)
    f2 = jnp.where(small, -0.5 + x / 6.0 - x * x / 24.0, (f1 - 1.0) / xs)
    accel = g * jnp.array([0.0, 0.0, -1.0], d.dtype)
    if extra is not None:
        accel = accel + extra
    return (d / tau + accel * tau * f2) / f1


def mirror(p: InterceptParams, point, v_in, spin, target, flight):
    """The racket's face normal and velocity that send a ball meeting it at ``point`` with velocity
    ``v_in`` and spin ``spin`` to land on ``target`` after ``flight`` seconds (on the arc of
    :func:`arc_velocity`: gravity and the drag of ``p.drag``, and with ``p.aero`` the spin's share of
    the aerodynamic force, Magnus chiefly, held at its mean over the flight).

    The kernel's racket contact (point contact, face moving along its normal, not turning) changes
    the ball's velocity by ``n (1 + e) (V - v_in.n) - grip * P (v_in + r n x spin)``, P the projection
    onto the face, ``grip = (1 + et0 + et1 |u|) / (1 + kappa)`` (u = P (...), the tangential slip) and
    ``e = e0 + e1 s``, s = V - v_in.n the normal approach speed (the racket model "updated"); the
    normal n along ``v_out - v_in + grip * P (...)`` (P depends on n) is found by ``MIRROR_STEPS``
    fixed-point steps, then s from ``(1 + e0 + e1 s) s`` = the normal change (a quadratic).

    With ``p.aero`` the stroke is planned ``SPIN_STEPS`` times: each pass gives the ball the spin
    of the previous stroke (the kernel's racket contact) and adds to the arc the acceleration that
    spin causes at the arc's mean velocity ``d / flight`` (the Magnus force is linear in the
    velocity, so that is its mean over a flight at constant C_M and spin).

    Arguments:
        p: :class:`InterceptParams`; point, v_in, spin: (B, 3); target: (2,) or (B, 2) landing point (x, y);
        flight: (B,) [s].

    Returns:
        (face angles (pitch, yaw) (B, 2) [rad] of :func:`~ttsim_jax.env.racket.rotation`, racket
        velocity (B, 3) [m/s]).
    """
    tau = flight[:, None]
    land = jnp.concatenate([jnp.broadcast_to(target, point[:, :2].shape), jnp.full_like(point[:, 2:], p.radius)], -1)
    d = land - point
    angle, v_racket = _invert(p, v_in, spin, arc_velocity(d, tau, p.gravity, p.drag))
    for _ in range(SPIN_STEPS - 1 if p.aero is not None else 0):
        extra = _spin_acceleration(p, point, v_in, spin, angle, v_racket, d / tau)
        angle, v_racket = _invert(p, v_in, spin, arc_velocity(d, tau, p.gravity, p.drag, extra))
    return angle, v_racket


def _spin_acceleration(p: InterceptParams, point, v_in, spin, angle, v_racket, v_mean):
    """(B, 3) the acceleration the spin that the stroke (``angle``, ``v_racket``) gives the ball adds
    to its flight at velocity ``v_mean``: the aerodynamic acceleration with that spin minus without."""
    def one(x, v, w, a, vr, vm):
        rot = rotation(a)
        face = Racket(pos=x - p.radius * rot[:, 0], rot=rot, vel=vr, ang_vel=jnp.zeros_like(vr), face=p.face)
        _, w_out, _ = racket_stage.racket_contact(p.contact, face, p.radius, p.mass, x, v, w)
        acc = lambda ww: aero_stage.acceleration(p.aero, p.radius, p.mass, x, vm, ww, 0.0)  # noqa: E731
        return acc(w_out) - acc(jnp.zeros_like(w_out))

    return jax.vmap(one)(point, v_in, spin, angle, v_racket, v_mean)


def _invert(p: InterceptParams, v_in, spin, v_out):
    """(face angles (B, 2), racket velocity (B, 3)) of the stroke that turns ``v_in`` into ``v_out``
    (the fixed-point inversion of the contact described in :func:`mirror`).

    Written over per-ball columns ((B,) arrays, one per component): a batch of 3-vectors made each
    dot product and norm a reduction of its own (a pass over the batch each, some 80 per stroke),
    and written out over slices of them, the unrolled steps were fused into one loop that
    recomputed every earlier step once per component. The fixed-point steps are a loop of static
    length, so each step's normal is computed once."""
    vi, w, vo = (jnp.unstack(a, axis=-1) for a in (v_in, spin, v_out))
    r = p.radius

    def dot(a, b):
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    def unit(d):
        size = jnp.maximum(component_norm(*d), 1e-6)
        return tuple(c / size for c in d)

    def change(n):
        # the face's grip acts on the tangential slip u = P (v_in + r n x spin)
        u = (vi[0] + r * (n[1] * w[2] - n[2] * w[1]), vi[1] + r * (n[2] * w[0] - n[0] * w[2]),
             vi[2] + r * (n[0] * w[1] - n[1] * w[0]))
        along = dot(u, n)
        u = tuple(a - along * b for a, b in zip(u, n))
        grip = jnp.maximum(p.grip + p.grip_slope * component_norm(*u), 0.0)
        return tuple(o - i + grip * a for o, i, a in zip(vo, vi, u))

    n = jax.lax.fori_loop(0, MIRROR_STEPS, lambda _, n: unit(change(n)), unit(tuple(o - i for o, i in zip(vo, vi))))
    push = dot(change(n), n)
    # e1 s^2 + (1 + e0) s - push = 0, the root that tends to push / (1 + e0) as e1 -> 0
    a = 1.0 + p.e_racket
    s = 2.0 * push / (a + safe_sqrt(a * a + 4.0 * p.e_slope * push))
    speed = s + dot(vi, n)
    # rotation(angle)[:, 0] = (-cos p cos y, -cos p sin y, sin p)
    angle = jnp.stack([jnp.arcsin(jnp.clip(n[2], -1.0, 1.0)), jnp.arctan2(-n[1], -n[0])], -1)
    return angle, jnp.stack([speed * c for c in n], -1)


def track(p: InterceptParams, limits, start, target, racket, prediction, ball_spin, hit, action):
    """The racket's acceleration command (as :func:`~ttsim_jax.env.racket.command` reads it) for a
    policy action in intercept mode.

    Arguments:
        p: :class:`InterceptParams`; limits: :class:`~ttsim_jax.env.racket.RacketLimits`; start: (3,)
        the racket's rest position; target: (2,) or (B, 2) the return's target point (x, y);
        racket: :class:`~ttsim_jax.env.racket.RacketState` (B, ...); prediction: :func:`predict` of
        the observed ball (point, velocity, time, valid); ball_spin: (B, 3) its observed spin (0 where
        it is not observed); hit: (B,) the racket met the ball; action: (B, 5).

    Returns:
        (B, 5) accelerations of the face centre and angles as fractions of their limits, in [-1, 1].
    """
    point, v_in, t_hit, valid = prediction
    flight, offset, angle_offset = stroke(p, action)
    angle, swing = mirror(p, point, v_in, ball_spin, target, flight)
    swing = jnp.clip(swing, -limits.max_speed, limits.max_speed)
    go = (valid & ~hit)[:, None]
    # the swing: at the racket's velocity through the hit point during the last swing_time
    lead = jnp.minimum(t_hit, p.swing_time)[:, None]
    ref = clip_workspace(limits, jnp.where(go, point + offset - swing * lead, start))
    ref_v = jnp.where(go & (t_hit < p.swing_time)[:, None], swing, 0.0)
    k, c = p.omega ** 2, 2.0 * p.omega  # critically damped
    accel = k * (ref - racket.pos) + c * (ref_v - racket.vel)
    angle = jnp.clip(jnp.where(go, angle + angle_offset, 0.0), limits.angle_lo, limits.angle_hi)
    angle_accel = k * (angle - racket.angle) - c * racket.rate
    out = jnp.concatenate([accel / limits.max_accel, angle_accel / limits.max_angle_accel], -1)
    return jnp.clip(jnp.nan_to_num(out), -1.0, 1.0)


def intercept_params(model: Model, config: TaskConfig) -> InterceptParams:
    """The tracker's settings of a task (``[intercept]``; the predicted bounce and stroke use the model's
    nominal ``table.e0`` and racket contact coefficients, the return's arc its drag)."""
    c = config.intercept
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return InterceptParams(
        x_hit=f32(c.x_hit), flight=f32(c.flight_time), offset=f32([c.offset_y, c.offset_z]),
        angle=f32([c.pitch, c.yaw]), swing_time=f32(c.swing_time), omega=f32(c.omega),
        min_height=f32(c.min_height), x_min=f32(config.racket.workspace_lo[0]),
        drag=f32(drag_per_speed2(model)), e_table=f32(model.table.e0), e_racket=f32(model.racket.e0),
        e_slope=f32(model.racket.e1), grip=f32((1.0 + model.racket.et0) / (1.0 + model.racket.kappa)),
        grip_slope=f32(model.racket.et1 / (1.0 + model.racket.kappa)),
        gravity=f32(-model.aero.gravity[2]), radius=f32(model.ball.radius),
        table=model.table if c.bounce == "model" else None,
        aero=model.aero if c.magnus else None, contact=model.racket, mass=f32(model.ball.mass),
        face=f32(config.racket.face), air=model.aero if c.air else None)


def drag_per_speed2(model: Model, speed: float = 8.0) -> float:
    """The ball's drag deceleration per squared speed [1/m] (spinless, at ``speed`` [m/s]), read from
    :func:`ttsim_jax.physics.aero.acceleration` along a horizontal flight (gravity and buoyancy act
    across it, a spinless ball has no Magnus force)."""
    from ttsim_jax.physics.aero import acceleration

    zero = jnp.zeros(3, jnp.float32)
    a = acceleration(model.aero, model.ball.radius, model.ball.mass, zero, zero.at[0].set(speed), zero, 0.0)
    return -float(a[0]) / speed ** 2
