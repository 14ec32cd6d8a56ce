"""Racket contacts with known states: a small synthetic dataset for tests and end-to-end checks.

:func:`synthetic_contact_dataset` makes flights into known racket states with a known
post-contact law, in the measured-data format: the truth against which the contact estimator
(:mod:`ttsim_jax.data.contact_states`) and the racket residual are checked. The full reality generator
(games, effects, truth files) is :func:`ttsim_jax.reality.generate`.
"""

from __future__ import annotations

import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.data.dataset import Dataset, Metadata
from ttsim_jax.fit.racket_arrays import model_and_name
from ttsim_jax.kernel.ball_step import ball_properties
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.rotations import matrix_to_quat

from .synthetic_stages import draw_contact_states


def _flight(p, v, w, times, kd, km, substeps=20):
    """Positions at ``times`` (n, T) (signed, from the contact) of flights starting at the contact
    state p, v (n, 3) with constant spin w (n, 3): dv/dt = g - kd |v| v + km (w x v), RK4."""
    g = np.array([0.0, 0.0, -9.81])

    def acc(v_):
        return g - kd * np.linalg.norm(v_, axis=1, keepdims=True) * v_ + km * np.cross(w, v_)

    out = np.zeros(times.shape + (3,))
    prev = np.zeros(len(p))
    for k in range(times.shape[1]):
        h = (times[:, k] - prev)[:, None] / substeps
        for _ in range(substeps):
            k1p, k1v = v, acc(v)
            k2p, k2v = v + 0.5 * h * k1v, acc(v + 0.5 * h * k1v)
            k3p, k3v = v + 0.5 * h * k2v, acc(v + 0.5 * h * k2v)
            k4p, k4v = v + h * k3v, acc(v + h * k3v)
            p = p + h / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
            v = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        out[:, k] = p
        prev = times[:, k]
    return out


