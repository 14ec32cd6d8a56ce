"""Synthetic contacts through one stage's law, for the stage fits' tests and studies.

The states a fit should recover, made by the stage's own model with known parameters:

* :func:`draw_contact_states`: random racket-frame pre-contact states;
* :func:`synthetic_arrays`: racket contacts through the racket base model (the arrays
  :func:`ttsim_jax.fit.racket.fit_racket` takes);
* :func:`synthetic_bounces`: table bounces through the table model (what
  :func:`ttsim_jax.fit.table.fit_table` takes).

Flights into contacts, in the measured-data format, are :mod:`ttsim_jax.reality.synthetic`; whole
games are :func:`ttsim_jax.reality.generate`.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit import racket as racket_fit
from ttsim_jax.fit import table as table_fit
from ttsim_jax.physics import racket as racket_stage


def draw_contact_states(rng: np.random.Generator, n: int, max_speed: float = 15.0, max_spin: float = 600.0):
    """Random racket-frame pre-contact states: (v~ (n, 3), w~ (n, 3), d (n, 2)).

    Speed 1..max_speed m/s within 60 degrees of the face normal (v~_x < 0), spin up to ``max_spin``
    rad/s in a uniform direction, d uniform over a 7.5 cm disc.
    """
    rad = 0.075 * np.sqrt(rng.uniform(0.0, 1.0, n))
    phi = rng.uniform(0.0, 2 * math.pi, n)
    d = np.stack([rad * np.cos(phi), rad * np.sin(phi)], 1)
    speed = rng.uniform(1.0, max_speed, n)
    cos_t = rng.uniform(0.5, 1.0, n)
    sin_t = np.sqrt(1.0 - cos_t**2)
    psi = rng.uniform(0.0, 2 * math.pi, n)
    v_t = speed[:, None] * np.stack([-cos_t, sin_t * np.cos(psi), sin_t * np.sin(psi)], 1)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    w_t = rng.uniform(0.0, max_spin, n)[:, None] * direction
    return v_t, w_t, d


def synthetic_arrays(params: racket_stage.RacketParams, radius: float, mass: float, n: int, *, seed: int = 0,
                     noise_vel: float = 0.0, noise_spin: float = 0.0, max_speed: float = 15.0,
                     max_spin: float = 600.0):
    """Racket-frame arrays (x (n, 8), y_obs (n, 6)) of contacts through the base model ``params``.

    Pre-contact states from :func:`draw_contact_states`;
    Gaussian noise ``noise_vel`` [m/s] / ``noise_spin`` [rad/s] on every component of both states.
    """
    v, w, d = draw_contact_states(np.random.default_rng(seed), n, max_speed, max_spin)
    x = np.concatenate([v, w, d], 1)
    vp, wp = racket_fit.predict(params, jnp.asarray(x, jnp.float32), jnp.float32(radius), jnp.float32(mass))
    y = np.concatenate([np.asarray(vp), np.asarray(wp)], 1).astype(np.float64)
    rng = np.random.default_rng(seed + 1)
    noise = np.concatenate([np.full(3, noise_vel), np.full(3, noise_spin)])
    x[:, :6] += rng.normal(size=(n, 6)) * noise
    y += rng.normal(size=(n, 6)) * noise
    return x, y


def synthetic_bounces(table, radius: float, n: int, *, seed: int = 0, noise_vel: float = 0.0,
                      noise_spin: float = 0.0) -> dict:
    """Bounces with known parameters: rally-like incoming states through the table model.

    Incoming: heading uniform, horizontal speed 2-12 m/s, v_z from -7 to -2.5 m/s, spin in the
    local frame up to 150 (about the heading), 500 (top/back spin) and 300 rad/s (about z); the
    outgoing state from :func:`~ttsim_jax.physics.table.local_contact` with ``table``. Gaussian
    noise of ``noise_vel`` [m/s] and ``noise_spin`` [rad/s] is added to every component of both.

    Returns:
        dict of float64 (n, 3) arrays ``vel_in``, ``spin_in``, ``vel_out``, ``spin_out`` (noisy) and
        ``true_*`` (without noise), and ``weight`` (n,) the residual's fade x bound factor.
    """
    rng = np.random.default_rng(seed)
    heading = rng.uniform(-np.pi, np.pi, n)
    vh = rng.uniform(2.0, 12.0, n)
    c, s = np.cos(heading), np.sin(heading)
    vel = np.stack([vh * c, vh * s, rng.uniform(-7.0, -2.5, n)], 1)
    w_loc = np.stack([rng.uniform(-150, 150, n), rng.uniform(-500, 500, n), rng.uniform(-300, 300, n)], 1)
    spin = np.stack([w_loc[:, 0] * c - w_loc[:, 1] * s, w_loc[:, 0] * s + w_loc[:, 1] * c, w_loc[:, 2]], 1)
    size = table_fit.padded_size(n)
    vp, wp, lam = (np.asarray(a, np.float64)[:n] for a in table_fit.predicted_bounces(table, jnp.asarray(radius, jnp.float32),
                                                                    jnp.asarray(table_fit.pad_rows(vel, size), jnp.float32),
                                                                    jnp.asarray(table_fit.pad_rows(spin, size), jnp.float32)))
    out = dict(true_vel_in=vel, true_spin_in=spin, true_vel_out=vp, true_spin_out=wp, weight=lam)
    for k in ("vel_in", "vel_out"):
        out[k] = out["true_" + k] + rng.normal(0.0, noise_vel, (n, 3))
    for k in ("spin_in", "spin_out"):
        out[k] = out["true_" + k] + rng.normal(0.0, noise_spin, (n, 3))
    return out
