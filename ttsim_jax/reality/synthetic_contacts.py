"""A synthetic racket-contact set with a known residual, and the experiment that checks that
training the residual network recovers it (``python -m ttsim_jax.reality.synthetic_contacts``).

Inputs are drawn over plausible racket-frame states (:func:`sample_racket_inputs`), the base model
is the paper's updated racket model (:func:`standin_base_fn`) or the simulator's own
(:func:`racket_base_fn`), and the observations add :func:`true_residual` and heteroscedastic
noise (:func:`make_synthetic_contacts`). :func:`recovery_experiment` trains on them and reports
how much of the residual the network recovers.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit.network_config import TrainConfig, load_train_config
from ttsim_jax.fit.network_training import split_by_contact, train_residual
from ttsim_jax.physics.network import ResidualConfig

BALL_RADIUS = 0.02
BALL_MASS = 4.0 / 3.0 * math.pi * BALL_RADIUS**3 * 81.2  # kg; ball density from the authors' code
FACE_RADIUS = 0.075  # contact positions of the synthetic set lie within this radius [m]


def standin_base_fn(x, e0=0.878, e1=-0.020, et0=0.819, et1=-0.010, e_s=0.805, kappa=1.5, radius=BALL_RADIUS):
    """The paper's updated racket base model in the racket frame (vectorised stand-in).

    Normal x: v+_x = -e_n v_x with e_n = clip(e0 + e1 |v_x|, 0, 1). Tangential: the contact
    point's velocity u = (v_y - r w_z, v_z + r w_y) changes by -alpha u, alpha = (1 + e_t) /
    (1 + kappa), e_t = clip(et0 + et1 |u|, 0, 1), and the spin by the matching angular impulse;
    the normal spin is damped by e_s. Defaults: the paper's Table IV.

    Arguments:
        x: (N, >= 6) racket-frame inputs (v~, w~[, d]); d is ignored.
        e0, e1, et0, et1, e_s, kappa, radius: model coefficients.

    Returns:
        (N, 6) post-contact (v+, w+) in the racket frame.
    """
    x = jnp.asarray(x)
    v, w = x[:, 0:3], x[:, 3:6]
    e_n = jnp.clip(e0 + e1 * jnp.abs(v[:, 0]), 0.0, 1.0)
    u_y = v[:, 1] - radius * w[:, 2]
    u_z = v[:, 2] + radius * w[:, 1]
    u = jnp.sqrt(u_y**2 + u_z**2 + 1e-12)
    e_t = jnp.clip(et0 + et1 * u, 0.0, 1.0)
    alpha = (1.0 + e_t) / (1.0 + kappa)
    k = kappa * alpha / radius
    v_plus = jnp.stack([-e_n * v[:, 0], v[:, 1] - alpha * u_y, v[:, 2] - alpha * u_z], axis=1)
    w_plus = jnp.stack([e_s * w[:, 0], w[:, 1] - k * u_z, w[:, 2] + k * u_y], axis=1)
    return jnp.concatenate([v_plus, w_plus], axis=1)


def racket_base_fn(racket_params, radius=BALL_RADIUS, mass=BALL_MASS, effects=()) -> Callable:
    """Wraps :func:`ttsim_jax.physics.racket.base_response` as a batched ``base_fn(x)``.

    Arguments:
        racket_params: a ``RacketParams`` pytree.
        radius, mass: the ball's.
        effects: racket-coefficient effects passed through.

    Returns:
        fn(x (N, n_inputs)) -> (N, 6) racket-frame (v+, w+); d = 0 for 6-input x.
    """
    from ttsim_jax.physics.racket import base_response  # the racket stage is optional here

    def single(v, w, d):
        return base_response(racket_params, v, w, d, radius, mass, effects)

    def fn(x):
        x = jnp.asarray(x)
        d = x[:, 6:8] if x.shape[1] >= 8 else jnp.zeros((x.shape[0], 2), x.dtype)
        v_plus, w_plus = jax.vmap(single)(x[:, 0:3], x[:, 3:6], d)
        return jnp.concatenate([v_plus, w_plus], axis=1)

    return fn


def true_residual(x):
    """The synthetic set's known residual (smooth, non-linear in v~, w~ and d).

    Physically flavoured: restitution lost towards the face's edge and a speed-dependent bump
    (normal velocity), spin-induced sideways deflection, extra normal-spin damping, and spin
    components driven by the tangential velocity with a contact-position dependence. Magnitudes
    up to ~1 m/s and ~100 rad/s.

    Arguments:
        x: (N, 8) inputs (v~, w~, d).

    Returns:
        (N, 6) residual (dv, dw) in the racket frame.
    """
    x = jnp.asarray(x)
    v, w = x[:, 0:3], x[:, 3:6]
    dy, dz = x[:, 6] / FACE_RADIUS, x[:, 7] / FACE_RADIUS
    rho2 = dy**2 + dz**2
    vn = -v[:, 0]
    dv = jnp.stack([
        -0.025 * vn * rho2 + 0.3 * jnp.sin(vn / 8.0),
        0.4 * jnp.tanh(w[:, 2] / 400.0) * (1.0 + 0.5 * dy),
        -0.4 * jnp.tanh(w[:, 1] / 400.0) + 0.2 * dz * jnp.tanh(vn / 10.0),
    ], axis=1)
    dw = jnp.stack([
        -0.1 * w[:, 0] * (1.0 - jnp.exp(-vn / 10.0)),
        40.0 * jnp.tanh(v[:, 2] / 8.0) * (1.0 - 0.5 * rho2),
        -40.0 * jnp.tanh(v[:, 1] / 8.0) + 15.0 * jnp.sin(math.pi * dy),
    ], axis=1)
    return jnp.concatenate([dv, dw], axis=1)


def sample_racket_inputs(n: int, seed: int, max_speed=35.0, max_spin=1000.0, face_radius=FACE_RADIUS):
    """Plausible racket-frame pre-contact inputs (N, 8).

    Relative speed uniform in [1, max_speed] m/s, arriving at the face (v~_x < 0) within 75
    degrees of the normal; spin magnitude uniform in [0, max_spin] rad/s, direction uniform on
    the sphere; contact position uniform over a disc of ``face_radius``.

    Arguments:
        n: number of contacts.
        seed: NumPy seed.
        max_speed, max_spin, face_radius: ranges.

    Returns:
        (n, 8) float32 array (v~, w~, d).
    """
    rng = np.random.default_rng(seed)
    speed = rng.uniform(1.0, max_speed, n)
    cos_t = rng.uniform(math.cos(math.radians(75.0)), 1.0, n)
    sin_t = np.sqrt(1.0 - cos_t**2)
    phi = rng.uniform(0.0, 2 * math.pi, n)
    v = speed[:, None] * np.stack([-cos_t, sin_t * np.cos(phi), sin_t * np.sin(phi)], axis=1)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    w = rng.uniform(0.0, max_spin, n)[:, None] * direction
    r = face_radius * np.sqrt(rng.uniform(0.0, 1.0, n))
    ang = rng.uniform(0.0, 2 * math.pi, n)
    d = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
    return np.concatenate([v, w, d], axis=1).astype(np.float32)


def make_synthetic_contacts(n: int, seed: int = 0, base_fn: Callable = standin_base_fn, n_inputs: int = 8,
                            vel_noise: float = 0.05, spin_noise: float = 4.0) -> dict:
    """A synthetic racket-contact set with a known residual and heteroscedastic noise.

    y_obs = base_fn(x) + true_residual(x) + noise, with noise standard deviations
    vel_noise (0.5 + |v~| / 35) per velocity component and spin_noise (0.5 + |w~| / 1000) per
    spin component. The residual depends on d; a 6-input network cannot see d and can only learn
    its d-average.

    Arguments:
        n: number of contacts.
        seed: seed of inputs and noise.
        base_fn: fn(x (N, 8)) -> (N, 6) base prediction (e.g. :func:`standin_base_fn` or
            :func:`racket_base_fn`).
        n_inputs: 8 or 6: columns of ``x`` returned.
        vel_noise, spin_noise: noise scales [m/s], [rad/s].

    Returns:
        dict of float32 numpy arrays: ``x`` (n, n_inputs), ``y_base``, ``y_obs``, ``residual``
        (the noise-free truth) and ``noise_std`` (n, 6).
    """
    if n_inputs not in (6, 8):
        raise ValueError(f"make_synthetic_contacts: n_inputs = {n_inputs!r}, must be 8 or 6")
    x8 = sample_racket_inputs(n, seed)
    y_base = np.asarray(base_fn(x8), np.float32)
    res = np.asarray(true_residual(x8), np.float32)
    rng = np.random.default_rng(seed + 1_000_003)
    speed = np.linalg.norm(x8[:, 0:3], axis=1, keepdims=True)
    spin = np.linalg.norm(x8[:, 3:6], axis=1, keepdims=True)
    std = np.concatenate([np.repeat(vel_noise * (0.5 + speed / 35.0), 3, 1),
                          np.repeat(spin_noise * (0.5 + spin / 1000.0), 3, 1)], axis=1).astype(np.float32)
    y_obs = y_base + res + std * rng.standard_normal((n, 6)).astype(np.float32)
    return dict(x=x8[:, :n_inputs], y_base=y_base, y_obs=y_obs.astype(np.float32), residual=res, noise_std=std)


def recovery_experiment(n_contacts: int = 20000, seed: int = 0, config: ResidualConfig | None = None,
                        tcfg: TrainConfig | None = None, base_fn: Callable = standin_base_fn,
                        progress: bool = True, checkpoint=None, resume: bool = False) -> dict:
    """Trains on a synthetic set with a known residual and reports how much of it is recovered.

    Arguments:
        n_contacts: size of the synthetic set (split 80/10/10).
        seed: seeds the data; also the training seed when ``tcfg`` is None.
        config: architecture (default: the paper's, 8 inputs, 1000 clusters).
        tcfg: training settings (default: :class:`TrainConfig`, the authors' hyper-parameters
            with equal loss weights, population batch-norm statistics and per-component sigma
            calibration).
        base_fn: the base model used to make the data.
        progress: tqdm bar.
        checkpoint, resume: see :func:`train_residual`.

    Returns:
        The report of :func:`train_residual` (test split: error drops, inside-one-sigma fractions
        after calibration) plus ``wall_seconds``, ``n_contacts``, ``seed``, the configurations
        and the noise floor (median error-vector norms of the noise alone on the test split:
        what a perfect residual would leave).
    """
    t0 = time.perf_counter()
    config = config or ResidualConfig()
    tcfg = tcfg or TrainConfig(seed=seed)
    data = make_synthetic_contacts(n_contacts, seed, base_fn=base_fn, n_inputs=config.n_inputs)
    model, report = train_residual(data["x"], data["y_base"], data["y_obs"], config, tcfg,
                                   checkpoint=checkpoint, resume=resume, progress=progress)
    _, _, test_idx = split_by_contact(n_contacts, tcfg.split, tcfg.seed)
    noise = data["y_obs"][test_idx] - data["y_base"][test_idx] - data["residual"][test_idx]
    report.update(
        n_contacts=n_contacts, seed=seed, wall_seconds=time.perf_counter() - t0,
        noise_floor_vel=float(np.median(np.linalg.norm(noise[:, :3], axis=1))),
        noise_floor_spin=float(np.median(np.linalg.norm(noise[:, 3:], axis=1))),
        config=config.to_dict(), train_config=tcfg.to_dict(),
    )
    return report


def main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(prog="python -m ttsim_jax.reality.synthetic_contacts",
                                 description="Synthetic recovery experiment for the racket residual network.")
    ap.add_argument("--config", help="residual TOML (default: the paper's settings)")
    ap.add_argument("--contacts", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--loss-weights", help="six comma-separated weights overriding the config's")
    ap.add_argument("--history", action="store_true", help="include the per-epoch losses")
    args = ap.parse_args(argv)
    config, tcfg = load_train_config(args.config) if args.config else (ResidualConfig(), TrainConfig())
    tcfg = dataclasses.replace(tcfg, seed=args.seed)
    if args.loss_weights:
        tcfg = dataclasses.replace(tcfg, loss_weights=tuple(float(w) for w in args.loss_weights.split(",")))
    rep = recovery_experiment(args.contacts, args.seed, config, tcfg)
    if not args.history:
        rep.pop("history")
    print(json.dumps(rep, indent=2))


if __name__ == "__main__":
    main()
