"""One ball's stages of a kernel step: free flight, the cheap tests of what *may* happen, the
exact detection of the earliest event, the contact responses and the bookkeeping after them.

Each function is of one ball ((3,) fields); :mod:`.step` vmaps them over a batch and gathers the
balls that need the exact stages into its contact buffer.
"""

from __future__ import annotations

from functools import reduce

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.params import Model
from ttsim_jax.physics import aero as aero_stage
from ttsim_jax.physics import events as ev
from ttsim_jax.physics import hooks
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics import table as table_stage
from ttsim_jax.physics.numerics import dot3
from ttsim_jax.state import Ball, Racket

# Beyond these a state is flagged invalid and frozen (m/s, rad/s, m).
MAX_SPEED, MAX_SPIN, MAX_DISTANCE = 200.0, 2.0e4, 100.0
# The candidates of :func:`detect` that are not rackets, in their order (a Proposal's ``slot``).
FIXED_SLOTS = (ev.TABLE, ev.REST, ev.FLOOR, ev.NET)


@struct.dataclass
class Proposal:
    """Result of :func:`detect` for one ball and step: the earliest event and the state at it.

    Attributes:
        kind: event kind (``physics.events``), NONE if nothing happens in the step.
        tau: time of the event as a fraction of the step (1 if none).
        racket: index of the racket hit, -1 otherwise.
        pre: :class:`Ball` at the event (the free-flight path at tau).
        slot: the event's candidate (``FIXED_SLOTS``, then one per racket).
    """

    kind: jnp.ndarray
    tau: jnp.ndarray
    racket: jnp.ndarray
    pre: Ball
    slot: jnp.ndarray



def ball_properties(model: Model):
    """(radius, mass) of the ball after effects (hook ``ball_properties``)."""
    return hooks.apply(model.effects, "ball_properties", (model.ball.radius, model.ball.mass))


def flight(model: Model, ball: Ball, t, dt, integrator: str = "rk4") -> Ball:
    """The ball at the end of the step in free flight."""
    radius, mass = ball_properties(model)
    return Ball(*aero_stage.flight_step(model.aero, radius, mass, ball.pos, ball.vel, ball.spin, t, dt,
                                        model.effects, integrator))


def settle(model: Model, ball: Ball, free: Ball) -> Ball:
    """The end of the step for a ball that started it in sustained contact with the table: put back
    onto the table (``physics.table.slide``: it rolls or slides instead of bouncing); ``free``
    otherwise. Such balls are flagged by :func:`may_have_event`, so this runs in the gathered rows."""
    radius, _ = ball_properties(model)
    touch = table_stage.touching(model.table, model.effects, radius, ball.pos, ball.vel)
    slid = table_stage.slide(model.table, radius, free.pos, free.vel, free.spin, model.effects)
    return Ball(*(jnp.where(touch, a, b) for a, b in zip(slid, (free.pos, free.vel, free.spin))))


def is_valid(ball: Ball):
    """Whether a state is finite and within the sane range (else it is flagged INVALID)."""
    # elementwise over the components, no reduction: each reduction over a short axis was a pass
    # over the batch of its own in every step (the checks tolerate the order of the sums)
    finite = reduce(jnp.logical_and, [jnp.isfinite(c) for a in (ball.pos, ball.vel, ball.spin)
                                      for c in jnp.unstack(a, axis=-1)])
    clean = jax.tree.map(lambda a: jnp.where(finite[..., None], a, 0.0), ball)
    far = reduce(jnp.maximum, [jnp.abs(c) for c in jnp.unstack(clean.pos, axis=-1)])
    sane = ((dot3(clean.vel, clean.vel) < MAX_SPEED**2) & (dot3(clean.spin, clean.spin) < MAX_SPIN**2)
            & (far < MAX_DISTANCE))
    return finite & sane


def refused_starts(model: Model, axes, ball: Ball, rackets: Racket | None, rackets_batched: bool):
    """(B,) whether each ball starts inside the table, the net or a racket (``events.inside_obstacle``).

    Arguments:
        model, axes: model parameters and their per-ball axes; ball: (B, 3) fields;
        rackets: the rackets at the start ((R, ...) fields, (B, R, ...) if ``rackets_batched``) or None.
    """
    def inside(m, b, r):
        return ev.inside_obstacle(m.table, m.effects, ball_properties(m)[0], b.pos, r)

    phys, phys_axes = model.replace(residual=None), axes.replace(residual=None)
    return jax.vmap(inside, in_axes=(phys_axes, 0, 0 if rackets_batched else None))(phys, ball, rackets)


