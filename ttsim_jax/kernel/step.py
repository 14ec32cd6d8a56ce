"""One step of the rally kernel for a batch of balls.

Contacts are rare (a few per ball per second), so a step does the least work for the balls that
have none:

1. Every ball (``vmap`` of the one-ball functions of :mod:`.ball_step`): free flight over the step (:func:`flight`) and a
   cheap test whether anything *may* happen in it (:func:`may_have_event`: the sign changes of the
   gap functions, leaving play, an invalid state). No time of impact, no contact model.
2. The balls that may have an event are gathered into a buffer of ``capacity`` rows, where the
   exact detection (:func:`detect`: time of impact refined on the Hermite path, face and table
   outlines), the contact models, the racket residual network, the rest of the step after the
   contact (:func:`finish`) and the bookkeeping (:func:`resolve`) run; the rows are scattered back
   and their events appended to the log. A step's events are handled one after the other in time
   order, each at its own time: after one, the rest of the step is searched again from the state
   after it (up to ``EVENTS_PER_STEP``), so that a ball crossing the net and landing a fraction of a
   millisecond later logs the crossing and bounces where it meets the table. A step with more such balls than ``capacity`` runs the
   same function on the whole batch (same result, full cost); a step with none skips it. The choice
   is a ``lax.switch`` at batch level, outside any vmap, so only one branch runs.

Per-ball parameters: ``model_axes`` is a pytree prefix of the model, like ``jax.vmap``'s
``in_axes``: 0 where a leaf carries a leading (B,) axis, None where it is shared (see
:func:`~ttsim_jax.kernel.axes.per_ball_axes`).
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.kernel.ball_step import FIXED_SLOTS, detect, finish, flight, may_hit, resolve, respond, settle, step_flags
from ttsim_jax.kernel.eventlog import EventLog
from ttsim_jax.params import Model
from ttsim_jax.physics import events as ev
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.numerics import matvec
from ttsim_jax.state import Ball, Racket

# The most events of one ball handled in one step; each kind (each racket) happens at most once in
# a step, so three cover a net crossing, a bounce and a racket contact within the same step.
EVENTS_PER_STEP = 3
# The "single" buffering's network rows: 1/NET_FRACTION of the contact buffer (B/32 rows), for buffers
# of at least NET_MIN_BUFFER rows. Two tracking rackets and 65,536 realistic shots over 1,000 steps
# gave at most 101 racket contacts in a step (0.15 % of the balls; the buffer of B/32 holds 3.1 %,
# B/256 0.39 %).
NET_FRACTION, NET_MIN_BUFFER = 8, 64



@struct.dataclass
class StepEvents:
    """What :func:`_events` found for the C balls of a buffer in one step (S = ``EVENTS_PER_STEP``).

    Attributes:
        next: :class:`Ball` (C, 3) after the step.
        events: an :class:`EventLog` of S slots per row: each row's events in the step in time order
            (NONE after the last; ``post`` is the state before a net crossing, which changes nothing).
        stopped: (C,) the kind that took the ball out of play in the step (0 if none).
    """

    next: Ball
    events: EventLog
    stopped: jnp.ndarray


class _Stage(NamedTuple):
    """The carry of :func:`_events`' stages: where the rest of the step starts and ends (Ball (C, 3)),
    the fraction of the step used (C,), the candidates already met (C, slots), and which rows go on."""

    start: Ball
    end: Ball
    tau: jnp.ndarray
    done: jnp.ndarray
    going: jnp.ndarray


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
    from ttsim_jax.physics.network import sampled_residual

    def one(net, xi, ei):
        out = sampled_residual(net, xi[None], None if ei is None else ei[None])
        return jax.tree.map(lambda a: a[0], out)

    return jax.vmap(one, in_axes=(res_axes, 0, None if eps is None else 0))(residual, x, eps)


@struct.dataclass
class _StepInputs:
    """What a step's event stage reads of the whole batch: the balls at the step's start (``ball``,
    ``alive``) and after its free flight (``free``), the rackets ((R, ...), or (B, R, ...) with
    ``rackets_batched``), the balls' ids, the step's time and length and its PRNG key."""

    ball: Ball
    alive: Any
    free: Ball
    rackets: Any
    ball_id: Any
    t: Any
    dt: Any
    key: Any
    rackets_batched: bool = struct.field(pytree_node=False, default=False)


def _events(model: Model, axes, inputs: _StepInputs, rows, *, sample: bool, net_rows=None, unrolled=False):
    """Exact detection, contact responses and bookkeeping for the balls ``rows`` (C,) of the batch.

    Each row's step is handled in up to ``EVENTS_PER_STEP`` stages: a stage finds the earliest event
    on what is left of the step (:func:`detect`), applies
    it at its own time (:func:`respond`, the residual network, :func:`finish`) and leaves the state
    after it (bounced, or unchanged after a net crossing, whose remaining path is the same free
    flight) to the next stage; a kind (a racket) handled in the step is not sought again in it, a
    terminal event ends the step. Rows out of range (>= B) are unused buffer slots; their results
    are dropped by the scatters. ``net_rows``: evaluate the residual network only on that many rows,
    gathered from those with a racket contact in the stage (the caller guarantees there are no
    more); None: on every row. ``unrolled``: the first stage outside any loop and one branch for
    the others (for a GPU, where a loop's every iteration and every branch costs a device-to-host
    copy of its predicate; the stage is compiled twice); else one loop over the stages, each after
    the first skipped where no row needs it (compiled once).

    Returns:
        :class:`StepEvents` of the C rows.
    """
    ball, alive, free, rackets, rackets_batched = (inputs.ball, inputs.alive, inputs.free, inputs.rackets,
                                                   inputs.rackets_batched)
    ball_id, t, dt, key = inputs.ball_id, inputs.t, inputs.dt, inputs.key
    b = alive.shape[0]
    safe = jnp.minimum(rows, b - 1)
    take = lambda a: a[safe]  # noqa: E731
    phys, phys_axes = model.replace(residual=None), axes.replace(residual=None)
    m_c = take_rows(phys, phys_axes, safe)
    ball_c, free_c = jax.tree.map(take, ball), jax.tree.map(take, free)
    free_c = jax.vmap(settle, in_axes=(phys_axes, 0, 0))(m_c, ball_c, free_c)
    alive_c = take(alive) & (rows < b)
    r_c = None if rackets is None else (jax.tree.map(take, rackets) if rackets_batched else rackets)
    t_ax = None if jnp.ndim(t) == 0 else 0
    t_c = t if t_ax is None else take(t)
    n = safe.shape[0]
    n_slots = len(FIXED_SLOTS) + (0 if rackets is None else rackets.pos.shape[-2])
    dtype = ball.pos.dtype
    r_ax = 0 if rackets_batched else None

    def stage(carry: _Stage, i):
        start, end, tau0, done, going = carry
        seg = (1.0 - tau0) * dt
        with jax.named_scope("detect"):
            prop = jax.vmap(detect, in_axes=(phys_axes, 0, 0, r_ax, 0, 0, 0))(m_c, start, end, r_c, seg, done,
                                                                              tau0 * dt)
        kind = jnp.where(going, prop.kind, ev.NONE)
        tau = tau0 + (1.0 - tau0) * prop.tau  # of the whole step
        hit = None
        if rackets is not None:
            j = jnp.maximum(prop.racket, 0)
            hit = (jax.tree.map(lambda a: a[jnp.arange(n), j], r_c) if rackets_batched
                   else jax.tree.map(lambda a: a[j], r_c))
            hit = jax.vmap(racket_stage.advance)(hit, tau * dt)  # the racket at the contact time
            hit = jax.vmap(racket_stage.facing)(hit, prop.pre.pos)  # turned onto the rim's normal there
        with jax.named_scope("respond"):
            post, x, rot = jax.vmap(respond, in_axes=(phys_axes, 0, 0, 0 if hit is not None else None))(
                m_c, prop.pre, kind, hit)
        is_r = kind == ev.RACKET
        sigma = jnp.zeros(kind.shape + (6,), dtype)
        if model.residual is not None:
            res_axes = axes.residual
            # the network's rows: every row, or the few with a racket contact (a racket contact is
            # rare, the network costs more than the rest of a row: evaluated on them only, scattered back)
            sub = jnp.arange(n) if net_rows is None else jnp.nonzero(is_r, size=net_rows, fill_value=n)[0]
            sub_safe = jnp.minimum(sub, n - 1)
            net = take_rows(model.residual, res_axes, safe[sub_safe])
            eps = None
            if sample:
                def draw(ball_key):
                    # the first stage's draws as they were before stages existed; later ones folded further
                    first = jax.random.normal(ball_key, (6,), dtype)
                    return jnp.where(i == 0, first, jax.random.normal(jax.random.fold_in(ball_key, i), (6,), dtype))

                # one key for the step, or one per ball (the fused path, where the balls' clocks differ)
                typed = jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
                own = jnp.ndim(key) > (0 if typed else 1)
                keys = key[safe[sub_safe]] if own else key
                eps = jax.vmap(lambda kk, j: draw(jax.random.fold_in(kk, j)), in_axes=(0 if own else None, 0))(
                    keys, ball_id[safe[sub_safe]])
            with jax.named_scope("residual_network"):
                out = _residual_rows(net, res_axes, x[sub_safe, :model.residual.config.n_inputs], eps)
            if net_rows is not None:
                out = {k: jnp.zeros((n,) + v.shape[1:], v.dtype).at[sub].set(v, mode="drop") for k, v in out.items()}
            dv, dw = jnp.where(is_r[:, None], out["dv"], 0.0), jnp.where(is_r[:, None], out["dw"], 0.0)
            post = post.replace(vel=post.vel + matvec(rot, dv.astype(dtype)),
                                spin=post.spin + matvec(rot, dw.astype(dtype)))
            sigma = jnp.concatenate([out["sigma_v"], out["sigma_w"]], axis=-1).astype(dtype)
        with jax.named_scope("finish"):
            after = jax.vmap(finish, in_axes=(phys_axes, 0, 0, t_ax, None))(m_c, post, tau, t_c, dt)
        bounced = ((kind == ev.TABLE) | is_r)[:, None]
        net_or_floor = ((kind == ev.NET) | (kind == ev.FLOOR))[:, None]
        # after a bounce the rest of the step starts from the bounce; after a net crossing from the
        # crossing, on the same path; a ball on the floor stops where it lands
        nxt_start = jax.tree.map(lambda a, p, s: jnp.where(bounced, a, jnp.where(net_or_floor, p, s)),
                                 post, prop.pre, start)
        nxt_end = jax.tree.map(lambda a, p, e: jnp.where(bounced, a, jnp.where(kind[:, None] == ev.FLOOR, p, e)),
                               after, prop.pre, end)
        log_post = jax.tree.map(lambda a, p: jnp.where(bounced, a, p), post, prop.pre)
        record = (kind, (t_c + tau * dt).astype(dtype), jnp.where(is_r, prop.racket, -1),
                  prop.pre, log_post, jnp.where(is_r[:, None], x[:, 6:8], 0.0), jnp.where(is_r[:, None], sigma, 0.0))
        slots = jnp.arange(n_slots)
        done = done | (slots == prop.slot[:, None]) | (slots == FIXED_SLOTS.index(ev.REST))
        # the next stage only for rows whose rest of the step may hold another event
        fixed, near = jax.vmap(may_hit, in_axes=(phys_axes, 0, 0, r_ax, 0, 0))(
            m_c, nxt_start, nxt_end, r_c, (1.0 - tau) * dt, tau * dt)
        more = jnp.stack(fixed, axis=-1) if near is None else jnp.concatenate([jnp.stack(fixed, axis=-1), near], -1)
        going = going & (bounced[:, 0] | (kind == ev.NET)) & jnp.any(more & ~done, axis=-1)
        return _Stage(nxt_start, nxt_end, jnp.where(going, tau, tau0), done, going), record

    def later(carry):
        """The stages after the first, over the rows that may have another event."""
        return jax.lax.scan(stage, carry, jnp.arange(1, EVENTS_PER_STEP))

    def idle(carry):
        zero3 = jnp.zeros((EVENTS_PER_STEP - 1, n, 3), dtype)
        none = Ball(zero3, zero3, zero3)
        shape = (EVENTS_PER_STEP - 1, n)
        return carry, (jnp.zeros(shape, jnp.int32), jnp.zeros(shape, dtype), -jnp.ones(shape, jnp.int32), none, none,
                       jnp.zeros(shape + (2,), dtype), jnp.zeros(shape + (6,), dtype))

    carry = _Stage(ball_c, free_c, jnp.zeros(n, dtype), jnp.zeros((n, n_slots), bool), alive_c)
    # a second event in a step is rare: the later stages run only where a row may have one (a branch)
    if unrolled:
        carry, first = stage(carry, 0)
        carry, rest = jax.lax.cond(jnp.any(carry.going), later, idle, carry)
        record = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), first, rest)
    else:
        def one(carry, i):
            def none(carry, i):
                carry, rest = idle(carry)
                return carry, jax.tree.map(lambda a: a[0], rest)

            return jax.lax.cond((i == 0) | jnp.any(carry.going), stage, none, carry, i)

        carry, record = jax.lax.scan(one, carry, jnp.arange(EVENTS_PER_STEP))
    kind, time, racket, pre, log_post, contact, sigma = jax.tree.map(lambda a: jnp.moveaxis(a, 0, 1), record)
    with jax.named_scope("resolve"):
        nxt, kind, time, stopped = jax.vmap(resolve, in_axes=(0, 0, 0, 0, 0, t_ax, None))(
            ball_c, alive_c, carry.end, kind, time, t_c, dt)
    found = EventLog(kind=kind, time=time, racket=racket, pre=pre, post=log_post, contact=contact, sigma=sigma,
                     count=jnp.sum(kind != ev.NONE, axis=1, dtype=jnp.int32))
    return StepEvents(next=nxt, events=found, stopped=stopped)


@struct.dataclass
class StepState:
    """What a step advances for a batch of B balls (``fn(model, state) -> state``).

    Attributes:
        ball: :class:`Ball` (B, 3); alive, status: (B,), as in
            :class:`~ttsim_jax.kernel.state.RallyState`; log: the :class:`EventLog` the step's
            events are appended to, or None to log nothing.
    """

    ball: Ball
    alive: jnp.ndarray
    status: jnp.ndarray
    log: EventLog | None


@dataclasses.dataclass(frozen=True)
class StepOptions:
    """The static options of :func:`step` (frozen: equal options are one compiled step).

    Attributes:
        integrator: flight integrator; capacity: contact buffer rows.
        sample: sample the residual network's correction from its predicted std (needs a key).
        reference: run the exact detection for every ball: the straightforward step the lean one is
            tested against.
        buffering: how the flagged balls reach the contact models (same results): ``"loop"`` runs
            buffers of ``capacity`` rows one after the other, each only when it holds a ball (a
            skipped branch is free on CPU); ``"single"`` runs one buffer at every step, and the
            whole batch in a step with more flagged balls than ``capacity`` (on a GPU every branch
            costs a device-to-host copy of its predicate, which made the loop ~1 ms a step; its
            branches are that choice and the rare second event of a step, :func:`_events`, whose
            stages it runs unrolled). With a residual network and rackets, ``"single"`` also
            evaluates the network on ``capacity // NET_FRACTION`` rows only, those of the buffer
            with a racket contact, and runs the whole batch in a step where more balls may meet a
            racket (:func:`~ttsim_jax.kernel.ball_step.may_need_network`) than that.
    """

    integrator: str = "rk4"
    capacity: int = 64
    sample: bool = False
    reference: bool = False
    buffering: str = "loop"


def step(model: Model, axes, state: StepState, ball_id, rackets: Racket | None, t, dt, *,
         options: StepOptions = StepOptions(), rackets_batched: bool = False, key=None) -> StepState:
    """Advances a batch of balls by one step.

    Arguments:
        model: model parameters; axes: its per-ball axes (pytree prefix of 0 / None).
        state: :class:`StepState` of the B balls; ball_id: (B,) their ids (the residual's draws follow them).
        rackets: :class:`Racket` with (R, ...) fields shared by all balls, (B, R, ...) if
            ``rackets_batched``, or None.
        t, dt: time at the start of the step ((), or (B,) when the balls' clocks differ, as in the
            fused path) and step length [s].
        options: :class:`StepOptions` (static).
        key: the step's PRNG key ((B,) keys, one per ball, when the balls' clocks differ), read with
            ``options.sample``.

    Returns:
        The :class:`StepState` after the step.
    """
    ball, alive, status, log = state.ball, state.alive, state.status, state.log
    integrator, capacity, sample = options.integrator, options.capacity, options.sample
    reference, buffering = options.reference, options.buffering
    b = alive.shape[0]
    phys, phys_axes = model.replace(residual=None), axes.replace(residual=None)
    r_ax = 0 if rackets_batched else None
    t_ax = None if jnp.ndim(t) == 0 else 0
    with jax.named_scope("flight"):
        free = jax.vmap(partial(flight, integrator=integrator), in_axes=(phys_axes, 0, t_ax, None))(phys, ball, t,
                                                                                                    dt)
    # one pass of the cheap tests gives both flags (the second is only read with a network and rackets)
    with jax.named_scope("flags"):
        flag, near = jax.vmap(step_flags, in_axes=(phys_axes, 0, 0, r_ax, None))(phys, ball, free, rackets, dt)
    flag, near = alive & flag, alive & near
    base = jax.tree.map(lambda f, o: jnp.where(alive[:, None], f, o), free, ball)
    capacity = min(capacity, b)
    inputs = _StepInputs(ball, alive, free, rackets, ball_id, t, dt, key, rackets_batched=rackets_batched)

    def events(rows):
        with jax.named_scope("events"):
            return _events(model, axes, inputs, rows, sample=sample, unrolled=buffering == "single")

    def write(rows, out: StepEvents):
        """The events ``out`` of the balls ``rows`` written into the batch (rows >= B are dropped)."""
        found = out.events
        kind = found.kind
        safe = jnp.minimum(rows, b - 1)
        put = lambda full, part: full.at[rows].set(part, mode="drop")  # noqa: E731
        def log_events(lg, stages):
            for i in stages:  # in time order
                at = lambda a: a[:, i]  # noqa: E731
                lg = lg.write(rows, kind[:, i] != ev.NONE, kind[:, i], found.time[:, i], found.racket[:, i],
                              jax.tree.map(at, found.pre), jax.tree.map(at, found.post), found.contact[:, i],
                              found.sigma[:, i])
            return lg

        new_log = log
        if log is not None:
            new_log = log_events(log, [0])
            later = partial(log_events, stages=range(1, kind.shape[1]))
            if buffering == "single":
                new_log = later(new_log)
            else:  # a step's second event is rare: its writes (scatters over every row) skipped without one
                new_log = jax.lax.cond(jnp.any(kind[:, 1:] != ev.NONE), later,
                                       lambda lg: jax.tree.map(_in_place_identity, lg), new_log)
        stops = out.stopped != 0
        return StepState(jax.tree.map(put, base, out.next), put(alive, alive[safe] & ~stops),
                         put(status, jnp.where(stops, out.stopped, status[safe])), new_log)

    if reference:
        rows = jnp.arange(b)
        return write(rows, events(rows))
    if buffering == "single":
        net_rows = capacity // NET_FRACTION if (model.residual is not None and rackets is not None
                                                and capacity >= NET_MIN_BUFFER) else None

        def one_buffer():
            rows = jnp.nonzero(flag, size=capacity, fill_value=b)[0]
            with jax.named_scope("events"):
                found = _events(model, axes, inputs, rows, sample=sample, net_rows=net_rows, unrolled=True)
            return write(rows, found)

        if capacity >= b:
            return one_buffer()
        everyone = jnp.arange(b)
        crowded = jnp.sum(flag) > capacity
        if net_rows is not None:
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
        # only the buffers that hold a ball run (a loop of a step's own length): a scan over all
        # B / capacity of them, most empty, cost more than the contacts (32 per block of 1,024
        # balls, each an iteration that wrote its blank results out)
        shapes = jax.eval_shape(events, rows[:capacity])
        out = jax.tree.map(lambda s: jnp.zeros((n_buf,) + s.shape, s.dtype), shapes)

        def one(i, out):
            res = events(jax.lax.dynamic_slice_in_dim(rows, i * capacity, capacity))
            return jax.tree.map(lambda a, x: jax.lax.dynamic_update_index_in_dim(a, x, i, 0), out, res)

        used = (jnp.sum(flag, dtype=jnp.int32) + capacity - 1) // capacity
        out = jax.lax.fori_loop(0, used, one, out)
        return write(rows, jax.tree.map(lambda a: a.reshape((n_buf * capacity,) + a.shape[2:]), out))

    return jax.lax.cond(jnp.any(flag), buffers,
                        lambda: jax.tree.map(_in_place_identity, StepState(base, alive, status, log)))
