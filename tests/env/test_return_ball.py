"""The functional ReturnBall environment: spaces, determinism, automatic reset, no retrace, extreme
inputs, domain randomisation, the rally's bookkeeping, the racket's kinematic limits and its
workspace over the table.

One compiled shape: 8 environments, built through ``gymnasium.make_vec`` (module fixture); every
test that steps reuses its compiled step.
"""

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ttsim_jax  # noqa: F401  (registers the environments)
from ttsim_jax.env import racket as racket_kin
from ttsim_jax.env import return_ball
from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.rally_rules import LEGAL, MISS, NET, OUT, OUTCOME_NAMES, RUNNING, VOLLEY, Rally, advance
from ttsim_jax.env.return_ball import jit_reset, jit_step
from ttsim_jax.params import ConfigError
from ttsim_jax.physics import events as ev

N = 8
# the "accel" form: the policy commands the racket (the default task puts the intercept tracker under it)
TASK = "return_ball_accel"
OVERRIDES = {"shots.bank": 64, "shots.aim": False}


@pytest.fixture(scope="module")
def vec():
    env = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=N, task=TASK, overrides=OVERRIDES)
    env.reset(seed=0)
    return env


@pytest.fixture(scope="module")
def run(vec):
    """Steps the vector environment with zero actions until every environment finished once."""
    obs0, _ = vec.reset(seed=1)
    env, params = vec.env, vec.params
    key = jax.random.PRNGKey(5)
    _, state = jit_reset(env, key, params)
    history = []
    for i in range(env.max_steps + 1):
        k = jax.random.fold_in(key, i)
        out = jit_step(env, k, state, jnp.zeros((N, 5)), params)
        history.append((state, out))
        state = out[1]
        done = np.stack([np.asarray(o[3]) | np.asarray(o[4]) for _, o in history])
        if done.any(0).all():
            break
    return history


def test_spaces_shapes_and_dtypes(vec):
    assert vec.single_observation_space.shape == (25,) and vec.single_observation_space.dtype == np.float32
    assert vec.single_action_space.shape == (5,) and vec.single_action_space.dtype == np.float32
    assert vec.observation_space.shape == (N, 25) and vec.action_space.shape == (N, 5)
    obs, _ = vec.reset(seed=2)
    assert obs.shape == (N, 25) and obs.dtype == np.float32 and vec.observation_space.contains(obs)
    obs, reward, terminated, truncated, info = vec.step(vec.action_space.sample())
    assert obs.shape == (N, 25) and obs.dtype == np.float32 and vec.observation_space.contains(obs)
    assert reward.shape == (N,) and reward.dtype == np.float32
    assert terminated.shape == truncated.shape == (N,) and terminated.dtype == bool
    assert info["outcome"].shape == (N,) and "final_obs" not in info
    assert vec.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP  # gymnasium's default


def test_same_key_same_step_other_key_other_shots(vec):
    env, params = vec.env, vec.params
    obs_a, state = jit_reset(env, jax.random.PRNGKey(3), params)
    obs_b, _ = jit_reset(env, jax.random.PRNGKey(3), params)
    obs_c, other = jit_reset(env, jax.random.PRNGKey(4), params)
    np.testing.assert_array_equal(obs_a, obs_b)
    assert not np.array_equal(np.asarray(state.shot), np.asarray(other.shot))
    action = jnp.full((N, 5), 0.3)
    one = jit_step(env, jax.random.PRNGKey(7), state, action, params)
    two = jit_step(env, jax.random.PRNGKey(7), state, action, params)
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(two)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the vector env seeded alike gives the same episode
    runs = []
    for _ in range(2):
        vec.reset(seed=11)
        runs.append([vec.step(np.full((N, 5), 0.2, np.float32))[:2] for _ in range(3)])
    for (o1, r1), (o2, r2) in zip(*runs):
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)


