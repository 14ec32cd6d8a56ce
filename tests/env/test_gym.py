"""Gymnasium adapters and registration: ``gymnasium.make`` / ``make_vec`` of ``ttsim/ReturnBall-v0``
and gymnasium's environment checker on the single environment (one compiled shape: one env)."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import ttsim_jax  # noqa: F401  (registers the environments)
from ttsim_jax.env.gym import ReturnBallEnv, ReturnBallVectorEnv

TASK = "return_ball_accel"
OVERRIDES = {"shots.bank": 32, "shots.aim": False}


@pytest.fixture(scope="module")
def env():
    return gymnasium.make("ttsim/ReturnBall-v0", task=TASK, overrides=OVERRIDES, render_mode="rgb_array")


def test_registered_on_import():
    spec = gymnasium.spec("ttsim/ReturnBall-v0")
    assert spec.entry_point == "ttsim_jax.env.gym:ReturnBallEnv"
    assert spec.vector_entry_point == "ttsim_jax.env.gym:ReturnBallVectorEnv"


def test_single_env_passes_gymnasiums_checker(env):
    assert isinstance(env.unwrapped, ReturnBallEnv)
    check_env(env.unwrapped)  # with its render check (rgb_array)


def test_single_env_episode_ends_and_reports_its_outcome(env):
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    for _ in range(env.unwrapped.env.max_steps):
        obs, reward, terminated, truncated, info = env.step(np.zeros(5, np.float32))
        assert env.observation_space.contains(obs) and np.isfinite(reward)
        if terminated or truncated:
            break
    assert terminated or truncated
    assert info["outcome"] != 0 or truncated
    with pytest.raises(gymnasium.error.ResetNeeded):
        ReturnBallEnv(task=TASK, overrides=OVERRIDES).step(np.zeros(5, np.float32))


def test_single_env_renders_its_rally_for_recording(env):
    """``render_mode="rgb_array"``: one uint8 frame per call, the ball's path growing with the
    episode; the same seed draws the same first frame; gymnasium's RecordVideo wrapper accepts it."""
    assert env.metadata["render_fps"] == env.unwrapped.env.config.control.rate_hz
    env.reset(seed=3)
    first = env.render()
    assert first.shape == (560, 640, 3) and first.dtype == np.uint8
    for _ in range(30):
        env.step(np.zeros(5, np.float32))
    later = env.render()
    assert not np.array_equal(later, first)
    assert len(env.unwrapped._trails.paths[0]) == 31
    env.reset(seed=3)
    np.testing.assert_array_equal(env.render(), first)
    assert ReturnBallEnv(task=TASK, overrides=OVERRIDES).render() is None  # no render mode, no frame
    with pytest.raises(ValueError, match="render_mode"):
        ReturnBallEnv(task=TASK, overrides=OVERRIDES, render_mode="human")


def test_make_vec_builds_the_batched_env_with_batched_spaces():
    vec = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=4096, task=TASK, overrides=OVERRIDES,
                             render_mode="rgb_array", render_envs=2)
    assert isinstance(vec, ReturnBallVectorEnv) and vec.num_envs == 4096
    assert vec.render_mode == "rgb_array" and vec._trails.n == 2 and vec.metadata["render_fps"] == 100.0
    with pytest.raises(gymnasium.error.ResetNeeded):
        vec.render()
    with pytest.raises(ValueError, match="render_envs"):
        ReturnBallVectorEnv(4, task=TASK, overrides=OVERRIDES, render_mode="rgb_array", render_envs=5)
    assert vec.observation_space.shape == (4096, 25) and vec.action_space.shape == (4096, 5)
    assert vec.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.SAME_STEP
    assert vec.env.reference is False  # large batches step the kernel's lean path
