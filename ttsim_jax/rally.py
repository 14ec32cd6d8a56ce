"""The rally kernel: one ``lax.scan`` over time steps composing flight, contacts and the network.

A step, for a batch of balls:

1. ``detect`` (vmapped, one ball): free flight over the step, then the earliest event of the step
   (table, racket faces, net, floor) with its time of impact and the state there.
2. Contacts, at batch level: only the balls with a table or racket contact this step are gathered
   into a fixed-capacity buffer, where ``respond`` (contact models), the racket residual network
   and ``finish`` (the rest of the step after the contact) run.
3. ``resolve`` (vmapped, one ball): picks the next state, logs the event, masks invalid states
   and retires balls that left play.

Racket plans: ``None``; a :class:`~ttsim_jax.state.Racket` schedule with a leading time axis
(``(T, R, ...)`` shared by all balls, or ``(B, T, R, ...)`` per ball; R rackets, the R axis may be
left out for one racket); or a :class:`RacketPolicy`, a pure function of (params, ball, t)
evaluated inside the scan (the form an RL environment uses).
"""

from __future__ import annotations

import math
from functools import partial
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.params import Model
from ttsim_jax.physics import aero as aero_stage
from ttsim_jax.physics import events as ev
from ttsim_jax.physics import hooks
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics import table as table_stage
from ttsim_jax.state import Ball, Racket

# Beyond these a state is flagged invalid and frozen (m/s, rad/s, m).
MAX_SPEED, MAX_SPIN, MAX_DISTANCE = 200.0, 2.0e4, 100.0


@struct.dataclass
class EventLog:
    """Contacts of one ball, in order; a fixed capacity K of slots.

    Attributes:
        kind: (K,) event kind (``physics.events.KIND_NAMES``), 0 in unused slots.
        time: (K,) time of the event [s].
        racket: (K,) index of the racket hit, -1 for other events.
        pre, post: :class:`Ball` with (K, 3) fields: state just before and after the event.
        contact: (K, 2) contact position on the racket face (d_y, d_z) [m].
        sigma: (K, 6) the residual network's predicted standard deviations of the racket-frame
            post-contact velocity and spin (zeros without a network).
        count: () number of events that happened; more than K means the last ones were dropped.
    """

    kind: jnp.ndarray
    time: jnp.ndarray
    racket: jnp.ndarray
    pre: Ball
    post: Ball
    contact: jnp.ndarray
    sigma: jnp.ndarray
    count: jnp.ndarray

    @classmethod
    def empty(cls, capacity: int, dtype) -> "EventLog":
        z3 = jnp.zeros((capacity, 3), dtype)
        zb = Ball(z3, z3, z3)
        return cls(kind=jnp.zeros(capacity, jnp.int32), time=jnp.zeros(capacity, dtype),
                   racket=-jnp.ones(capacity, jnp.int32), pre=zb, post=zb,
                   contact=jnp.zeros((capacity, 2), dtype), sigma=jnp.zeros((capacity, 6), dtype),
                   count=jnp.zeros((), jnp.int32))

    def record(self, happened, kind, time, racket, pre: Ball, post: Ball, contact, sigma) -> "EventLog":
        capacity = self.kind.shape[0]
        slot = jnp.minimum(self.count, capacity - 1)
        write = happened & (self.count < capacity)

        def put(buf, value):
            return buf.at[slot].set(jnp.where(write, value, buf[slot]))

        return EventLog(
            kind=put(self.kind, kind), time=put(self.time, time), racket=put(self.racket, racket),
            pre=jax.tree.map(put, self.pre, pre), post=jax.tree.map(put, self.post, post),
            contact=put(self.contact, contact), sigma=put(self.sigma, sigma),
            count=self.count + happened.astype(jnp.int32))


@struct.dataclass
class RallyState:
    """State of the batch between steps.

    Attributes:
        ball: :class:`Ball` with (B, 3) fields.
        alive: (B,) False once the ball hit the floor, left play, came to rest on the table or
            became invalid (then frozen).
        status: (B,) why it stopped (``FLOOR``, ``OUT``, ``REST``, ``INVALID``), 0 while alive.
        events: :class:`EventLog` with a leading (B,) axis.
        time: () current time [s].
    """

    ball: Ball
    alive: jnp.ndarray
    status: jnp.ndarray
    events: EventLog
    time: jnp.ndarray


