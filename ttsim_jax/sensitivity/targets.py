"""What a sensitivity study differentiates: a shot's outcome, read from the rally kernel's event log.

A shot (:mod:`ttsim_jax.sensitivity.cases`) runs as one rollout of the kernel: the racket is in play
for ``WINDOW`` steps (the contact, its time of impact, the racket model and the residual network, as
in any rally), then withdrawn out of reach for the flight until the horizon. The first event must
be the racket's and the second, the landing, a table contact; its point and time are the kernel's
(refined time of impact), so they are differentiable in every input.

Targets (:data:`TARGETS`): ``landing`` (x, y of the ball centre at the landing [m]),
``landing_time`` (from the racket contact to the landing [s]), ``net_clearance`` (height of the
ball's underside above the net's top edge where its centre crosses the net plane x = 0 [m]) and
``bounce_speed`` (the ball's speed just after the landing [m/s]).

Every target is read from one program (:func:`program_outcome`, all of :data:`COLUMNS`), so all
share one compilation; a target keeps its own columns (:func:`for_target`). One rollout, not a
racket window and a flight apart: the compiled program holds the kernel's step once.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.kernel.execution import Execution
from ttsim_jax.kernel.record import Record
from ttsim_jax.kernel.rollout import rollout
from ttsim_jax.kernel.state import init_state
from ttsim_jax.physics import events as ev
from ttsim_jax.sensitivity.cases import WINDOW, contact_time
from ttsim_jax.state import Ball, Racket

TARGETS = {
    "landing": ("landing_x", "landing_y"),
    "landing_time": ("landing_time",),
    "net_clearance": ("net_clearance",),
    "bounce_speed": ("bounce_speed",),
}
UNITS = {"landing_x": "m", "landing_y": "m", "landing_time": "s", "net_clearance": "m", "bounce_speed": "m/s"}
# what the one program computes; every target is some of these columns
COLUMNS = ("landing_x", "landing_y", "landing_time", "bounce_speed", "net_clearance")


@struct.dataclass
class Outcome:
    """A batch of shots' outcomes.

    Attributes:
        values: (B, k) the target's components (:data:`TARGETS`; every column of :data:`COLUMNS`
            from :func:`program_outcome`), 0 where not ``valid``.
        sequence: (B, 2) int32: the kinds of the shot's first two events (``physics.events``):
            (RACKET, TABLE) for a shot that lands.
        valid: (B,) the shot hit the racket, then landed on the table within the horizon (and,
            for ``net_clearance``, crossed the net plane).
        crossed: (B,) the ball's centre crossed the net plane x = 0 (toward the other side).
        steps: (B,) int32: the rollout steps (racket window included) the outcome depends on: through
            the step of the landing (for a shot that lands) and of the net crossing; a shorter
            rollout of at least that many steps gives the same outcome (the event log keeps its
            first two events). The whole rollout for a shot that does not land.
    """

    values: jnp.ndarray
    sequence: jnp.ndarray
    valid: jnp.ndarray
    crossed: jnp.ndarray
    steps: jnp.ndarray


def check_target(target: str) -> tuple[str, ...]:
    """The component names of ``target``; an unknown target raises ValueError naming the known ones."""
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r}; known: {', '.join(TARGETS)}")
    return TARGETS[target]


def columns_of(target: str) -> tuple[int, ...]:
    """Where ``target``'s components are among :data:`COLUMNS`."""
    return tuple(COLUMNS.index(c) for c in check_target(target))


def for_target(out: Outcome, target: str) -> Outcome:
    """``out`` (every column) reduced to ``target``'s components and validity (works on numpy and jax)."""
    valid = out.valid & out.crossed if target == "net_clearance" else out.valid
    values = out.values[:, list(columns_of(target))]
    return out.replace(values=values * valid[:, None], valid=valid)


def _net_crossing(start: Ball, traj: Ball, dt):
    """(B,) height of the ball centre where it first crosses x = 0, whether it does and in which step
    (counted from 1).

    The crossing step is found on the recording (every step); inside it, two Newton steps on the
    cubic Hermite path (``events.hermite``) find the crossing, so the height is smooth in the inputs.
    """
    pos = jnp.concatenate([start.pos[:, None], traj.pos], 1)
    vel = jnp.concatenate([start.vel[:, None], traj.vel], 1)
    side = jnp.sign(start.pos[:, :1])
    before = side * pos[:, :, 0] > 0.0
    cross = before[:, :-1] & ~before[:, 1:]
    found = jnp.any(cross, 1)
    k = jnp.argmax(cross, 1)
    take = lambda a, i: jnp.take_along_axis(a, (k + i)[:, None, None], 1)[:, 0]  # noqa: E731
    p0, v0, p1, v1 = take(pos, 0), take(vel, 0), take(pos, 1), take(vel, 1)
    dx = p1[:, 0] - p0[:, 0]
    tau = jnp.clip(-p0[:, 0] / jnp.where(dx == 0.0, 1.0, dx), 0.0, 1.0)
    for _ in range(2):
        p, v = ev.hermite(p0, v0, p1, v1, dt, tau[:, None])
        slope = v[:, 0] * dt
        tau = jnp.clip(tau - p[:, 0] / jnp.where(slope == 0.0, 1.0, slope), 0.0, 1.0)
    p, _ = ev.hermite(p0, v0, p1, v1, dt, tau[:, None])
    return p[:, 2], found, k + 1


