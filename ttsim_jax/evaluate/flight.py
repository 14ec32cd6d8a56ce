"""Flight-segment position error of a model, as the paper evaluates it.

Per segment: the initial position is the first observation, the spin the measured one, the
initial velocity is fitted (Gauss-Newton on the positions, through the model's own flight stage
and coefficient models), and the error is the 3-D position RMSE over the segment's samples,
sqrt(mean_i |p_model(t_i) - p_i|^2). Segments are batched like the identification's fits
(:func:`ttsim_jax.fit.aero.batches`); one compilation per model family.
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit import aero as A

ITERATIONS = 6


def _rmse_one(aero, air, tau, pos, mask, spin, n, iterations):
    p0 = pos[0]

    def res(v0):
        ps, _ = A.integrate(aero, p0, v0, tau, spin, n, air)
        return ((ps - pos) * mask[:, None]).ravel()

    def body(_, v0):
        # One integration carries the residual and the three tangents.
        r, jac = jax.vmap(lambda t: jax.jvp(res, (v0,), (t,)), out_axes=(None, 1))(jnp.eye(3, dtype=v0.dtype))
        h = jac.T @ jac
        step = A._spd_solve(h + 1e-9 * jnp.trace(h) * jnp.eye(3, dtype=h.dtype) + 1e-30, jac.T @ r)
        cand = v0 - step
        return jnp.where(jnp.all(jnp.isfinite(cand)), cand, v0)

    v0 = jax.lax.fori_loop(0, iterations, body, A.initial_guess(tau, pos, mask)[3:6])
    r = res(v0)
    return jnp.sqrt(jnp.sum(r**2) / jnp.maximum(jnp.sum(mask), 1.0)), v0


_rmse_batch = jax.jit(jax.vmap(_rmse_one, in_axes=(None, None, 0, 0, 0, 0, None, None)), static_argnames="iterations")


def flight_rmse(model, times: Sequence[np.ndarray], positions: Sequence[np.ndarray], spins, *,
                iterations: int = ITERATIONS, batch: int = A.BATCH) -> np.ndarray:
    """3-D position RMSE [m] of ``model``'s flight per segment (initial velocity fitted).

    Arguments:
        model: a loaded :class:`~ttsim_jax.params.Model` (its ball, air and coefficient models).
        times: list of (T_i,) sample times [s]; positions: list of (T_i, 3) positions [m].
        spins: (S, 3) measured spins [rad/s].
        iterations: Gauss-Newton iterations on the initial velocity.
        batch: segments per compiled call.

    Returns:
        (S,) RMSE [m] (NaN for segments with fewer than 3 samples).
    """
    dtype = np.float32
    air = A.Air.from_model(model, dtype)
    aero = jax.tree.map(lambda x: jnp.asarray(x, dtype), model.aero)
    spins = np.asarray(spins, np.float64).reshape(len(times), 3)
    out = np.full(len(times), np.nan)
    for idx, (tau, pos, mask, spin), n_max in A.batches(times, positions, spins, batch, dtype):
        rmse, _ = _rmse_batch(aero, air, tau, pos, mask, spin, jnp.asarray(n_max), iterations)
        out[idx] = np.asarray(rmse)[: len(idx)]
    return out
