"""The rally kernel: one ``lax.scan`` over time steps composing flight, contacts and the network.

A step, for a batch of balls:

1. ``detect`` (vmapped, one ball): free flight over the step, then the earliest contact of the
   step (table, racket faces, net, floor) with its time of impact, the state there, and the base
   models' post-contact state.
2. The racket residual network, at batch level: only the balls in racket contact this step are
   gathered into a fixed-capacity buffer and evaluated (``physics.residual.gathered_residual``).
3. ``resolve`` (vmapped, one ball): adds the network's correction, flies the rest of the step from
   the contact, logs the event, masks invalid states and retires balls that left play.

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
        alive: (B,) False once the ball hit the floor, left play or became invalid (then frozen).
        status: (B,) why it stopped (``FLOOR``, ``OUT``, ``INVALID``), 0 while alive.
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
    """Result of :func:`detect` for one ball and step."""

    kind: jnp.ndarray
    tau: jnp.ndarray
    racket: jnp.ndarray
    free: Ball
    pre: Ball
    post: Ball
    x: jnp.ndarray
    rot: jnp.ndarray


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


# --------------------------------------------------------------------------- one ball
def ball_properties(model: Model):
    """(radius, mass) of the ball after effects (hook ``ball_properties``)."""
    return hooks.apply(model.effects, "ball_properties", (model.ball.radius, model.ball.mass))


def detect(model: Model, ball: Ball, rackets: Racket | None, t, dt, integrator: str = "rk4") -> Proposal:
    """Free flight over a step and the earliest contact in it, for one ball.

    Arguments:
        model: model parameters (its ``residual`` is ignored here).
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
    free = Ball(p1, v1, w1)

    cands = [(ev.TABLE, ev.table_candidate(model.table, fx, radius, p0, v0, p1, v1, dt)),
             (ev.FLOOR, ev.floor_candidate(model.table, radius, p0, v0, p1, v1, dt)),
             (ev.NET, ev.net_candidate(model.table, radius, p0, v0, p1, v1, dt))]
    n_fixed = len(cands)
    if rackets is not None:
        rc = jax.vmap(ev.racket_candidate, in_axes=(0, None, None, None, None, None, None))(
            rackets, radius, p0, v0, p1, v1, dt)
        cands += [(ev.RACKET, ev.Candidate(rc.hit[j], rc.tau[j])) for j in range(rc.hit.shape[0])]
    kind, tau, index = ev.earliest(cands)

    pos, vel = ev.hermite(p0, v0, p1, v1, dt, tau)
    pre = Ball(pos, vel, w0 + tau * (w1 - w0))

    tp, tv, tw = table_stage.table_contact(model.table, radius, pre.pos, pre.vel, pre.spin, fx)
    post_pos = jnp.where(kind == ev.TABLE, tp, pre.pos)
    post_vel = jnp.where(kind == ev.TABLE, tv, pre.vel)
    post_spin = jnp.where(kind == ev.TABLE, tw, pre.spin)
    racket_index = jnp.where(kind == ev.RACKET, index - n_fixed, -1).astype(jnp.int32)
    x = jnp.zeros(8, p0.dtype)
    rot = jnp.eye(3, dtype=p0.dtype)
    if rackets is not None:
        hit = jax.tree.map(lambda a: a[jnp.maximum(racket_index, 0)], rackets)
        hit = hit.replace(pos=hit.pos + tau * dt * hit.vel)
        rv, rw, rstate = racket_stage.racket_contact(model.racket, hit, radius, mass, pre.pos, pre.vel, pre.spin, fx)
        is_r = kind == ev.RACKET
        post_vel = jnp.where(is_r, rv, post_vel)
        post_spin = jnp.where(is_r, rw, post_spin)
        x = jnp.where(is_r, jnp.concatenate([rstate["v"], rstate["w"], rstate["d"]]), x)
        rot = jnp.where(is_r, rstate["rot"], rot)
    return Proposal(kind=kind, tau=tau, racket=racket_index, free=free, pre=pre,
                    post=Ball(post_pos, post_vel, post_spin), x=x, rot=rot)


def resolve(model: Model, ball: Ball, alive, status, log: EventLog, prop: Proposal, dv, dw, sigma, t, dt):
    """Completes a step for one ball: network correction, rest of the step, event log, masks.

    Arguments:
        model: model parameters; ball: the state at the start of the step; alive, status, log:
        the ball's bookkeeping; prop: from :func:`detect`; dv, dw: (3,) racket-frame residual
        correction (zeros unless a racket contact); sigma: (6,) its predicted std; t, dt: time and
        step.

    Returns:
        (ball, alive, status, log) after the step.
    """
    kind = prop.kind
    is_r = kind == ev.RACKET
    post = Ball(prop.post.pos, prop.post.vel + jnp.where(is_r, prop.rot @ dv, 0.0),
                prop.post.spin + jnp.where(is_r, prop.rot @ dw, 0.0))

    # The rest of the step after a contact is short and happens once per contact: a second-order
    # Taylor step (one acceleration) costs a quarter of an RK4 step and errs by O(dt^3) once.
    rest = (1.0 - prop.tau) * dt
    f = aero_stage.derivative(model.aero, *ball_properties(model), model.effects)
    _, acc, dspin = f((post.pos, post.vel, post.spin), t + prop.tau * dt)
    after = Ball(post.pos + rest * post.vel + 0.5 * rest * rest * acc, post.vel + rest * acc, post.spin + rest * dspin)

    bounced = (kind == ev.TABLE) | is_r
    nxt = jax.tree.map(lambda a, b, c: jnp.where(bounced, a, jnp.where(kind == ev.FLOOR, b, c)),
                       after, prop.pre, prop.free)
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
    log_post = jax.tree.map(lambda a, b: jnp.where(bounced, a, b), post, prop.pre)
    log = log.record(happened, kind, time, prop.racket, prop.pre, log_post, prop.x[6:8],
                     jnp.where(is_r, sigma, 0.0))
    stops = (kind == ev.FLOOR) | (kind == ev.OUT) | (kind == ev.INVALID)
    new_status = jnp.where(alive & stops, kind, status)
    nxt = jax.tree.map(lambda a, b: jnp.where(alive, a, b), nxt, ball)
    return nxt, alive & ~stops, new_status, log


