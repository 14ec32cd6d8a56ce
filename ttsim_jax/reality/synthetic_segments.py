"""Flight segments from known parameters, sampled like a tracking system: the truth against which
the flight fit (:mod:`ttsim_jax.fit.flightfit`) and the aerodynamic identification are checked."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.physics.aero import AeroParams, ConstantCoefficient, flight_step

from ttsim_jax.fit.flightfit import CD_0, CM_0


def synthetic_segments(aero: AeroParams, radius, mass, n: int, *, seed: int = 0, coefficients=None,
                       rate: float = 143.0, duration=(0.3, 0.6), speed=(4.0, 16.0), spin_rate=(50.0, 500.0),
                       noise: float = 0.002, substeps: int = 7):
    """Flight segments from known parameters, sampled like a tracking system, for identifiability checks.

    Balls start near one end line (x = -1.3 m, y in +-0.3 m, z in 0.2-0.4 m) heading towards +x
    (heading within +-10 deg, elevation -5 to 15 deg) with spin along a random axis.

    Arguments:
        aero: flight parameters of the truth (any coefficient models).
        radius, mass: ball radius [m] and mass [kg].
        n: number of segments.
        seed: random seed.
        coefficients: optional (n, 2) constant (C_D, C_M) per segment, replacing aero's models.
        rate: sampling rate [Hz]; duration: range of segment durations [s].
        speed: range of initial speeds [m/s]; spin_rate: range of spin rates [rad/s].
        noise: standard deviation of the position noise per axis [m].
        substeps: RK4 steps per sampling interval of the truth.

    Returns:
        (times list of (T_i,), positions list of (T_i, 3) noisy, spins (n, 3), states (n, 6) true
        initial position and velocity).
    """
    rng = np.random.default_rng(seed)
    p0 = np.stack([np.full(n, -1.3), rng.uniform(-0.3, 0.3, n), rng.uniform(0.2, 0.4, n)], 1)
    head, elev = np.radians(rng.uniform(-10, 10, n)), np.radians(rng.uniform(-5, 15, n))
    v0 = rng.uniform(*speed, n)[:, None] * np.stack(
        [np.cos(elev) * np.cos(head), np.cos(elev) * np.sin(head), np.sin(elev)], 1)
    axis = rng.normal(size=(n, 3))
    spins = rng.uniform(*spin_rate, n)[:, None] * axis / np.linalg.norm(axis, axis=1, keepdims=True)
    counts = np.round(rng.uniform(*duration, n) * rate).astype(int) + 1
    steps = int(counts.max() - 1) * substeps
    h = 1.0 / (rate * substeps)
    coef = np.tile([[CD_0, CM_0]], (n, 1)) if coefficients is None else np.asarray(coefficients, np.float64)
    dtype = jnp.zeros(()).dtype

    def one(p, v, w, c):
        air = aero if coefficients is None else aero.replace(drag=ConstantCoefficient(c[0]),
                                                             magnus=ConstantCoefficient(c[1]))

        def step(carry, _):
            p, v = carry
            p, v, _ = flight_step(air, radius, mass, p, v, w, 0.0, h)
            return (p, v), p

        _, ps = jax.lax.scan(step, (p, v), None, length=steps)
        return jnp.concatenate([p[None], ps[substeps - 1::substeps]])

    arr = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    paths = np.asarray(jax.jit(jax.vmap(one))(arr(p0), arr(v0), arr(spins), arr(coef)), np.float64)
    times, positions = [], []
    for i, k in enumerate(counts):
        times.append(np.arange(k) / rate)
        positions.append(paths[i, :k] + rng.normal(0.0, noise, (k, 3)))
    return times, positions, spins, np.concatenate([p0, v0], 1)