@struct.dataclass
class RacketPolicy:
    """A racket plan evaluated inside the scan: ``fn(params, ball, t) -> Racket`` ((R, ...) fields).

    ``fn`` is static (part of the compiled program); ``params`` is a pytree argument, so new
    policy parameters never recompile.
    """

    params: Any
    fn: Callable = struct.field(pytree_node=False)


@struct.dataclass
class Proposal:
    """Result of :func:`detect` for one ball and step: the earliest event and the states around it.

    Attributes:
        kind: event kind (``physics.events``), NONE if nothing happens in the step.
        tau: time of the event as a fraction of the step (1 if none).
        racket: index of the racket hit, -1 otherwise.
        free: :class:`Ball` at the end of the step in free flight.
        pre: :class:`Ball` at the event (the free-flight path at tau).
    """

    kind: jnp.ndarray
    tau: jnp.ndarray
    racket: jnp.ndarray
    free: Ball
    pre: Ball


@struct.dataclass
class Response:
    """What a contact does to one ball.

    Attributes:
        post: :class:`Ball` just after the contact (residual correction included).
        after: :class:`Ball` at the end of the step, flown on from the contact.
        contact: (2,) contact position on the racket face (zeros for the table).
        sigma: (6,) the residual network's predicted std (zeros without one).
    """

    post: Ball
    after: Ball
    contact: jnp.ndarray
    sigma: jnp.ndarray


@struct.dataclass
class RallyResult:
    """Output of :func:`simulate`.

    Attributes:
        final: :class:`Ball` (B, 3) at the end (or where the ball stopped).
        alive, status: (B,) see :class:`RallyState`.
        events: :class:`EventLog` with a leading (B,) axis.
        trajectory: :class:`Ball` with (B, N, 3) fields, the state every ``record_every`` steps
            (None when not recorded).
        times: (N,) times of the recorded states.
    """

    final: Ball
    alive: jnp.ndarray
    status: jnp.ndarray
    events: EventLog
    trajectory: Any = None
    times: Any = None


def init_state(ball: Ball, max_events: int = 8, t0=0.0) -> RallyState:
    """A batch state for ``ball`` with (B, 3) fields."""
    b = ball.pos.shape[0]
    log = EventLog.empty(max_events, ball.pos.dtype)
    return RallyState(ball=ball, alive=jnp.ones(b, bool), status=jnp.zeros(b, jnp.int32),
                      events=jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), log),
                      time=jnp.asarray(t0, ball.pos.dtype))


def refuse_overlaps(model: Model, state: RallyState, rackets: Racket | None, *, model_batched: bool = False,
                    rackets_batched: bool = False) -> RallyState:
    """Flags the balls that start inside the table, the net or a racket as INVALID (stopped).

    Arguments:
        model: model parameters (leading (B,) axis if ``model_batched``); state: a fresh state;
        rackets: the rackets at the start, (R, ...) fields ((B, R, ...) if ``rackets_batched``) or
        None.

    Returns:
        The state with those balls stopped, status ``INVALID``.
    """
    def inside(m, ball, r):
        return ev.inside_obstacle(m.table, m.effects, ball_properties(m)[0], ball.pos, r)

    bad = jax.vmap(inside, in_axes=(0 if model_batched else None, 0, 0 if rackets_batched else None))(
        model.replace(residual=None), state.ball, rackets)
    return state.replace(alive=state.alive & ~bad, status=jnp.where(bad, ev.INVALID, state.status))


# --------------------------------------------------------------------------- one ball
def ball_properties(model: Model):
    """(radius, mass) of the ball after effects (hook ``ball_properties``)."""
    return hooks.apply(model.effects, "ball_properties", (model.ball.radius, model.ball.mass))


