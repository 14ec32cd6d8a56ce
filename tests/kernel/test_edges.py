"""Physics at its edges: sustained contact (rolling, sliding, rest), the table's edges, ends and
corners, balls starting inside an obstacle, and the bounds on the table residual matrices."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, load_model
from ttsim_jax.physics import table as tbl
from ttsim_jax.physics.events import FLOOR, INVALID, REST, TABLE

from padding import AWAY, resting_racket, simulate_shared

R = 0.02
L2, W2 = 1.37, 0.7625  # half length and half width of the table
MODEL = load_model("conti2026")


def still_air(m):
    """The model without air (no drag, lift or buoyancy): contact closed forms hold exactly."""
    return m.replace(aero=m.aero.replace(rho_air=jnp.zeros_like(m.aero.rho_air)))


def weightless(m):
    """Without air and gravity: the ball flies straight, contact points are closed forms."""
    m = still_air(m)
    return m.replace(aero=m.aero.replace(gravity=jnp.zeros_like(m.aero.gravity)))


def run(m, b, dt=1e-3, racket_pos=AWAY):
    """The suite's shared rollout (every simulation here: one compilation per dtype) with a
    resting racket at ``racket_pos``."""
    return simulate_shared(m, b, dt, resting_racket(racket_pos))


def kinds(r, i=0):
    return np.asarray(r.events.kind[i, : int(r.events.count[i])]).tolist()


# --------------------------------------------------------------------------- sustained contact
def test_rolling_ball_rolls_off_the_end_alike_at_every_dt():
    # rolling (contact point at rest: v_x = r w_y) at 1 m/s from x = 1.1: it rolls, is not frozen
    # as REST, and falls off the end to the floor at the same time and place whatever dt
    b = Ball.create([[1.1, 0.1, R]], [[1.0, 0.0, 0.0]], [[0.0, 50.0, 0.0]])
    landings = []
    for dt in (0.5e-3, 1e-3, 2e-3):
        r = run(MODEL, b, dt)
        assert kinds(r) == [FLOOR], dt  # no bounce on the way, no REST
        landings.append((float(r.events.time[0, 0]), *np.asarray(r.events.pre.pos[0, 0, :2])))
    landings = np.asarray(landings)
    assert landings[0, 1] > L2 + R
    assert np.ptp(landings[:, 0]) < 2e-3  # s
    assert np.ptp(landings[:, 1]) < 2e-3  # m


def test_sliding_ball_reaches_the_rolling_speed_of_a_shell():
    # friction conserves the angular momentum about the contact point: a shell sliding at v0
    # without spin rolls at kappa / (1 + kappa) v0 = 0.6 v0, after (v0 - 0.6 v0) / (mu g)
    m = still_air(MODEL)
    v0, dt = 2.0, 1e-3
    b = Ball.create([[-1.0, 0.0, R]], [[v0, 0.0, 0.0]])
    t_roll = 0.4 * v0 / (0.25 * 9.81)
    r = run(m, b, dt)
    vx = np.asarray(r.trajectory.vel[0, :, 0])
    times = np.asarray(r.times)
    on = np.asarray(r.trajectory.pos[0, :, 0]) < L2
    np.testing.assert_allclose(vx[on & (times > t_roll + 0.02)], 0.6 * v0, rtol=1e-6)
    before = times < t_roll - 0.02
    np.testing.assert_allclose(vx[before], v0 - 0.25 * 9.81 * times[before], rtol=1e-3)
    np.testing.assert_allclose(np.asarray(r.trajectory.pos[0, on, 2]), R, atol=1e-9)  # on the surface


def test_rest_needs_the_whole_velocity_small():
    # at rest, and spinning in place with backspin (the contact point slides): the first rests,
    # the second is driven away by friction
    b = Ball.create([[0.3, 0.1, R], [-1.0, 0.1, R]], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
                    [[0.0, 0.0, 0.0], [0.0, -100.0, 0.0]])
    r = run(MODEL, b)
    assert int(r.status[0]) == REST and kinds(r, 0) == [REST]
    assert kinds(r, 1)[-1] == FLOOR  # driven off the end (-x) by its backspin
    assert float(r.events.pre.pos[1, 0, 0]) < -L2


# --------------------------------------------------------------------------- the table box
@pytest.mark.parametrize("dt", [1e-3, 4e-3])
@pytest.mark.parametrize("z", [-0.005, -0.012])  # centre below the surface: the end face
def test_ball_below_the_surface_hits_the_end_face(dt, z):
    m = still_air(MODEL)
    b = Ball.create([[L2 + 0.2, 0.1, z]], [[-5.0, 0.0, 0.0]])
    r = run(m, b, dt)
    assert kinds(r)[0] == TABLE
    np.testing.assert_allclose(float(r.events.pre.pos[0, 0, 0]), L2 + R, atol=1e-6)
    assert float(r.events.time[0, 0]) == pytest.approx((0.2 - R) / 5.0, abs=1e-6)
    assert float(r.events.post.vel[0, 0, 0]) > 4.0  # back along +x


@pytest.mark.parametrize("dt", [1e-3, 4e-3])
def test_edge_contact_normal_from_the_nearest_point_of_the_edge(dt):
    # centre 1 cm above the surface level, arriving horizontally at the end: it meets the edge
    # line (x = L/2, z = 0) where its centre is r from it, i.e. at x = L/2 + sqrt(r^2 - 0.01^2),
    # with the normal (sqrt(3)/2, 0, 1/2); in the step where that happens
    m = weightless(MODEL)
    b = Ball.create([[L2 + 0.1, 0.1, 0.01]], [[-5.0, 0.0, 0.0]])
    r = run(m, b, dt)
    assert kinds(r)[0] == TABLE
    x_c = L2 + np.sqrt(R**2 - 0.01**2)
    np.testing.assert_allclose(np.asarray(r.events.pre.pos[0, 0]), [x_c, 0.1, 0.01], atol=1e-6)
    assert float(r.events.time[0, 0]) == pytest.approx((L2 + 0.1 - x_c) / 5.0, abs=1e-6)
    n = np.array([np.sqrt(3) / 2, 0.0, 0.5])
    post = np.asarray(r.events.post.vel[0, 0])
    assert post @ n > 0.0  # leaves the edge
    assert post[2] > 0.5  # thrown upwards by the edge, not passed through or bounced off a wall


def test_corner_contact_and_a_near_miss():
    m = weightless(MODEL)
    d = np.array([-1.0, -1.0, 0.0]) / np.sqrt(2)  # diagonally onto the corner (L/2, W/2, 0)
    corner = np.array([L2, W2, 0.0])
    start = corner - 0.1 * d
    b = Ball.create([start, start + [0.0, 0.0, 0.021]], [5.0 * d, 5.0 * d])
    r = run(m, b)
    assert kinds(r, 0)[0] == TABLE
    np.testing.assert_allclose(np.linalg.norm(np.asarray(r.events.pre.pos[0, 0]) - corner), R, atol=1e-6)
    assert TABLE not in kinds(r, 1)  # passes 1 mm above the corner


def test_ball_clipping_an_edge_within_one_step_is_caught():
    # falling at 40 m/s past the end, 1.5 cm out: it overlaps the end face only mid-step at 2 ms
    # steps (8 cm a step, the table is 2.5 cm thick), and must not pass through the table
    m = still_air(MODEL)
    b = Ball.create([[L2 + 0.015, 0.1, 0.035]], [[0.0, 0.0, -40.0]])
    r = run(m, b, 2e-3)
    assert kinds(r)[0] == TABLE
    assert float(r.events.post.vel[0, 0, 0]) > 5.0  # deflected out, away from the end
    dist, _ = tbl.box_distance(m.table, (), r.events.pre.pos[0, 0])
    assert float(dist) == pytest.approx(R, abs=1e-4)


# --------------------------------------------------------------------------- start states
def test_balls_starting_inside_table_net_or_racket_are_refused(dtype):
    m = load_model("conti2026", dtype=dtype)
    pos = [[0.5, 0.0, -0.01], [1.0, 0.3, 0.005], [0.0, 0.2, 0.08], [-1.6, 0.01, 0.21],  # inside
           [0.5, 0.0, R], [0.0, 0.2, 0.2], [-1.55, 0.0, 0.2]]  # touching / clear
    b = Ball.create(pos, [[3.0, 0.0, -1.0]] * 7, dtype=dtype)
    r = run(m, b, racket_pos=(-1.6, 0.0, 0.2))
    assert np.asarray(r.status).tolist()[:4] == [INVALID] * 4
    assert INVALID not in np.asarray(r.status).tolist()[4:]
    np.testing.assert_array_equal(np.asarray(r.final.pos[:4]), np.asarray(b.pos[:4]))  # not flown


# --------------------------------------------------------------------------- residual bounds
def test_grazing_ball_bounces_lower_each_time_and_rests():
    b = Ball.create([[-1.3, 0.0, 0.03]], [[2.0, 0.0, -0.5]])
    r = run(MODEL, b)
    k = kinds(r)
    bounces = np.asarray(r.events.post.vel[0, : len(k), 2])[np.asarray(k) == TABLE]
    assert len(bounces) >= 2
    assert np.all(np.diff(bounces) <= 0.0)


def test_skimming_ball_hops_higher_and_never_gains_energy():
    # v_xy = 3 m/s, v_z = -0.15 m/s: the law's normal restitution is above 1 (physics/table.py), so
    # the hops grow while the ball has horizontal speed to give (they shrink once friction took it:
    # the grazing ball above), and the kinetic energy at each impact (the same height) only falls
    b = Ball.create([[-1.3, 0.0, 0.021]], [[3.0, 0.0, -0.15]])
    r = run(MODEL, b)
    k = np.asarray(kinds(r))
    table = k == TABLE
    hops = np.asarray(r.events.post.vel[0, : len(k), 2])[table]
    e_pre = np.asarray(tbl.kinetic_energy(MODEL.table.kappa, R, r.events.pre.vel[0, : len(k)],
                                          r.events.pre.spin[0, : len(k)]))[table]
    assert len(hops) >= 6 and hops[-1] > 1.5 * hops[0]
    assert np.all(np.diff(hops) > 0.0)
    assert np.all(np.diff(e_pre) < 0.0)


def test_vertical_drop_stays_vertical(dtype):
    m = load_model("conti2026", dtype=dtype)
    v, w = tbl.local_contact(m.table, jnp.asarray(R, dtype), jnp.array([0.0, 0.0, -4.0], dtype), jnp.zeros(3, dtype))
    np.testing.assert_array_equal(np.asarray(v[:2]), 0.0)
    np.testing.assert_array_equal(np.asarray(w), 0.0)
    b = Ball.create([[0.3, 0.1, 0.3]], [[0.0, 0.0, 0.0]], dtype=dtype)
    r = run(m, b)
    assert kinds(r).count(TABLE) >= 3
    np.testing.assert_array_equal(np.asarray(r.final.pos[0, :2]), np.asarray(b.pos[0, :2]))
    np.testing.assert_array_equal(np.asarray(r.final.spin[0]), 0.0)


def test_residual_fade_is_smooth_and_full_in_the_data_range():
    f = jax.vmap(lambda s: tbl.residual_fade(jnp.stack([s, 0.0 * s, -3.0 + 0.0 * s])))
    s = jnp.linspace(0.0, 3.0, 301)
    fade = np.asarray(f(s))
    assert fade[0] == 0.0 and np.all(fade[s >= tbl.RESIDUAL_FADE_SPEED] == 1.0)
    assert np.all(np.diff(fade) >= 0.0) and np.max(np.abs(np.diff(fade))) < 0.02