# --------------------------------------------------------------------------- batch
def _residual_correction(model: Model, prop: Proposal, alive, capacity, key, sample):
    b = prop.kind.shape[0]
    dtype = prop.x.dtype
    if model.residual is None:
        z = jnp.zeros((b, 3), dtype)
        return z, z, jnp.zeros((b, 6), dtype)
    from ttsim_jax.physics.residual import gathered_residual

    n_in = model.residual.config.n_inputs
    mask = (prop.kind == ev.RACKET) & alive
    out = gathered_residual(model.residual, prop.x[:, :n_in], mask, capacity, key=key, sample=sample)
    return out["dv"], out["dw"], jnp.concatenate([out["sigma_v"], out["sigma_w"]], axis=-1)


def step(model: Model, state: RallyState, rackets: Racket | None, dt, *, integrator: str = "rk4",
         rackets_batched: bool = False, model_batched: bool = False, capacity: int = 64,
         key=None, sample: bool = False) -> RallyState:
    """Advances a batch by one step.

    Arguments:
        model: model parameters (leaves with a leading (B,) axis if ``model_batched``).
        state: the batch state.
        rackets: :class:`Racket` with (R, ...) fields shared by all balls, (B, R, ...) if
            ``rackets_batched``, or None.
        dt: step [s].
        integrator: flight integrator (static).
        capacity: size of the residual network's contact buffer (static).
        key, sample: PRNG key and whether to sample the residual from its predicted std.

    Returns:
        The state after the step.
    """
    phys = model.replace(residual=None)
    m_ax = 0 if model_batched else None
    r_ax = 0 if rackets_batched else None
    t = state.time
    prop = jax.vmap(partial(detect, integrator=integrator), in_axes=(m_ax, 0, r_ax, None, None))(
        phys, state.ball, rackets, t, dt)
    dv, dw, sigma = _residual_correction(model, prop, state.alive, capacity, key, sample)
    ball, alive, status, log = jax.vmap(resolve, in_axes=(m_ax, 0, 0, 0, 0, 0, 0, 0, 0, None, None))(
        phys, state.ball, state.alive, state.status, state.events, prop, dv, dw, sigma, t, dt)
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
             record_every: int = 0, max_events: int = 8, residual_capacity: int | None = None,
             sample_residual: bool = False, key=None, t0: float = 0.0, model_batched: bool = False,
             memory_budget_bytes: int = 2 << 30) -> RallyResult:
    """Simulates a batch of balls for ``n_steps`` steps of ``dt``.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model` (with a leading (B,) axis on every leaf if
            ``model_batched``, e.g. from ``stack_models``).
        ball: :class:`Ball` with (B, 3) fields (or (3,) for a single ball; outputs keep B = 1).
        n_steps: number of steps (static: a new value compiles anew).
        dt: step [s] (traced: changing it does not recompile).
        racket: None, a :class:`Racket` schedule ((T, [R,] ...) or (B, T, R, ...) fields, T >= n_steps;
            entry k is the racket at t0 + k dt), or a :class:`RacketPolicy`.
        integrator: ``"rk4"``, ``"rk2"`` or ``"euler"``.
        record_every: record the ball every that many steps (0: no trajectory); must divide n_steps.
        max_events: capacity of each ball's event log.
        residual_capacity: contacts per step the residual network evaluates at once (default B/32,
            at least 8); more contacts are still handled correctly, at full-batch cost.
        sample_residual: sample the residual from its predicted std (domain randomisation).
        key: PRNG key for sampling (default ``PRNGKey(0)``).
        t0: start time [s].
        model_batched: whether ``model`` has a leading batch axis.
        memory_budget_bytes: a trajectory recording above this is refused.

    Returns:
        A :class:`RallyResult`.
    """
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
    capacity = residual_capacity or min(batch, max(8, math.ceil(batch / 32)))
    key = jax.random.PRNGKey(0) if key is None else key
    dtype = ball.pos.dtype
    return _simulate(model, ball, schedule, policy, jnp.asarray(dt, dtype), jnp.asarray(t0, dtype), key,
                     n_steps=n_steps, integrator=integrator, record_every=record_every, max_events=max_events,
                     capacity=capacity, sample=sample_residual, model_batched=model_batched,
                     rackets_batched=batched)
