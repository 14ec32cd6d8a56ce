"""Flight-segment position error of a model, as the paper evaluates it.

Per segment: the initial position is the first observation (or, with ``fit_position``, fitted
too), the spin the measured one, the initial velocity is fitted (Gauss-Newton on the positions, through the model's own flight stage
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


def _rmse_one(aero, air, tau, pos, mask, spin, n, iterations, fit_position):
    guess = A.initial_guess(tau, pos, mask)

    def res(x):
        p0 = x[:3] if fit_position else pos[0]
        ps, _ = A.integrate(aero, p0, x[-3:], tau, spin, n, air)
        return ((ps - pos) * mask[:, None]).ravel()

    def body(_, x):
        # One integration carries the residual and the tangents.
        eye = jnp.eye(x.shape[0], dtype=x.dtype)
        r, jac = jax.vmap(lambda t: jax.jvp(res, (x,), (t,)), out_axes=(None, 1))(eye)
        h = jac.T @ jac
        cand = x - A._spd_solve(h + 1e-9 * jnp.trace(h) * eye + 1e-30, jac.T @ r)
        return jnp.where(jnp.all(jnp.isfinite(cand)), cand, x)

    x = jax.lax.fori_loop(0, iterations, body, guess[:6] if fit_position else guess[3:6])
    r = res(x)
    return jnp.sqrt(jnp.sum(r**2) / jnp.maximum(jnp.sum(mask), 1.0)), x


_rmse_batch = jax.jit(jax.vmap(_rmse_one, in_axes=(None, None, 0, 0, 0, 0, None, None, None)),
                      static_argnames=("iterations", "fit_position"))


def flight_rmse(model, times: Sequence[np.ndarray], positions: Sequence[np.ndarray], spins, *,
                fit_position: bool = False, iterations: int = ITERATIONS, batch: int = A.BATCH) -> np.ndarray:
    """3-D position RMSE [m] of ``model``'s flight per segment (initial velocity fitted).

    Arguments:
        model: a loaded :class:`~ttsim_jax.params.Model` (its ball, air and coefficient models).
        times: list of (T_i,) sample times [s]; positions: list of (T_i, 3) positions [m].
        spins: (S, 3) measured spins [rad/s].
        fit_position: also fit the initial position (the identification's protocol) instead of
            taking the first observation (the paper's evaluation).
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
        rmse, _ = _rmse_batch(aero, air, tau, pos, mask, spin, jnp.asarray(n_max), iterations, fit_position)
        out[idx] = np.asarray(rmse)[: len(idx)]
    return out
