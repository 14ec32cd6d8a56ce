import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Racket, load_model
from ttsim_jax.physics import racket as rk
from ttsim_jax.physics.contact import surface_velocity

from padding import B, N, simulate_shared

R = 0.02


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_tangential_restitution_reverses_surface_velocity_by_et():
    m = load_model("conti2026")
    rot = rot_z(2.6) @ rot_y(0.3)
    racket = Racket.create(jnp.array([1.5, 0.1, 0.2]), rot=jnp.asarray(rot), vel=jnp.array([-4.0, 0.5, 1.0]),
                           ang_vel=jnp.array([3.0, -10.0, 20.0]))
    n = rot[:, 0]
    pos = np.asarray(racket.pos) + (R - 1e-4) * n + 0.01 * rot[:, 1] - 0.02 * rot[:, 2]
    vel, spin = jnp.asarray(-8.0 * n + 2.0 * rot[:, 1]), jnp.array([100.0, -300.0, 50.0])
    v_p, w_p, st = rk.racket_contact(m.racket, racket, R, m.ball.mass, jnp.asarray(pos), vel, spin)
    rot_e = st["rot"]
    to_c = lambda x: (rot_e.T @ x)[jnp.array([1, 2, 0])]  # noqa: E731  world -> contact frame
    u0 = surface_velocity(to_c(vel - st["v_surf"]), to_c(spin - st["w_surf"]), R)
    u1 = surface_velocity(to_c(v_p - st["v_surf"]), to_c(w_p - st["w_surf"]), R)
    e_t = np.clip(0.819 - 0.010 * float(jnp.linalg.norm(u0)), 0, 1)
    np.testing.assert_allclose(np.asarray(u1), -e_t * np.asarray(u0), rtol=1e-9, atol=1e-9)
    # normal: v_n+ = -e_n v_n with e_n = 0.878 - 0.020 |v_n|
    vn0, vn1 = float(to_c(vel - st["v_surf"])[2]), float(to_c(v_p - st["v_surf"])[2])
    assert vn1 == pytest.approx(-(0.878 - 0.020 * abs(vn0)) * vn0, rel=1e-10)
    # normal spin damped by e_s
    assert float(to_c(w_p - st["w_surf"])[2]) == pytest.approx(0.805 * float(to_c(spin - st["w_surf"])[2]), rel=1e-10)


def test_nakashima_alpha_is_kp_over_m_and_ignores_racket_spin():
    m = load_model("nakashima2011")
    racket = Racket.create(jnp.zeros(3), ang_vel=jnp.array([0.0, 0.0, 30.0]))
    pos, vel, spin = jnp.array([R, 0.05, 0.0]), jnp.array([-5.0, 2.0, 0.0]), jnp.zeros(3)
    v1, w1, _ = rk.racket_contact(m.racket, racket, R, m.ball.mass, pos, vel, spin)
    v0, w0, _ = rk.racket_contact(m.racket, racket.replace(ang_vel=jnp.zeros(3)), R, m.ball.mass, pos, vel, spin)
    np.testing.assert_allclose(np.asarray(v1), np.asarray(v0))
    alpha = 1.928e-3 / float(m.ball.mass)
    assert alpha == pytest.approx(0.709, abs=2e-3)
    assert float(v1[1]) == pytest.approx((1 - alpha) * 2.0, rel=1e-9)
    assert float(v1[0]) == pytest.approx(0.81 * 5.0, rel=1e-9)
    # refined: the surface moves with w_R x r at the contact point
    refined = m.racket.replace(kind="refined")
    v2, _, st = rk.racket_contact(refined, racket, R, m.ball.mass, pos, vel, spin)
    np.testing.assert_allclose(np.asarray(st["v_surf"]), np.cross([0, 0, 30.0], [0, 0.05, 0.0]), atol=1e-12)
    assert float(v2[1]) != pytest.approx(float(v1[1]))


def test_back_face_mirrors_front_face():
    m = load_model("conti2026")
    racket = Racket.create(jnp.zeros(3))
    vel, spin = jnp.array([-6.0, 1.0, 0.5]), jnp.array([20.0, 150.0, -80.0])
    pos = jnp.array([R * 0.99, 0.01, 0.02])
    v_f, w_f, _ = rk.racket_contact(m.racket, racket, R, m.ball.mass, pos, vel, spin)
    # the same contact seen from the back: rotate the whole scene 180 degrees about z
    flip = jnp.diag(jnp.array([-1.0, -1.0, 1.0]))
    v_b, w_b, st = rk.racket_contact(m.racket, racket, R, m.ball.mass, flip @ pos, flip @ vel, flip @ spin)
    np.testing.assert_allclose(np.asarray(flip @ v_b), np.asarray(v_f), atol=1e-10)
    np.testing.assert_allclose(np.asarray(flip @ w_b), np.asarray(w_f), atol=1e-8)


def schedule(racket, n):
    return jax.tree.map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), racket)


def moving_racket(x0, vx, n, dt=1e-3):
    t = jnp.arange(n) * dt
    pos = jnp.stack([x0 + vx * t, jnp.zeros(n), 0.2 * jnp.ones(n)], -1)
    rot = jnp.broadcast_to(jnp.diag(jnp.array([-1.0, -1.0, 1.0])), (n, 3, 3))
    return Racket(pos=pos, rot=rot, vel=jnp.broadcast_to(jnp.array([vx, 0, 0.0]), (n, 3)),
                  ang_vel=jnp.zeros((n, 3)), face=jnp.broadcast_to(jnp.array([0.0775, 0.0755]), (n, 2)))


@pytest.mark.parametrize("dt", [1e-3, 4e-3])
def test_no_tunnelling_fast_ball_against_fast_racket(dt):
    # ball 35 m/s against a racket coming at 10 m/s: 45 mm relative per 1 ms step > ball diameter
    m = load_model("conti2026")
    sweep = np.linspace(0.0, 1.0, 2 * B).reshape(2, B)  # phases of the ball within a step, B at a time
    for phases in sweep:
        b = Ball.create(np.stack([0.5 + 0.045 * phases, np.zeros(B), 0.2 * np.ones(B)], -1),
                        np.tile([35.0, 0.0, 0.0], (B, 1)))
        r = simulate_shared(m, b, dt, moving_racket(2.3, -10.0, N, dt))  # the suite's shared shape
        kinds = np.asarray(r.events.kind[:, 0])
        assert np.all(kinds == 2), kinds
        assert np.all(np.asarray(r.events.post.vel[:, 0, 0]) < -10.0)  # sent back faster than the racket moves


def test_contact_outside_face_outline_misses():
    m = load_model("conti2026")
    b = Ball.create([[0.5, 0.12, 0.2]], [[10.0, 0.0, 0.0]])  # 12 cm off-centre: outside the face
    r = simulate_shared(m, b, 1e-3, moving_racket(1.8, 0.0, N))
    assert 2 not in np.asarray(r.events.kind[0]).tolist()
    assert float(r.final.pos[0, 0]) > 1.8  # it went past the racket's plane
