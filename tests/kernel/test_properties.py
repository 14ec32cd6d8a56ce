"""Property-based sweep over initial states and racket poses (hypothesis).

Each example is a whole batch of balls run through one compiled simulation of fixed shape per
dtype (the step dt is traced, so drawing it does not recompile). Properties, for finite inputs:
no NaN or inf anywhere; no ball that started clear of the table and the rackets ends a step inside
the table or a racket face, or passes through a racket face inside its outline (resting rackets,
and rackets moving and rotating about their handle); every low crossing of the net plane is logged;
no contact with the table or a resting racket creates kinetic energy.
Shrinking is off (a 64-ball example shrinks for minutes); a failure prints the whole batch.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from ttsim_jax import Ball, Racket, Record, load_model, simulate
from ttsim_jax.physics import table as tbl
from ttsim_jax.physics.events import INVALID, NET, RACKET, TABLE

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


def face_local(rot, centre, path):
    """(B, N, 3) recorded centres ``path`` (B, N, 3) in the racket frame of the racket's pose at each
    point (``rot`` (B, N, 3, 3), ``centre`` (B, N, 3))."""
    return np.einsum("bkji,bkj->bki", rot, path - centre)


def through_face(local, face):
    """(B, N - 1) whether the centre crosses the face plane between recorded points inside the face
    outline (semi-axes ``face`` (B, 2)), the crossing point interpolated linearly in the racket frame."""
    h0, h1 = local[:, :-1, 0], local[:, 1:, 0]
    cross = h0 * h1 < 0.0
    s = np.where(cross, h0 / np.where(cross, h0 - h1, 1.0), 0.0)[..., None]
    at = local[:, :-1] + s * (local[:, 1:] - local[:, :-1])
    return cross & (np.sum((at[..., 1:3] / face[:, None]) ** 2, -1) <= 1.0)


def in_face(local, face):
    """(B, N) whether the ball overlaps the face by more than half its radius inside the outline."""
    return (np.abs(local[..., 0]) < 0.5 * R) & (np.sum((local[..., 1:3] / face[:, None]) ** 2, -1) <= 1.0)


def clear_of_face(local, face):
    """(B,) whether a ball is clear of the face and its rim (farther than a radius from the plane, or
    outside the outline widened by a radius and 5 %)."""
    return (np.abs(local[..., 0]) >= R) | (np.sum((local[..., 1:3] / (face + 1.05 * R)) ** 2, -1) > 1.0)


def table_gap(model, pos):
    flat = jnp.asarray(pos.reshape(-1, 3))
    g = jax.vmap(lambda p: tbl.gap(model.table, (), model.ball.radius, p))(flat)
    return np.asarray(g).reshape(pos.shape[:-1])


# float32 by default (the simulator's usual type); float64 with -m slow
@pytest.mark.parametrize("dtype", [np.float32, pytest.param(np.float64, marks=pytest.mark.slow)], ids=["f32", "f64"])
@settings(max_examples=10, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example])
@given(examples=st.lists(ball, min_size=B, max_size=B), dt=st.sampled_from([0.5e-3, 1e-3, 2e-3]))
def test_no_nan_no_penetration_no_energy_created(dtype, examples, dt):
    model = MODELS[dtype]
    balls, racket, sched = build(examples, dtype)
    r = simulate(model, balls, STEPS, dt, racket=sched,
                     record=Record(every=1, max_events=16))
    for leaf in jax.tree.leaves((r.final, r.trajectory, r.events.pre, r.events.post, r.events.time)):
        assert np.all(np.isfinite(np.asarray(leaf)))

    start = np.asarray(balls.pos)
    traj = np.asarray(r.trajectory.pos)
    path = np.concatenate([start[:, None], traj], axis=1)
    poses = [np.broadcast_to(np.asarray(a)[:, None], (B, STEPS + 1) + a.shape[1:]) for a in (racket.rot, racket.pos)]
    local = face_local(*poses, path)
    face = np.asarray(racket.face)
    clear = (table_gap(model, start) >= 0.0) & clear_of_face(local[:, 0], face)
    status = np.asarray(r.status)
    assert not np.any(clear & (status == INVALID))
    gaps = table_gap(model, traj)[clear]
    assert gaps.min(initial=0.0) > -1e-3, "a ball ended a step inside the table"
    assert not np.any(np.any(through_face(local, face), 1) & clear), "a ball passed through a racket face"
    assert not np.any(np.any(in_face(local, face), 1) & clear), "a ball ended a step inside a racket face"

    kind = np.asarray(r.events.kind)
    used = np.arange(kind.shape[1])[None] < np.minimum(np.asarray(r.events.count), kind.shape[1])[:, None]
    for k, kappa in ((TABLE, model.table.kappa), (RACKET, model.racket.kappa)):
        sel = used & (kind == k)
        e_pre = np.asarray(tbl.kinetic_energy(kappa, R, r.events.pre.vel, r.events.pre.spin))[sel]
        e_post = np.asarray(tbl.kinetic_energy(kappa, R, r.events.post.vel, r.events.post.spin))[sel]
        assert np.all(e_post <= e_pre * (1.0 + TOL[dtype]) + TOL[dtype]), k


# --------------------------------------------------------------------------- net-cord balls
# Balls that cross the net plane low and land on the table within a step and a half of the
# crossing (before or after it): the two events share a step about half the time. Each batch
# runs the compiled shape above (its racket is parked out of reach).
NET_CORD_BATCHES = 4
PARKED = np.array([6.0, 4.0, 6.0])


def net_cord_balls(seed, dt):
    """(ball, racket, schedule) of B balls that cross x = 0 low and land near the net.

    The ballistic path through the crossing (0, y, z_c) reaches the table top (centre one radius
    above it) delta after it, |delta| < 1.5 dt; the ball starts a few steps (and at least 3 cm)
    before the crossing.
    """
    rng = np.random.default_rng(seed)
    g = 9.81
    vx = rng.choice([-1.0, 1.0], B) * rng.uniform(2.0, 25.0, B)
    vel_c = np.stack([vx, rng.uniform(-2.0, 2.0, B), -rng.uniform(0.3, 6.0, B)], -1)
    delta = rng.uniform(-1.5, 1.5, B) * dt
    z_c = R - vel_c[:, 2] * delta + 0.5 * g * delta**2
    cross = np.stack([np.zeros(B), rng.uniform(-0.6, 0.6, B), z_c], -1)
    back = np.maximum(3 * dt, 0.03 / np.abs(vx)) + rng.uniform(0.0, 1.0, B) * dt
    grav = np.array([0.0, 0.0, -g])
    pos = cross - vel_c * back[:, None] + 0.5 * grav * back[:, None] ** 2
    vel = vel_c - grav * back[:, None]
    spin = np.stack([unit(rng.integers(0, LEVELS, 3)) for _ in range(B)]) * rng.uniform(0.0, 600.0, (B, 1))
    racket = Racket.create(np.broadcast_to(PARKED, (B, 3)), dtype=None)
    return pos, vel, spin, racket


def crossings_logged(model, start, traj, times, kind, etime, used):
    """(crossings, logged): per ball, the steps in which the centre crosses x = 0 where the ball can
    touch the net (clear of the net's outline by 1 mm, crossing point interpolated linearly), and
    how many of them have a NET event logged in that step."""
    t = model.table
    path = np.concatenate([start[:, None], traj], axis=1)
    t_path = np.concatenate([[0.0], times])
    x0, x1 = path[:, :-1, 0], path[:, 1:, 0]
    cross = (x0 * x1 < 0.0) | ((x1 == 0.0) & (x0 != 0.0))
    s = np.where(cross, x0 / np.where(cross, x0 - x1, 1.0), 0.0)[..., None]
    at = path[:, :-1] + s * (path[:, 1:] - path[:, :-1])
    r, m = float(model.ball.radius), 1e-3
    low = (at[..., 2] < float(t.net_height) + r - m) & (at[..., 2] > -r + m)
    inside = np.abs(at[..., 1]) < 0.5 * float(t.width) + float(t.net_overhang) + r - m
    cross &= low & inside
    net = used & (kind == NET)
    lo, hi = t_path[:-1] - 1e-9, t_path[1:] + 1e-9  # (N,) step windows
    in_step = (etime[:, None, :] > lo[None, :, None]) & (etime[:, None, :] <= hi[None, :, None])
    logged = np.any(in_step & net[:, None, :], axis=-1)
    return cross, cross & logged


@pytest.mark.parametrize("dtype", [np.float32, np.float64], ids=["f32", "f64"])
def test_net_cord_balls_bounce_on_time_and_every_crossing_is_logged(dtype):
    """Net-cord balls (net crossing and table contact in the same step or a step apart, either
    order): no ball ends a step inside the table, every table contact is applied where the ball
    touches the table (not at the end of its step), every low crossing of the net plane is logged
    as a NET event, once."""
    model = MODELS[dtype]
    n_cross = 0
    for seed in range(NET_CORD_BATCHES):
        dt = (0.5e-3, 1e-3, 2e-3)[seed % 3]
        pos, vel, spin, racket = net_cord_balls(seed, dt)
        racket = jax.tree.map(lambda a: jnp.asarray(a, dtype), racket)
        sched = jax.tree.map(lambda a: jnp.broadcast_to(a[:, None, None], (B, STEPS, 1) + a.shape[1:]), racket)
        balls = Ball.create(pos, vel, spin, dtype=dtype)
        r = simulate(model, balls, STEPS, dt, racket=sched,
                     record=Record(every=1, max_events=16))
        status = np.asarray(r.status)
        assert not np.any(status == INVALID), seed
        traj = np.asarray(r.trajectory.pos, np.float64)
        gaps = table_gap(MODELS[np.float64], traj)
        assert gaps.min() > -tbl.CONTACT_SLOP, f"a ball ended a step {-gaps.min() * 1e3:.2f} mm inside the table"
        kind, count = np.asarray(r.events.kind), np.asarray(r.events.count)
        assert np.all(count <= kind.shape[1])
        used = np.arange(kind.shape[1])[None] < count[:, None]
        table = used & (kind == TABLE)
        assert np.all(np.any(table, axis=1)), "a net-cord ball never touched the table"
        pre_gap = table_gap(MODELS[np.float64], np.asarray(r.events.pre.pos, np.float64))[table]
        assert np.abs(pre_gap).max() < tbl.CONTACT_SLOP, f"a table contact applied {-pre_gap.min() * 1e3:.2f} mm deep"
        cross, logged = crossings_logged(model, np.asarray(pos), traj, np.asarray(r.times), kind,
                                         np.asarray(r.events.time), used)
        assert np.all(cross.sum(1) >= 1)
        assert np.array_equal(cross, logged), f"{int(cross.sum() - logged.sum())} net crossings not logged"
        assert np.array_equal(np.sum(used & (kind == NET), 1), cross.sum(1)), "a net crossing logged twice"
        n_cross += int(cross.sum())
    assert n_cross >= B * NET_CORD_BATCHES


# --------------------------------------------------------------------------- rotating rackets
# Each ball has its own racket, its face centre moving at 8 m/s in a random direction and the face
# turning at 30 rad/s about the handle (the racket z-axis through the face centre), so that its rim
# sweeps at up to 8 + 2.3 m/s; the ball, mostly slow, is put where the face's rim band (within a
# radius of the rim) or the face will be a few steps later.
ROTATING_BATCHES = 4
FACE_SPEED, HANDLE_SPIN = 8.0, 30.0


def rotating_rackets(seed, dt):
    """(pos, vel, spin) of B balls and the (B, STEPS + 1) poses of their rackets (Racket fields)."""
    rng = np.random.default_rng(seed)
    g = np.array([0.0, 0.0, -9.81])
    rot = np.stack([rotation(q) for q in rng.normal(size=(B, 4))])
    v_r = np.stack([unit(k) for k in rng.integers(0, LEVELS, (B, 3))]) * FACE_SPEED
    w_r = rng.choice([-1.0, 1.0], (B, 1)) * HANDLE_SPIN * rot[:, :, 2]
    face = np.broadcast_to(np.array([0.0775, 0.0755]), (B, 2))
    t_meet = rng.uniform(4.0, 12.0, B) * dt
    centre = np.stack([rng.uniform(1.8, 2.2, B), rng.uniform(-0.5, 0.5, B), rng.uniform(0.35, 0.8, B)], -1)
    # where the ball is at t_meet, in the racket frame: across the rim band or on the face
    rho, phi = rng.uniform(0.5, 1.0, B) + np.where(rng.random(B) < 0.75, R / 0.0765 * rng.uniform(0.0, 1.2, B), 0.0), \
        rng.uniform(0.0, 2 * np.pi, B)
    meet = np.stack([rng.uniform(-1.5, 1.5, B) * R, rho * face[:, 0] * np.cos(phi), rho * face[:, 1] * np.sin(phi)], -1)
    speed = np.where(np.arange(B) % 4 == 0, rng.uniform(3.0, 30.0, B), rng.uniform(0.0, 3.0, B))
    vel_m = np.stack([unit(k) for k in rng.integers(0, LEVELS, (B, 3))]) * speed[:, None]
    t = np.arange(STEPS + 1)[None, :] * dt - t_meet[:, None]  # (B, STEPS + 1) time from the meeting
    turn = np.stack([np.stack([rotation_vector_matrix(w * s) for s in ts]) for w, ts in zip(w_r, t)])
    rots = turn @ rot[:, None]
    centres = centre[:, None] + t[..., None] * v_r[:, None]
    p_meet = centre + np.einsum("bij,bj->bi", rot, meet)
    pos = p_meet - vel_m * t_meet[:, None] + 0.5 * g * t_meet[:, None] ** 2
    vel = vel_m - g * t_meet[:, None]
    spin = np.stack([unit(k) for k in rng.integers(0, LEVELS, (B, 3))]) * rng.uniform(0.0, 300.0, (B, 1))
    poses = dict(pos=centres, rot=rots, vel=np.broadcast_to(v_r[:, None], centres.shape),
                 ang_vel=np.broadcast_to(w_r[:, None], centres.shape), face=np.broadcast_to(face[:, None], (B, STEPS + 1, 2)))
    return pos, vel, spin, poses


def rotation_vector_matrix(v):
    """Rotation matrix of a rotation vector (Rodrigues, numpy)."""
    th = np.linalg.norm(v)
    if th < 1e-12:
        return np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]) / th
    return np.eye(3) + np.sin(th) * k + (1.0 - np.cos(th)) * (k @ k)


@pytest.mark.parametrize("dtype", [np.float32, np.float64], ids=["f32", "f64"])
def test_rotating_racket_rim_never_sweeps_through_a_ball(dtype):
    """Rackets moving at 8 m/s and turning at 30 rad/s about the handle, balls (mostly slow) where
    the face's rim will be: no ball that started clear of the face passes through it inside its
    outline or ends a step inside it, and rim contacts happen (the balls meet the rim band)."""
    model = MODELS[dtype]
    hits = 0
    for seed in range(ROTATING_BATCHES):
        dt = (1e-3, 2e-3, 0.5e-3)[seed % 3]
        pos, vel, spin, poses = rotating_rackets(100 + seed, dt)
        sched = Racket(**{k: jnp.asarray(v[:, :STEPS, None], dtype) for k, v in poses.items()})
        r = simulate(model, Ball.create(pos, vel, spin, dtype=dtype), STEPS, dt, racket=sched,
                     record=Record(every=1, max_events=16))
        path = np.concatenate([pos[:, None], np.asarray(r.trajectory.pos, np.float64)], axis=1)
        local = face_local(poses["rot"], poses["pos"], path)
        face = poses["face"][:, 0]
        clear = clear_of_face(local[:, 0], face)
        assert np.all(np.isfinite(path))
        assert not np.any(clear & (np.asarray(r.status) == INVALID))
        crossed = np.any(through_face(local, face), 1) & clear
        assert not np.any(crossed), f"{int(crossed.sum())} balls passed through a racket face"
        inside = np.any(in_face(local, face), 1) & clear
        assert not np.any(inside), f"{int(inside.sum())} balls ended a step inside a racket face"
        kind = np.asarray(r.events.kind)
        hits += int(np.sum(np.any((kind == RACKET) & (np.arange(kind.shape[1]) < np.asarray(r.events.count)[:, None]), 1)))
    assert hits > ROTATING_BATCHES * B // 3