def may_hit(model: Model, ball: Ball, free: Ball, rackets: Racket | None, dt, span=None):
    """For each candidate of :func:`detect`, in its order (``FIXED_SLOTS``, then the rackets), a
    cheap superset of its hits (one ball, from ``ball`` to ``free`` over ``dt``): the sign changes of
    the gap functions behind it; the conditions that need the time of impact are left to
    :func:`detect`. Every candidate added there needs its test here.

    Arguments:
        rackets: the rackets at the start of the path; or, with ``span``, where they are at some
            time within the ``span`` seconds before it starts, which leaves only their reach
            (``events.racket_within_reach``) as their test (the rest of a step, tested against the
            rackets at the start of the step).

    Returns:
        (fixed, rackets): a list of () bool in the order of ``FIXED_SLOTS``, and (R,) bool (None
        without rackets).
    """
    radius, _ = ball_properties(model)
    p0, v0, p1, v1 = ball.pos, ball.vel, free.pos, free.vel
    fixed = [ev.table_may_hit(model.table, model.effects, radius, p0, p1),
             # sustained contact: it slides in :func:`settle` and may come to rest
             table_stage.touching(model.table, model.effects, radius, p0, v0),
             ev.floor_may_hit(model.table, radius, p1), ev.net_may_hit(model.table, radius, p0, v0, p1, v1, dt)]
    if rackets is None:
        return fixed, None
    if span is None:
        return fixed, _racket_flags(model, ball, free, rackets, dt)
    return fixed, jax.vmap(ev.racket_within_reach, in_axes=(0,) + (None,) * 7)(rackets, radius, p0, v0, p1, v1, dt,
                                                                              span + dt)


def step_flags(model: Model, ball: Ball, free: Ball, rackets: Racket | None, dt):
    """(:func:`may_have_event`, :func:`may_need_network`) of one ball, from one :func:`may_hit`."""
    fixed, near = may_hit(model, ball, free, rackets, dt)
    racket = jnp.zeros((), bool) if near is None else jnp.any(near)
    event = reduce(jnp.logical_or, fixed) | racket | ev.out_of_play(free.pos) | ~is_valid(free)
    # sustained table contact: its end of step (:func:`settle`) may move the ball onto a racket
    return event, racket | fixed[FIXED_SLOTS.index(ev.REST)]


def may_have_event(model: Model, ball: Ball, free: Ball, rackets: Racket | None, dt):
    """Whether :func:`detect` or :func:`resolve` could report anything for this step (one ball):
    :func:`may_hit`, leaving play or an invalid state."""
    return step_flags(model, ball, free, rackets, dt)[0]


def _racket_flags(model: Model, ball: Ball, free: Ball, rackets: Racket, dt):
    radius, _ = ball_properties(model)
    return jax.vmap(ev.racket_may_hit, in_axes=(0,) + (None,) * 6)(rackets, radius, ball.pos, ball.vel, free.pos,
                                                                  free.vel, dt)


def may_need_network(model: Model, ball: Ball, free: Ball, rackets: Racket, dt):
    """A superset of the balls whose step ends in a racket contact (one ball): the racket test on the
    free flight, and every ball in sustained table contact, whose end of step :func:`settle` moves."""
    return step_flags(model, ball, free, rackets, dt)[1]


def detect(model: Model, ball: Ball, free: Ball, rackets: Racket | None, dt, done=None, elapsed=0.0) -> Proposal:
    """The earliest event of the step (or of the rest of a step) for one ball, with its refined time
    of impact.

    Arguments:
        model: model parameters (its ``residual`` is not used here).
        ball: one ball at the start of the step, (3,) fields; free: the same at its end in free flight.
        rackets: :class:`Racket` with (R, ...) fields at the start of the step, or None.
        dt: step length [s] (of the rest of the step).
        done: (len(FIXED_SLOTS) + R,) bool, candidates left out (already handled in this step), or None.
        elapsed: time [s] from the start of the step to ``ball`` (the rest of a step starts later).

    Returns:
        A :class:`Proposal`.
    """
    fx = model.effects
    radius, _ = ball_properties(model)
    p0, v0, w0 = ball.pos, ball.vel, ball.spin
    p1, v1, w1 = free.pos, free.vel, free.spin
    # a ball in sustained contact does not bounce: it slid in flight() and may come to rest
    table = ev.table_candidate(model.table, fx, radius, p0, v0, p1, v1, dt)
    touch = table_stage.touching(model.table, fx, radius, p0, v0)
    cands = [(ev.TABLE, table.replace(hit=table.hit & ~touch)),
             (ev.REST, ev.rest_candidate(model.table, fx, radius, p0, v0, p1, v1, w1)),
             (ev.FLOOR, ev.floor_candidate(model.table, radius, p0, v0, p1, v1, dt)),
             (ev.NET, ev.net_candidate(model.table, radius, p0, v0, p1, v1, dt))]
    n_fixed = len(cands)
    if rackets is not None:
        rc = jax.vmap(ev.racket_candidate, in_axes=(0,) + (None,) * 7)(rackets, radius, p0, v0, p1, v1, dt, elapsed)
        cands += [(ev.RACKET, ev.Candidate(rc.hit[j], rc.tau[j])) for j in range(rc.hit.shape[0])]
    if done is not None:
        cands = [(k, c.replace(hit=c.hit & ~done[j])) for j, (k, c) in enumerate(cands)]
    kind, tau, index = ev.earliest(cands)
    pos, vel = ev.hermite(p0, v0, p1, v1, dt, tau)
    racket_index = jnp.where(kind == ev.RACKET, index - n_fixed, -1).astype(jnp.int32)
    return Proposal(kind=kind, tau=tau, racket=racket_index, pre=Ball(pos, vel, w0 + tau * (w1 - w0)), slot=index)


