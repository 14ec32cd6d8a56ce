"""``rollout``: a resumable, jittable run of the rally kernel; ``simulate``: a rally from start to end.

A rollout advances a :class:`~ttsim_jax.kernel.state.RallyState` by ``n_steps`` and returns the new
state and what happened (the event log and, if asked, a recording). Two rollouts of n steps give the
same state as one of 2n steps, so an RL environment can step the rally 10 ms at a time.

Reverse mode: the scan over steps is split into chunks, and both a step and a chunk are
rematerialised (``jax.checkpoint``) on the way back, so a gradient through N steps stores the
state about 2 sqrt(N) times instead of N times with every intermediate of every step.
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.kernel import fused as fused_path
from ttsim_jax.kernel.axes import StaticAxes, check_per_ball, resolve_axes, split_per_ball
from ttsim_jax.kernel.eventlog import EventLog
from ttsim_jax.kernel.execution import Execution
from ttsim_jax.kernel.fused_params import in_flight
from ttsim_jax.kernel.plans import RacketPolicy, check_reach, normalise_schedule
from ttsim_jax.kernel.record import Record
from ttsim_jax.kernel.state import RallyState, init_state
from ttsim_jax.kernel.ball_step import refused_starts
from ttsim_jax.kernel.step import StepOptions, StepState, step
from ttsim_jax.params import Model
from ttsim_jax.physics import events as ev
from ttsim_jax.sizes import SizeError, budget_bytes
from ttsim_jax.state import Ball


@struct.dataclass
class RolloutOutput:
    """What a rollout returns beside the state.

    Attributes:
        events: :class:`~ttsim_jax.kernel.eventlog.EventLog` of this rollout's events ((B, K) slots),
            None when ``Record.max_events`` is 0.
        trajectory: :class:`~ttsim_jax.state.Ball` with (B, N, 3) fields, the state every
            ``Record.every`` steps (None when not recorded).
        times: (N,) times of the recorded states (None when not recorded).
    """

    events: Any = None
    trajectory: Any = None
    times: Any = None


@struct.dataclass
class RallyResult:
    """Output of :func:`simulate`.

    Attributes:
        final: :class:`Ball` (B, 3) at the end (or where the ball stopped).
        alive, status: (B,) see :class:`~ttsim_jax.kernel.state.RallyState`.
        events: :class:`EventLog` with (B, K) slots.
        trajectory: :class:`Ball` with (B, N, 3) fields (None when not recorded).
        times: (N,) times of the recorded states.
        state: the final :class:`RallyState`, to resume with :func:`rollout`.
    """

    final: Ball
    alive: jnp.ndarray
    status: jnp.ndarray
    events: EventLog
    trajectory: Any = None
    times: Any = None
    state: Any = None


@struct.dataclass
class Carry:
    """What the scan over steps carries, for one set of balls (B,): what a step advances (the balls,
    whether each is in play, its status, the event log: a
    :class:`~ttsim_jax.kernel.step.StepState`) and the rollout's step counter (() int)."""

    balls: StepState
    step: Any


