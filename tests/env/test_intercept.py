"""The "intercept" action mode: the hit-point predictor against closed forms and the kernel's own
drag-free flight, the mirror law against the kernel's racket contact, the tracked racket meeting the
ball at the predicted point within its limits, extreme actions, the spaces and gymnasium's checker.

One compiled environment shape: 8 environments in intercept mode with a target drawn per episode
(module fixture; a fixed target is the same program with a spread of 0), plus the
single-environment checker; the predictor and the mirror law run eagerly on small arrays.
"""

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import ttsim_jax  # noqa: F401  (registers the environments)
from ttsim_jax import Ball, Record, init_state, load_model, rollout
from ttsim_jax.env import intercept
from ttsim_jax.env import racket as racket_kin
from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.intercept import intercept_params
from ttsim_jax.env.return_ball import ReturnBall, jit_reset, jit_step_env
from ttsim_jax.physics import events as ev
from ttsim_jax.physics.racket import racket_contact
from ttsim_jax.state import Racket

N = 8
# the "accel" task switched to the intercept mode: its tracker settings are the code's defaults
ACCEL = "return_ball_accel"
OVERRIDES = {"shots.bank": 64, "shots.aim": True, "control.action": "intercept"}
# the goal-conditioned form (configs/tasks/return_ball_goal.toml's box)
GOAL = {"reward.target_point": [-0.75, 0.0], "reward.target_spread": [0.45, 0.55], "observation.target": True}
G = 9.81


@pytest.fixture(scope="module")
def params():
    model = load_model("conti2026", dtype=jnp.float32)
    # the drag-free flight and plain bounce, whose closed forms the predictor tests check
    return intercept_params(model, load_task_config("return_ball",
                                                    {"intercept.air": False, "intercept.bounce": "plain"}))


@pytest.fixture(scope="module")
def plane(params):
    """The tracker's settings with every ball met at the plane x_hit (min_height far below)."""
    return params.replace(min_height=jnp.float32(-1e3))


def _closed_form(p0, v0, x_hit, e, r, bounces):
    """Crossing of x = x_hit after ``bounces`` drag-free bounces at z = r (numpy, scalar maths)."""
    p, v, t = np.array(p0, float), np.array(v0, float), 0.0
    for _ in range(bounces):
        dt = (v[2] + np.sqrt(v[2] ** 2 + 2 * G * (p[2] - r))) / G
        p = p + v * dt + [0, 0, -0.5 * G * dt * dt]
        v = np.array([v[0], v[1], -e * (v[2] - G * dt)])
        t += dt
    dt = (x_hit - p[0]) / v[0]
    return p + v * dt + [0, 0, -0.5 * G * dt * dt], t + dt


def test_predictor_matches_the_closed_form_with_one_and_two_bounces(plane):
    params = plane
    # a drive bouncing on the agent's half, a serve bouncing first on its own half, a ball already bounced
    pos = jnp.array([[-1.0, 0.1, 0.35], [-1.3, -0.2, 0.25], [0.6, 0.0, 0.1]], jnp.float32)
    vel = jnp.array([[6.0, 0.3, 0.5], [3.5, 0.4, -0.5], [4.0, -0.2, 1.5]], jnp.float32)
    point, v_hit, t, valid = intercept.predict(params, pos, vel, jnp.array([False, False, True]))
    x, e, r = float(params.x_hit), float(params.e_table), float(params.radius)
    assert np.asarray(valid).all()
    for i, bounces in enumerate((1, 2, 0)):
        want_p, want_t = _closed_form(pos[i], vel[i], x, e, r, bounces)
        np.testing.assert_allclose(point[i], want_p, atol=2e-5)
        np.testing.assert_allclose(t[i], want_t, atol=2e-6)
    # a serve's first bounce lies on its own half (x < 0), the drive's on the agent's
    first = [float(pos[i, 0] + vel[i, 0] * (vel[i, 2] + np.sqrt(vel[i, 2] ** 2 + 2 * G * (pos[i, 2] - r))) / G)
             for i in range(2)]
    assert first[1] < 0 < first[0]
    np.testing.assert_allclose(v_hit[2], vel[2] - np.array([0, 0, G]) * float(t[2]), atol=2e-5)