def racket_schedule(racket: Racket, total: int, dt) -> Racket:
    """(B, total, 1, ...) racket schedule of a shot: in play for the first ``WINDOW`` steps, moving
    with its velocity (orientation held), then withdrawn: 100 m behind its face, at rest, where no
    ball can reach it in a flight."""
    dtype = racket.pos.dtype
    k = jnp.arange(total, dtype=dtype) * dt - contact_time(dt)  # each step's start, from the contact
    play = (jnp.arange(total) < WINDOW)[None, :, None]
    pos = racket.pos[:, None] + k[None, :, None] * racket.vel[:, None]
    away = racket.pos[:, None] - 100.0 * racket.rot[:, None, :, 0]
    schedule = jax.tree.map(lambda a: jnp.broadcast_to(a[:, None], (a.shape[0], total) + a.shape[1:]), racket)
    schedule = schedule.replace(pos=jnp.where(play, pos, away), vel=jnp.where(play, schedule.vel, 0.0),
                                ang_vel=jnp.where(play, schedule.ang_vel, 0.0))
    return jax.tree.map(lambda a: a[:, :, None], schedule)


@partial(jax.jit, static_argnames=("n_steps", "buffering"))
def program_outcome(model, ball: Ball, racket: Racket, dt, *, n_steps: int, buffering: str | None = None) -> Outcome:
    """Runs shots through the kernel and reads every column of :data:`COLUMNS`.

    One rollout records the ball at every step (the net crossing is read from it); in reverse mode
    the kernel then rematerialises each step once (its chunks are single steps). Each ball stops at
    its second event (``rollout(record=Record(until_events=2))``: the landing, for a shot that lands), and steps
    where every ball has stopped are skipped: a batch of shots that land early costs little more
    than its flights to the landing, whatever the horizon.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model` with a leading (B,) axis on every leaf (per shot,
            so that a reverse-mode Jacobian gives each shot its own parameter gradient).
        ball: :class:`Ball` (B, 3) at the start, ``cases.contact_time(dt)`` before the contact.
        racket: :class:`Racket` (B, ...) at the contact; in play for ``cases.WINDOW`` steps,
            moving with its velocity (its orientation held), then withdrawn (:func:`racket_schedule`).
        dt: step [s].
        n_steps: steps of the flight after the racket window (static): the horizon.
        buffering: the kernel's contact buffering (``rollout``; static): the same outcome either way.
            Reverse mode wants ``"single"``: the transpose of each skipped buffer of ``"loop"``
            still writes zero cotangents for the whole batch and every per-shot parameter (2.4x
            the backward pass's time through 300 steps of 512 shots, float32, CPU).

    Returns:
        An :class:`Outcome` with every column of :data:`COLUMNS`.
    """
    dtype = ball.pos.dtype
    total = WINDOW + n_steps
    schedule = racket_schedule(racket, total, dt)
    _, out = rollout(model, init_state(ball), total, dt, schedule, model_axes=0,
                     record=Record(every=1, max_events=2, until_events=2), execution=Execution(buffering=buffering))
    log = out.events
    sequence = log.kind[:, :2]
    valid = (sequence[:, 0] == ev.RACKET) & (sequence[:, 1] == ev.TABLE)
    post = log.post.vel[:, 1]
    z, crossed, cross_step = _net_crossing(ball, out.trajectory, jnp.asarray(dt, dtype))
    values = jnp.concatenate([
        log.pre.pos[:, 1, :2],  # landing point
        (log.time[:, 1] - log.time[:, 0])[:, None],  # landing time
        jnp.sqrt(jnp.sum(post * post, -1) + jnp.finfo(dtype).tiny)[:, None],  # speed after the bounce
        (z - model.ball.radius - model.table.net_height)[:, None],  # net clearance
    ], -1)
    values = jnp.where(valid[:, None], values, 0.0)
    # the step holding the landing (its time t + tau dt, tau in (0, 1]); the start time is 0
    landed = jnp.floor(log.time[:, 1] / dt).astype(jnp.int32) + 1
    steps = jnp.where(valid, jnp.maximum(landed, jnp.where(crossed, cross_step, 0)), total)
    return Outcome(values=values, sequence=sequence.astype(jnp.int32), valid=valid, crossed=crossed,
                   steps=jnp.minimum(steps, total).astype(jnp.int32))


def shot_outcome(model, ball: Ball, racket: Racket, dt, *, target: str, n_steps: int) -> Outcome:
    """:func:`program_outcome` reduced to ``target`` (:func:`for_target`).

    Arguments:
        target: a key of :data:`TARGETS`; the others as :func:`program_outcome`.

    Returns:
        An :class:`Outcome`.
    """
    check_target(target)
    return for_target(program_outcome(model, ball, racket, dt, n_steps=n_steps), target)
