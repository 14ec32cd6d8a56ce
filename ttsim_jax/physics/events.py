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

A racket face moves and turns over the step (its velocity and angular velocity). Besides the
signed gap to its plane, the distance from the face as a whole, rim included, is sampled like the
table's gap, so that a rim sweeping onto the ball (or a ball arriving over the rim) is a contact.

Everything is branch-free (``jnp.where``) so that vmap runs one path for every ball. One detection
gives the earliest contact of a stretch of path (:func:`earliest`); the rally kernel
(``kernel.step``) handles it at its own time and detects again on the rest of the step, so a step
holds its contacts in time order (a net crossing, then a bounce a fraction of a millisecond later).
"""

from __future__ import annotations

from functools import reduce

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics import table as table_stage
from ttsim_jax.physics.numerics import component_norm, dot3, safe_divide, safe_norm, triple

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
# Newton steps for the time at which a ball comes within a radius of a racket's face or rim.
RIM_ITERATIONS = 1
# A rim contact found this much earlier (fraction of the step) than a contact with the face itself
# is taken instead; within it the two are the same contact, met where the face is.
RIM_LEAD = 1e-3


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


def _sampled_root(gap, frozen, p0, v0, p1, v1, dt, iterations):
    """(g0, g_min, tau): a gap at the start of the step, its least value at mid-step and at the end,
    and the time it first falls through zero.

    The mid-step sample catches an obstacle met and left again within the step; the root is sought
    in the half of the step where the gap first turns negative, by bracketed Newton steps on
    ``frozen`` (the gap with its parameters out of the derivative), then given the implicit
    derivative of ``gap``.
    """
    half = 0.5 * jnp.ones_like(dt)
    g0, g1 = gap(p0, 0.0), gap(p1, 1.0)
    gh = gap(hermite(p0, v0, p1, v1, dt, half)[0], half)
    first = gh < 0.0
    start = jnp.where(first, 0.0, half)
    ga, gb = jnp.where(first, g0, gh), jnp.where(first, gh, g1)
    tau = start + half * jnp.clip(safe_divide(ga, ga - gb, 0.0), 0.0, 1.0)
    sg = jax.lax.stop_gradient
    tau = _bracketed_newton(sg(tau), sg(start), sg(start + half), frozen, sg(p0), sg(v0), sg(p1), sg(v1), sg(dt),
                            iterations)
    return g0, jnp.minimum(gh, g1), _implicit(tau, gap, p0, v0, p1, v1, dt)


def table_candidate(table, effects, radius, p0, v0, p1, v1, dt):
    """Contact with the table box (playing surface, edges, ends, sides, underside).

    The gap is also sampled at mid-step (:func:`_sampled_root`), so that a ball that clips an edge
    or a corner and is clear of it again by the end of the step is still caught, in that step.
    """
    sg = jax.lax.stop_gradient
    g0, g_min, tau = _sampled_root(
        lambda p, s: table_stage.gap(table, effects, radius, p),
        lambda p, s: table_stage.gap(sg(table), sg(effects), sg(radius), p), p0, v0, p1, v1, dt, TABLE_ITERATIONS)
    pos, vel = hermite(p0, v0, p1, v1, dt, tau)
    _, normal = table_stage.box_distance(table, effects, pos)
    hit = _crossing(g0, g_min, radius) & (dot3(vel, normal) < 0.0)
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
    # the components compared one by one: a reduction over three is a pass over the batch of its own
    meets = reduce(jnp.logical_and, [lo[i] <= box_hi[i] for i in range(3)] + [hi[i] >= box_lo[i] for i in range(3)])
    return meets & (table_stage.gap(table, effects, radius, p0) >= -PENETRATION_TOLERANCE * radius)


def rest_candidate(table, effects, radius, p0, v0, p1, v1, w1):
    """A ball in sustained contact with the table at the start of the step that is at rest at its
    end (``physics.table.at_rest``); at the end of the step (tau = 1)."""
    hit = table_stage.touching(table, effects, radius, p0, v0) & table_stage.at_rest(table, effects, radius, p1, v1, w1)
    return Candidate(hit=hit, tau=jnp.ones_like(p0[0]))


def racket_candidate(racket, radius, p0, v0, p1, v1, dt, elapsed=0.0):
    """Contact with one racket face (either side, or its rim), moving and turning at constant rates
    over the step (``physics.racket.advance``).

    The search runs in the face's own frame, where the face is at rest: the path there is the
    Hermite path of the ball's relative motion at both ends (``physics.racket.relative_motion``;
    exact for a face that does not turn, within O(dt^4) for one that does). Two tests, the earlier
    hit wins: the gap to the face's plane closes (signed on the ball's side at the start, so that a
    ball that crosses the face within one step is caught) with the contact point inside the
    outline; and the distance from the face, its rim beyond the outline, falls below a radius at
    mid-step or at the end of the step (:func:`_sampled_root`): the rim of a moving, turning face
    sweeping onto the ball, or a ball arriving over the rim. Either needs the ball to approach the
    face there.

    Arguments:
        racket: the racket ``elapsed`` seconds before this stretch of path starts (at the start of
            the step); p0, v0, p1, v1, dt: the path, ``dt`` long.
    """
    q0, u0 = racket_stage.relative_motion(racket, p0, v0, elapsed)
    q1, u1 = racket_stage.relative_motion(racket, p1, v1, elapsed + dt)
    side = jnp.where(q0[0] >= 0.0, 1.0, -1.0)
    g0, g1 = side * q0[0] - radius, side * q1[0] - radius
    tau_face = _root(g0, g1, lambda q, s: side * q[0] - radius, q0, u0, q1, u1, dt)
    at, vel = hermite(q0, u0, q1, u1, dt, tau_face)
    inside = (at[1] / racket.face[0]) ** 2 + (at[2] / racket.face[1]) ** 2 <= 1.0
    hit_face = _crossing(g0, g1, radius) & inside & (side * vel[0] < 0.0)

    def clearance(face):
        return lambda q, s: component_norm(*racket_stage.face_offset(q, face)) - radius

    c0, c_min, tau_rim = _sampled_root(clearance(racket.face), clearance(jax.lax.stop_gradient(racket.face)),
                                       q0, u0, q1, u1, dt, RIM_ITERATIONS)
    at, vel = hermite(q0, u0, q1, u1, dt, tau_rim)
    normal = racket_stage.face_offset(at, racket.face)  # from the face to the ball, not normalised
    hit_rim = _crossing(c0, c_min, radius) & (vel[0] * normal[0] + vel[1] * normal[1] + vel[2] * normal[2] < 0.0)
    rim_first = hit_rim & ~(hit_face & (tau_face <= tau_rim + RIM_LEAD))
    return Candidate(hit=hit_face | hit_rim, tau=jnp.where(rim_first, tau_rim, tau_face))


def racket_may_hit(racket, radius, p0, v0, p1, v1, dt):
    """Cheap superset of :func:`racket_candidate`'s hits: the ball comes within a radius of the
    face's plane in the step, within the face's reach (:func:`racket_within_reach`).

    The plane: the ball's heights h0, h1 above it at the start and the end of the step (the end's
    normal turned to first order) bound its height along the step within a margin: the Hermite
    path's bow (``SWEEP_MARGIN``), the product of the turning normal and the moving ball (theta D / 4
    for a turn theta = dt |w| and a relative displacement D) and the turn's curvature and first-order
    error (theta^2 times the distance from the face centre). The margin takes the reach for D and
    for the distance (a ball beyond it is not flagged anyway) and |w|'s L1 norm for |w|.
    """
    n0 = racket.rot[:, 0]
    turn = dt * racket.ang_vel
    rel0 = p0 - racket.pos
    rel1 = p1 - racket.pos - dt * racket.vel
    # the end's height along n0 + turn x n0: the cross product's term as a triple product (the
    # cross product of batched vectors is a concatenation, an operation of its own on a CPU)
    h0, h1 = dot3(n0, rel0), dot3(n0, rel1) + triple(turn, n0, rel1)
    reach, moved = _racket_reach(racket, radius, p0, v0, p1, v1, dt, dt)
    theta = jnp.abs(turn[0]) + jnp.abs(turn[1]) + jnp.abs(turn[2])
    margin = SWEEP_MARGIN + theta * (0.25 * moved + theta * (reach + moved + SWEEP_MARGIN))
    band = (jnp.minimum(h0, h1) - margin <= radius) & (jnp.maximum(h0, h1) + margin >= -radius)
    return band & (dot3(rel0, rel0) <= reach * reach)


def _racket_reach(racket, radius, p0, v0, p1, v1, dt, span):
    """(reach, moved): :func:`racket_within_reach`'s bound on the distance from the face centre, and
    the part of it that bounds the ball's displacement relative to the centre."""
    moved = safe_norm(p1 - p0) + dt * (safe_norm(v0) + safe_norm(v1)) / 3.0 + span * safe_norm(racket.vel)
    return jnp.maximum(racket.face[..., 0], racket.face[..., 1]) + radius + moved + 1e-3, moved