def test_predictor_agrees_with_the_kernels_drag_free_flight(plane):
    """Air off (rho_air = 0): the kernel's flight is pure gravity; its 1 ms integrator places the
    ball within g dt t / 2 ~ 2 mm of the parabola after 0.4 s, so 3 mm and 1 ms are the tolerances."""
    model = load_model("conti2026")
    model = model.replace(aero=model.aero.replace(rho_air=jnp.zeros_like(model.aero.rho_air)))
    pos = np.array([[0.5, 0.1, 0.2], [0.3, -0.3, 0.25]])
    vel = np.array([[3.0, 0.2, 1.8], [3.5, 0.1, 1.2]])  # both above the table until the plane
    params = plane
    point, _, t, valid = intercept.predict(params, jnp.asarray(pos, jnp.float32), jnp.asarray(vel, jnp.float32),
                                           jnp.array([True, True]))
    dt, n = 1e-3, 500
    _, out = rollout(model, init_state(Ball(pos=pos, vel=vel, spin=np.zeros_like(pos))), n, dt,
                     record=Record(max_events=2, every=1))
    traj = np.swapaxes(np.asarray(out.trajectory.pos), 0, 1)  # (n, B, 3)
    times = np.asarray(out.times)
    for b in range(2):
        k = int(np.argmax(traj[:, b, 0] >= float(params.x_hit)))  # first sample past the plane
        f = (float(params.x_hit) - traj[k - 1, b, 0]) / (traj[k, b, 0] - traj[k - 1, b, 0])
        crossing = traj[k - 1, b] + f * (traj[k, b] - traj[k - 1, b])
        when = times[k - 1] + f * (times[k] - times[k - 1])
        assert valid[b]
        np.testing.assert_allclose(point[b], crossing, atol=3e-3)
        np.testing.assert_allclose(t[b], when, atol=1e-3)


def test_model_bounce_predicts_the_kernels_spinning_bounce(plane):
    """``[intercept] bounce = "model"``: the predicted bounce is the model's table contact, so with
    the air off the prediction of a spinning ball before its bounce meets the kernel's flight
    within the integrator's error; the plain bounce (spin and friction left out) misses by
    centimetres."""
    model = load_model("conti2026")
    model = model.replace(aero=model.aero.replace(rho_air=jnp.zeros_like(model.aero.rho_air)))
    pos = np.array([[0.2, 0.0, 0.3], [0.2, 0.1, 0.3], [0.3, -0.1, 0.25], [0.2, 0.0, 0.3]])
    vel = np.array([[5.0, 0.3, -0.5], [4.0, 0.2, -0.5], [4.5, -0.3, 0.0], [5.0, 0.0, -0.5]])
    spin = np.array([[0.0, 150.0, 0.0], [0.0, -150.0, 0.0], [0.0, 50.0, 120.0], [0.0, 0.0, 0.0]])
    spun = plane.replace(table=model.table)
    args = (jnp.asarray(pos, jnp.float32), jnp.asarray(vel, jnp.float32), jnp.zeros(4, bool),
            jnp.asarray(spin, jnp.float32))
    point, _, t, valid = map(np.asarray, intercept.predict(spun, *args))
    plain, _, _, _ = map(np.asarray, intercept.predict(plane, *args))
    dt, n = 1e-3, 600
    _, out = rollout(model, init_state(Ball(pos=pos, vel=vel, spin=spin)), n, dt, record=Record(max_events=2, every=1))
    traj = np.swapaxes(np.asarray(out.trajectory.pos), 0, 1)
    times = np.asarray(out.times)
    assert (np.asarray(out.events.kind)[:, 0] == ev.TABLE).all()  # each bounces once before the plane
    worst_plain = 0.0
    for b in range(4):
        k = int(np.argmax(traj[:, b, 0] >= float(plane.x_hit)))
        f = (float(plane.x_hit) - traj[k - 1, b, 0]) / (traj[k, b, 0] - traj[k - 1, b, 0])
        crossing = traj[k - 1, b] + f * (traj[k, b] - traj[k - 1, b])
        assert valid[b]
        np.testing.assert_allclose(point[b], crossing, atol=3e-3)
        np.testing.assert_allclose(t[b], times[k - 1] + f * (times[k] - times[k - 1]), atol=1e-3)
        if b < 3:
            worst_plain = max(worst_plain, float(np.linalg.norm(plain[b] - crossing)))
    assert worst_plain > 0.02


