"""ReturnBall behind brax's ``Env`` contract: a step is the single environment's step, brax's
training wrapper batches it, ours restarts finished environments with new shots, and brax's PPO
trains it unmodified. Skipped where brax is not installed (it is not a dependency).

Shapes: the "accel" task with 32 unaimed shots, as ``test_single.py``.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("brax", reason="brax is not installed (not a dependency of ttsim-jax: pip install brax)")

from brax.envs.wrappers import training as brax_training  # noqa: E402

from ttsim_jax.env import load_task_config  # noqa: E402
from ttsim_jax.env.brax_env import BraxReturnBall, wrap_for_training  # noqa: E402

TASK = "return_ball_accel"
OVERRIDES = {"shots.bank": 32, "shots.aim": False}
N = 8


@pytest.fixture(scope="module", autouse=True)
def float32():
    """brax's agents compute in float32 (its GAE scan mixes the value net's float32 with the
    rewards), so this module runs without the suite's ``jax_enable_x64``, as brax users do."""
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", False)
    yield
    jax.config.update("jax_enable_x64", before)


@pytest.fixture(scope="module")
def env(float32):
    return BraxReturnBall(load_task_config(TASK, OVERRIDES))


def test_a_step_is_the_single_environments_step(env):
    """``reset`` and ``step`` give brax's State whose observation, reward and termination are the
    single environment's with the key the state carries; the sizes are brax's."""
    assert env.observation_size == env.single.obs_dim == len(env.observation_names) and env.action_size == 5
    state = jax.jit(env.reset)(jax.random.PRNGKey(3))
    assert state.obs.shape == (env.observation_size,) and float(state.done) == 0.0
    action = jnp.full((5,), 0.3, jnp.float32)
    nxt = jax.jit(env.step)(state, action)
    _, key = jax.random.split(state.info["rng"])
    obs, _, reward, terminated, _, info = jax.jit(env.single.step_env)(key, state.pipeline_state, action, env.params)
    np.testing.assert_array_equal(np.asarray(nxt.obs), np.asarray(obs))
    # two programs: the reward's float32 sum may round differently
    assert float(nxt.reward) == pytest.approx(float(reward), rel=1e-6) and float(nxt.done) == float(terminated)
    assert float(nxt.metrics["legal"]) == float(info["legal"])
    assert not np.array_equal(np.asarray(nxt.info["rng"]), np.asarray(state.info["rng"]))  # a new key each step


def _run_until_every_env_finished(wrapped, steps):
    state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(0), N))
    first_shot = np.asarray(state.pipeline_state.shot)

    def body(s, _):
        before = s.pipeline_state.shot
        s = wrapped.step(s, jnp.zeros((N, 5), jnp.float32))
        return s, (s.done, before, s.pipeline_state.shot, s.pipeline_state.t)

    _, (done, before, after, t) = jax.jit(lambda s: jax.lax.scan(body, s, None, length=steps))(state)
    return first_shot, np.asarray(done) > 0, np.asarray(after), np.asarray(t)


def test_our_wrapper_restarts_a_finished_environment_with_a_new_shot_brax_s_replays_the_first(env):
    """Over ``max_steps`` steps every environment finishes at least once; after each finish ours
    starts a new episode (step 0) whose shot is drawn afresh (so over the finishes not all are the
    environment's first), brax's own wrapper restarts every one with its first shot."""
    steps = env.max_steps + 2
    for wrap, replays in ((wrap_for_training, False), (brax_training.wrap, True)):
        first, done, shot, t = _run_until_every_env_finished(wrap(env, episode_length=env.max_steps), steps)
        assert done.any(axis=0).all()
        assert (t[done] == 0).all()  # a finished environment starts afresh
        same = shot[done] == np.broadcast_to(first, done.shape)[done]
        assert same.all() == replays, wrap


def test_brax_ppo_trains_it_unmodified(env):
    """brax's PPO trainer runs on the environment for a few iterations with our wrapper and reports
    finite episode metrics, the legal-return rate among them."""
    from brax.training.agents.ppo import train as ppo

    seen = []
    _, params, metrics = ppo.train(
        environment=env, num_timesteps=2 * N * 5 * 2, episode_length=env.max_steps, wrap_env_fn=wrap_for_training,
        num_envs=N, batch_size=N, num_minibatches=1, unroll_length=5, num_updates_per_batch=1, num_evals=2,
        num_eval_envs=N, seed=1, progress_fn=lambda step, m: seen.append((step, dict(m))))
    assert len(seen) == 2 and seen[-1][0] > 0
    assert "eval/episode_legal" in metrics and np.isfinite(float(metrics["eval/episode_legal"]))
    assert all(np.isfinite(np.asarray(leaf)).all() for leaf in jax.tree.leaves(params))