def test_vmap_over_keys_matches_separate_resets(vec):
    env, params = vec.env, vec.params
    keys = jax.random.split(jax.random.PRNGKey(9), 2)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    for i in range(2):
        o, s = jit_reset(env, keys[i], params)
        np.testing.assert_allclose(obs[i], o, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(state.shot[i], s.shot)


def test_autoreset_gives_a_fresh_episode_and_keeps_the_final_observation(vec, run):
    env, params = vec.env, vec.params
    seen = 0
    for before, (obs, state, reward, terminated, truncated, info) in run:
        done = np.asarray(terminated | truncated)
        for i in np.flatnonzero(done):
            seen += 1
            final = np.asarray(info["final_obs"][i])
            # the final observation is the finished episode's: its clock is the step count, not 0
            assert final[-3] == pytest.approx(float(before.t[i] + 1) * env.period, rel=1e-5)
            assert not np.array_equal(final, np.asarray(obs[i]))
            # the new episode: time 0, nothing happened, ball alive at a shot of the bank
            assert obs[i, -3] == 0.0 and obs[i, -2] == 0.0 and obs[i, -1] == 0.0
            assert int(state.t[i]) == 0 and int(state.progress.outcome[i]) == RUNNING
            assert bool(state.rally.alive[i])
            np.testing.assert_array_equal(np.asarray(state.rally.ball.pos[i]),
                                          np.asarray(params.shots.pos[int(state.shot[i])]))
            assert np.all(np.asarray(state.racket.vel[i]) == 0.0)
        for i in np.flatnonzero(~done):  # the others go on
            assert int(state.t[i]) == int(before.t[i]) + 1
            np.testing.assert_array_equal(np.asarray(info["final_obs"][i]), np.asarray(obs[i]))
    assert seen >= N
    # a racket standing still never returns a ball: every ending is a miss or the opponent's fault
    outcomes = np.concatenate([np.asarray(o[5]["outcome"])[np.asarray(o[3])] for _, o in run])
    assert not np.isin(outcomes, [LEGAL]).any()


def test_no_retrace_across_steps(vec):
    vec.reset(seed=4)
    vec.step(vec.action_space.sample())
    size = return_ball._step._cache_size()
    for _ in range(5):
        vec.step(vec.action_space.sample())
    vec.reset(seed=5)
    vec.step(vec.action_space.sample())
    # a float64 or integer action is cast, not compiled for
    jit_step(vec.env, np.array([0, 1], np.uint32), vec._state, np.zeros((N, 5), np.float64), vec.params)
    jit_step(vec.env, jax.random.PRNGKey(1), vec._state, np.zeros((N, 5), np.int64), vec.params)
    assert return_ball._step._cache_size() == size


def test_extreme_actions_and_states_stay_finite(vec):
    env, params = vec.env, vec.params
    _, state = jit_reset(env, jax.random.PRNGKey(1), params)
    ball = state.rally.ball
    wild = ball.replace(pos=ball.pos.at[0].set(jnp.nan).at[1].set(1e9), vel=ball.vel.at[2].set(1e6),
                        spin=ball.spin.at[3].set(jnp.inf))
    state = state.replace(rally=state.rally.replace(ball=wild))
    action = jnp.array([[jnp.nan, jnp.inf, -jnp.inf, 1e30, -1e30]] * N, jnp.float32)
    for i in range(3):
        obs, state, reward, terminated, truncated, info = jit_step(env, jax.random.PRNGKey(i), state, action, params)
        assert np.isfinite(np.asarray(obs)).all() and np.isfinite(np.asarray(reward)).all()
        pos = np.asarray(state.racket.pos)
        assert (pos >= np.asarray(params.limits.lo) - 1e-6).all() and (pos <= np.asarray(params.limits.hi) + 1e-6).all()
        assert np.isfinite(np.asarray(state.racket.vel)).all()


@pytest.mark.parametrize("finished", [[1, 6, 17], list(range(10))])
def test_restarts_give_each_finished_environment_its_own_new_episode(vec, finished):
    """A step makes new episodes for ``reset_rows`` rows (8 of 20 environments here) and gives each
    finished environment one; more finished than that (the second case) takes the whole batch's."""
    n = 20
    env = return_ball.ReturnBall(vec.env.config, n)
    params = vec.params
    assert env.reset_rows == 8
    done = jnp.zeros(n, bool).at[jnp.asarray(finished)].set(True)
    obs, state = jax.jit(env._restarts)(jax.random.PRNGKey(3), params, done)
    ids = np.asarray(state.rally.ball_id)
    shots = np.asarray(state.shot)
    for i in finished:
        assert ids[i] == i  # the kernel's draws follow the environment, not its row among the new ones
        assert int(state.t[i]) == 0 and int(state.progress.outcome[i]) == RUNNING and bool(state.rally.alive[i])
        np.testing.assert_array_equal(np.asarray(state.rally.ball.pos[i]), np.asarray(params.shots.pos[shots[i]]))
        np.testing.assert_array_equal(np.asarray(obs[i]), np.asarray(env.observe(state))[i])
    # distinct episodes, not one copied into every finished environment
    assert len({tuple(np.asarray(state.model_values[i])) for i in finished}) == len(finished)


def test_domain_randomisation_draws_per_environment_values_in_range(vec):
    env, params = vec.env, vec.params
    assert env.paths == ("table.e0", "racket.e0", "aero.rho_air")
    _, state = jit_reset(env, jax.random.PRNGKey(2), params)
    v = np.asarray(state.model_values)
    assert v.shape == (N, 3)
    assert (v >= np.asarray(params.rand_lo)).all() and (v <= np.asarray(params.rand_hi)).all()
    assert len(np.unique(v[:, 0])) == N
    model, axes = env.model_for(params, state.model_values)
    np.testing.assert_array_equal(np.asarray(model.table.e0), v[:, 0])
    np.testing.assert_array_equal(np.asarray(model.aero.rho_air), v[:, 2])
    assert axes.table.e0 == 0 and axes.table.mu is None


def test_normal_laws_are_drawn_around_their_mean_within_three_deviations():
    """``{mean = M, std = S}`` entries: a truncated normal per environment, beside uniform ranges
    (the reset's draw, evaluated for 4,096 environments without compiling an environment)."""
    from ttsim_jax.env.return_ball import ReturnBall

    env = ReturnBall(load_task_config(TASK, dict(OVERRIDES, **{"randomisation": {
        "table.e0": {"mean": 0.95, "std": 0.01}, "racket.e0": [0.84, 0.90]}})), 4096)
    assert env.config.randomisation == (("table.e0", 0.95, 0.01, "normal"), ("racket.e0", 0.84, 0.90, "uniform"))
    lo, hi, normal = jnp.array([0.95, 0.84]), jnp.array([0.01, 0.90]), jnp.array([True, False])
    draw = jax.jit(lambda k: env.draw_model_values(k, lo, hi, normal))
    v = np.asarray(draw(jax.random.PRNGKey(0)))
    assert v.shape == (4096, 2)
    assert abs(v[:, 0].mean() - 0.95) < 4 * 0.01 / 64 and 0.0095 < v[:, 0].std() < 0.0105
    assert np.abs(v[:, 0] - 0.95).max() <= 0.03 + 1e-6
    assert (v[:, 1] >= 0.84).all() and (v[:, 1] <= 0.90).all() and abs(v[:, 1].mean() - 0.87) < 0.002


def _events(*rows):
    """(kind (1,), pos (1, 3)) per event."""
    return [(jnp.array([k]), jnp.array([p], jnp.float32)) for k, p in rows]


def _play(rows):
    p = Rally(bounced=jnp.zeros(1, bool), hit=jnp.zeros(1, bool), outcome=jnp.zeros(1, jnp.int32),
              landing=jnp.zeros((1, 2), jnp.float32))
    for kind, pos in _events(*rows):
        p = advance(p, kind, pos, jnp.array(True))
    return p


@pytest.mark.parametrize("rows, outcome", [
    ([(ev.TABLE, (0.8, 0.1, 0.02)), (ev.RACKET, (1.6, 0.1, 0.3)), (ev.TABLE, (-0.9, 0.2, 0.02))], LEGAL),
    ([(ev.TABLE, (-0.9, 0.0, 0.02)), (ev.TABLE, (0.6, 0.0, 0.02)), (ev.RACKET, (1.5, 0.0, 0.3)),
      (ev.NET, (0.0, 0.0, 0.1)), (ev.TABLE, (-0.5, 0.0, 0.02))], NET),  # a serve, returned into the net
    ([(ev.RACKET, (1.5, 0.0, 0.3))], VOLLEY),
    ([(ev.TABLE, (0.8, 0.1, 0.02)), (ev.TABLE, (1.2, 0.1, 0.02))], MISS),
    ([(ev.TABLE, (0.8, 0.1, 0.02)), (ev.FLOOR, (2.0, 0.1, -0.74))], MISS),
    ([(ev.TABLE, (0.8, 0.1, 0.02)), (ev.RACKET, (1.6, 0.1, 0.3)), (ev.FLOOR, (-3.0, 0.0, -0.74))], OUT),
    ([(ev.TABLE, (0.8, 0.1, 0.02)), (ev.RACKET, (1.6, 0.1, 0.3)), (ev.TABLE, (0.5, 0.0, 0.02))], OUT),
    ([(ev.TABLE, (0.8, 0.1, 0.02)), (ev.RACKET, (1.6, 0.1, 0.3)), (ev.RACKET, (1.6, 0.1, 0.3))], OUT),
    ([(ev.TABLE, (0.8, 0.1, 0.02)), (ev.RACKET, (1.6, 0.1, 0.3))], RUNNING),
])
def test_rally_bookkeeping(rows, outcome):
    p = _play(rows)
    assert int(p.outcome[0]) == outcome
    if outcome == LEGAL:
        np.testing.assert_allclose(np.asarray(p.landing[0]), [-0.9, 0.2])
    # nothing after the end changes it
    later = advance(p, jnp.array([ev.TABLE]), jnp.array([[-0.5, 0.0, 0.02]], jnp.float32), jnp.array(True))
    if outcome != RUNNING:
        assert int(later.outcome[0]) == outcome


def test_racket_respects_its_limits_and_the_schedule_is_its_motion():
    limits = racket_kin.RacketLimits(
        lo=jnp.array([1.4, -1.0, 0.0]), hi=jnp.array([3.0, 1.0, 1.2]), max_speed=jnp.array(8.0),
        max_accel=jnp.array(80.0), angle_lo=jnp.array([-1.0, -0.8]), angle_hi=jnp.array([1.0, 0.8]),
        max_rate=jnp.array(15.0), max_angle_accel=jnp.array(600.0), face=jnp.array([0.0775, 0.0755]),
        table_x=jnp.array(1.37), table_z=jnp.array(0.0))
    state = racket_kin.RacketState(pos=jnp.array([2.0, 0.0, 0.3]), vel=jnp.zeros(3), angle=jnp.zeros(2),
                                   rate=jnp.zeros(2))
    period, n = 0.01, 10
    speeds = []
    command = jax.jit(racket_kin.command, static_argnums=(4,))
    for k in range(40):
        old = state
        state, sched, effort = command(limits, state, jnp.array([1.0, -1.0, 1.0, 1.0, -1.0]), period, n)
        # full acceleration: 80 m/s^2 over 10 ms is 0.8 m/s per period and axis, less only at the
        # speed limit; a coordinate stopped by a wall of the workspace stops
        at_wall = (np.asarray(state.pos) == np.asarray(limits.lo)) | (np.asarray(state.pos) == np.asarray(limits.hi))
        dv = np.abs(np.asarray(state.vel - old.vel))
        at_speed = np.abs(np.asarray(state.vel)) >= 8.0 - 1e-5
        assert np.all(dv[~at_wall] <= 0.8 + 1e-5) and np.all(np.asarray(state.vel)[at_wall] == 0.0)
        np.testing.assert_allclose(dv[~at_wall & ~at_speed], 0.8, atol=1e-5)
        assert np.all(np.abs(np.asarray(state.vel)) <= 8.0 + 1e-5)
        assert np.all(np.asarray(state.pos) >= np.asarray(limits.lo) - 1e-6)
        assert np.all(np.asarray(state.pos) <= np.asarray(limits.hi) + 1e-6)
        # the schedule moves at constant velocity per physics step and ends where the racket ends
        p, v = np.asarray(sched.pos[:, 0]), np.asarray(sched.vel[:, 0])
        np.testing.assert_allclose(p[1:], p[:-1] + v[:-1] * period / n, atol=1e-5)
        np.testing.assert_allclose(p[-1] + v[-1] * period / n, np.asarray(state.pos), atol=1e-5)
        assert 0.0 <= float(effort) <= 1.0 + 1e-6
        rot = np.asarray(sched.rot[0, 0])
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-5)
        speeds.append(float(np.abs(np.asarray(state.vel)).max()))
    assert max(speeds) == pytest.approx(8.0, abs=1e-4)  # it does reach its speed limit
    # it ended at the walls it was driven into (x, z at the top, y at the bottom), stopped there
    np.testing.assert_allclose(np.asarray(state.pos), [3.0, -1.0, 1.2], atol=1e-6)
    np.testing.assert_allclose(np.asarray(state.vel), 0.0, atol=1e-6)
    # at rest with zero angles the face looks at the opponent
    np.testing.assert_allclose(np.asarray(racket_kin.rotation(jnp.zeros(2)))[:, 0], [-1.0, 0.0, 0.0], atol=1e-7)


