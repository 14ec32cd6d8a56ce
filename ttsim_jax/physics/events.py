"""What touches what inside one step, and when.

Each step first flies the ball freely over the whole step. Every contact is then found from the
free-flight path: a contact happens when a signed gap function (ball surface to table, to each
racket face, to the floor; ball centre to the net plane) changes sign over the step. The time of
impact tau (fraction of the step) comes from the linear zero of the gap, refined by one Newton step
on the cubic Hermite interpolant of the path (position and velocity at both ends), so the contact
point is fourth-order accurate in dt and the landing point converges as dt shrinks. Continuous
detection of this kind cannot tunnel: a ball at 35 m/s against a racket at 10 m/s moves 4.5 cm
relative to it in a 1 ms step, more than its diameter, and the sign change is still seen.

The table is a box (``physics.table``): its gap is also sampled at mid-step, so that a ball that
clips an edge or a corner within a step is caught, and its time of impact takes a few Newton steps
kept inside the bracket of the sign change (the gap has a kink where the nearest point of the box
moves from an edge onto a face). A ball in sustained contact with the table (rolling, sliding) has
no table contacts; it ends as REST once slow (``rest_candidate``).

Everything is branch-free (``jnp.where``) so that vmap runs one path for every ball; the earliest
contact of the step wins (at most one per ball per step).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.physics import table as table_stage
from ttsim_jax.physics.numerics import safe_divide, safe_norm

NONE, TABLE, RACKET, NET, FLOOR, OUT, INVALID, REST = range(8)
KIND_NAMES = ("none", "table", "racket", "net", "floor", "out", "invalid", "rest")

# A contact is accepted if the ball started the step no deeper than this (fraction of its radius)
# into the surface: a ball resting on the table or just released by a contact is re-detected. A
# ball deeper than this in the table or a racket, or with its centre inside the net's band, at the
# start of a simulation is refused (INVALID, see :func:`inside_obstacle`).
PENETRATION_TOLERANCE = 0.5
# Balls leaving this box are out of play [m].
PLAY_BOX = (8.0, 6.0, 8.0)
# Newton steps for the table's time of impact (the first is as accurate as the other contacts'
# on the playing surface; edges and corners need the others).
TABLE_ITERATIONS = 4
# Margin [m] of the swept box in :func:`table_may_hit`: the Hermite path bows off its chord by
# under |a| dt^2 / 8 (0.1 mm at 200 m/s^2 and 2 ms) and a tilted surface rises 1 mm in 0.1 m.
SWEEP_MARGIN = 2e-3


def hermite(p0, v0, p1, v1, dt, tau):
    """Position and velocity at fraction ``tau`` of the step on the cubic Hermite interpolant.

    Written in the displacement p1 - p0, so that a coordinate that does not move (a vertical
    drop's x and y) stays exactly constant in any float type.
    """
    t2, t3 = tau * tau, tau * tau * tau
    dp = p1 - p0
    pos = p0 + (-2 * t3 + 3 * t2) * dp + (t3 - 2 * t2 + tau) * dt * v0 + (t3 - t2) * dt * v1
    dpos = (-6 * t2 + 6 * tau) * dp + (3 * t2 - 4 * tau + 1) * dt * v0 + (3 * t2 - 2 * tau) * dt * v1
    return pos, dpos / dt


def _bracketed_newton(tau, lo, hi, gap_fn, p0, v0, p1, v1, dt, iterations):
    """Newton steps on the Hermite path from ``tau``, kept inside the bracket [lo, hi] of a gap that
    falls through zero (bisection where a step leaves it): robust where the gap has a kink, as
    where the nearest point of the table moves from an edge onto a face."""
    for _ in range(iterations):
        g, dg = jax.jvp(lambda s: gap_fn(hermite(p0, v0, p1, v1, dt, s)[0], s), (tau,), (jnp.ones_like(tau),))
        lo, hi = jnp.where(g >= 0.0, tau, lo), jnp.where(g < 0.0, tau, hi)
        tau_n = tau - safe_divide(g, dg, 0.0)
        tau = jnp.where((tau_n >= lo) & (tau_n <= hi), tau_n, 0.5 * (lo + hi))
    return tau


def _root(g0, g1, gap_fn, p0, v0, p1, v1, dt):
    """tau in [0, 1] where the gap crosses zero: linear guess, one Newton step on the Hermite path."""
    tau = jnp.clip(safe_divide(g0, g0 - g1, 0.0), 0.0, 1.0)
    g, dg = jax.jvp(lambda s: gap_fn(hermite(p0, v0, p1, v1, dt, s)[0], s), (tau,), (jnp.ones_like(tau),))
    tau_n = tau - safe_divide(g, dg, 0.0)
    return _implicit(jnp.where((tau_n >= 0.0) & (tau_n <= 1.0), tau_n, tau), gap_fn, p0, v0, p1, v1, dt)


def _implicit(tau, gap_fn, p0, v0, p1, v1, dt):
    """``tau`` (a root of the gap on the Hermite path) unchanged, with the derivative of the exact
    root by the implicit function theorem, d tau = -(d gap) / (d gap / d tau), instead of the
    derivative of the iterations that found it: exact at the root, and it keeps the second-order
    terms of every Newton step out of reverse mode (they dominated the compile time of a gradient).
    """
    tau = jax.lax.stop_gradient(tau)
    g, dg = jax.jvp(lambda s: gap_fn(hermite(p0, v0, p1, v1, dt, s)[0], s), (tau,), (jnp.ones_like(tau),))
    return tau - safe_divide(g - jax.lax.stop_gradient(g), jax.lax.stop_gradient(dg), 0.0)


def _crossing(g0, g1, radius):
    """A surface gap that closes within the step, from no deeper than the tolerance."""
    return (g1 < 0.0) & (g0 >= -PENETRATION_TOLERANCE * radius)


@struct.dataclass
class Candidate:
    """One possible contact within a step: whether it happens, and when (fraction of the step)."""

    hit: jnp.ndarray
    tau: jnp.ndarray


def table_candidate(table, effects, radius, p0, v0, p1, v1, dt):
    """Contact with the table box (playing surface, edges, ends, sides, underside).

    The gap is also sampled at mid-step, so that a ball that clips an edge or a corner and is
    clear of it again by the end of the step is still caught, in that step; the root is then
    sought in the half of the step where the gap first turns negative.
    """
    gap = lambda p, s: table_stage.gap(table, effects, radius, p)  # noqa: E731
    half = 0.5 * jnp.ones_like(dt)
    g0, g1 = gap(p0, 0.0), gap(p1, 1.0)
    gh = gap(hermite(p0, v0, p1, v1, dt, half)[0], half)
    first = gh < 0.0
    start = jnp.where(first, 0.0, half)
    ga, gb = jnp.where(first, g0, gh), jnp.where(first, gh, g1)
    tau = start + half * jnp.clip(safe_divide(ga, ga - gb, 0.0), 0.0, 1.0)
    sg = jax.lax.stop_gradient
    tau = _bracketed_newton(sg(tau), sg(start), sg(start + half), lambda p, s: table_stage.gap(
        sg(table), sg(effects), sg(radius), p), sg(p0), sg(v0), sg(p1), sg(v1), sg(dt), TABLE_ITERATIONS)
    tau = _implicit(tau, gap, p0, v0, p1, v1, dt)
    pos, vel = hermite(p0, v0, p1, v1, dt, tau)
    _, normal = table_stage.box_distance(table, effects, pos)
    hit = _crossing(g0, jnp.minimum(gh, g1), radius) & (jnp.dot(vel, normal) < 0.0)
    return Candidate(hit=hit, tau=tau)


def table_may_hit(table, effects, radius, p0, p1):
    """Cheap superset of :func:`table_candidate`'s hits: the box swept by the ball over the step
    (the chord p0 -> p1, widened by a radius and ``SWEEP_MARGIN`` for the path's bow and a tilted
    surface) meets the table, which the ball did not start deep in."""
    h0, h1 = table_stage.surface(effects, p0)[0], table_stage.surface(effects, p1)[0]
    reach = radius + SWEEP_MARGIN
    lo, hi = jnp.minimum(p0, p1) - reach, jnp.maximum(p0, p1) + reach
    box_hi = jnp.stack([0.5 * table.length, 0.5 * table.width, jnp.maximum(h0, h1)])
    box_lo = jnp.stack([-0.5 * table.length, -0.5 * table.width, jnp.minimum(h0, h1) - table_stage.THICKNESS])
    meets = jnp.all(lo <= box_hi) & jnp.all(hi >= box_lo)
    return meets & (table_stage.gap(table, effects, radius, p0) >= -PENETRATION_TOLERANCE * radius)


def rest_candidate(table, effects, radius, p0, v0, p1, v1, w1):
    """A ball in sustained contact with the table at the start of the step that is at rest at its
    end (``physics.table.at_rest``); at the end of the step (tau = 1)."""
    hit = table_stage.touching(table, effects, radius, p0, v0) & table_stage.at_rest(table, effects, radius, p1, v1, w1)
    return Candidate(hit=hit, tau=jnp.ones_like(p0[0]))


def racket_candidate(racket, radius, p0, v0, p1, v1, dt):
    """Contact with one racket face moving at constant velocity over the step (either face)."""
    n = racket.rot[:, 0]
    h = lambda p, s: jnp.dot(n, p - racket.pos - s * dt * racket.vel)  # noqa: E731
    h0, h1 = h(p0, 0.0), h(p1, 1.0)
    side = jnp.where(h0 >= 0.0, 1.0, -1.0)
    gap = lambda p, s: side * h(p, s) - radius  # noqa: E731
    g0, g1 = side * h0 - radius, side * h1 - radius
    tau = _root(g0, g1, gap, p0, v0, p1, v1, dt)
    pos, vel = hermite(p0, v0, p1, v1, dt, tau)
    local = racket.rot.T @ (pos - racket.pos - tau * dt * racket.vel)
    inside = jnp.sum((local[1:3] / racket.face) ** 2) <= 1.0
    approaching = side * jnp.dot(n, vel - racket.vel) < 0.0
    hit = _crossing(g0, g1, radius) & approaching & inside
    return Candidate(hit=hit, tau=tau)


def racket_may_hit(racket, radius, p0, v0, p1, v1, dt):
    """Cheap superset of :func:`racket_candidate`'s hits: the gap to the face's plane closes, and
    the ball passes within the face's reach.

    A hit's contact point lies on the step's Hermite path, which stays in the hull of its Bezier
    control points (p0, p0 + v0 dt / 3, p1 - v1 dt / 3, p1), so within D = |p1 - p0| + dt (|v0| +
    |v1|) / 3 of p0; and inside the face's ellipse, so across the face normal within its larger
    semi-axis of the face centre, which moves dt |v_racket| in the step. At the start of the step the
    ball is therefore within that semi-axis + D + dt |v_racket| (+ 1 mm for rounding) of the centre
    across the normal. Without this test a tracking racket's plane, which sweeps through the whole
    court, flagged every ball it crossed.
    """
    n = racket.rot[:, 0]
    rel = p0 - racket.pos
    h0, h1 = jnp.dot(n, rel), jnp.dot(n, p1 - racket.pos - dt * racket.vel)
    side = jnp.where(h0 >= 0.0, 1.0, -1.0)
    across = rel - h0 * n
    reach = (jnp.max(racket.face) + safe_norm(p1 - p0) + dt * (safe_norm(v0) + safe_norm(v1)) / 3.0
             + dt * safe_norm(racket.vel) + 1e-3)
    return _crossing(side * h0 - radius, side * h1 - radius, radius) & (jnp.sum(across * across) <= reach * reach)


def net_candidate(table, radius, p0, v0, p1, v1, dt):
    """The ball centre crossing the net plane x = 0 low enough to touch the net (reported only)."""
    gap = lambda p, s: p[0]  # noqa: E731
    tau = _root(p0[0], p1[0], gap, p0, v0, p1, v1, dt)
    pos, _ = hermite(p0, v0, p1, v1, dt, tau)
    crosses = net_may_hit(p0, p1)
    touches = (pos[2] < table.net_height + radius) & (pos[2] > -radius) & (
        jnp.abs(pos[1]) < 0.5 * table.width + table.net_overhang + radius)
    return Candidate(hit=crosses & touches, tau=tau)


def net_may_hit(p0, p1):
    """The ball centre crosses the net plane x = 0 in the step (superset of :func:`net_candidate`)."""
    return (p0[0] * p1[0] < 0.0) | ((p1[0] == 0.0) & (p0[0] != 0.0))


def floor_may_hit(table, radius, p1):
    """The ball ends the step below the floor (the same test as :func:`floor_candidate`)."""
    return p1[2] - radius - table.floor_z < 0.0


def floor_candidate(table, radius, p0, v0, p1, v1, dt):
    gap = lambda p, s: p[2] - radius - table.floor_z  # noqa: E731
    g0, g1 = gap(p0, 0.0), gap(p1, 1.0)
    tau = _root(g0, g1, gap, p0, v0, p1, v1, dt)
    return Candidate(hit=floor_may_hit(table, radius, p1), tau=tau)


def out_of_play(pos):
    box = jnp.asarray(PLAY_BOX, pos.dtype)
    return jnp.any(jnp.abs(pos) > box)


def earliest(candidates: list[tuple[int, Candidate]]):
    """(kind, tau, index) of the earliest hit among (kind, candidate) pairs; NONE if none hit.

    ``index`` is the position in the list (to find which racket was hit).
    """
    taus = jnp.stack([jnp.where(c.hit, c.tau, jnp.inf) for _, c in candidates])
    kinds = jnp.asarray([k for k, _ in candidates], jnp.int32)
    i = jnp.argmin(taus).astype(jnp.int32)
    hit = jnp.isfinite(taus[i])
    return jnp.where(hit, kinds[i], NONE), jnp.where(hit, taus[i], 1.0), i


def inside_obstacle(table, effects, radius, pos, rackets=None):
    """Whether a ball at ``pos`` overlaps the table or a racket, or the net, by more than
    PENETRATION_TOLERANCE of its radius: a state no contact can resolve (refused at the start).

    Arguments:
        table: table parameters; effects: the model's effects; radius: ball radius [m];
        pos: (3,) ball centre; rackets: :class:`Racket` with (R, ...) fields, or None.

    Returns:
        () bool.
    """
    deep = (1.0 - PENETRATION_TOLERANCE) * radius
    inside = table_stage.gap(table, effects, radius, pos) < -PENETRATION_TOLERANCE * radius
    # the net: a rectangle in the plane x = 0 from the surface to its top, out to its posts
    half = 0.5 * table.width + table.net_overhang
    to_net = pos - jnp.stack([jnp.zeros_like(pos[0]), jnp.clip(pos[1], -half, half),
                              jnp.clip(pos[2], 0.0, table.net_height)])
    inside |= jnp.sum(to_net * to_net) < deep * deep
    if rackets is not None:
        local = jnp.einsum("rji,rj->ri", rackets.rot, pos - rackets.pos)  # racket frame
        on_face = jnp.sum((local[:, 1:3] / rackets.face) ** 2, axis=-1) <= 1.0
        inside |= jnp.any(on_face & (jnp.abs(local[:, 0]) < deep))
    return inside