def test_air_prediction_meets_the_kernels_flight_with_drag_and_magnus(plane):
    """``[intercept] air = true``: with the model's drag and Magnus force in the predicted flights
    (constant over each flight, at the velocity a third of the way through it), the predicted
    crossing of the plane meets the kernel's flight (air on, a spinning bounce through the model's
    table contact) within 1.5 cm and 8 ms over flights of 0.2-0.45 s; the drag-free prediction
    misses the fast spinning balls by more than 8 cm."""
    model = load_model("conti2026")
    # bounced topspin, backspin, sidespin and spinless balls, and two drives before their bounce
    pos = np.array([[0.05, 0.0, 0.06], [0.05, 0.1, 0.05], [0.1, -0.1, 0.07], [0.05, 0.0, 0.05],
                    [-0.8, 0.1, 0.35], [-1.0, -0.2, 0.3]])
    vel = np.array([[7.0, 0.3, 1.8], [5.0, -0.2, 2.0], [6.0, 0.2, 1.8], [6.0, 0.0, 1.5],
                    [11.0, 0.2, -1.0], [7.0, 0.3, 0.5]])
    spin = np.array([[0.0, 400.0, 0.0], [0.0, -300.0, 0.0], [0.0, 100.0, 200.0], [0.0, 0.0, 0.0],
                     [0.0, 350.0, 50.0], [0.0, -250.0, 0.0]])
    bounced = jnp.array([True, True, True, True, False, False])
    aired = plane.replace(air=model.aero, table=model.table)
    args = (jnp.asarray(pos, jnp.float32), jnp.asarray(vel, jnp.float32), bounced, jnp.asarray(spin, jnp.float32))
    point, _, t, valid = map(np.asarray, intercept.predict(aired, *args))
    still, _, _, _ = map(np.asarray, intercept.predict(aired.replace(air=None), *args))
    dt, n = 1e-3, 700
    _, out = rollout(model, init_state(Ball(pos=pos, vel=vel, spin=spin)), n, dt, record=Record(max_events=2, every=1))
    traj = np.swapaxes(np.asarray(out.trajectory.pos), 0, 1)
    times = np.asarray(out.times)
    kinds = np.asarray(out.events.kind)
    assert (kinds[4:, 0] == ev.TABLE).all() and (kinds[:4, 0] != ev.TABLE).all()  # one bounce, where it should
    misses = []
    for b in range(len(pos)):
        k = int(np.argmax(traj[:, b, 0] >= float(plane.x_hit)))
        assert k > 0
        f = (float(plane.x_hit) - traj[k - 1, b, 0]) / (traj[k, b, 0] - traj[k - 1, b, 0])
        crossing = traj[k - 1, b] + f * (traj[k, b] - traj[k - 1, b])
        when = times[k - 1] + f * (times[k] - times[k - 1])
        assert valid[b] and 0.2 < when < 0.45
        np.testing.assert_allclose(point[b], crossing, atol=0.015)
        np.testing.assert_allclose(t[b], when, atol=8e-3)
        misses.append(float(np.linalg.norm(still[b] - crossing)))
    assert min(misses[i] for i in (0, 2, 4)) > 0.08


def _second_bounce(p0, v0, r):
    """(time, x) of a drag-free ball's next fall to z = r (numpy)."""
    t = (v0[2] + np.sqrt(v0[2] ** 2 + 2 * G * (p0[2] - r))) / G
    return t, p0[0] + v0[0] * t