def _limits(lo_x, table_z):
    return racket_kin.RacketLimits(
        lo=jnp.array([lo_x, -1.0, 0.0]), hi=jnp.array([3.0, 1.0, 1.2]), max_speed=jnp.array(8.0),
        max_accel=jnp.array(80.0), angle_lo=jnp.array([-1.0, -0.8]), angle_hi=jnp.array([1.0, 0.8]),
        max_rate=jnp.array(15.0), max_angle_accel=jnp.array(600.0), face=jnp.array([0.0775, 0.0755]),
        table_x=jnp.array(1.37), table_z=jnp.array(table_z))


def test_workspace_over_the_table_keeps_the_face_above_it():
    """Driven forwards and down from behind the table, the racket goes over the table down to
    workspace_lo x, its face centre never below the table's surface plus the clearance there (but
    down to the box's floor behind the table), stopping its fall on that raised floor."""
    limits = _limits(0.6, 0.05)
    state = racket_kin.RacketState(pos=jnp.array([1.8, 0.0, 0.3]), vel=jnp.zeros(3), angle=jnp.zeros(2),
                                   rate=jnp.zeros(2))
    command = jax.jit(racket_kin.command, static_argnums=(4,))
    period, n = 0.01, 10
    lowest_behind, lowest_over = np.inf, np.inf
    for _ in range(40):
        state, sched, _ = command(limits, state, jnp.array([-1.0, 0.0, -1.0, 0.0, 0.0]), period, n)
        p, v = np.asarray(sched.pos[:, 0]), np.asarray(sched.vel[:, 0])
        for q in np.concatenate([p, np.asarray(state.pos)[None]]):
            if q[0] < 1.37:
                lowest_over = min(lowest_over, q[2])
            else:
                lowest_behind = min(lowest_behind, q[2])
        np.testing.assert_allclose(p[1:], p[:-1] + v[:-1] * period / n, atol=1e-5)  # still its motion
        np.testing.assert_allclose(p[-1] + v[-1] * period / n, np.asarray(state.pos), atol=1e-5)
    assert lowest_over >= 0.05 - 1e-6 and lowest_behind < 0.05  # the floor rises only over the table
    np.testing.assert_allclose(np.asarray(state.pos), [0.6, 0.0, 0.05], atol=1e-6)  # at the near wall, on the floor
    np.testing.assert_allclose(np.asarray(state.vel), 0.0, atol=1e-6)


