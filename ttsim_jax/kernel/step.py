"""One step of the rally kernel for a batch of balls.

Contacts are rare (a few per ball per second), so a step does the least work for the balls that
have none:

1. Every ball (``vmap`` of one-ball functions): free flight over the step (:func:`flight`) and a
   cheap test whether anything *may* happen in it (:func:`may_have_event`: the sign changes of the
   gap functions, leaving play, an invalid state). No time of impact, no contact model.
2. The balls that may have an event are gathered into a buffer of ``capacity`` rows, where the
   exact detection (:func:`detect`: time of impact refined on the Hermite path, face and table
   outlines), the contact models, the racket residual network, the rest of the step after the
   contact (:func:`finish`) and the bookkeeping (:func:`resolve`) run; the rows are scattered back
   and their events appended to the log. A step with more such balls than ``capacity`` runs the
   same function on the whole batch (same result, full cost); a step with none skips it. The choice
   is a ``lax.switch`` at batch level, outside any vmap, so only one branch runs.

Per-ball parameters: ``model_axes`` is a pytree prefix of the model, like ``jax.vmap``'s
``in_axes``: 0 where a leaf carries a leading (B,) axis, None where it is shared (see
:func:`~ttsim_jax.kernel.rollout.per_ball_axes`).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.kernel.eventlog import EventLog
from ttsim_jax.params import Model
from ttsim_jax.physics import aero as aero_stage
from ttsim_jax.physics import events as ev
from ttsim_jax.physics import hooks
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics import table as table_stage
from ttsim_jax.state import Ball, Racket

# Beyond these a state is flagged invalid and frozen (m/s, rad/s, m).
MAX_SPEED, MAX_SPIN, MAX_DISTANCE = 200.0, 2.0e4, 100.0
# The "single" buffering's network rows: 1/NET_FRACTION of the contact buffer (B/32 rows), for buffers
# of at least NET_MIN_BUFFER rows. Two tracking rackets and 65,536 realistic shots over 1,000 steps
# gave at most 101 racket contacts in a step (0.15 % of the balls; the buffer of B/32 holds 3.1 %,
# B/256 0.39 %).
NET_FRACTION, NET_MIN_BUFFER = 8, 64


@struct.dataclass
class Proposal:
    """Result of :func:`detect` for one ball and step: the earliest event and the state at it.

    Attributes:
        kind: event kind (``physics.events``), NONE if nothing happens in the step.
        tau: time of the event as a fraction of the step (1 if none).
        racket: index of the racket hit, -1 otherwise.
        pre: :class:`Ball` at the event (the free-flight path at tau).
    """

    kind: jnp.ndarray
    tau: jnp.ndarray
    racket: jnp.ndarray
    pre: Ball


# --------------------------------------------------------------------------- one ball
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
    finite = jnp.all(jnp.isfinite(ball.as_array()))
    clean = jax.tree.map(lambda a: jnp.where(finite, a, 0.0), ball)
    sane = ((jnp.sum(clean.vel * clean.vel) < MAX_SPEED**2) & (jnp.sum(clean.spin * clean.spin) < MAX_SPIN**2)
            & (jnp.max(jnp.abs(clean.pos)) < MAX_DISTANCE))
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


def may_have_event(model: Model, ball: Ball, free: Ball, rackets: Racket | None, dt):
    """Whether :func:`detect` or :func:`resolve` could report anything for this step (one ball).

    A superset of the events: the sign changes of the gap functions behind every candidate of
    :func:`detect` (the conditions that need the time of impact are left to it), leaving play and
    an invalid state. Every candidate added to :func:`detect` needs its test here.
    """
    radius, _ = ball_properties(model)
    p0, v0, p1, v1 = ball.pos, ball.vel, free.pos, free.vel
    flag = ev.table_may_hit(model.table, model.effects, radius, p0, p1)
    # sustained contact (it slides in :func:`settle` and may come to rest)
    flag |= table_stage.touching(model.table, model.effects, radius, p0, v0)
    flag |= ev.floor_may_hit(model.table, radius, p1)
    flag |= ev.net_may_hit(p0, p1)
    if rackets is not None:
        flag |= racket_may_hit(model, ball, free, rackets, dt)
    return flag | ev.out_of_play(p1) | ~is_valid(free)


def racket_may_hit(model: Model, ball: Ball, free: Ball, rackets: Racket, dt):
    """Whether the ball may meet any racket in the step (one ball; the racket test of :func:`may_have_event`)."""
    radius, _ = ball_properties(model)
    return jnp.any(jax.vmap(ev.racket_may_hit, in_axes=(0,) + (None,) * 6)(rackets, radius, ball.pos, ball.vel,
                                                                          free.pos, free.vel, dt))


def may_need_network(model: Model, ball: Ball, free: Ball, rackets: Racket, dt):
    """A superset of the balls whose step ends in a racket contact (one ball): the racket test on the
    free flight, and every ball in sustained table contact, whose end of step :func:`settle` moves."""
    radius, _ = ball_properties(model)
    return (racket_may_hit(model, ball, free, rackets, dt)
            | table_stage.touching(model.table, model.effects, radius, ball.pos, ball.vel))


def detect(model: Model, ball: Ball, free: Ball, rackets: Racket | None, dt) -> Proposal:
    """The earliest event of the step for one ball, with its refined time of impact.

    Arguments:
        model: model parameters (its ``residual`` is not used here).
        ball: one ball at the start of the step, (3,) fields; free: the same at its end in free flight.
        rackets: :class:`Racket` with (R, ...) fields, or None.
        dt: step length [s].

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
        rc = jax.vmap(ev.racket_candidate, in_axes=(0, None, None, None, None, None, None))(
            rackets, radius, p0, v0, p1, v1, dt)
        cands += [(ev.RACKET, ev.Candidate(rc.hit[j], rc.tau[j])) for j in range(rc.hit.shape[0])]
    kind, tau, index = ev.earliest(cands)
    pos, vel = ev.hermite(p0, v0, p1, v1, dt, tau)
    racket_index = jnp.where(kind == ev.RACKET, index - n_fixed, -1).astype(jnp.int32)
    return Proposal(kind=kind, tau=tau, racket=racket_index, pre=Ball(pos, vel, w0 + tau * (w1 - w0)))


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


