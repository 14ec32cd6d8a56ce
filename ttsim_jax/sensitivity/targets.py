"""What a sensitivity study differentiates: a shot's outcome, read from the rally kernel's event log.

A shot (:mod:`ttsim_jax.sensitivity.cases`) runs as two rollouts of the kernel: ``WINDOW`` steps with
the racket (the contact, its time of impact, the racket model and the residual network, as in any
rally), then the flight without racket until the horizon. The landing is the first event of the
flight and must be a table contact; its point and time are the kernel's (refined time of impact),
so they are differentiable in every input.

Targets (:data:`TARGETS`): ``landing`` (x, y of the ball centre at the landing [m]),
``landing_time`` (from the racket contact to the landing [s]), ``net_clearance`` (height of the
ball's underside above the net's top edge where its centre crosses the net plane x = 0 [m]) and
``bounce_speed`` (the ball's speed just after the landing [m/s]).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from flax import struct

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


@struct.dataclass
class Outcome:
    """A batch of shots' outcomes.

    Attributes:
        values: (B, k) the target's components (:data:`TARGETS`), 0 where not ``valid``.
        sequence: (B, 2) int32: the first event kind of the racket window and the first event of
            the flight (``physics.events``): (RACKET, TABLE) for a shot that lands.
        valid: (B,) the shot hit the racket, then landed on the table within the horizon (and,
            for ``net_clearance``, crossed the net plane before landing).
    """

    values: jnp.ndarray
    sequence: jnp.ndarray
    valid: jnp.ndarray


def check_target(target: str) -> tuple[str, ...]:
    """The component names of ``target``; an unknown target raises ValueError naming the known ones."""
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r}; known: {', '.join(TARGETS)}")
    return TARGETS[target]


def _net_crossing(start: Ball, traj: Ball, dt):
    """(B,) height of the ball centre where it first crosses x = 0, and whether it does.

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
    return p[:, 2], found


@partial(jax.jit, static_argnames=("target", "n_steps"))
def shot_outcome(model, ball: Ball, racket: Racket, dt, *, target: str, n_steps: int) -> Outcome:
    """Runs shots through the kernel and reads their target.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model` with a leading (B,) axis on every leaf (per shot,
            so that a reverse-mode Jacobian gives each shot its own parameter gradient).
        ball: :class:`Ball` (B, 3) at the start, ``cases.contact_time(dt)`` before the contact.
        racket: :class:`Racket` (B, ...) at the contact; in play for ``cases.WINDOW`` steps,
            moving with its velocity (its orientation held).
        dt: step [s].
        target: a key of :data:`TARGETS` (static).
        n_steps: steps of the flight after the racket window (static): the horizon.

    Returns:
        An :class:`Outcome`.
    """
    check_target(target)
    dtype = ball.pos.dtype
    k = jnp.arange(WINDOW, dtype=dtype) * dt - contact_time(dt)  # each window step's start, from the contact
    schedule = jax.tree.map(lambda a: jnp.broadcast_to(a[:, None], (a.shape[0], WINDOW) + a.shape[1:]), racket)
    schedule = schedule.replace(pos=racket.pos[:, None] + k[None, :, None] * racket.vel[:, None])
    schedule = jax.tree.map(lambda a: a[:, :, None], schedule)  # (B, T, R=1, ...)
    state, hit = rollout(model, init_state(ball), WINDOW, dt, schedule, model_axes=0, max_events=2)
    start = state.ball
    record = 1 if target == "net_clearance" else 0
    state, out = rollout(model, state, n_steps, dt, None, model_axes=0, max_events=2, record_every=record)
    sequence = jnp.stack([hit.events.kind[:, 0], out.events.kind[:, 0]], -1)
    valid = (sequence[:, 0] == ev.RACKET) & (hit.events.count == 1) & (sequence[:, 1] == ev.TABLE)
    land = out.events.pre.pos[:, 0]
    if target == "landing":
        values = land[:, :2]
    elif target == "landing_time":
        values = (out.events.time[:, 0] - hit.events.time[:, 0])[:, None]
    elif target == "bounce_speed":
        post = out.events.post.vel[:, 0]
        values = jnp.sqrt(jnp.sum(post * post, -1) + jnp.finfo(dtype).tiny)[:, None]
    else:
        z, found = _net_crossing(start, out.trajectory, jnp.asarray(dt, dtype))
        valid = valid & found
        values = (z - model.ball.radius - model.table.net_height)[:, None]
    values = jnp.where(valid[:, None], values, 0.0)
    return Outcome(values=values, sequence=sequence.astype(jnp.int32), valid=valid)