@pytest.mark.parametrize("lo_x, table_z", [(1.4, 0.05), (0.6, 0.0)])
def test_workspace_configured_as_the_old_box_is_the_old_box(lo_x, table_z):
    """A box that stays behind the table's end, or a floor over the table no higher than the box's,
    clips exactly as the plain box [lo, hi] does."""
    limits = _limits(lo_x, table_z)
    pos = jax.random.uniform(jax.random.PRNGKey(0), (4096, 3), minval=jnp.array([0.0, -1.5, -0.5]),
                             maxval=jnp.array([3.5, 1.5, 1.5]))
    want = jnp.clip(pos, limits.lo, limits.hi)
    np.testing.assert_array_equal(np.asarray(racket_kin.clip_workspace(limits, pos)), np.asarray(want))
    # while a raised floor over a box reaching the table does clip differently
    raised = racket_kin.clip_workspace(_limits(0.6, 0.05), pos)
    assert (np.asarray(raised) != np.asarray(jnp.clip(pos, _limits(0.6, 0.05).lo, _limits(0.6, 0.05).hi))).any()


def test_start_below_the_clearance_over_the_table_is_refused():
    from ttsim_jax.env.return_ball import ReturnBall

    config = load_task_config(TASK, dict(OVERRIDES, **{"racket.workspace_lo": [0.6, -1.0, 0.0],
                                                       "racket.table_clearance": 0.05,
                                                       "racket.start": [1.0, 0.0, 0.02]}))
    with pytest.raises(ConfigError, match=r"return_ball_accel.toml: \[racket\] start = \[1.0, 0.0, 0.02\] .*table_clearance"):
        ReturnBall(config, 2).default_params()