def resolve(ball: Ball, alive, free: Ball, prop: Proposal, post: Ball, after: Ball, t, dt):
    """Completes a step for one ball that may have an event: the next state and what to log.

    Arguments:
        ball: the state at the start of the step; alive: whether the ball is in play;
        free: the state at the end of the step in free flight; prop: from :func:`detect`;
        post, after: the state just after the contact and at the end of the step (used for table
        and racket contacts only); t, dt: step start and length.

    Returns:
        (next ball, kind, event time, logged post-event state, stops): kind is NONE when nothing
        happened; ``stops`` says the ball leaves play (FLOOR, OUT, INVALID, REST).
    """
    kind = prop.kind
    bounced = (kind == ev.TABLE) | (kind == ev.RACKET)
    nxt = jax.tree.map(lambda a, b, c: jnp.where(bounced, a, jnp.where(kind == ev.FLOOR, b, c)),
                       after, prop.pre, free)
    out = (kind == ev.NONE) & ev.out_of_play(nxt.pos)
    kind = jnp.where(out, ev.OUT, kind)
    invalid = ~is_valid(nxt)
    kind = jnp.where(invalid, ev.INVALID, kind)
    nxt = jax.tree.map(lambda a, b: jnp.where(invalid | ~alive, b, a), nxt, ball)
    kind = jnp.where(alive, kind, ev.NONE)
    time = t + jnp.where(out | invalid, 1.0, prop.tau) * dt
    log_post = jax.tree.map(lambda a, b: jnp.where(bounced, a, b), post, prop.pre)
    stops = (kind == ev.FLOOR) | (kind == ev.OUT) | (kind == ev.INVALID) | (kind == ev.REST)
    return nxt, kind, time, log_post, stops


