"""The single-environment functional form (gymnax's shape): vmapped by the user, each environment
follows its own key exactly as the batched environment of one does, and the whole-loop-jit example
runs.

Shapes: the "accel" task with 32 unaimed shots, as ``test_gym.py`` (its one-environment step
without reset is the reference here), vmapped over 2 environments.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax.env import SingleReturnBall, load_task_config
from ttsim_jax.env.return_ball import ReturnBall, jit_reset, jit_step_env
from ttsim_jax.env.single import batch, unbatch

TASK = "return_ball_accel"
OVERRIDES = {"shots.bank": 32, "shots.aim": False}


@pytest.fixture(scope="module")
def env():
    return SingleReturnBall(load_task_config(TASK, OVERRIDES))


def test_vmapped_steps_follow_each_environments_key_as_the_batched_form(env):
    """``jax.vmap(env.reset)`` and ``jax.vmap(env.step_env)`` over two keys give, for each
    environment, what the batched environment of one gives with that key: observation, reward,
    flags and state."""
    params = env.default_params()
    keys = jax.random.split(jax.random.PRNGKey(4), 2)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    assert obs.shape == (2, env.obs_dim) and state.t.shape == (2,) and state.rally.step.shape == (2,)
    one = ReturnBall(env.config, 1, reference=True)
    assert one == env.batched
    for i in range(2):
        o, s = jit_reset(one, keys[i], params)
        np.testing.assert_array_equal(np.asarray(obs[i]), np.asarray(o[0]))
        assert int(state.shot[i]) == int(s.shot[0])
    assert int(state.shot[0]) != int(state.shot[1]) or not np.array_equal(obs[0], obs[1])
    action = jnp.array([[0.5, -0.3, 0.2, 0.1, -0.1], [-0.4, 0.6, -0.2, 0.0, 0.3]], jnp.float32)
    vstep = jax.jit(jax.vmap(env.step_env, in_axes=(0, 0, 0, None)))
    for k in range(3):
        step_keys = jax.vmap(lambda key: jax.random.fold_in(key, k))(keys)
        before = state
        obs, state, reward, terminated, truncated, info = vstep(step_keys, before, action, params)
        for i in range(2):
            mine = jax.tree.map(lambda a: a[i], before)
            want = jit_step_env(one, step_keys[i], batch(mine), action[i][None], params)
            np.testing.assert_allclose(np.asarray(obs[i]), np.asarray(want[0][0]), rtol=1e-5, atol=1e-6)
            assert float(reward[i]) == pytest.approx(float(want[2][0]), rel=1e-5, abs=1e-7)
            assert bool(terminated[i]) == bool(want[3][0]) and bool(truncated[i]) == bool(want[4][0])
            np.testing.assert_allclose(np.asarray(state.racket.pos[i]), np.asarray(want[1].racket.pos[0]), atol=1e-6)
    assert not np.allclose(np.asarray(state.racket.pos[0]), np.asarray(state.racket.pos[1]))  # their own actions


def test_batch_and_unbatch_are_inverse_and_keep_the_kernels_clock(env):
    params = env.default_params()
    _, state = jax.eval_shape(lambda k: env.batched.reset(k, params), jax.random.PRNGKey(0))
    one = jax.eval_shape(unbatch, state)
    assert one.t.shape == () and one.rally.ball.pos.shape == (3,) and one.rally.step.shape == ()
    again = jax.eval_shape(batch, one)
    assert jax.tree.map(lambda a: a.shape, again) == jax.tree.map(lambda a: a.shape, state)


def test_a_batched_action_is_refused_naming_the_shape(env):
    params = env.default_params()
    _, state = jax.eval_shape(lambda k: env.reset(k, params), jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"action of shape \(2, 5\): expected \(5,\), one environment's action "
                                         r"\(vmap the step for a batch\)"):
        jax.eval_shape(lambda s: env.step(jax.random.PRNGKey(0), s, jnp.zeros((2, 5)), params), state)
    with pytest.raises(ValueError, match=r"action of shape \(3, 4\): expected \(3, 5\)"):
        batched = ReturnBall(env.config, 3)
        _, s3 = jax.eval_shape(lambda k: batched.reset(k, params), jax.random.PRNGKey(0))
        jax.eval_shape(lambda s: batched.step_env(jax.random.PRNGKey(0), s, jnp.zeros((3, 4)), params), s3)


def test_whole_loop_jit_example_runs(example, capsys):
    out = example("functional_loop").main(["--task", TASK, "--bank", "32", "--num-envs", "2", "--steps", "4"])
    assert out["env_steps_per_s"] > 0 and np.isfinite(out["mean_reward"])
    assert "2 environments x 4 steps" in capsys.readouterr().out


def test_a_gymnax_style_loop_runs_from_make():
    from ttsim_jax.env import make

    env, params = make("ReturnBall-v0", task=load_task_config(TASK, OVERRIDES))
    assert env == SingleReturnBall(load_task_config(TASK, OVERRIDES))
    obs_space, act_space = env.observation_space(params), env.action_space(params)
    assert obs_space.shape == (env.obs_dim,) == (len(env.observation_names),) and act_space.shape == (5,)
    # vmapped over two environments as the first test: the same programs (the compilation cache has them)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    step = jax.jit(jax.vmap(env.step_env, in_axes=(0, 0, 0, None)))
    total = 0.0
    for i in range(4):
        k_act, k_step = jax.random.split(jax.random.fold_in(keys[0], i))
        action = jax.random.uniform(k_act, (2,) + act_space.shape, minval=act_space.low, maxval=act_space.high)
        obs, state, reward, terminated, truncated, info = step(jax.random.split(k_step, 2), state, action, params)
        assert all(obs_space.contains(np.asarray(o)) for o in obs) and np.isfinite(np.asarray(reward)).all()
        total += float(np.sum(reward))
    assert np.isfinite(total)
    with pytest.raises(ValueError, match="ReturnBall-v0"):
        make("CartPole-v1")