def test_a_target_drawn_per_episode_must_be_observed_and_lie_on_the_opponents_half():
    """``[reward] target_spread`` draws each episode's target: refused unless the policy observes it,
    with a negative half-width, and where the box reaches past the opponent's half (at the
    parameters, which know the table); the bundled goal task loads and names its two entries."""
    from ttsim_jax.env.return_ball import ReturnBall

    with pytest.raises(ConfigError, match=r"return_ball_accel.toml: \[reward\] target_spread = \[0.2, 0.2\] .*"
                                          r"\[observation\] target = true"):
        load_task_config(TASK, {"reward.target_spread": [0.2, 0.2]})
    with pytest.raises(ConfigError, match=r"\[reward\] target_spread = \[-0.1, 0.2\]: must not be negative"):
        load_task_config(TASK, {"reward.target_spread": [-0.1, 0.2], "observation.target": True})
    for point, spread in (([-0.9, 0.0], [1.0, 0.0]), ([-0.2, 0.0], [0.3, 0.0]), ([-0.9, 0.5], [0.0, 0.3])):
        config = load_task_config(TASK, dict(OVERRIDES, **{"reward.target_point": point, "reward.target_spread": spread,
                                                           "observation.target": True}))
        with pytest.raises(ConfigError, match=r"return_ball_accel.toml: \[reward\] target_point = .* reaches beyond "
                                              r"the opponent's half"):
            ReturnBall(config, 2).sizing_params()
    goal = ReturnBall(load_task_config("return_ball_goal", {"shots.bank": 8, "shots.aim": False}), 2)
    assert goal.observation_names[-2:] == ("target.x", "target.y") and goal.obs_dim == 35
    assert goal.config.reward.target_spread == (0.45, 0.55)