# --------------------------------------------------------------------------- batch
def _in_place_identity(a):
    """``a`` unchanged, written as an in-place update of itself.

    A ``lax.switch`` branch that returns its operand as is makes XLA copy the operand into the
    switch's result on every step (for the event log of 65,536 balls, 65 MB a step); when every
    branch updates the operand in place, the result shares its buffer and nothing is copied.
    """
    corner = (0,) * a.ndim
    return jax.lax.dynamic_update_slice(a, jax.lax.dynamic_slice(a, corner, (1,) * a.ndim), corner)


def take_rows(tree, axes, rows):
    """Rows ``rows`` of the leaves of ``tree`` that carry a per-ball axis (``axes`` 0), the rest as is."""
    return jax.tree.map(lambda ax, sub: sub if ax is None else jax.tree.map(lambda a: a[rows], sub),
                        axes, tree, is_leaf=lambda x: x is None)


def _residual_rows(residual, res_axes, x, eps):
    """The residual network's attenuated correction for each row of ``x`` (C, n_in).

    Each row is evaluated with its own weights when the network is per ball (``res_axes`` 0),
    with shared ones otherwise (vmap turns the shared case into one matrix product).
    """
    from ttsim_jax.physics.residual import sampled_residual

    def one(net, xi, ei):
        out = sampled_residual(net, xi[None], None if ei is None else ei[None])
        return jax.tree.map(lambda a: a[0], out)

    return jax.vmap(one, in_axes=(res_axes, 0, None if eps is None else 0))(residual, x, eps)


