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


def test_the_spec_holds_the_tasks_episode_length_and_no_time_limit_is_added(env):
    """``env.spec.max_episode_steps`` is the task's (the environment truncates there itself), for
    the single and the vector form, and no TimeLimit wrapper duplicates it."""
    steps = env.unwrapped.env.max_steps
    assert steps > 0 and env.spec.max_episode_steps == steps == env.unwrapped.spec.max_episode_steps
    wrapper, chain = env, []
    while isinstance(wrapper, gymnasium.Wrapper):
        chain.append(type(wrapper).__name__)
        wrapper = wrapper.env
    assert "TimeLimit" not in chain, chain
    vec = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=2, task=TASK, overrides=OVERRIDES)
    assert vec.spec.max_episode_steps == steps
    vec.close()
    again = gymnasium.make(env.spec)  # made again from its spec: a time limit at the same step, harmless
    assert again.spec.max_episode_steps == steps
    again.close()


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
    assert vec.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    same = ReturnBallVectorEnv(4, task=TASK, overrides=OVERRIDES, autoreset_mode="SameStep")
    assert same.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.SAME_STEP
    assert vec.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP  # set per instance
    with pytest.raises(ValueError, match="autoreset_mode must be AutoresetMode.NEXT_STEP or SAME_STEP"):
        ReturnBallVectorEnv(4, task=TASK, overrides=OVERRIDES, autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED)
    assert vec.env.reference is False  # large batches step the kernel's lean path


def test_a_second_environment_of_the_same_task_compiles_nothing(env):
    """Environments are equal by their settings, so a second ``gymnasium.make`` of the same task, and
    gymnasium's sync vector environment of such copies, run the programs the first one compiled:
    no compilation (counted by JAX's compile events and the jitted functions' caches)."""
    import jax

    from ttsim_jax.env import return_ball

    env.reset(seed=0)
    env.step(np.zeros(5, np.float32))
    programs = (return_ball._reset, return_ball._step_env)
    sizes = [f._cache_size() for f in programs]
    compiles = []

    def listen(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        second = gymnasium.make("ttsim/ReturnBall-v0", task=TASK, overrides=OVERRIDES)
        second.reset(seed=1)
        second.step(np.zeros(5, np.float32))
        sync = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=2, vectorization_mode="sync", task=TASK,
                                  overrides=OVERRIDES)
        sync.reset(seed=2)
        sync.step(np.zeros((2, 5), np.float32))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiles == []
    assert [f._cache_size() for f in programs] == sizes
    assert second.unwrapped.env == env.unwrapped.env and second.unwrapped.env is not env.unwrapped.env
    other = ReturnBallEnv(task=TASK, overrides=dict(OVERRIDES, **{"reward.motion": 0.5}))
    assert other.env != env.unwrapped.env and hash(other.env) != hash(env.unwrapped.env)


def test_actions_are_checked_naming_the_space(env):
    from ttsim_jax.env.gym import ActionError

    env.reset(seed=0)
    with pytest.raises(ActionError, match=r"action of shape \(4,\): the action space is Box\(-1.0, 1.0, \(5,\)"):
        env.step(np.zeros(4, np.float32))
    with pytest.raises(ActionError, match=r"action of shape \(1, 5\)"):
        env.step(np.zeros((1, 5), np.float32))
    with pytest.raises(ActionError, match=r"the action holds NaN or infinite values: \[0.0, nan, 0.0, 0.0, 0.0\]"):
        env.step(np.array([0.0, np.nan, 0.0, 0.0, 0.0]))
    with pytest.raises(ActionError, match="dtype"):
        env.step(np.array(["a"] * 5))
    assert isinstance(ActionError("x"), ValueError)


def test_stable_baselines3_checker_accepts_the_single_env(env):
    checker = pytest.importorskip("stable_baselines3.common.env_checker",
                                  reason="stable_baselines3 is not installed (not a dependency)")
    checker.check_env(env.unwrapped, warn=True, skip_render_check=True)


def test_making_an_environment_turns_the_compilation_cache_on_unless_told_not_to(tmp_path):
    """A library user's process gets the persistent compilation cache when it makes an environment,
    in the folder ``TTSIM_COMPILE_CACHE`` names, and none with ``TTSIM_COMPILE_CACHE=off``, as the
    ``ttsim`` commands (a child process each: the cache is a process setting)."""
    import os
    import subprocess
    import sys

    code = ("import jax\nfrom ttsim_jax.env import ReturnBall\nbefore = jax.config.jax_compilation_cache_dir\n"
            "ReturnBall('return_ball_accel', 1)\nprint(before, jax.config.jax_compilation_cache_dir)")
    base = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "TTSIM_COMPILE_CACHE")}
    for setting, want in ((str(tmp_path / "cc"), str(tmp_path / "cc")), ("off", "None")):
        run = subprocess.run([sys.executable, "-c", code], env=dict(base, TTSIM_COMPILE_CACHE=setting),
                             capture_output=True, text=True, check=True)
        assert run.stdout.split() == ["None", want]