def respond(model: Model, pre: Ball, kind, racket: Racket | None):
    """Base-model response of one ball to its contact (table or racket).

    Arguments:
        model: model parameters; pre: the ball at the contact; kind: TABLE or RACKET;
        racket: the racket hit, (...) fields at the contact time (None without rackets).

    Returns:
        (post, x, rot): post-contact :class:`Ball`, the residual network's racket-frame input (8,)
        (zeros for the table) and the racket frame (3, 3) in which its correction is expressed.
    """
    fx = model.effects
    radius, mass = ball_properties(model)
    tp, tv, tw = table_stage.table_contact(model.table, radius, pre.pos, pre.vel, pre.spin, fx)
    post = Ball(tp, tv, tw)
    x = jnp.zeros(8, pre.pos.dtype)
    rot = jnp.eye(3, dtype=pre.pos.dtype)
    if racket is not None:
        rv, rw, rstate = racket_stage.racket_contact(model.racket, racket, radius, mass, pre.pos, pre.vel,
                                                     pre.spin, fx)
        is_r = kind == ev.RACKET
        post = Ball(jnp.where(is_r, pre.pos, tp), jnp.where(is_r, rv, tv), jnp.where(is_r, rw, tw))
        x = jnp.where(is_r, racket_stage.network_input(rstate), x)
        rot = jnp.where(is_r, rstate["rot"], rot)
    return post, x, rot


def finish(model: Model, post: Ball, tau, t, dt) -> Ball:
    """Flies a ball on from its contact to the end of the step.

    The rest of the step is short and happens once per contact: a second-order Taylor step (one
    acceleration) costs a quarter of an RK4 step and errs by O(dt^3) once per contact.
    """
    rest = (1.0 - tau) * dt
    f = aero_stage.derivative(model.aero, *ball_properties(model), model.effects)
    _, acc, dspin = f((post.pos, post.vel, post.spin), t + tau * dt)
    return Ball(post.pos + rest * post.vel + 0.5 * rest * rest * acc, post.vel + rest * acc, post.spin + rest * dspin)


def resolve(ball: Ball, alive, nxt: Ball, kind, time, t, dt):
    """Completes a step for one ball that may have had events: the next state and what to log.

    Arguments:
        ball: the state at the start of the step; alive: whether the ball is in play;
        nxt: the state at the end of the step after its events (the free flight if none);
        kind, time: (S,) the step's events in time order (NONE after the last) and their times;
        t, dt: step start and length.

    Returns:
        (next ball, kind (S,), time (S,), stopped): a step without events that ends out of play logs
        OUT, a step that ends in an invalid state logs INVALID (in place of its events, frozen);
        ``stopped`` is the kind that takes the ball out of play (FLOOR, OUT, INVALID, REST), 0 if none.
    """
    out = (kind[0] == ev.NONE) & ev.out_of_play(nxt.pos)
    invalid = ~is_valid(nxt)
    first = jnp.where(invalid, ev.INVALID, jnp.where(out, ev.OUT, kind[0]))
    later = jnp.arange(kind.shape[0]) > 0
    kind = jnp.where(later, jnp.where(invalid, ev.NONE, kind), first)
    kind = jnp.where(alive, kind, ev.NONE)
    time = jnp.where(later | ~(out | invalid), time, t + dt)
    nxt = jax.tree.map(lambda a, b: jnp.where(invalid | ~alive, b, a), nxt, ball)
    terminal = (kind == ev.FLOOR) | (kind == ev.OUT) | (kind == ev.INVALID) | (kind == ev.REST)
    return nxt, kind, time, jnp.max(jnp.where(terminal, kind, 0))
