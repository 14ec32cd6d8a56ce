"""Racket plans: where the rackets are at each step.

A plan is ``None`` (no racket); a :class:`~ttsim_jax.state.Racket` *schedule* with a leading time
axis, entry k being the rackets at the rollout's k-th step (``(T, R, ...)`` shared by all balls, or
``(B, T, R, ...)`` per ball; the R axis may be left out for one racket); or a :class:`RacketPolicy`,
a pure function of (params, ball, t) evaluated inside the scan (the form an RL environment uses).
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.state import Racket


@struct.dataclass
class RacketPolicy:
    """A racket plan evaluated inside the scan: ``fn(params, ball, t) -> Racket`` ((R, ...) fields).

    ``fn`` is static (part of the compiled program); ``params`` is a pytree argument, so new
    policy parameters never recompile.

    ``reach`` (optional, static) lets the fused path (:mod:`~ttsim_jax.kernel.fused`) fly a ball
    through many steps without evaluating the policy: ``reach(params, dt) -> (R, 2, 3)``, per racket
    the lower and upper corners of a box that holds every point of its face over any step of
    length ``dt``, whatever the ball and the time: the face around its centre at the step's start
    (``pos``, a face point lying within ``max(face)`` of it) and where the step moves it
    (``pos + dt vel``). A ball far from every box flies fused; near one it takes the ordinary step,
    with the policy evaluated at its own time. Without ``reach`` a policy takes the reference path.
    The fused path checks the promise wherever it evaluates the policy: a ball whose rackets lie
    outside their boxes there ends ``INVALID`` (its rollout there cannot be trusted), where the
    reference path, which checks nothing, would fly on.
    """

    params: Any
    fn: Callable = struct.field(pytree_node=False)
    reach: Callable | None = struct.field(pytree_node=False, default=None)


def check_reach(policy: RacketPolicy, ball, dt) -> None:
    """Refuses a :attr:`RacketPolicy.reach` whose boxes are not (R, 2, 3) for the R rackets the
    policy gives (shapes only, from ``jax.eval_shape``: nothing runs), before anything compiles.

    Arguments:
        policy: the policy; ball: the rollout's (B, 3) balls; dt: the step [s] (a number or traced).
    """
    if policy.reach is None:
        return
    scalar = jax.ShapeDtypeStruct((), ball.pos.dtype)
    one = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), ball)
    rackets = jax.eval_shape(policy.fn, policy.params, one, scalar)
    boxes = jax.eval_shape(policy.reach, policy.params, scalar)
    n = rackets.pos.shape[0] if len(rackets.pos.shape) == 2 else 1
    shape = getattr(boxes, "shape", None)
    if shape != (n, 2, 3):
        raise ValueError(f"RacketPolicy.reach(params, dt) gives shape {shape}; it must be ({n}, 2, 3): for each "
                         f"of the {n} rackets the policy gives, the lower and upper corners of the box its face "
                         "stays in")


def face_boxes(pos, vel, face, dt):
    """(..., 2, 3) the box holding every point of a racket's face over a step of ``dt``: the face
    around its centre ``pos`` and around ``pos + dt vel`` (a face point lies within ``max(face)`` of
    its centre). What :attr:`RacketPolicy.reach` must hold.

    Arguments:
        pos, vel: (..., 3) the centre and its velocity; face: (..., 2) the face's semi-axes [m].
    """
    end = pos + dt * vel
    half = jnp.max(face, axis=-1, keepdims=True)
    return jnp.stack([jnp.minimum(pos, end) - half, jnp.maximum(pos, end) + half], axis=-2)


def within_reach(racket: Racket, boxes, dt, tol=0.0):
    """(...,) bool over ``racket``'s leading axes before R: every racket's :func:`face_boxes` lies
    inside its box of ``boxes`` ((R, 2, 3), a :attr:`RacketPolicy.reach`), within ``tol`` [m]."""
    faces = face_boxes(racket.pos, racket.vel, racket.face, dt)
    inside = (faces[..., 0, :] >= boxes[..., 0, :] - tol) & (faces[..., 1, :] <= boxes[..., 1, :] + tol)
    return jnp.all(inside, axis=(-2, -1))


def normalise_schedule(racket: Racket, n_steps: int, batch: int):
    """(schedule with (T, [B,] R, ...) fields cut to ``n_steps``, per-ball?) from the accepted layouts."""
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