def _small_rotations(rng, n, max_angle):
    """(n, 3, 3) rotations about uniformly random axes by angles uniform in [0, max_angle] (Rodrigues)."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = rng.uniform(0.0, max_angle, n)
    k = np.zeros((n, 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - np.swapaxes(k, 1, 2)
    s, c = np.sin(ang)[:, None, None], np.cos(ang)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def synthetic_contact_dataset(n: int, seed: int = 0, model="conti2026", residual_fn: Callable | None = None,
                              rate: float = 200.0, span: float = 0.06, noise: float = 0.0, max_speed: float = 15.0,
                              max_spin: float = 600.0, kd: float = 0.11, km: float = 1e-3):
    """A dataset of ``n`` racket contacts with known pre- and post-contact states.

    Each contact is its own session: a flight of ``span`` seconds into a racket (random pose
    facing -x near x = 1.4 m, random linear and angular velocity), one ``racket`` event with the
    racket state, and a flight of ``span`` seconds out. The racket-frame pre-contact state
    (v~, w~, d) is drawn (speed 1..max_speed m/s within 60 degrees of the normal, spin up to
    ``max_spin`` rad/s, d within 7.5 cm), the post-contact state is the model's base response plus
    ``residual_fn(x8)`` (none by default), and both are turned into the world frame with the
    model's racket frame convention. Flights: gravity, drag ``kd`` |v| v and Magnus ``km`` w x v,
    sampled at ``rate`` Hz (the sampling phase is random per contact), optional Gaussian position
    noise ``noise`` [m]. Spin is given to every sample with confidence 1.

    Arguments:
        n: number of contacts.
        seed: NumPy seed.
        model: the model name / path / :class:`~ttsim_jax.params.Model` (racket parameters).
        residual_fn: fn(x (N, 8)) -> (N, 6) racket-frame residual added to the base response, or
            None.
        rate, span, noise, max_speed, max_spin, kd, km: see above.

    Returns:
        (dataset, truth) with ``truth`` a dict of float64 arrays: ``x`` (n, 8), ``y_base``,
        ``y_obs`` (n, 6) in the racket frame, ``distance`` (n,), ``event_id`` (n,), and the
        world-frame ``vel_in``, ``spin_in``, ``vel_out``, ``spin_out`` (n, 3).
    """
    m, name = model_and_name(model)
    radius, mass = (float(v) for v in ball_properties(m))
    rng = np.random.default_rng(seed)
    base_rot = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])  # normal along -x
    rot = _small_rotations(rng, n, math.radians(30.0)) @ base_rot
    # heights spread over 0.8 m: the validator reads z reversals clustered at one height as a
    # misplaced table surface
    r_pos = np.stack([rng.uniform(1.3, 1.5, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0.1, 0.9, n)], 1)
    r_vel = np.stack([rng.uniform(-6.0, 0.0, n), rng.uniform(-1.0, 1.0, n), rng.uniform(0.0, 3.0, n)], 1)
    r_ang = rng.uniform(-10.0, 10.0, (n, 3))
    v_t, w_t, d = draw_contact_states(rng, n, max_speed, max_spin)

    # ball centre at the contact: one radius in front of the face at d
    local = np.concatenate([np.full((n, 1), radius), d], 1)
    p_c = r_pos + np.einsum("nij,nj->ni", rot, local)
    offset = p_c - radius * rot[:, :, 0] - r_pos
    w_surf = r_ang if racket_stage.uses_racket_spin(m.racket) else np.zeros_like(r_ang)
    v_surf = r_vel + np.cross(w_surf, offset)
    vel_in = np.einsum("nij,nj->ni", rot, v_t) + v_surf
    spin_in = np.einsum("nij,nj->ni", rot, w_t) + w_surf

    x8 = np.concatenate([v_t, w_t, d], 1)

    def base(v, w, dd):
        return racket_stage.base_response(m.racket, v, w, dd, radius, mass)

    vb, wb = jax.vmap(base)(jnp.asarray(v_t), jnp.asarray(w_t), jnp.asarray(d))
    y_base = np.concatenate([np.asarray(vb), np.asarray(wb)], 1).astype(np.float64)
    y_obs = y_base + (0.0 if residual_fn is None else np.asarray(residual_fn(x8), np.float64))
    vel_out = np.einsum("nij,nj->ni", rot, y_obs[:, :3]) + v_surf
    spin_out = np.einsum("nij,nj->ni", rot, y_obs[:, 3:]) + w_surf

    k = int(math.floor(span * rate))
    phase = rng.uniform(0.05, 0.95, (n, 2)) / rate
    steps = np.arange(k) / rate
    t_in = -(phase[:, :1] + steps[None, :])  # (n, k), descending from the contact
    t_out = phase[:, 1:] + steps[None, :]
    p_in = _flight(p_c, vel_in, spin_in, t_in, kd, km)[:, ::-1]
    p_out = _flight(p_c, vel_out, spin_out, t_out, kd, km)
    t_in = t_in[:, ::-1]
    # Gravity is uniform, so lifting a whole contact changes nothing but keeps steep flights above
    # the floor (validation refuses balls below it).
    lift = np.maximum(-0.5 - np.minimum(p_in[..., 2].min(1), p_out[..., 2].min(1)), 0.0)
    for a in (p_in, p_out):
        a[..., 2] += lift[:, None]
    p_c[:, 2] += lift
    r_pos[:, 2] += lift
    t_c = 1.0
    times = np.concatenate([t_in, t_out], 1) + t_c
    pos = np.concatenate([p_in, p_out], 1)
    if noise:
        pos = pos + rng.normal(0.0, noise, pos.shape)
    spins = np.concatenate([np.repeat(spin_in[:, None], k, 1), np.repeat(spin_out[:, None], k, 1)], 1)
    ds = Dataset.from_arrays(
        np.repeat(np.arange(n), 2 * k), times.reshape(-1), pos.reshape(-1, 3), spin=spins.reshape(-1, 3),
        events=dict(session_id=np.arange(n), t=np.full(n, t_c), kind=np.full(n, "racket", object), pos=p_c),
        rackets=dict(pos=r_pos, quat=matrix_to_quat(rot), vel=r_vel, ang_vel=r_ang, contact=d),
        metadata=Metadata(source=f"ttsim_jax.reality.synthetic_contact_dataset(n={n}, seed={seed}, "
                                 f"model={name!r})", notes="synthetic racket contacts with known states"),
    )
    truth = dict(x=x8, y_base=y_base, y_obs=y_obs, distance=np.linalg.norm(d, axis=1), event_id=np.arange(n),
                 vel_in=vel_in, spin_in=spin_in, vel_out=vel_out, spin_out=spin_out)
    return ds, truth


def synthetic_rig_dataset(laws: dict, n: int, seed: int = 0, model="conti2026", max_speed: float = 10.0,
                          max_spin: float = 400.0) -> Dataset:
    """A racket-bounce rig's dataset (as ``ttsim data import --source tt_rackets`` writes one): per
    racket configuration, ``n`` bounces on a racket at rest with their states measured directly
    (the ``contact_states`` table), through a known law.

    Arguments:
        laws: configuration name -> its racket parameters (:class:`~ttsim_jax.physics.racket.RacketParams`)
            or the updated base model's (e0, e1, et0, et1, e_s) over ``model``'s racket.
        n: bounces per configuration; seed: seeds the incoming states (one stream per configuration).
        model: its ball's radius and mass, and the base of a law given as five numbers.
        max_speed, max_spin: the incoming states' bounds (:func:`~ttsim_jax.reality.synthetic_stages.draw_contact_states`).

    Returns:
        The dataset (racket face centre at the tt_rackets importer's position, normal along world z,
        contact at the face centre; ``rackets.config`` the law's name).
    """
    from ttsim_jax.data.importers.tt_rackets import RACKET_POSITION, RACKET_QUAT
    from ttsim_jax.fit.racket import updated_params

    m, _ = model_and_name(model)
    radius, mass = ball_properties(m)
    ids, states, names = [], [], []
    for k, (name, law) in enumerate(laws.items()):
        params = law if isinstance(law, racket_stage.RacketParams) else updated_params(m.racket, law)
        v, w, _ = draw_contact_states(np.random.default_rng(seed + k), n, max_speed, max_spin)
        d = jnp.zeros((n, 2))
        vp, wp = jax.vmap(lambda vi, wi, di: racket_stage.base_response(params, vi, wi, di, radius, mass))(
            jnp.asarray(v), jnp.asarray(w), d)
        frame = np.stack([v, w, np.asarray(vp, np.float64), np.asarray(wp, np.float64)], 1)  # (n, 4, 3) racket frame
        states.append(frame[:, :, [1, 2, 0]])  # racket (x~ normal, y~, z~) -> world (y~, z~, x~) at this pose
        ids.append((k + 1) * 10000 + np.arange(n))
        names += [name] * n
    ids, s = np.concatenate(ids), np.concatenate(states)
    total = len(ids)
    face = np.tile(RACKET_POSITION, (total, 1))
    return Dataset.from_arrays(
        np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)),
        events=dict(event_id=ids, session_id=0, t=np.arange(total, dtype=float), kind="racket",
                    pos=face + [0.0, 0.0, float(radius)]),
        rackets=dict(event_id=ids, pos=face, quat=np.tile(RACKET_QUAT, (total, 1)), vel=np.zeros((total, 3)),
                     ang_vel=np.zeros((total, 3)), contact=np.zeros((total, 2)), config=np.array(names, object)),
        segments=None, metadata=Metadata(source="ttsim_jax.reality.synthetic_rig_dataset"),
        contact_states=dict(event_id=ids, v_in=s[:, 0], w_in=s[:, 1], v_out=s[:, 2], w_out=s[:, 3]))