def _events(model: Model, axes, ball: Ball, alive, free: Ball, rackets, rackets_batched, rows, ball_id, t, dt,
            key, sample, net_rows=None):
    """Exact detection, contact response and bookkeeping for the balls ``rows`` (C,) of the batch.

    Rows out of range (>= B) are unused buffer slots; their results are dropped by the scatters.
    ``net_rows``: evaluate the residual network only on that many rows, gathered from those with a
    racket contact (the caller guarantees there are no more); None: on every row.

    Returns:
        (rows, next ball (C, 3), kind (C,), event time (C,), racket index (C,), pre, log_post,
        contact (C, 2), sigma (C, 6), stops (C,)).
    """
    b = alive.shape[0]
    safe = jnp.minimum(rows, b - 1)
    take = lambda a: a[safe]  # noqa: E731
    phys, phys_axes = model.replace(residual=None), axes.replace(residual=None)
    m_c = take_rows(phys, phys_axes, safe)
    ball_c, free_c = jax.tree.map(take, ball), jax.tree.map(take, free)
    free_c = jax.vmap(settle, in_axes=(phys_axes, 0, 0))(m_c, ball_c, free_c)
    alive_c = take(alive) & (rows < b)
    r_c = None if rackets is None else (jax.tree.map(take, rackets) if rackets_batched else rackets)
    r_ax = 0 if rackets_batched else None
    prop = jax.vmap(detect, in_axes=(phys_axes, 0, 0, r_ax, None))(m_c, ball_c, free_c, r_c, dt)
    kind, tau = prop.kind, prop.tau
    hit = None
    if rackets is not None:
        j = jnp.maximum(prop.racket, 0)
        hit = (jax.tree.map(lambda a: a[jnp.arange(j.shape[0]), j], r_c) if rackets_batched
               else jax.tree.map(lambda a: a[j], r_c))
        hit = hit.replace(pos=hit.pos + (tau * dt)[:, None] * hit.vel)  # the racket at the contact time
    post, x, rot = jax.vmap(respond, in_axes=(phys_axes, 0, 0, 0 if hit is not None else None))(
        m_c, prop.pre, kind, hit)
    sigma = jnp.zeros(kind.shape + (6,), x.dtype)
    if model.residual is not None:
        res_axes = axes.residual
        # the network's rows: every row, or the few with a racket contact (a racket contact is rare,
        # the network costs more than the rest of a row: evaluated on them only, scattered back)
        sub = (jnp.arange(kind.shape[0]) if net_rows is None
               else jnp.nonzero(kind == ev.RACKET, size=net_rows, fill_value=kind.shape[0])[0])
        sub_safe = jnp.minimum(sub, kind.shape[0] - 1)
        net = take_rows(model.residual, res_axes, safe[sub_safe])
        eps = None
        if sample:
            ids = ball_id[safe[sub_safe]]
            eps = jax.vmap(lambda i: jax.random.normal(jax.random.fold_in(key, i), (6,), x.dtype))(ids)
        out = _residual_rows(net, res_axes, x[sub_safe, :model.residual.config.n_inputs], eps)
        if net_rows is not None:
            out = {k: jnp.zeros(kind.shape + v.shape[1:], v.dtype).at[sub].set(v, mode="drop") for k, v in out.items()}
        is_r = (kind == ev.RACKET)[:, None]
        dv, dw = jnp.where(is_r, out["dv"], 0.0), jnp.where(is_r, out["dw"], 0.0)
        post = post.replace(vel=post.vel + jnp.einsum("cij,cj->ci", rot, dv.astype(x.dtype)),
                            spin=post.spin + jnp.einsum("cij,cj->ci", rot, dw.astype(x.dtype)))
        sigma = jnp.where(is_r, jnp.concatenate([out["sigma_v"], out["sigma_w"]], axis=-1), 0.0).astype(x.dtype)
    t_ax = None if jnp.ndim(t) == 0 else 0
    t_c = t if t_ax is None else take(t)
    after = jax.vmap(finish, in_axes=(phys_axes, 0, 0, t_ax, None))(m_c, post, tau, t_c, dt)
    nxt, kind, time, log_post, stops = jax.vmap(resolve, in_axes=(0, 0, 0, 0, 0, 0, t_ax, None))(
        ball_c, alive_c, free_c, prop, post, after, t_c, dt)
    is_r = kind == ev.RACKET
    contact = jnp.where(is_r[:, None], x[:, 6:8], 0.0)
    sigma = jnp.where(is_r[:, None], sigma, 0.0)
    return nxt, kind, time, prop.racket, prop.pre, log_post, contact, sigma, stops