def test_moving_hit_point_lies_before_a_short_balls_second_bounce(params, plane):
    """Drag-free, bounced balls (closed forms): a short ball never rising to min_height is met at its
    apex; one rising above it where it sinks back through it; one whose apex lies before x_min at
    x_min; each before its second bounce on the agent's half (x < 1.37), where the plane's hit would
    come after it. A long ball is met at the plane as before."""
    r, h, x_min = float(params.radius), float(params.min_height), float(params.x_min)
    assert (h, x_min) == pytest.approx((0.3, 0.6))  # the task file's: the cases below are built for them
    pos = np.array([[0.3, 0.0, 0.03], [0.2, 0.1, 0.03], [0.3, 0.0, 0.03], [0.6, 0.0, 0.1]])
    vel = np.array([[2.0, 0.0, 1.5], [1.8, 0.2, 3.0], [1.0, 0.0, 2.0], [4.0, 0.0, 3.0]])
    apex = vel[0, 2] / G
    sink = (vel[1, 2] + np.sqrt(vel[1, 2] ** 2 - 2 * G * (h - pos[1, 2]))) / G
    reach = (x_min - pos[2, 0]) / vel[2, 0]
    args = (jnp.asarray(pos, jnp.float32), jnp.asarray(vel, jnp.float32), jnp.ones(4, bool))
    point, v_hit, t, valid = map(np.asarray, intercept.predict(params, *args))
    plane_point, _, plane_t, _ = map(np.asarray, intercept.predict(plane, *args))
    assert valid.all()
    for i, want_t in enumerate((apex, sink, reach)):
        want = pos[i] + vel[i] * want_t - [0, 0, 0.5 * G * want_t ** 2]
        np.testing.assert_allclose(point[i], want, atol=1e-5)
        np.testing.assert_allclose(t[i], want_t, atol=1e-5)
        t2, x2 = _second_bounce(pos[i], vel[i], r)
        assert x2 < 1.37 and t[i] < t2 and point[i, 0] < x2 and point[i, 2] > r  # above the table, in time
        assert plane_t[i] > t2  # the plane x_hit would come after the second bounce
    np.testing.assert_allclose(point[1, 2], h, atol=1e-5)
    np.testing.assert_allclose(v_hit[0, 2], 0.0, atol=1e-5)  # the apex
    np.testing.assert_allclose(point[3], plane_point[3], atol=1e-6)  # the long ball: at the plane
    np.testing.assert_allclose(point[3, 0], float(params.x_hit), atol=1e-6)


def test_return_arc_with_drag_lands_on_the_target_through_the_kernels_flight(params):
    """The arc of :func:`intercept.arc_velocity`, flown spinless through the kernel with air on, lands
    within 4 cm of the target and 10 ms of the planned flight time; the drag-free parabola's start
    velocity falls more than 15 cm short."""
    model = load_model("conti2026")
    pos = np.array([[1.2, 0.1, 0.3], [1.0, -0.2, 0.25]])
    land = np.array([[-0.9, 0.0, float(params.radius)]] * 2)
    tau = np.array([[0.45], [0.4]])  # landing within the 0.5 s flown
    landings = []
    for drag in (params.drag, 0.0):
        v0 = np.asarray(intercept.arc_velocity(jnp.asarray(land - pos, jnp.float32), jnp.asarray(tau, jnp.float32),
                                               params.gravity, drag), float)
        _, out = rollout(model, init_state(Ball(pos=pos, vel=v0, spin=np.zeros_like(pos))), 500, 1e-3,
                         record=Record(max_events=2, every=1))
        kind, where, when = (np.asarray(a) for a in (out.events.kind, out.events.pre.pos, out.events.time))
        assert (kind[:, 0] == ev.TABLE).all()  # over the net, onto the table
        landings.append((where[:, 0, :2], when[:, 0]))
    (with_drag, t_drag), (parabola, _) = landings
    np.testing.assert_allclose(with_drag, land[:, :2], atol=0.04)
    np.testing.assert_allclose(t_drag, tau[:, 0], atol=0.01)
    assert (parabola[:, 0] > land[:, 0] + 0.15).all()


def test_predictor_flags_balls_going_away_or_past_the_plane(params):
    pos = jnp.array([[0.5, 0.0, 0.2], [1.6, 0.0, 0.2], [0.5, 0.0, 0.2]], jnp.float32)
    vel = jnp.array([[-3.0, 0.0, 1.0], [3.0, 0.0, 1.0], [jnp.nan, 0.0, 1.0]], jnp.float32)
    point, v_hit, t, valid = intercept.predict(params, pos, vel, jnp.array([True, True, True]))
    assert not np.asarray(valid).any()
    assert np.isfinite(np.asarray(t)).all() and np.isfinite(np.asarray(point)[:2]).all()


