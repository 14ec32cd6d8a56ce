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
    """

    params: Any
    fn: Callable = struct.field(pytree_node=False)


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