def step(model: Model, axes, ball: Ball, alive, status, ball_id, log: EventLog | None, rackets: Racket | None,
         t, dt, *, rackets_batched: bool = False, integrator: str = "rk4", capacity: int = 64, key=None,
         sample: bool = False, reference: bool = False, buffering: str = "loop"):
    """Advances a batch of balls by one step.

    Arguments:
        model: model parameters; axes: its per-ball axes (pytree prefix of 0 / None).
        ball: :class:`Ball` (B, 3); alive, status, ball_id: (B,) see :class:`~ttsim_jax.kernel.state.RallyState`.
        log: the :class:`EventLog` to append to, or None to log nothing.
        rackets: :class:`Racket` with (R, ...) fields shared by all balls, (B, R, ...) if
            ``rackets_batched``, or None.
        t, dt: time at the start of the step ((), or (B,) when the balls' clocks differ, as in the
            fused path) and step length [s].
        integrator: flight integrator (static); capacity: contact buffer rows (static).
        key, sample: the step's PRNG key and whether to sample the residual from its predicted std.
        reference: run the exact detection for every ball (static): the straightforward step the
            lean one is tested against.
        buffering: how the flagged balls reach the contact models (static; same results):
            ``"loop"`` runs buffers of ``capacity`` rows one after the other, each only when it
            holds a ball (a skipped branch is free on CPU); ``"single"`` runs one buffer at every
            step, branch-free, and the whole batch in a step with more flagged balls than
            ``capacity`` (on a GPU every branch costs a device-to-host copy of its predicate, which
            made the loop ~1 ms a step). With a residual network and rackets, ``"single"`` also
            evaluates the network on ``capacity // NET_FRACTION`` rows only, those of the buffer
            with a racket contact, and runs the whole batch in a step where more balls may meet a
            racket (:func:`may_need_network`) than that.

    Returns:
        (ball, alive, status, log) after the step.
    """
    b = alive.shape[0]
    phys, phys_axes = model.replace(residual=None), axes.replace(residual=None)
    r_ax = 0 if rackets_batched else None
    t_ax = None if jnp.ndim(t) == 0 else 0
    free = jax.vmap(partial(flight, integrator=integrator), in_axes=(phys_axes, 0, t_ax, None))(phys, ball, t, dt)
    flag = alive & jax.vmap(may_have_event, in_axes=(phys_axes, 0, 0, r_ax, None))(phys, ball, free, rackets, dt)
    base = jax.tree.map(lambda f, o: jnp.where(alive[:, None], f, o), free, ball)
    capacity = min(capacity, b)

    def events(rows):
        return _events(model, axes, ball, alive, free, rackets, rackets_batched, rows, ball_id, t, dt, key, sample)

    def write(rows, out):
        """The events ``out`` of the balls ``rows`` written into the batch (rows >= B are dropped)."""
        nxt, kind, time, racket, pre, post, contact, sigma, stops = out
        safe = jnp.minimum(rows, b - 1)
        put = lambda full, part: full.at[rows].set(part, mode="drop")  # noqa: E731
        new_log = None if log is None else log.write(rows, kind != ev.NONE, kind, time, racket, pre, post,
                                                     contact, sigma)
        return (jax.tree.map(put, base, nxt), put(alive, alive[safe] & ~stops),
                put(status, jnp.where(stops, kind, status[safe])), new_log)

    if reference:
        rows = jnp.arange(b)
        return write(rows, events(rows))
    if buffering == "single":
        net_rows = capacity // NET_FRACTION if (model.residual is not None and rackets is not None
                                                and capacity >= NET_MIN_BUFFER) else None

        def one_buffer():
            rows = jnp.nonzero(flag, size=capacity, fill_value=b)[0]
            return write(rows, _events(model, axes, ball, alive, free, rackets, rackets_batched, rows, ball_id, t,
                                       dt, key, sample, net_rows))

        if capacity >= b:
            return one_buffer()
        everyone = jnp.arange(b)
        crowded = jnp.sum(flag) > capacity
        if net_rows is not None:
            near = alive & jax.vmap(may_need_network, in_axes=(phys_axes, 0, 0, r_ax, None))(phys, ball, free,
                                                                                              rackets, dt)
            crowded |= jnp.sum(near) > net_rows
        return jax.lax.cond(crowded, lambda: write(everyone, events(everyone)), one_buffer)
    if buffering != "loop":
        raise ValueError(f"buffering must be 'loop' or 'single', got {buffering!r}")
    # The flagged balls go through one buffer of ``capacity`` rows at a time: usually once, a few
    # times when many balls have an event in the same step. One buffer shape means one compiled copy
    # of the contact models whatever the count (a second, full-batch branch doubled compile time);
    # the buffers' results are written once, after the loop, so that no loop carries the event log.
    n_buf = -(-b // capacity)

    def buffers():
        rows = jnp.nonzero(flag, size=n_buf * capacity, fill_value=b)[0]
        if n_buf == 1:
            return write(rows, events(rows))
        blank = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(events, rows[:capacity]))

        def one(_, r):
            return None, jax.lax.cond(r[0] < b, events, lambda r: blank, r)

        _, out = jax.lax.scan(one, None, rows.reshape(n_buf, capacity))
        return write(rows, jax.tree.map(lambda a: a.reshape((n_buf * capacity,) + a.shape[2:]), out))

    return jax.lax.cond(jnp.any(flag), buffers,
                        lambda: jax.tree.map(_in_place_identity, (base, alive, status, log)))