def test_sizing_params_have_the_drawn_parameters_shapes_without_drawing_the_bank(monkeypatch):
    """What a job is sized by before it is refused (``rl.training.memory_bytes``): the parameters'
    shapes and dtypes, without drawing or aiming the shot bank (20 s and more on a cold cache)."""
    env = return_ball.ReturnBall(load_task_config(TASK, OVERRIDES), 4)

    def no_bank(*args):
        raise AssertionError("the shot bank was drawn")

    monkeypatch.setattr(return_ball, "shot_bank", no_bank)
    sized = env.sizing_params()
    monkeypatch.undo()
    drawn = env.default_params()
    shape = lambda tree: jax.tree.map(lambda a: (jnp.shape(a), jnp.result_type(a)), tree)  # noqa: E731
    assert shape(sized) == shape(drawn)
    assert sized.shots.vel.shape[0] == OVERRIDES["shots.bank"] and float(jnp.abs(drawn.shots.vel).max()) > 1.0
    assert env.sizing_params() is drawn  # once drawn, the real ones


def test_angular_velocity_is_the_rotation_rate():
    angle, rate, h = jnp.array([0.3, -0.4]), jnp.array([2.0, -5.0]), 1e-4
    r0, r1 = (np.asarray(racket_kin.rotation(a), np.float64) for a in (angle, angle + h * rate))
    skew = (r1 - r0) / h @ r0.T
    omega = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
    np.testing.assert_allclose(omega, np.asarray(racket_kin.angular_velocity(angle, rate)), atol=2e-2)


