import jax.numpy as jnp
import numpy as np

from ttsim_jax import Ball, load_model
from ttsim_jax.physics.events import TABLE
from ttsim_jax.shots import SHOT_TYPES, aim, refine_aim, sample_shots

import padding as shared
from padding import simulate_shared


def test_sampler_is_seeded_and_within_the_papers_ranges():
    a, la = sample_shots(500, seed=3)
    b, lb = sample_shots(500, seed=3)
    c, _ = sample_shots(500, seed=4)
    np.testing.assert_array_equal(a.vel, b.vel)
    assert (la == lb).all() and not np.allclose(a.vel, c.vel)
    assert set(la) == set(SHOT_TYPES)
    speed = np.linalg.norm(a.vel, axis=-1)
    spin = np.linalg.norm(a.spin, axis=-1)
    assert speed.max() < 40.0 and spin.max() <= 1000.0 * np.sqrt(2)
    assert speed[la == "smash"].min() > 19.0 and speed[la == "push"].max() < 10.0
    # topspin for a ball moving along +x is +y spin; backspin -y
    assert np.all(a.spin[la == "topspin_drive", 1] > 0) and np.all(a.spin[la == "push", 1] < 0)


def test_aim_through_the_model_lands_on_target():
    model = load_model("conti2026", dtype=jnp.float32)
    rng = np.random.default_rng(0)
    n = 64
    start = np.stack([rng.uniform(-2.2, -1.5, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.2, 0.5, n)], -1)
    target = np.stack([rng.uniform(0.4, 1.2, n), rng.uniform(-0.6, 0.6, n), np.full(n, 0.02)], -1)
    speed, top = rng.uniform(8, 18, n), rng.uniform(0, 600, n)
    vel = aim(start, target, speed, top)
    heading = vel[:, :2] / np.linalg.norm(vel[:, :2], axis=-1, keepdims=True)
    spin = top[:, None] * np.stack([-heading[:, 1], heading[:, 0], np.zeros(n)], -1)
    balls = Ball(start.astype(np.float32), vel.astype(np.float32), spin.astype(np.float32))

    def miss(b):
        first, ok = [], []
        for i in range(0, n, shared.B):  # the suite's shared shape, B balls at a time
            r = simulate_shared(model, Ball(*(jnp.asarray(x[i:i + shared.B]) for x in (b.pos, b.vel, b.spin))))
            first.append(np.asarray(r.events.pre.pos[:, 0, :2]))
            ok.append(np.asarray(r.events.kind[:, 0]) == TABLE)
        first, ok = np.concatenate(first), np.concatenate(ok)
        return np.where(ok, np.linalg.norm(first - target[:, :2], axis=-1), np.inf)

    before, after = miss(balls), miss(refine_aim(model, balls, target[:, :2]))
    assert np.median(after) < 0.03  # within 3 cm of the target
    assert np.median(after) < 0.2 * np.median(before)
