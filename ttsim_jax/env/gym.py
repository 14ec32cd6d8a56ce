"""Gymnasium adapters of the functional :class:`~ttsim_jax.env.return_ball.ReturnBall`.

:class:`ReturnBallVectorEnv` steps all its environments in one jitted call (reset of finished
environments included: autoreset mode ``SAME_STEP``, declared in ``metadata``);
:class:`ReturnBallEnv` is one environment (gymnasium's ``Env``, no automatic reset).
Both return numpy arrays.
"""

from __future__ import annotations

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import ReturnBall, jit_reset, jit_step, jit_step_env
from ttsim_jax.env.spaces import action_space, observation_space


def _key(rng: np.random.Generator):
    """A raw PRNG key (uint32 pair) drawn on the host: no device call beside the step itself."""
    return rng.integers(0, 2**32, size=2, dtype=np.uint32)


def _host(info: dict) -> dict:
    return {k: np.asarray(v) for k, v in info.items()}


class ReturnBallVectorEnv(gymnasium.vector.VectorEnv):
    """``num_envs`` ReturnBall environments stepped by one jitted call.

    Arguments:
        num_envs: number of environments.
        task: task file or bundled task name (default ``return_ball``).
        overrides: ``{"section.key": value}`` on top of the task file (e.g. ``{"shots.bank": 256}``).
        block_size: the kernel's block size (default: its own choice).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, task=None, overrides: dict | None = None, block_size: int | None = None):
        self.env = ReturnBall(load_task_config(task, overrides), num_envs, block_size)
        self.params = self.env.default_params()
        self.num_envs = self.env.num_envs
        self.single_observation_space = observation_space(self.env)
        self.single_action_space = action_space(self.env)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._state = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Starts every environment afresh; returns (obs (N, D), info)."""
        if seed is not None:
            self._np_random, self._np_random_seed = seeding.np_random(seed)
            self.action_space.seed(seed)
        obs, self._state = jit_reset(self.env, _key(self.np_random), self.params)
        return np.asarray(obs), {}

    def step(self, actions):
        """One control step of every environment; finished ones restart in the same step.

        Returns:
            (obs, reward, terminated, truncated, info) as numpy arrays; ``info["final_obs"]`` (N, D)
            is the last observation of the environments that finished (``info["_final_obs"]``).
        """
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        obs, self._state, reward, terminated, truncated, info = jit_step(
            self.env, _key(self.np_random), self._state, np.asarray(actions, np.float32), self.params)
        info = _host(info)
        terminated, truncated = np.asarray(terminated), np.asarray(truncated)
        info["_final_obs"] = terminated | truncated
        return np.asarray(obs), np.asarray(reward), terminated, truncated, info


class ReturnBallEnv(gymnasium.Env):
    """One ReturnBall environment (gymnasium ``Env``); arguments as :class:`ReturnBallVectorEnv`."""

    metadata = {"render_modes": []}

    def __init__(self, task=None, overrides: dict | None = None):
        self.env = ReturnBall(load_task_config(task, overrides), 1)
        self.params = self.env.default_params()
        self.observation_space = observation_space(self.env)
        self.action_space = action_space(self.env)
        self._state = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, self._state = jit_reset(self.env, _key(self.np_random), self.params)
        return np.asarray(obs[0]), {}

    def step(self, action):
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        obs, self._state, reward, terminated, truncated, info = jit_step_env(
            self.env, _key(self.np_random), self._state, np.asarray(action, np.float32)[None], self.params)
        info = {k: v[0] for k, v in _host(info).items()}
        return np.asarray(obs[0]), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info