@pytest.mark.parametrize("spin", [(0.0, 0.0, 0.0), (0.0, 150.0, 40.0)])
def test_mirror_law_sends_the_ball_on_the_planned_arc_through_the_kernels_contact(params, spin):
    """The kernel's contact (speed-dependent restitution e1 and grip et1 included) turns the incoming
    ball into the planned outgoing velocity, within 0.2 % of its speed (the fixed-point iteration's
    residual); with the arc's drag off the planned velocity is the parabola's."""
    model = load_model("conti2026")
    rp = model.racket
    assert float(rp.e1) != 0.0 and float(rp.et1) != 0.0
    params = params.replace(drag=jnp.float32(0.0), aero=None)
    point = jnp.array([[1.45, 0.2, 0.25]], jnp.float32)
    v_in = jnp.array([[5.0, -0.4, -1.5]], jnp.float32)
    w = jnp.array([spin], jnp.float32)
    target, flight = jnp.array([-0.9, 0.0], jnp.float32), jnp.array([0.5], jnp.float32)
    angle, v_racket = intercept.mirror(params, point, v_in, w, target, flight)
    rot = racket_kin.rotation(angle[0])
    n = rot[:, 0]
    np.testing.assert_allclose(np.cross(v_racket[0], n), 0.0, atol=1e-5)  # the face moves along its normal
    racket = Racket(pos=point[0] - params.radius * n, rot=rot, vel=v_racket[0], ang_vel=jnp.zeros(3),
                    face=jnp.array([0.0775, 0.0755]))
    v_out, _, _ = racket_contact(rp, racket, model.ball.radius, model.ball.mass, point[0], v_in[0], w[0])
    tau = 0.5
    want = (np.array([-0.9, 0.0, float(params.radius)]) - np.asarray(point[0])) / tau + [0, 0, 0.5 * G * tau]
    tol = 2e-3 * np.linalg.norm(want)
    np.testing.assert_allclose(np.asarray(v_out), want, atol=tol)


def test_return_planned_with_its_spin_lands_on_the_target_through_the_kernel(params):
    """``[intercept] magnus``: the stroke planned with the acceleration of the spin it gives the ball
    (held at its mean over the flight) lands within 6 cm of the target when the kernel flies the
    ball the contact sends out (air, spin and all); planned without it, the same balls land more
    than 20 cm away. Same shapes as the drag test's rollout (2 balls, 500 steps)."""
    model = load_model("conti2026")
    assert params.aero is not None  # on in the intercept task
    point = jnp.array([[1.45, 0.2, 0.25], [1.45, 0.1, 0.2]], jnp.float32)
    v_in = jnp.array([[5.0, -0.4, -1.5], [3.0, 0.0, 0.5]], jnp.float32)
    w_in = jnp.array([[0.0, 250.0, 30.0], [0.0, -100.0, 50.0]], jnp.float32)  # topspin, backspin and sidespin
    target, flight = jnp.array([-0.9, 0.0], jnp.float32), jnp.array([0.4, 0.4], jnp.float32)
    errors = []
    for p in (params, params.replace(aero=None)):
        angle, v_racket = intercept.mirror(p, point, v_in, w_in, target, flight)
        outs = []
        for b in range(2):
            rot = racket_kin.rotation(angle[b])
            face = Racket(pos=point[b] - p.radius * rot[:, 0], rot=rot, vel=v_racket[b], ang_vel=jnp.zeros(3),
                          face=p.face)
            outs.append(racket_contact(model.racket, face, model.ball.radius, model.ball.mass, point[b], v_in[b],
                                       w_in[b])[:2])
        v_out, w_out = (np.stack([np.asarray(o[i]) for o in outs]) for i in (0, 1))
        assert (np.linalg.norm(w_out, axis=-1) > 50.0).all()  # the return spins
        _, out = rollout(model, init_state(Ball(pos=np.asarray(point, float), vel=v_out, spin=w_out)), 500, 1e-3,
                         record=Record(max_events=2, every=1))
        kind, where = np.asarray(out.events.kind), np.asarray(out.events.pre.pos)
        assert (kind[:, 0] == ev.TABLE).all()
        errors.append(np.linalg.norm(where[:, 0, :2] - np.asarray(target), axis=-1))
    with_spin, without = errors
    assert (with_spin < 0.06).all() and (without > 0.2).all(), (with_spin, without)


