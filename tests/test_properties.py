"""Property-based sweep over initial states and racket poses (hypothesis).

Each example is a whole batch of balls run through one compiled simulation of fixed shape per
dtype (the step dt is traced, so drawing it does not recompile). Properties, for finite inputs:
no NaN or inf anywhere; no ball that started clear of the table and the rackets ends a step inside
the table or passes through a racket face (the racket's rim is not modelled: the check is on the
inner half of the face); no contact with the table or a resting racket creates kinetic energy.
Shrinking is off (a 64-ball example shrinks for minutes); a failure prints the whole batch.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from ttsim_jax import Ball, Racket, load_model, simulate
from ttsim_jax.physics import table as tbl
from ttsim_jax.physics.events import INVALID, RACKET, TABLE

B, STEPS = 64, 120
R = 0.02
MODELS = {np.float32: load_model("conti2026", dtype=jnp.float32), np.float64: load_model("conti2026", dtype=jnp.float64)}
TOL = {np.float32: 1e-5, np.float64: 1e-10}  # relative energy rounding


# Each ball is 19 draws of 16-bit integers mapped linearly onto ranges: a batch of floats would
# exceed hypothesis's example size, integers keep it small (and still shrink towards the low ends).
N_DRAWS = 19
LEVELS = 65535


def lin(k, lo, hi):
    return lo + (hi - lo) * np.asarray(k, float) / LEVELS


def unit(k):
    v = lin(k, -1.0, 1.0)
    return v / max(np.linalg.norm(v), 1e-3)


def decode(d):
    """(position, velocity, spin, racket centre, racket quaternion) of one ball's draws."""
    pos = np.array([lin(d[0], -1.8, 1.8), lin(d[1], -1.1, 1.1), lin(d[2], -0.15, 0.6)])
    if d[3] % 4 == 0:
        pos[2] = R  # on the table (or level with it beyond its edges)
    vel = unit(d[4:7]) * lin(d[7], 0.0, 40.0)
    spin = unit(d[8:11]) * lin(d[11], 0.0, 1200.0)
    racket = np.array([lin(d[12], -2.0, 2.0), lin(d[13], -1.2, 1.2), lin(d[14], -0.1, 0.6)])
    quat = np.array([lin(d[15], 0.05, 1.0), *lin(d[16:19], -1.0, 1.0)])
    return pos, vel, spin, racket, quat


ball = st.tuples(*[st.integers(0, LEVELS)] * N_DRAWS)


def rotation(q):
    w, x, y, z = np.asarray(q) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def build(examples, dtype):
    pos, vel, spin, centre, quat = (np.array(x) for x in zip(*map(decode, examples)))
    racket = Racket.create(centre, rot=np.stack([rotation(q) for q in quat]), dtype=dtype)
    sched = jax.tree.map(lambda a: jnp.broadcast_to(a[:, None, None], (B, STEPS, 1) + a.shape[1:]), racket)
    return Ball.create(pos, vel, spin, dtype=dtype), racket, sched


def through_face(racket, path):
    """Whether the centre crosses a racket's face plane between recorded points, within the
    inner half of the face outline (a ball reaching the face there has met the face, not its rim,
    which is not modelled)."""
    rot, centre, face = np.asarray(racket.rot), np.asarray(racket.pos), np.asarray(racket.face)
    local = np.einsum("bji,bkj->bki", rot, path - centre[:, None])
    h0, h1 = local[:, :-1, 0], local[:, 1:, 0]
    cross = h0 * h1 < 0.0
    s = np.where(cross, h0 / np.where(cross, h0 - h1, 1.0), 0.0)[..., None]
    at = local[:, :-1] + s * (local[:, 1:] - local[:, :-1])
    inner = np.sum((at[..., 1:3] / (0.5 * face[:, None])) ** 2, -1) <= 1.0
    return np.any(cross & inner, axis=1)


def table_gap(model, pos):
    flat = jnp.asarray(pos.reshape(-1, 3))
    g = jax.vmap(lambda p: tbl.gap(model.table, (), model.ball.radius, p))(flat)
    return np.asarray(g).reshape(pos.shape[:-1])


@pytest.mark.parametrize("dtype", [np.float32, np.float64], ids=["f32", "f64"])
@settings(max_examples=10, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example])
@given(examples=st.lists(ball, min_size=B, max_size=B), dt=st.sampled_from([0.5e-3, 1e-3, 2e-3]))
def test_no_nan_no_penetration_no_energy_created(dtype, examples, dt):
    model = MODELS[dtype]
    balls, racket, sched = build(examples, dtype)
    r = simulate(model, balls, STEPS, dt, racket=sched, record_every=1, max_events=16)
    for leaf in jax.tree.leaves((r.final, r.trajectory, r.events.pre, r.events.post, r.events.time)):
        assert np.all(np.isfinite(np.asarray(leaf)))

    start = np.asarray(balls.pos)
    local = np.einsum("bji,bj->bi", np.asarray(racket.rot), start - np.asarray(racket.pos))
    off_racket = (np.abs(local[:, 0]) >= R) | (np.sum((local[:, 1:3] / np.asarray(racket.face)) ** 2, -1) > 1.0)
    clear = (table_gap(model, start) >= 0.0) & off_racket
    status = np.asarray(r.status)
    assert not np.any(clear & (status == INVALID))
    traj = np.asarray(r.trajectory.pos)
    gaps = table_gap(model, traj)[clear]
    assert gaps.min(initial=0.0) > -1e-3, "a ball ended a step inside the table"
    path = np.concatenate([start[:, None], traj], axis=1)
    assert not np.any(through_face(racket, path) & clear), "a ball passed through a racket face"

    kind = np.asarray(r.events.kind)
    used = np.arange(kind.shape[1])[None] < np.minimum(np.asarray(r.events.count), kind.shape[1])[:, None]
    for k, kappa in ((TABLE, model.table.kappa), (RACKET, model.racket.kappa)):
        sel = used & (kind == k)
        e_pre = np.asarray(tbl.kinetic_energy(kappa, R, r.events.pre.vel, r.events.pre.spin))[sel]
        e_post = np.asarray(tbl.kinetic_energy(kappa, R, r.events.post.vel, r.events.post.spin))[sel]
        assert np.all(e_post <= e_pre * (1.0 + TOL[dtype]) + TOL[dtype]), k