@pytest.mark.parametrize("overrides, message", [
    ({"shots.max_speed": -1.0}, "max_speed"),
    ({"racket.workspace_lo": [1.4, 2.0, 0.0]}, "workspace_lo"),
    ({"control.rate_hz": 300.0}, "whole number"),
    ({"reward.bogus": 1.0}, "bogus"),
    ({"shots.types": ["serve", "tomahawk"]}, "tomahawk"),
    ({"randomisation.table.e0": [0.9, 0.8]}, "low must not exceed high"),
    ({"control.action": "torque"}, r"\[control\] action = 'torque': expected one of \['accel', 'intercept'\]"),
    ({"control.action": 1}, r"\[control\] action = 1: expected a string"),
    ({"intercept.flight_time": [0.8, 0.3]}, r"\[intercept\] flight_time"),
    ({"intercept.omega": 0.0}, r"\[intercept\] omega = 0.0: must be positive"),
    ({"observation.latency_steps": -1}, r"\[observation\] latency_steps = -1: must not be negative"),
    ({"observation.latency_steps": 1.5}, r"\[observation\] latency_steps = 1.5: expected an integer"),
    ({"racket.table_clearance": -0.1}, r"\[racket\] table_clearance = -0.1: must not be negative"),
    ({"racket.workspace_lo": [-0.2, -1.0, 0.0]}, r"\[racket\] workspace_lo = \[-0.2, -1.0, 0.0\]: x must be positive"),
    ({"intercept.min_height": "low"}, r"\[intercept\] min_height = 'low': expected a finite number"),
    ({"intercept.bounce": "spin"}, r"\[intercept\] bounce = 'spin': expected one of \['plain', 'model'\]"),
    ({"intercept.magnus": 1}, r"\[intercept\] magnus = 1: expected true or false"),
    ({"intercept.air": "on"}, r"\[intercept\] air = 'on': expected true or false"),
    ({"observation.plan": "yes"}, r"\[observation\] plan = 'yes': expected true or false"),
    ({"randomisation.table.e0": {"mean": 0.95, "std": -0.01}}, r"\[randomisation\] 'table.e0': std = -0.01"),
    ({"randomisation.table.e0": {"mean": 0.95}}, r"'table.e0' = \{'mean': 0.95\}: expected \[low, high\]"),
    ({"randomisation.table.e0": {"fit": "nope.fit.json"}}, r"'table.e0'.fit = 'nope.fit.json': cannot read"),
    ({"randomisation.aero.rho_air": {"fit": "x.fit.json"}}, r"'aero.rho_air': `ttsim fit` gives no standard error"),
])
def test_bad_task_file_is_refused_naming_file_and_key(overrides, message):
    with pytest.raises(ConfigError, match=message) as info:
        load_task_config(TASK, overrides)
    assert "return_ball_accel.toml" in str(info.value)


def test_a_renamed_bundled_task_is_refused_naming_its_new_name():
    with pytest.raises(ConfigError, match=r"return_ball_intercept.toml: no such task file \(bundled tasks: "
                                          r"return_ball, return_ball_accel, .*; return_ball_intercept is now return_ball\)"):
        load_task_config("return_ball_intercept")


def test_unknown_randomised_parameter_is_refused():
    from ttsim_jax.env.return_ball import ReturnBall

    config = load_task_config(TASK, dict(OVERRIDES, **{"randomisation.table.bounciness": [0.1, 0.2]}))
    with pytest.raises(ConfigError, match="bounciness"):
        ReturnBall(config, 2).default_params()


def test_latency_shows_the_ball_as_it_was_that_many_steps_ago():
    """With ``latency_steps = 2`` the observed ball (position, velocity, spin) is the true ball two
    control steps earlier (the reset's ball until then), while the racket part is current."""
    from ttsim_jax.env.return_ball import ReturnBall

    env = ReturnBall(load_task_config(TASK, dict(OVERRIDES, **{"observation.latency_steps": 2})), N)
    params = env.default_params()
    key = jax.random.PRNGKey(3)
    obs, state = jit_reset(env, key, params)
    balls, racket_obs = [state.rally.ball], []
    action = jnp.tile(jnp.array([[-0.5, 0.3, 0.2, 0.1, -0.1]]), (N, 1))
    for i in range(4):
        obs, state, *_ = jit_step(env, jax.random.fold_in(key, i), state, action, params)
        balls.append(state.rally.ball)
        np.testing.assert_allclose(np.asarray(obs[:, 9:12]), np.asarray(state.racket.pos), atol=1e-6)
        racket_obs.append(obs)
    for i, o in enumerate(racket_obs, start=1):  # observation after step i shows the ball after step i - 2
        seen = balls[max(i - 2, 0)]
        want = np.concatenate([seen.pos, np.asarray(seen.vel) / 10.0, np.asarray(seen.spin) / 300.0], -1)
        np.testing.assert_allclose(np.asarray(o[:, :9]), want, rtol=1e-6, atol=1e-6)
    assert not np.allclose(np.asarray(balls[4].pos), np.asarray(balls[2].pos))  # the ball moved meanwhile