@pytest.fixture(scope="module")
def episode():
    """8 environments in intercept mode, each with its own target, played with action 0 until every
    one finished, with the prediction made before each step."""
    env = ReturnBall(load_task_config("return_ball", dict(OVERRIDES, **GOAL)), N)
    p = env.default_params()
    key = jax.random.PRNGKey(3)
    _, state = jit_reset(env, key, p)
    rows = []
    done = np.zeros(N, bool)

    @jax.jit
    def plan(p, state):
        point, v_hit, t, valid = intercept.predict(p.intercept, state.rally.ball.pos, state.rally.ball.vel,
                                                   state.progress.bounced, state.rally.ball.spin)
        flight, _, _ = intercept.stroke(p.intercept, jnp.zeros((N, 5)))
        _, swing = intercept.mirror(p.intercept, point, v_hit, state.rally.ball.spin, state.target, flight)
        return point, v_hit, t, valid, swing

    for i in range(env.max_steps):
        point, v_hit, t, valid, swing = plan(p, state)
        out = jit_step_env(env, jax.random.fold_in(key, i), state, jnp.zeros((N, 5)), p)
        rows.append(dict(racket=state.racket, point=np.asarray(point), swing=np.asarray(swing), t=np.asarray(t),
                         valid=np.asarray(valid), v_hit=np.asarray(v_hit),
                         contact=np.asarray(out[5]["contact"]), done=done.copy(), obs=np.asarray(out[0]),
                         reward=np.asarray(out[2]), target=np.asarray(state.target),
                         outcome=np.asarray(out[5]["outcome"]), landing=np.asarray(out[1].progress.landing)))
        state = out[1]
        done |= np.asarray(out[3]) | np.asarray(out[4])
        if done.all():
            break
    return env, p, rows


def test_tracked_racket_meets_the_ball_at_the_predicted_point_and_time_within_its_limits(episode):
    env, p, rows = episode
    lim = p.limits
    met = 0
    for b in range(N):
        hits = [i for i, r in enumerate(rows) if r["contact"][b]]
        if not hits:
            continue
        met += 1
        i = hits[0]
        # the step before the contact: the predicted hit lies within this control period or the next
        before = rows[i]
        assert before["valid"][b] and before["t"][b] <= 2.5 * env.period
        rk = before["racket"]
        gap = np.asarray(rk.pos[b]) + np.asarray(rk.vel[b]) * before["t"][b] - before["point"][b]
        assert np.abs(gap[1:]).max() < 0.05  # within the face (semi-axes 7.6 cm) across and in height
        # moving with the planned stroke (a PD's lag behind its ramp of swing_time)
        assert np.linalg.norm(np.asarray(rk.vel[b]) - before["swing"][b]) < 0.75
    assert met >= 6  # of 8 shots with this seed (7 meet the ball)
    for r in rows:
        rk = r["racket"]
        assert (np.abs(np.asarray(rk.vel)) <= np.asarray(lim.max_speed) + 1e-4).all()
        pos = np.asarray(rk.pos)
        assert (pos >= np.asarray(lim.lo) - 1e-5).all() and (pos <= np.asarray(lim.hi) + 1e-5).all()
        over = pos[:, 0] < float(lim.table_x)  # over the table: above its surface plus the clearance
        assert (pos[over, 2] >= float(lim.table_z) - 1e-5).all()
        assert (np.abs(np.asarray(rk.rate)) <= np.asarray(lim.max_rate) + 1e-4).all()


def test_observed_plan_is_the_prediction_the_tracker_acts_on_next(episode):
    """With ``[observation] plan`` (on in the intercept task) the observation ends with the
    prediction the tracker makes from the same ball at the next step: point, velocity / 10, time,
    valid; zeros where there is none."""
    env, p, rows = episode
    assert env.config.observation.plan and env.obs_dim == 25 + 8 + 2
    seen_valid = seen_invalid = 0
    for now, nxt in zip(rows[:-1], rows[1:]):
        plan = now["obs"][:, -10:-2]
        for b in np.flatnonzero(~nxt["done"]):
            if nxt["valid"][b]:
                seen_valid += 1
                np.testing.assert_allclose(plan[b, :3], nxt["point"][b], rtol=1e-5, atol=1e-5)
                np.testing.assert_allclose(plan[b, 3:6], nxt["v_hit"][b] / 10.0, rtol=1e-5, atol=1e-5)
                np.testing.assert_allclose(plan[b, 6], nxt["t"][b], rtol=1e-5, atol=1e-5)
                assert plan[b, 7] == 1.0
            else:
                seen_invalid += 1
                np.testing.assert_array_equal(plan[b], np.zeros(8, np.float32))
    assert seen_valid > 50 and seen_invalid > 5