def detect(model: Model, ball: Ball, rackets: Racket | None, t, dt, integrator: str = "rk4") -> Proposal:
    """Free flight over a step and the earliest event in it, for one ball.

    Arguments:
        model: model parameters (its ``residual`` is not used here).
        ball: one ball, (3,) fields.
        rackets: :class:`Racket` with (R, ...) fields, or None.
        t, dt: time at the start of the step and step length [s].
        integrator: flight integrator name (static).

    Returns:
        A :class:`Proposal`.
    """
    fx = model.effects
    radius, mass = ball_properties(model)
    p0, v0, w0 = ball.pos, ball.vel, ball.spin
    p1, v1, w1 = aero_stage.flight_step(model.aero, radius, mass, p0, v0, w0, t, dt, fx, integrator)

    # a ball in sustained contact with the table slides or rolls on it (physics.table.slide)
    # instead of bouncing every step, and rests once slow
    touch = table_stage.touching(model.table, fx, radius, p0, v0)
    p1, v1, w1 = jax.tree.map(lambda a, b: jnp.where(touch, a, b),
                              table_stage.slide(model.table, radius, p1, v1, w1, fx), (p1, v1, w1))
    table = ev.table_candidate(model.table, fx, radius, p0, v0, p1, v1, dt)
    rest = touch & table_stage.at_rest(model.table, fx, radius, p1, v1, w1)
    cands = [(ev.TABLE, table.replace(hit=table.hit & ~touch)),
             (ev.REST, ev.Candidate(hit=rest, tau=jnp.ones_like(table.tau))),
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
    return Proposal(kind=kind, tau=tau, racket=racket_index, free=Ball(p1, v1, w1),
                    pre=Ball(pos, vel, w0 + tau * (w1 - w0)))


def respond(model: Model, pre: Ball, kind, racket: Racket | None, tau, t, dt):
    """Base-model response of one ball to its contact (table or racket).

    Arguments:
        model: model parameters; pre: the ball at the contact; kind: TABLE or RACKET;
        racket: the racket hit, (...) fields at the contact time (None without rackets);
        tau, t, dt: contact time as a fraction of the step, step start and length.

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


def resolve(ball: Ball, alive, status, log: EventLog, prop: Proposal, resp: Response, t, dt):
    """Completes a step for one ball: picks the next state, masks invalid ones, logs the event.

    Arguments:
        ball: the state at the start of the step; alive, status, log: the ball's bookkeeping;
        prop: from :func:`detect`; resp: the ball's :class:`Response` (used for table and racket
        contacts only); t, dt: time and step.

    Returns:
        (ball, alive, status, log) after the step.
    """
    kind = prop.kind
    bounced = (kind == ev.TABLE) | (kind == ev.RACKET)
    nxt = jax.tree.map(lambda a, b, c: jnp.where(bounced, a, jnp.where(kind == ev.FLOOR, b, c)),
                       resp.after, prop.pre, prop.free)
    out = (kind == ev.NONE) & ev.out_of_play(nxt.pos)
    kind = jnp.where(out, ev.OUT, kind)
    finite = jnp.all(jnp.isfinite(nxt.as_array()))
    sane = (jnp.linalg.norm(jnp.where(finite, nxt.vel, 0.0)) < MAX_SPEED) & (
        jnp.linalg.norm(jnp.where(finite, nxt.spin, 0.0)) < MAX_SPIN) & (
        jnp.max(jnp.abs(jnp.where(finite, nxt.pos, 0.0))) < MAX_DISTANCE)
    invalid = ~(finite & sane)
    kind = jnp.where(invalid, ev.INVALID, kind)
    nxt = jax.tree.map(lambda a, b: jnp.where(invalid, b, a), nxt, ball)

    happened = alive & (kind != ev.NONE)
    time = t + jnp.where(out | invalid, 1.0, prop.tau) * dt
    log_post = jax.tree.map(lambda a, b: jnp.where(bounced, a, b), resp.post, prop.pre)
    is_r = kind == ev.RACKET
    log = log.record(happened, kind, time, prop.racket, prop.pre, log_post, jnp.where(is_r, resp.contact, 0.0),
                     jnp.where(is_r, resp.sigma, 0.0))
    stops = (kind == ev.FLOOR) | (kind == ev.OUT) | (kind == ev.INVALID) | (kind == ev.REST)
    new_status = jnp.where(alive & stops, kind, status)
    nxt = jax.tree.map(lambda a, b: jnp.where(alive, a, b), nxt, ball)
    return nxt, alive & ~stops, new_status, log


# --------------------------------------------------------------------------- batch
def _respond_gathered(model: Model, prop: Proposal, rackets, idx, t, dt, key, sample, model_batched,
                      rackets_batched) -> Response:
    """Contact responses of the balls ``idx`` (indices into the batch; out of range = unused slot).

    Returns a :class:`Response` for the whole batch: computed rows at ``idx``, zeros elsewhere.
    """
    b = prop.kind.shape[0]
    valid = idx < b
    safe = jnp.minimum(idx, b - 1)
    take = lambda a: a[safe]  # noqa: E731
    phys = model.replace(residual=None)
    kind = jnp.where(valid, take(prop.kind), ev.NONE)
    tau, pre = take(prop.tau), jax.tree.map(take, prop.pre)
    m_c = jax.tree.map(take, phys) if model_batched else phys
    hit = None
    if rackets is not None:
        per_ball = jax.tree.map(take, rackets) if rackets_batched else rackets  # ([C,] R, ...)
        j = jnp.maximum(take(prop.racket), 0)
        hit = (jax.tree.map(lambda a: a[jnp.arange(j.shape[0]), j], per_ball) if rackets_batched
               else jax.tree.map(lambda a: a[j], per_ball))
        hit = hit.replace(pos=hit.pos + (tau * dt)[:, None] * hit.vel)  # the racket at the contact time
    m_ax = 0 if model_batched else None
    post, x, rot = jax.vmap(respond, in_axes=(m_ax, 0, 0, 0 if hit is not None else None, 0, None, None))(
        m_c, pre, kind, hit, tau, t, dt)
    sigma = jnp.zeros(kind.shape + (6,), x.dtype)
    if model.residual is not None:
        from ttsim_jax.physics.residual import gathered_residual

        is_r = kind == ev.RACKET
        n_in = model.residual.config.n_inputs
        out = gathered_residual(model.residual, x[:, :n_in], is_r, kind.shape[0], key=key, sample=sample)
        post = post.replace(vel=post.vel + jnp.einsum("cij,cj->ci", rot, out["dv"]),
                            spin=post.spin + jnp.einsum("cij,cj->ci", rot, out["dw"]))
        sigma = jnp.concatenate([out["sigma_v"], out["sigma_w"]], axis=-1)
    after = jax.vmap(finish, in_axes=(m_ax, 0, 0, None, None))(m_c, post, tau, t, dt)
    resp = Response(post=post, after=after, contact=x[:, 6:8], sigma=sigma)
    return jax.tree.map(lambda v: jnp.zeros((b,) + v.shape[1:], v.dtype).at[idx].set(v, mode="drop"), resp)


def step(model: Model, state: RallyState, rackets: Racket | None, dt, *, integrator: str = "rk4",
         rackets_batched: bool = False, model_batched: bool = False, capacity: int = 64,
         key=None, sample: bool = False) -> RallyState:
    """Advances a batch by one step.

    Contacts are rare (a few per ball per second), so their responses (contact models, the residual
    network, the rest of the step) are computed only for the balls that have one this step,
    gathered into a buffer of ``capacity`` rows; a step with more contacts than that runs them for
    the whole batch instead (same result), and a step without contacts skips them.

    Arguments:
        model: model parameters (leaves with a leading (B,) axis if ``model_batched``).
        state: the batch state.
        rackets: :class:`Racket` with (R, ...) fields shared by all balls, (B, R, ...) if
            ``rackets_batched``, or None.
        dt: step [s].
        integrator: flight integrator (static).
        capacity: contact buffer size (static).
        key, sample: PRNG key and whether to sample the residual from its predicted std.

    Returns:
        The state after the step.
    """
    phys = model.replace(residual=None)
    m_ax = 0 if model_batched else None
    r_ax = 0 if rackets_batched else None
    t = state.time
    b = state.alive.shape[0]
    prop = jax.vmap(partial(detect, integrator=integrator), in_axes=(m_ax, 0, r_ax, None, None))(
        phys, state.ball, rackets, t, dt)
    mask = state.alive & ((prop.kind == ev.TABLE) | (prop.kind == ev.RACKET))
    count = jnp.sum(mask)
    capacity = min(capacity, b)
    respond_idx = partial(_respond_gathered, model, prop, rackets, t=t, dt=dt, key=key, sample=sample,
                          model_batched=model_batched, rackets_batched=rackets_batched)
    buffered = lambda: respond_idx(jnp.nonzero(mask, size=capacity, fill_value=b)[0])  # noqa: E731
    everyone = lambda: respond_idx(jnp.arange(b))  # noqa: E731
    nothing = lambda: jax.tree.map(jnp.zeros_like, jax.eval_shape(everyone))  # noqa: E731
    resp = jax.lax.switch(jnp.where(count == 0, 0, jnp.where(count <= capacity, 1, 2)), [nothing, buffered, everyone])
    ball, alive, status, log = jax.vmap(resolve, in_axes=(0, 0, 0, 0, 0, 0, None, None))(
        state.ball, state.alive, state.status, state.events, prop, resp, t, dt)
    return RallyState(ball=ball, alive=alive, status=status, events=log, time=t + dt)


def _normalise_schedule(racket: Racket, n_steps: int, batch: int):
    """(schedule with (T, [B,] R, ...) fields, batched?) from the accepted racket layouts."""
    nd = racket.pos.ndim
    if nd == 2:  # (T, 3): one racket
        racket = jax.tree.map(lambda a: a[:, None], racket)
        nd = 3
    if nd == 3:  # (T, R, 3)
        batched = False
    elif nd == 4:  # (B, T, R, 3) -> (T, B, R, 3)
        if racket.pos.shape[0] != batch:
            raise ValueError(f"racket schedule has {racket.pos.shape[0]} balls, the batch has {batch}")
        racket = jax.tree.map(lambda a: jnp.moveaxis(a, 0, 1), racket)
        batched = True
    else:
        raise ValueError(f"racket schedule pos must be (T, 3), (T, R, 3) or (B, T, R, 3); got {racket.pos.shape}")
    if racket.pos.shape[0] < n_steps:
        raise ValueError(f"racket schedule covers {racket.pos.shape[0]} steps, the simulation needs {n_steps}")
    return jax.tree.map(lambda a: a[:n_steps], racket), batched


@partial(jax.jit, static_argnames=("n_steps", "integrator", "record_every", "max_events", "capacity",
                                   "sample", "model_batched", "rackets_batched"))
def _simulate(model, ball, schedule, policy, dt, t0, key, *, n_steps, integrator, record_every, max_events,
              capacity, sample, model_batched, rackets_batched):
    state = init_state(ball, max_events, t0)
    if policy is not None:
        start = jax.vmap(policy.fn, in_axes=(None, 0, None))(policy.params, state.ball, state.time)
    else:
        start = None if schedule is None else jax.tree.map(lambda a: a[0], schedule)
    state = refuse_overlaps(model, state, start, model_batched=model_batched,
                            rackets_batched=rackets_batched or policy is not None)
    stepper = partial(step, integrator=integrator, model_batched=model_batched, capacity=capacity, sample=sample)

    def body(carry, xs):
        state, key = carry
        rackets, batched = xs, rackets_batched
        if policy is not None:
            rackets = jax.vmap(policy.fn, in_axes=(None, 0, None))(policy.params, state.ball, state.time)
            batched = True
        key, sub = jax.random.split(key)
        return (stepper(model, state, rackets, dt, rackets_batched=batched, key=sub), key), None

    every = record_every or n_steps
    n_out = n_steps // every
    xs = None if schedule is None else jax.tree.map(lambda a: a.reshape((n_out, every) + a.shape[1:]), schedule)

    def chunk(carry, xs_chunk):
        carry, _ = jax.lax.scan(body, carry, xs_chunk, length=every)
        return carry, (carry[0].ball, carry[0].time) if record_every else None

    (state, _), rec = jax.lax.scan(chunk, (state, key), xs, length=n_out)
    traj, times = (None, None)
    if record_every:
        traj = jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), rec[0])
        times = rec[1]
    return RallyResult(final=state.ball, alive=state.alive, status=state.status, events=state.events,
                       trajectory=traj, times=times)


def recording_bytes(batch: int, n_steps: int, record_every: int, itemsize: int) -> int:
    """Memory a trajectory recording needs: 9 numbers per ball per recorded step."""
    return 0 if not record_every else batch * (n_steps // record_every) * 9 * itemsize


def simulate(model: Model, ball: Ball, n_steps: int, dt: float = 1e-3, racket=None, *, integrator: str = "rk4",
             record_every: int = 0, max_events: int = 8, contact_capacity: int | None = None,
             sample_residual: bool = False, key=None, t0: float = 0.0, model_batched: bool = False,
             memory_budget_bytes: int = 2 << 30) -> RallyResult:
    """Simulates a batch of balls for ``n_steps`` steps of ``dt``.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model` (with a leading (B,) axis on every leaf if
            ``model_batched``, e.g. from ``stack_models``).
        ball: :class:`Ball` with (B, 3) fields (or (3,) for a single ball; outputs keep B = 1), cast
            to the model's float dtype.
        n_steps: number of steps (static: a new value compiles anew).
        dt: step [s] (traced: changing it does not recompile).
        racket: None, a :class:`Racket` schedule ((T, [R,] ...) or (B, T, R, ...) fields, T >= n_steps;
            entry k is the racket at t0 + k dt), or a :class:`RacketPolicy`.
        integrator: ``"rk4"``, ``"rk2"`` or ``"euler"``.
        record_every: record the ball every that many steps (0: no trajectory); must divide n_steps.
        max_events: capacity of each ball's event log.
        contact_capacity: contacts per step resolved in the gathered buffer (contact models and
            residual network; default B/32, at least 8); a step with more contacts is still exact,
            at full-batch cost.
        sample_residual: sample the residual from its predicted std (domain randomisation).
        key: PRNG key for sampling (default ``PRNGKey(0)``).
        t0: start time [s].
        model_batched: whether ``model`` has a leading batch axis.
        memory_budget_bytes: a trajectory recording above this is refused.

    Returns:
        A :class:`RallyResult`.
    """
    # the simulation runs in the model's float dtype; balls given in another one are cast to it
    ball = jax.tree.map(lambda a: jnp.asarray(a, model.ball.radius.dtype), ball)
    if ball.pos.ndim == 1:
        ball = jax.tree.map(lambda a: a[None], ball)
    if ball.pos.ndim != 2 or ball.pos.shape[-1] != 3:
        raise ValueError(f"ball fields must be (B, 3); got pos {ball.pos.shape}")
    batch = ball.pos.shape[0]
    if n_steps <= 0:
        raise ValueError(f"n_steps must be positive, got {n_steps}")
    if record_every and n_steps % record_every:
        raise ValueError(f"record_every={record_every} must divide n_steps={n_steps}")
    need = recording_bytes(batch, n_steps, record_every, ball.pos.dtype.itemsize)
    if need > memory_budget_bytes:
        raise ValueError(
            f"recording {batch} balls every {record_every} steps for {n_steps} steps needs "
            f"{need / 2**30:.2f} GiB, above the memory budget of {memory_budget_bytes / 2**30:.2f} GiB; "
            "record less often (record_every), fewer balls, or raise memory_budget_bytes")
    schedule, policy, batched = None, None, False
    if isinstance(racket, RacketPolicy):
        policy = racket
    elif racket is not None:
        schedule, batched = _normalise_schedule(racket, n_steps, batch)
    capacity = contact_capacity or min(batch, max(8, math.ceil(batch / 32)))
    key = jax.random.PRNGKey(0) if key is None else key
    dtype = ball.pos.dtype
    return _simulate(model, ball, schedule, policy, jnp.asarray(dt, dtype), jnp.asarray(t0, dtype), key,
                     n_steps=n_steps, integrator=integrator, record_every=record_every, max_events=max_events,
                     capacity=capacity, sample=sample_residual, model_batched=model_batched,
                     rackets_batched=batched)