def test_the_observation_names_point_at_what_they_name(vec, run):
    env = vec.env
    names = env.observation_names
    assert len(names) == len(env.observation_fields) == env.obs_dim == 25 and len(set(names)) == len(names)
    state, out = run[3]
    obs = np.asarray(env.observe(state))
    seen, rk = env.seen_ball(state), state.racket
    col = names.index
    np.testing.assert_allclose(obs[:, col("ball.pos.z")], np.asarray(seen.pos[:, 2]), atol=1e-6)
    np.testing.assert_allclose(obs[:, col("ball.vel.x")] * 10.0, np.asarray(seen.vel[:, 0]), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(obs[:, col("ball.spin.y")] * 300.0, np.asarray(seen.spin[:, 1]), rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(obs[:, col("racket.pos.y")], np.asarray(rk.pos[:, 1]), atol=1e-6)
    np.testing.assert_allclose(obs[:, col("racket.yaw_rate")] * 10.0, np.asarray(rk.rate[:, 1]), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(obs[:, col("time")], np.asarray(state.t) * env.period, atol=1e-6)
    assert dict(env.observation_fields)["ball.vel.x"] == "10 m/s"


@pytest.mark.parametrize("spin, plan", [(False, False), (True, True)])
def test_the_observation_names_follow_the_observation_settings(spin, plan):
    import dataclasses

    cfg = load_task_config(TASK, OVERRIDES)
    cfg = dataclasses.replace(cfg, observation=dataclasses.replace(cfg.observation, spin=spin, plan=plan))
    env = return_ball.ReturnBall(cfg, 2)
    assert len(env.observation_names) == env.obs_dim
    assert ("ball.spin.x" in env.observation_names) == spin and ("plan.exists" in env.observation_names) == plan


def test_the_shot_type_codes_name_the_tasks_types(vec, run):
    env = vec.env
    assert env.shot_type_names == tuple(load_task_config(TASK, OVERRIDES).shots.types)
    codes = np.concatenate([np.asarray(out[5]["shot_type"]) for _, out in run])
    assert codes.min() >= 0 and codes.max() < len(env.shot_type_names)
    assert OUTCOME_NAMES[LEGAL] == "legal" and OUTCOME_NAMES[RUNNING] == "running"


def test_a_bank_too_large_to_draw_is_refused_before_it_is_drawn():
    """An aimed bank's drawing holds about 0.6 MB a shot (``bank.AIM_BYTES_PER_SHOT``, measured):
    10^8 shots are refused with the estimate, as the library builds the parameters (gymnasium's
    ``make``, ``ttsim train``), before anything is drawn; an unaimed bank costs far less a shot."""
    from ttsim_jax.env import bank
    from ttsim_jax.sizes import SizeError

    huge = load_task_config("return_ball", {"shots.bank": 10**8})
    assert bank.bank_bytes(huge) == 10**8 * bank.AIM_BYTES_PER_SHOT
    with pytest.raises(SizeError, match=r"\[shots\] bank = 100000000 \(aimed through the model\) needs about"):
        return_ball.ReturnBall(huge, 2).default_params()
    unaimed = load_task_config("return_ball", {"shots.bank": 10**8, "shots.aim": False})
    assert bank.bank_bytes(unaimed) < bank.bank_bytes(huge) / 100


def test_the_unknown_rubber_task_is_the_default_task_with_a_rubber_the_tracker_does_not_plan_with():
    # examples/ppo_gymnasium.py starts on this task; it must stay the default task but for the rubber
    import dataclasses

    base = load_task_config("return_ball")
    rubber = load_task_config("return_ball_unknown_rubber")
    assert rubber.racket_config == "racket_05" and rubber.intercept.racket_known is False
    same = dataclasses.replace(rubber, racket_config="", source=base.source,
                               intercept=dataclasses.replace(rubber.intercept, racket_known=True))
    assert same == base
