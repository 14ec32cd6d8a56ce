"""Padding a small scenario up to a test module's one compiled batch size, and the suite's shared
rollout shape.

Modules that run the shared shape (:func:`simulate_shared`) compile each model family and dtype
once per test run between them: the same function with the same shapes and static arguments
is the same program, which the persistent compilation cache of conftest.py hands from one test
process to the next.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import Ball, Racket, Record, simulate

B = 8  # balls
N = 1600  # steps
RECORD = 10  # steps between recorded points
AWAY = (0.0, 5.0, 2.0)  # a racket beside the table, 2 m up, that no ball of a test comes near


def pad_balls(balls: Ball, n: int) -> Ball:
    """``balls`` filled up to ``n`` balls with balls at rest on the floor beside the table (they
    touch nothing the others touch), so every scenario of a module shares one compiled shape."""
    k = balls.pos.shape[0]
    filler = Ball.create(np.tile([[3.0, 0.0, -0.74]], (n - k, 1)), np.zeros((n - k, 3)), dtype=balls.pos.dtype)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), balls, filler)


def resting_racket(pos=AWAY, n: int = N) -> Racket:
    """A schedule of ``n`` steps of one racket at rest at ``pos`` (face normal +x)."""
    return jax.tree.map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), Racket.create(jnp.asarray(pos, float)))


def simulate_shared(model, balls: Ball, dt: float = 1e-3, racket: Racket | None = None, **kwargs):
    """``simulate`` in the shared shape: ``balls`` padded to B, N steps of ``dt`` (traced: any dt
    shares the shape), a one-racket schedule of N steps (default: :func:`resting_racket`), the
    ball recorded every RECORD steps, 8 events.

    Arguments:
        model: a model; its dtype is the simulation's.
        balls: up to B balls.
        dt: step [s].
        racket: a (N, ...) racket schedule, or None.
        kwargs: passed on to ``simulate`` (e.g. ``integrator``; a static one compiles anew).

    Returns:
        ``simulate``'s result for the padded batch.
    """
    racket = resting_racket() if racket is None else racket
    return simulate(model, pad_balls(balls, B), N, dt, racket=racket, record=Record(every=RECORD), **kwargs)