def racket_within_reach(racket, radius, p0, v0, p1, v1, dt, span):
    """Whether the ball, on a path from p0 to p1 ``dt`` long, may come within a radius of the face
    while the racket moves for ``span`` seconds from where it is.

    A contact point lies on the Hermite path, which stays in the hull of its Bezier control points
    (p0, p0 + v0 dt / 3, p1 - v1 dt / 3, p1), so within D = |p1 - p0| + dt (|v0| + |v1|) / 3 of
    p0; and within a radius of the face, whose points stay within its larger semi-axis of its centre,
    which moves span |v_racket|. The ball therefore starts within that semi-axis + radius + D + span
    |v_racket| (+ 1 mm for rounding) of the centre. Without this test a tracking racket's plane,
    which sweeps through the whole court, flagged every ball it crossed.
    """
    reach, _ = _racket_reach(racket, radius, p0, v0, p1, v1, dt, span)
    rel0 = p0 - racket.pos
    return dot3(rel0, rel0) <= reach * reach


def net_candidate(table, radius, p0, v0, p1, v1, dt):
    """The ball centre crossing the net plane x = 0 low enough to touch the net (reported only)."""
    gap = lambda p, s: p[0]  # noqa: E731
    tau = _root(p0[0], p1[0], gap, p0, v0, p1, v1, dt)
    pos, _ = hermite(p0, v0, p1, v1, dt, tau)
    crosses = net_crosses(p0, p1)
    touches = (pos[2] < table.net_height + radius) & (pos[2] > -radius) & (
        jnp.abs(pos[1]) < 0.5 * table.width + table.net_overhang + radius)
    return Candidate(hit=crosses & touches, tau=tau)