def test_each_episode_aims_at_its_own_target_which_it_observes(episode):
    """A target drawn per episode (``[reward] target_spread``): inside its box, different across
    episodes, constant through one, the observation's last two entries; the scripted stroke
    (action 0) lands a legal return near its own episode's target, nearer than to the others', and
    the reward's target term is scored against it."""
    env, p, rows = episode
    target = rows[0]["target"]
    lo, hi = np.array([-1.2, -0.55]), np.array([-0.3, 0.55])
    assert ((target >= lo - 1e-6) & (target <= hi + 1e-6)).all()
    assert np.ptp(target, axis=0).min() > 0.2  # 8 draws spread over the box
    for r in rows:
        np.testing.assert_array_equal(r["target"], target)
        np.testing.assert_array_equal(r["obs"][:, -2:], target)
    # the step each legal return landed (the outcome stays set after it)
    legal = [(b, next(i for i, r in enumerate(rows) if r["outcome"][b] == 1)) for b in range(N)
             if any(r["outcome"][b] == 1 for r in rows)]
    assert len(legal) >= 5, legal  # of 8 shots with this seed
    own, others = [], []
    for b, i in legal:
        land = rows[i]["landing"][b]
        own.append(np.linalg.norm(land - target[b]))
        others.append(np.mean([np.linalg.norm(land - target[o]) for o in range(N) if o != b]))
        # legal + target * (1 - d / target_scale) for the episode's own target, d < target_scale
        w = p.reward
        want = float(w["legal"]) + float(w["target"]) * max(0.0, 1.0 - own[-1] / float(w["target_scale"]))
        assert abs(rows[i]["reward"][b] - want) < 1e-4 + float(w["motion"])
    assert np.median(own) < 0.2 and np.median(own) < 0.4 * np.median(others), (own, others)


def test_extreme_and_non_finite_actions_stay_finite(episode):
    env, p, _ = episode
    key = jax.random.PRNGKey(9)
    _, state = jit_reset(env, key, p)
    actions = jnp.array([[1e9, -1e9, 1e9, -1e9, 1e9], [jnp.nan] * 5, [jnp.inf, -jnp.inf, 0, 0, 0],
                         [-1, -1, -1, -1, -1], [1, 1, 1, 1, 1], [0.5] * 5, [-0.5] * 5, [0] * 5], jnp.float32)
    for i in range(60):
        obs, state, reward, *_ = jit_step_env(env, jax.random.fold_in(key, i), state, actions, p)
        assert np.isfinite(np.asarray(obs)).all() and np.isfinite(np.asarray(reward)).all()
        assert np.isfinite(np.asarray(state.racket.pos)).all() and np.isfinite(np.asarray(state.racket.angle)).all()


def test_spaces_are_those_of_the_accel_mode_the_plan_appended():
    vec = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=N, task=ACCEL, overrides=OVERRIDES)
    plain = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=N, task=ACCEL, overrides={"shots.bank": 64, "shots.aim": False})
    assert vec.single_observation_space == plain.single_observation_space
    assert vec.single_action_space == plain.single_action_space
    planned = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=N, task=ACCEL,
                                 overrides=dict(OVERRIDES, **{"observation.plan": True}))
    assert planned.single_observation_space.shape == (plain.single_observation_space.shape[0] + 8,)
    assert planned.single_observation_space.dtype == np.float32


def test_default_task_is_the_intercept_mode_and_passes_gymnasiums_checker():
    """``gymnasium.make("ttsim/ReturnBall-v0")`` without a task: the bundled default, the intercept
    mode with the air in its prediction and the plan in its observation (a small unaimed bank)."""
    env = gymnasium.make("ttsim/ReturnBall-v0", overrides={"shots.bank": 32, "shots.aim": False})
    config = env.unwrapped.env.config
    assert config.control.action == "intercept" and config.intercept.air and config.observation.plan
    assert env.observation_space.shape == (33,)
    check_env(env.unwrapped, skip_render_check=True)
