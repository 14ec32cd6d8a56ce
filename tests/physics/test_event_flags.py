"""The kernel's cheap per-step tests against the exact detection they stand in for."""

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import load_model
from ttsim_jax.kernel.ball_step import is_valid
from ttsim_jax.physics import events as ev


def _crossings(n, dt, seed=0):
    """n steps of length dt whose centre crosses the net plane, at heights from below the table to
    30 cm above the net and across its whole width and beyond."""
    rng = np.random.default_rng(seed)
    vel = np.stack([rng.uniform(2.0, 15.0, n) * rng.choice([-1.0, 1.0], n), rng.uniform(-3, 3, n),
                    rng.uniform(-6, 6, n)], -1)
    mid = np.stack([np.zeros(n), rng.uniform(-1.2, 1.2, n), rng.uniform(-0.05, 0.45, n)], -1)
    frac = rng.uniform(0.0, 1.0, n)
    p0 = mid - frac[:, None] * vel * dt
    # the end bends away from the chord: the Hermite path between them bows
    v1 = vel + rng.uniform(-40, 40, (n, 3)) * dt
    p1 = p0 + 0.5 * (vel + v1) * dt
    return p0, vel, p1, v1


def test_net_flag_is_a_superset_of_net_touches_and_skips_high_crossings():
    table = load_model("conti2026").table
    radius = 0.02
    for dt in (1e-3, 2e-2):
        p0, v0, p1, v1 = (jnp.asarray(a) for a in _crossings(20000, dt))
        hit = jax.vmap(lambda a, b, c, d: ev.net_candidate(table, radius, a, b, c, d, dt).hit)(p0, v0, p1, v1)
        flag = jax.vmap(lambda a, b, c, d: ev.net_may_hit(table, radius, a, b, c, d, dt))(p0, v0, p1, v1)
        hit, flag = np.asarray(hit), np.asarray(flag)
        assert hit.sum() > 1000 and (~flag).sum() > 1000  # both kinds are drawn
        assert not np.any(hit & ~flag)  # no touch goes unflagged
        high = np.minimum(np.asarray(p0)[:, 2], np.asarray(p1)[:, 2]) > float(table.net_height) + radius + 0.05
        assert not np.any(flag & high)


def test_is_valid_flags_non_finite_and_insane_states():
    from ttsim_jax import Ball

    ok = Ball.create(jnp.array([0.1, 0.2, 0.3]), jnp.array([5.0, 0.0, 1.0]), jnp.array([0.0, 100.0, 0.0]))
    assert bool(is_valid(ok))
    for field, index, value in [("pos", 0, np.nan), ("vel", 2, np.inf), ("spin", 1, -np.inf), ("vel", 0, 250.0),
                                ("spin", 2, 3.0e4), ("pos", 1, -150.0)]:
        bad = ok.replace(**{field: getattr(ok, field).at[index].set(value)})
        assert not bool(is_valid(bad)), (field, index, value)