def chunk_length(n_steps: int) -> int:
    """Steps per rematerialised chunk: about sqrt(n_steps), the memory-optimal split.

    A divisor of ``n_steps`` within a factor 2 of the square root is preferred: a remainder would
    need a second scan, hence a second compiled copy of the step (a third more compile time).
    """
    root = max(1, math.isqrt(n_steps))
    divisors = [d for d in range(max(1, root // 2), 2 * root + 1) if n_steps % d == 0]
    return min(divisors, key=lambda d: abs(math.log(d / root)), default=root)


def default_block(batch: int, fused: bool = False) -> int:
    """Balls per block: none (0), everywhere. Blocks of 1,024 balls once kept a CPU step's working
    set in cache; since a step runs only the contact buffers that hold a ball and the flight step
    writes fewer temporaries, the whole batch at once is faster on a CPU too (interleaved, 2 cores:
    0.60x the time at 4,096 balls over 10 steps with a racket per ball, 0.62x at 16,384, 0.84x
    and 0.71x at 65,536 without and with two tracking rackets over 100 steps); each block repeats a
    step's fixed costs. ``block_size`` still splits a batch (same results), e.g. to bound memory."""
    return 0


@dataclasses.dataclass(frozen=True)
class _Plan:
    """Everything static about a rollout, resolved once by :func:`rollout` from its arguments and
    its :class:`Execution` (the path among them): the jitted rollout's one static argument.

    ``fused``: the fused path's sub-steps per launch, 0 for the reference path."""

    axes: StaticAxes
    n_steps: int
    record: Record
    step: StepOptions
    rackets_batched: bool
    remat: bool
    block: int
    fused: int


@partial(jax.jit, static_argnames=("plan",))
def _rollout(model, state: RallyState, schedule, policy, dt, key, *, plan: _Plan):
    """The jitted rollout; on the fused path (``plan.fused`` > 0, its sub-steps per launch) a
    ``custom_jvp`` whose derivative is the reference path's, so reverse mode never meets the kernel."""
    if not plan.fused:
        return _run(model, state, schedule, policy, dt, key, plan)

    def path(p):
        return lambda m, s, sc, pol, d, k: _run(m, s, sc, pol, d, k, p)

    run = jax.custom_jvp(path(plan))
    run.defjvp(lambda primals, tangents: jax.jvp(path(dataclasses.replace(plan, fused=0)), primals, tangents))
    return run(model, state, schedule, policy, dt, key)


def _run(model, state: RallyState, schedule, policy, dt, key, plan: _Plan):
    n_steps, record, rackets_batched, remat, block = (plan.n_steps, plan.record, plan.rackets_batched, plan.remat,
                                                      plan.block)
    record_every, max_events, until, fused, sample = (record.every, record.max_events, record.until_events, plan.fused,
                                                      plan.step.sample)
    axes = plan.axes.tree()
    b = state.batch
    dtype = state.ball.pos.dtype
    dt = jnp.asarray(dt, dtype)
    # a new dt starts counting steps afresh from the current time
    same = (state.dt == dt) | (state.step == 0)
    t0 = jnp.where(same, state.t0, state.time)
    step0 = jnp.where(same, state.step, 0)
    stepper = partial(step, options=plan.step)
    every = record_every or chunk_length(n_steps)
    n_chunks, tail = divmod(n_steps, every)

    def run_balls(model, ball, alive, status, ball_id, schedule):
        """The whole rollout for a set of balls (the batch, or one block of it)."""
        log = EventLog.empty(alive.shape[0], max_events, dtype) if max_events else None

        def body(carry: Carry, xs):
            balls, k = carry.balls, carry.step
            ball, alive = balls.ball, balls.alive
            t = t0 + k.astype(dtype) * dt
            rackets, batched = xs, rackets_batched
            if policy is not None:
                rackets = jax.vmap(policy.fn, in_axes=(None, 0, None))(policy.params, ball, t)
                rackets = jax.tree.map(lambda a: a.astype(dtype), rackets)  # python-float params may be wider
                batched = True
            sub = jax.random.fold_in(key, k) if sample else None
            def advance(moving):
                new = stepper(model, axes, balls.replace(alive=moving), ball_id, rackets, t, dt,
                              rackets_batched=batched, key=sub)
                return new.replace(alive=jnp.where(moving, new.alive, alive)) if until else new

            if not until:
                balls = advance(alive)
            else:
                # balls whose log holds ``until`` events are frozen (out of play for the step, still
                # alive); a step with none to advance is skipped whole
                moving = alive & (balls.log.count < until)
                balls = jax.lax.cond(jnp.any(moving), lambda: advance(moving), lambda: balls)
            return Carry(balls, k + 1), None

        if remat:
            body = jax.checkpoint(body, prevent_cse=False)

        def run(carry, xs, length):
            return jax.lax.scan(body, carry, xs, length=length)[0]

        def chunk(carry, xs_chunk):
            carry = run(carry, xs_chunk, every)
            return carry, ((carry.balls.ball, t0 + carry.step.astype(dtype) * dt) if record_every else None)

        if remat:
            chunk = jax.checkpoint(chunk, prevent_cse=False)
        split = lambda a, lo, n, shape: None if a is None else jax.tree.map(  # noqa: E731
            lambda x: x[lo:lo + n].reshape(shape + x.shape[1:]), a)
        carry = Carry(StepState(ball, alive, status, log), step0)
        if fused:
            return run_fused(model, carry, ball_id, schedule)
        carry, rec = jax.lax.scan(chunk, carry, split(schedule, 0, n_chunks * every, (n_chunks, every)),
                                  length=n_chunks)
        if tail:
            carry = run(carry, split(schedule, n_chunks * every, tail, (tail,)), tail)
        return carry, rec

    def run_fused(model, carry, ball_id, schedule):
        """The rollout on the fused path: the balls' clocks meet at every recorded step."""
        length = record_every or n_steps
        drive = fused_path.Drive(schedule=schedule, policy=policy, t0=t0, dt=dt, step0=step0,
                                 key=key if sample else None, rackets_batched=rackets_batched)
        launch = fused_path.Launch(substeps=fused)

        def segment(carry: Carry, n):
            balls = fused_path.advance(model, axes, carry.balls, ball_id, carry.step, n, drive, stepper, launch=launch)
            return Carry(balls, carry.step + n)

        def chunk(carry, _):
            carry = segment(carry, length)
            return carry, ((carry.balls.ball, t0 + carry.step.astype(dtype) * dt) if record_every else None)

        return jax.lax.scan(chunk, carry, None, length=n_steps // length)

    # a rally that has not started yet (dt 0): refuse balls inside the table, the net or a racket
    start = None if schedule is None else jax.tree.map(lambda a: a[0], schedule)
    if policy is not None:
        start = jax.vmap(policy.fn, in_axes=(None, 0, None))(policy.params, state.ball, t0)
    bad = (state.dt == 0) & refused_starts(model, axes, state.ball, start, rackets_batched or policy is not None)
    state = state.replace(alive=state.alive & ~bad, status=jnp.where(bad, ev.INVALID, state.status))
    per_ball_sched = schedule is not None and rackets_batched  # (T, B, R, ...)
    if not block or b <= block:
        carry, rec = run_balls(model, state.ball, state.alive, state.status, state.ball_id, schedule)
    else:
        # blocks of balls, one after the other, each with its own time scan; padded with dead balls
        n_blocks = -(-b // block)
        pad = n_blocks * block - b

        def blocks(a, axis=0, dead=None):
            widths = [(0, 0)] * a.ndim
            widths[axis] = (0, pad)
            if pad:  # padding balls repeat the last one (finite physics) unless given a value
                a = jnp.pad(a, widths, mode="edge") if dead is None else jnp.pad(a, widths, constant_values=dead)
            a = a.reshape(a.shape[:axis] + (n_blocks, block) + a.shape[axis + 1:])
            return jnp.moveaxis(a, axis, 0)

        per_ball, rebuild = split_per_ball(model, axes)
        xs = dict(model=[blocks(a) for a in per_ball], ball=jax.tree.map(blocks, state.ball),
                  alive=blocks(state.alive, dead=False),
                  status=blocks(state.status), ball_id=blocks(state.ball_id),
                  schedule=jax.tree.map(lambda a: blocks(a, 1), schedule) if per_ball_sched else None)
        shared_sched = None if per_ball_sched else schedule

        def one(x):
            return run_balls(rebuild(x["model"]), x["ball"], x["alive"], x["status"], x["ball_id"],
                             x["schedule"] if per_ball_sched else shared_sched)

        carry, rec = jax.lax.map(one, xs)
        unblock = lambda a, axis=0: jnp.moveaxis(a, 0, axis).reshape(  # noqa: E731
            a.shape[1:axis + 1] + (n_blocks * block,) + a.shape[axis + 2:])[(slice(None),) * axis + (slice(0, b),)]
        carry = Carry(jax.tree.map(unblock, carry.balls), carry.step[0])
        if record_every:
            rec = (jax.tree.map(lambda a: unblock(a, 1), rec[0]), rec[1][0])
    balls = carry.balls
    new_state = state.replace(ball=balls.ball, alive=balls.alive, status=balls.status, step=carry.step, t0=t0,
                              dt=dt)
    out = RolloutOutput(events=balls.log)
    if record_every:
        out = out.replace(trajectory=jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), rec[0]), times=rec[1])
    return new_state, out


def recording_bytes(batch: int, n_steps: int, record_every: int, itemsize: int) -> int:
    """Memory a trajectory recording needs: 9 numbers per ball per recorded step."""
    return 0 if not record_every else batch * (n_steps // record_every) * 9 * itemsize


def _nbytes(tree) -> int:
    return int(sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(tree)))


def memory_bytes(batch: int, n_steps: int, record_every: int, max_events: int, dtype) -> dict[str, int]:
    """What a forward rollout holds per batch [bytes]: its state, event log and recording, and the
    total (their sum; a step's temporaries come on top, a few hundred bytes per ball of a block).

    The sizes come from the shapes of the arrays themselves (``jax.eval_shape``), so they follow
    any change of the state or the log.
    """
    ball = Ball(*(jax.ShapeDtypeStruct((batch, 3), dtype),) * 3)
    state = _nbytes(jax.eval_shape(init_state, ball))
    log = _nbytes(jax.eval_shape(lambda: EventLog.empty(batch, max_events, dtype))) if max_events else 0
    rec = recording_bytes(batch, n_steps, record_every, jnp.dtype(dtype).itemsize)
    return dict(state=state, event_log=log, recording=rec, total=state + log + rec)


def default_buffering() -> str:
    """``"loop"`` on CPU, ``"single"`` elsewhere (see :func:`~ttsim_jax.kernel.step.step`)."""
    return "loop" if jax.default_backend() == "cpu" else "single"


#: Least batch at which ``fused="auto"`` takes the fused path on a CPU. Measured on 2 cores (flight
#: + table, ``benchmarks/README.md``, one run): 3.7x the reference path at 1,024 balls (0.86x the
#: lean hand-written numba loop) and 5.4x at 65,536 (1.20x the lean loop). It compiles about 12 s
#: longer than the reference path (measured with Pallas's interpret mode, where the smaller batches
#: ran 1.4-1.6x faster: less than a small batch's run saves).
FUSED_AUTO_MIN_BATCH_CPU = 1024

#: Fewest steps of a rollout for which ``fused="auto"`` takes the fused path on a CPU. Since the
#: reference step skips the event work of balls that have no event, it flies the first hundred
#: steps of a batch of shots (free flight) faster than the kernel: flight + table, conti2026,
#: float32, the event log read, fused / reference at 1,024, 8,192 and 65,536 balls: 0.62, 0.76
#: and 0.88 over 100 steps, 1.12, 1.21 and 1.56 over 300, 1.48, 1.66 and 1.89 over 1,000
#: (``benchmarks/fused_auto.py``, ``benchmarks/results/fused_auto_cpu.json``).
FUSED_AUTO_MIN_STEPS_CPU = 300


def fused_pays(batch: int, rackets_batched: bool = False, air_hooks: bool = False, policy: bool = False,
               n_steps: int | None = None, per_ball: bool = False) -> bool:
    """Whether ``fused="auto"`` takes the fused path (where it covers the rollout) for ``batch`` balls
    over ``n_steps`` steps (None: many) on this backend: on a GPU always but with per-ball
    parameters (``per_ball``, which the Triton kernel reads since 2026-11-29, not measured there),
    on a CPU from :data:`FUSED_AUTO_MIN_BATCH_CPU` balls and :data:`FUSED_AUTO_MIN_STEPS_CPU` steps;
    nowhere with a racket schedule per ball, and on a CPU not with an effect that moves the air
    (``air_velocity``). Both the
    CPU's fused path covers, but they ran slower than the reference path. With rackets per ball
    (4,096 balls, two rackets per ball: 0.14-0.20x over 10-300 steps; the environment's default task
    0.63x of its env-steps/s), a racket brought to its ball keeps the ball inside its box, so the
    kernel stops it every step and the loop pays a launch's whole-batch work per step (running the
    ordinary step on the stopped balls only was tried: no faster). With ``air_flow`` (spin decay
    and wind drawn per ball, 65,536 balls, 300 steps: 0.83x, 0.44x today, ``benchmarks/fused_effects.py``) the
    gusts' sum over their components, a reduction over a short axis, ends the kernel's loop over the
    balls at each of its four evaluations a sub-step (written out, the fused path ran 1.55x, but the
    rounding of the sum changed and the diagnosis of one withheld-effect case with it). Nor with a
    racket policy, on any backend: its reach (:attr:`~ttsim_jax.kernel.plans.RacketPolicy.reach`)
    spans every place the policy may put a racket, a slab across the table for the tracking
    rackets, which every ball crosses in ordinary steps, each a whole batch's (two tracking
    rackets and per-ball table and air parameters, conti2026, float32, on this 2-core CPU: 0.38x
    the reference path's speed at 8,192 balls and 100 steps, 1.04x at 65,536 balls and 300 steps,
    ``benchmarks/fused_effects.py``); not measured on a GPU."""
    backend = jax.default_backend()
    if policy or rackets_batched:
        return False
    if backend == "gpu":
        return not per_ball
    long = n_steps is None or n_steps >= FUSED_AUTO_MIN_STEPS_CPU
    return backend == "cpu" and batch >= FUSED_AUTO_MIN_BATCH_CPU and long and not air_hooks


def default_capacity(batch: int) -> int:
    """Contact buffer rows: B/32, at least 8 (a ball has a contact every ~100-300 steps)."""
    return min(batch, max(8, math.ceil(batch / 32)))


def rollout(model: Model, state: RallyState, n_steps: int, dt: float = 1e-3, racket=None, *,
            integrator: str = "rk4", model_axes=None, record: Record = Record(), sample_key=None,
            execution: Execution = Execution()) -> tuple[RallyState, RolloutOutput]:
    """Advances a rally by ``n_steps`` steps of ``dt``; pure and jittable, resumable from its state.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model`.
        state: a :class:`~ttsim_jax.kernel.state.RallyState` (from :func:`init_state` or a previous
            rollout); cast to nothing: its ball dtype is the simulation's dtype.
        n_steps: number of steps (static: a new value compiles anew).
        dt: step [s] (traced: changing it does not recompile).
        racket: None, a :class:`~ttsim_jax.state.Racket` schedule ((T, [R,] ...) or (B, T, R, ...)
            fields, T >= n_steps; entry k is the racket at the rollout's k-th step), or a
            :class:`~ttsim_jax.kernel.plans.RacketPolicy`.
        integrator: ``"rk4"``, ``"rk2"`` or ``"euler"``.
        model_axes: which model leaves carry a per-ball leading (B,) axis: None (all shared), 0 (all
            per ball, e.g. ``stack_models``), or a pytree prefix of the model with 0 / None
            (:func:`~ttsim_jax.kernel.axes.per_ball_axes`). Only the leaves a study varies need to be per ball.
        record: what is recorded (:class:`~ttsim_jax.kernel.record.Record`: the trajectory every
            that many steps, the event log's slots, a stop after a number of events); default
            ``Record()``: an event log of 8 slots, no trajectory.
        sample_key: a PRNG key: the residual network's correction is sampled from its predicted
            std, each draw depending on the key, the step and the ball's id only; None (default):
            its mean correction.
        execution: how it runs, same results (:class:`~ttsim_jax.kernel.execution.Execution`: event
            buffer, rematerialisation, blocks, buffering, the fused path, the memory budget).

    Returns:
        (state, :class:`RolloutOutput`).
    """
    if not isinstance(record, Record):
        raise TypeError(f"record must be a ttsim_jax.Record, got {type(record).__name__}")
    if not isinstance(execution, Execution):
        raise TypeError(f"execution must be a ttsim_jax.Execution, got {type(execution).__name__}")
    ball = state.ball
    if ball.pos.ndim != 2 or ball.pos.shape[-1] != 3:
        raise ValueError(f"state.ball fields must be (B, 3); got pos {ball.pos.shape}")
    batch = ball.pos.shape[0]
    if not isinstance(n_steps, int) or n_steps <= 0:
        raise ValueError(f"n_steps must be positive (an int), got {n_steps!r}")
    record.check(n_steps)
    need = memory_bytes(batch, n_steps, record.every, record.max_events, ball.pos.dtype)
    memory_budget_bytes, source = budget_bytes(execution.memory_budget_bytes)
    if need["total"] > memory_budget_bytes:
        gib = lambda n: f"{n / 2**30:.2f} GiB"  # noqa: E731
        raise SizeError(
            f"a rollout of {batch} balls for {n_steps} steps (Record(every={record.every}, "
            f"max_events={record.max_events})) needs {gib(need['total'])} (state {gib(need['state'])}, event log "
            f"{gib(need['event_log'])}, recording {gib(need['recording'])}), above the memory budget of "
            f"{gib(memory_budget_bytes)} ({source}); record less often (Record(every=...)), log fewer events "
            "(Record(max_events=...)), run fewer balls per call, or raise the budget "
            "(Execution(memory_budget_bytes=...), TTSIM_MEMORY_BUDGET)")
    axes = resolve_axes(model, model_axes)
    check_per_ball(model, axes, batch)
    schedule, policy, batched = None, None, False
    if isinstance(racket, RacketPolicy):
        policy = racket
        check_reach(policy, ball, dt)
    elif racket is not None:
        schedule, batched = normalise_schedule(racket, n_steps, batch)
        schedule = jax.tree.map(lambda a: jnp.asarray(a, ball.pos.dtype), schedule)
    fused = execution.fused
    if fused:
        why = fused_path.unsupported(model, axes, integrator=integrator, policy=policy, rackets_batched=batched)
        if why is None and record.until_events:
            why = "until_events"
        if why is not None and fused is True:
            raise ValueError(f"fused=True: the fused path does not cover {why}; use fused=False or 'auto'")
        air = in_flight(model, ("air_velocity",))
        pays = fused_pays(batch, batched, air, policy is not None, n_steps, fused_path.per_ball_physics(axes))
        fused = why is None and not execution.reference and (fused is True or pays)
    block = default_block(batch, fused) if execution.block_size is None else int(execution.block_size)
    capacity = execution.contact_capacity or default_capacity(min(batch, block) if block else batch)
    buffering = default_buffering() if execution.buffering is None else execution.buffering
    sample = sample_key is not None
    options = StepOptions(integrator=integrator, capacity=int(capacity), sample=sample,
                          reference=execution.reference, buffering=buffering)
    plan = _Plan(axes=StaticAxes(axes), n_steps=n_steps, record=record, step=options, rackets_batched=batched,
                 remat=execution.remat, block=block, fused=fused_path.SUBSTEPS if fused else 0)
    key = sample_key if sample else jax.random.PRNGKey(0)
    return _rollout(model, state, schedule, policy, dt, key, plan=plan)


def simulate(model: Model, ball: Ball, n_steps: int, dt: float = 1e-3, racket=None, *, integrator: str = "rk4",
             model_axes=None, record: Record = Record(), sample_key=None,
             execution: Execution = Execution()) -> RallyResult:
    """Simulates a batch of balls from the start (time 0) for ``n_steps`` steps: :func:`init_state`
    then :func:`rollout` (start at another time with ``rollout(model, init_state(ball, t0), ...)``).

    Arguments:
        model: a :class:`~ttsim_jax.params.Model`.
        ball: :class:`Ball` with (B, 3) fields (or (3,) for one ball; outputs keep B = 1), cast to
            the model's float dtype.
        n_steps, dt, racket, integrator, model_axes, record, sample_key, execution: as for
            :func:`rollout`.

    Returns:
        A :class:`RallyResult` (its ``state`` resumes the rally).
    """
    ball = jax.tree.map(lambda a: jnp.asarray(a, model.ball.radius.dtype), ball)
    if ball.pos.ndim == 1:
        ball = jax.tree.map(lambda a: a[None], ball)
    state, out = rollout(model, init_state(ball), n_steps, dt, racket, integrator=integrator, model_axes=model_axes,
                         record=record, sample_key=sample_key, execution=execution)
    return RallyResult(final=state.ball, alive=state.alive, status=state.status, events=out.events,
                       trajectory=out.trajectory, times=out.times, state=state)