def net_crosses(p0, p1):
    """The ball centre crosses the net plane x = 0 in the step."""
    return (p0[0] * p1[0] < 0.0) | ((p1[0] == 0.0) & (p0[0] != 0.0))


def net_may_hit(table, radius, p0, v0, p1, v1, dt):
    """Cheap superset of :func:`net_candidate`'s hits: the centre crosses the net plane and the
    Hermite path's control points (p0, p0 + v0 dt / 3, p1 - v1 dt / 3, p1), whose hull holds the
    crossing, reach the band where it would touch the net (most balls cross well above it)."""
    c0, c1 = p0 + v0 * (dt / 3.0), p1 - v1 * (dt / 3.0)
    lo = lambda i: jnp.minimum(jnp.minimum(p0[i], c0[i]), jnp.minimum(c1[i], p1[i]))  # noqa: E731
    hi = lambda i: jnp.maximum(jnp.maximum(p0[i], c0[i]), jnp.maximum(c1[i], p1[i]))  # noqa: E731
    half = 0.5 * table.width + table.net_overhang + radius
    band = (lo(2) < table.net_height + radius) & (hi(2) > -radius) & (lo(1) < half) & (hi(1) > -half)
    return net_crosses(p0, p1) & band


def floor_may_hit(table, radius, p1):
    """The ball ends the step below the floor (the same test as :func:`floor_candidate`)."""
    return p1[2] - radius - table.floor_z < 0.0


def floor_candidate(table, radius, p0, v0, p1, v1, dt):
    gap = lambda p, s: p[2] - radius - table.floor_z  # noqa: E731
    g0, g1 = gap(p0, 0.0), gap(p1, 1.0)
    tau = _root(g0, g1, gap, p0, v0, p1, v1, dt)
    return Candidate(hit=floor_may_hit(table, radius, p1), tau=tau)


def out_of_play(pos):
    return reduce(jnp.logical_or, [jnp.abs(pos[..., i]) > PLAY_BOX[i] for i in range(3)])


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
