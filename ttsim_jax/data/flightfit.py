"""The flight fit that filters segments: the simulator's flight stage with constant aerodynamic
coefficients, fitted per segment by Levenberg-Marquardt in JAX.

As in the paper's data filtering (and the authors' code), a segment is kept when a
constant-coefficient aerodynamic model fits it within 20 mm RMSE: the free parameters are the
initial position, the initial velocity, C_D and C_M, and the model is exactly
:func:`ttsim_jax.physics.aero.flight_step` (RK4) with :class:`~ttsim_jax.physics.aero.ConstantCoefficient`
coefficients and the spin given (C_M has no effect when the spin is zero). The RMSE is that of
the 3-D position error, sqrt(mean_i |p_fit(t_i) - p_i|^2). Any other ``rmse_fn(times,
positions, spin) -> rmse_m`` can be given to :func:`ttsim_jax.data.segment.filter_segments`.
"""

from __future__ import annotations

from functools import partial
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.physics.aero import AeroParams, ConstantCoefficient, flight_step

#: Where the fit starts: Nakashima's coefficients.
CD_0, CM_0 = 0.54, 0.069
#: Ball and air of the fit (the paper's ball; standard air at 20 C).
RADIUS, MASS, RHO_AIR, NU = 0.02, 2.721e-3, 1.204, 1.506e-5
_SUBSTEPS = 2
_ITERATIONS = 20
_BATCH = 64


def _aero(cd, cm):
    dtype = cd.dtype
    return AeroParams(rho_air=jnp.asarray(RHO_AIR, dtype), nu=jnp.asarray(NU, dtype),
                      gravity=jnp.array([0.0, 0.0, -9.81], dtype), buoyancy=jnp.asarray(1.0, dtype),
                      drag=ConstantCoefficient(cd), magnus=ConstantCoefficient(cm))


def _predict(theta, tau, spin):
    """Positions at times ``tau`` (T,) from the state at tau[0]; padded times repeat (dt = 0)."""
    p0, v0, cd, cm = theta[:3], theta[3:6], theta[6], theta[7]
    aero = _aero(cd, cm)

    def interval(state, dt):
        p, v = state
        h = dt / _SUBSTEPS
        for _ in range(_SUBSTEPS):
            p, v, _ = flight_step(aero, RADIUS, MASS, p, v, spin, 0.0, h)
        return (p, v), p

    _, ps = jax.lax.scan(interval, (p0, v0), jnp.diff(tau))
    return jnp.concatenate([p0[None], ps], axis=0)


def _residual(theta, tau, pos, mask, spin):
    return ((_predict(theta, tau, spin) - pos) * mask[:, None]).ravel()


def _initial_guess(tau, pos, mask):
    # A per-axis parabola gives position and velocity at tau[0] well enough for LM to converge.
    a = jnp.stack([jnp.ones_like(tau), tau, tau**2], axis=-1) * mask[:, None]
    coef, *_ = jnp.linalg.lstsq(a, pos * mask[:, None])
    return jnp.concatenate([coef[0], coef[1], jnp.array([CD_0, CM_0], pos.dtype)])


def _fit_one(tau, pos, mask, spin):
    theta = _initial_guess(tau, pos, mask)
    res = partial(_residual, tau=tau, pos=pos, mask=mask, spin=spin)
    cost0 = jnp.sum(res(theta) ** 2)

    def body(_, carry):
        theta, lam, cost = carry
        r = res(theta)
        jac = jax.jacfwd(res)(theta)
        jtj = jac.T @ jac
        # The absolute term keeps the system solvable when k_m has no effect (zero spin).
        a = jtj + lam * (jnp.diag(jnp.diag(jtj)) + 1e-9 * jnp.eye(theta.shape[0], dtype=theta.dtype))
        step = -jnp.linalg.solve(a, jac.T @ r)
        cand = theta + step
        c_new = jnp.sum(res(cand) ** 2)
        ok = jnp.isfinite(c_new) & (c_new < cost)
        return (jnp.where(ok, cand, theta), jnp.where(ok, lam * 0.3, lam * 10.0), jnp.where(ok, c_new, cost))

    theta, _, cost = jax.lax.fori_loop(0, _ITERATIONS, body, (theta, jnp.asarray(1e-3, pos.dtype), cost0))
    n = jnp.maximum(jnp.sum(mask), 1.0)
    return theta, jnp.sqrt(cost / n)


@jax.jit
def fit_flight_batch(tau, pos, mask, spin):
    """Fits the flight model to a padded batch of segments.

    Arguments:
        tau: (S, T) times relative to each segment's first sample [s]; padding repeats the last time.
        pos: (S, T, 3) observed positions [m].
        mask: (S, T) 1 for real samples, 0 for padding.
        spin: (S, 3) spin of each segment [rad/s] (zeros when unknown).

    Returns:
        (theta, rmse): (S, 8) parameters ``[p0 (3), v0 (3), C_D, C_M]`` and (S,) RMSE [m].
    """
    return jax.vmap(_fit_one)(tau, pos, mask, spin)


def _bucket(n: int) -> int:
    # Few distinct padded lengths -> few compilations.
    return max(8, 1 << int(np.ceil(np.log2(max(n, 1)))))


def ballistic_rmse_many(times: Sequence[np.ndarray], positions: Sequence[np.ndarray], spins=None) -> np.ndarray:
    """RMSE of the fitted flight model for many segments at once.

    Arguments:
        times: list of (T_i,) sample times [s] per segment (strictly increasing).
        positions: list of (T_i, 3) positions [m].
        spins: optional list/array of (3,) spins [rad/s] (default zeros).

    Returns:
        (S,) RMSE [m] per segment (NaN for segments with fewer than 2 samples).
    """
    n_seg = len(times)
    out = np.full(n_seg, np.nan)
    if spins is None:
        spins = np.zeros((n_seg, 3))
    spins = np.asarray(spins, np.float64).reshape(n_seg, 3)
    lengths = np.array([len(t) for t in times], int)
    buckets: dict[int, list[int]] = {}
    for i, n in enumerate(lengths):
        if n >= 2:
            buckets.setdefault(_bucket(n), []).append(i)
    for size, members in sorted(buckets.items()):
        for start in range(0, len(members), _BATCH):
            idx = members[start : start + _BATCH]
            tau = np.zeros((_BATCH, size), np.float32)
            pos = np.zeros((_BATCH, size, 3), np.float32)
            mask = np.zeros((_BATCH, size), np.float32)
            spin = np.zeros((_BATCH, 3), np.float32)
            for row, i in enumerate(idx):
                n = lengths[i]
                t = np.asarray(times[i], np.float64)
                tau[row, :n] = t - t[0]
                tau[row, n:] = tau[row, n - 1]
                pos[row, :n] = positions[i]
                pos[row, n:] = positions[i][-1]
                mask[row, :n] = 1.0
                spin[row] = spins[i]
            _, rmse = fit_flight_batch(tau, pos, mask, spin)
            out[idx] = np.asarray(rmse)[: len(idx)]
    return out


def ballistic_rmse(times, positions, spin=None) -> float:
    """RMSE [m] of the flight model fitted to one segment; the default ``rmse_fn``.

    Arguments:
        times: (T,) sample times [s].
        positions: (T, 3) positions [m].
        spin: optional (3,) spin [rad/s].

    Returns:
        sqrt(mean |p_fit - p|^2) over the samples [m].
    """
    spins = None if spin is None else np.asarray(spin, np.float64)[None]
    return float(ballistic_rmse_many([np.asarray(times)], [np.asarray(positions)], spins)[0])
