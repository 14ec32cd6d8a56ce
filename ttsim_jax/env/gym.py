"""Gymnasium adapters of the functional :class:`~ttsim_jax.env.return_ball.ReturnBall`.

:class:`ReturnBallVectorEnv` steps all its environments in one jitted call (reset of finished
environments included: autoreset mode ``SAME_STEP``, declared in ``metadata``);
:class:`ReturnBallEnv` is one environment (gymnasium's ``Env``, no automatic reset).
Both return numpy arrays.

Both render with ``render_mode="rgb_array"`` (:mod:`.render`: the ball's path this episode and the
racket face over the table, from above and from the side): ``render()`` returns an (H, W, 3) uint8
frame, a tuple of them from the vector environment (its first ``render_envs`` environments), so
gymnasium's ``RecordVideo`` and ``HumanRendering`` wrappers work on the single environment.
"""

from __future__ import annotations

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

import jax

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import ReturnBall, jit_reset, jit_step, jit_step_env
from ttsim_jax.env.spaces import action_space, observation_space


def _key(rng: np.random.Generator):
    """A raw PRNG key (uint32 pair) drawn on the host: no device call beside the step itself."""
    return rng.integers(0, 2**32, size=2, dtype=np.uint32)


def _host(info: dict) -> dict:
    return {k: np.asarray(v) for k, v in info.items()}


def _render_mode(mode, modes):
    if mode is not None and mode not in modes:
        raise ValueError(f"render_mode must be one of {modes} or None, got {mode!r}")
    return mode


class _Trails:
    """The first ``n`` environments' ball paths on the host, for :class:`~ttsim_jax.env.render.RallyFrames`.

    Only what a frame shows leaves the device: n balls' and rackets' positions per step.
    """

    def __init__(self, env, params, n: int):
        from ttsim_jax.env.render import RallyFrames, rotations

        self.rotations = rotations
        self.env, self.n = env, n
        table = params.model.table
        self.frames = RallyFrames(np.asarray(params.limits.face), float(table.length), float(table.width))
        self.paths = [[] for _ in range(n)]
        self.now = None

    def update(self, state, restart=None):
        """Appends the balls of ``state``; environments where ``restart`` (N,) is set (all when None)
        start a new path."""
        n = self.n
        first = lambda tree: jax.tree.map(lambda a: a[:n], tree)  # noqa: E731
        ball, rk, progress, t = jax.device_get(first((state.rally.ball.pos, state.racket, state.progress, state.t)))
        for i in range(n):
            if restart is None or restart[i]:
                self.paths[i] = []
            self.paths[i].append(ball[i])
        self.now = (rk.pos, self.rotations(rk.angle), progress, t)

    def draw(self):
        from ttsim_jax.env.render import progress_text

        pos, rot, p, t = self.now
        return tuple(self.frames.frame(np.stack(self.paths[i]), pos[i], rot[i],
                                       progress_text(float(t[i]) * self.env.period, bool(p.bounced[i]),
                                                     bool(p.hit[i]), int(p.outcome[i])))
                     for i in range(self.n))


class ReturnBallVectorEnv(gymnasium.vector.VectorEnv):
    """``num_envs`` ReturnBall environments stepped by one jitted call.

    Arguments:
        num_envs: number of environments.
        task: task file or bundled task name (default ``return_ball``).
        overrides: ``{"section.key": value}`` on top of the task file (e.g. ``{"shots.bank": 256}``).
        block_size: the kernel's block size (default: its own choice).
        render_mode: None or ``"rgb_array"``: :meth:`render` returns a frame of each of the first
            ``render_envs`` environments (a finished environment's path starts afresh with its new
            episode, in the same step).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"]}

    def __init__(self, num_envs: int = 1, task=None, overrides: dict | None = None, block_size: int | None = None,
                 render_mode: str | None = None, render_envs: int = 1):
        self.env = ReturnBall(load_task_config(task, overrides), num_envs, block_size)
        self.params = self.env.default_params()
        self.render_mode = _render_mode(render_mode, self.metadata["render_modes"])
        self.metadata = dict(self.metadata, render_fps=self.env.config.control.rate_hz)
        if not 1 <= render_envs <= self.env.num_envs:
            raise ValueError(f"render_envs must be in [1, num_envs={self.env.num_envs}], got {render_envs}")
        self._trails = _Trails(self.env, self.params, render_envs) if self.render_mode else None
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
        if self._trails is not None:
            self._trails.update(self._state)
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
        if self._trails is not None:
            self._trails.update(self._state, restart=info["_final_obs"])
        return np.asarray(obs), np.asarray(reward), terminated, truncated, info

    def render(self):
        """A tuple of (H, W, 3) uint8 frames of the first ``render_envs`` environments (None
        without ``render_mode``)."""
        if self._trails is None:
            return None
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        return self._trails.draw()


class ReturnBallEnv(gymnasium.Env):
    """One ReturnBall environment (gymnasium ``Env``); arguments as :class:`ReturnBallVectorEnv`
    (``render_mode="rgb_array"``: :meth:`render` returns one frame)."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, task=None, overrides: dict | None = None, render_mode: str | None = None):
        self.env = ReturnBall(load_task_config(task, overrides), 1)
        self.params = self.env.default_params()
        self.render_mode = _render_mode(render_mode, self.metadata["render_modes"])
        self.metadata = dict(self.metadata, render_fps=self.env.config.control.rate_hz)
        self._trails = _Trails(self.env, self.params, 1) if self.render_mode else None
        self.observation_space = observation_space(self.env)
        self.action_space = action_space(self.env)
        self._state = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, self._state = jit_reset(self.env, _key(self.np_random), self.params)
        if self._trails is not None:
            self._trails.update(self._state)
        return np.asarray(obs[0]), {}

    def step(self, action):
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        obs, self._state, reward, terminated, truncated, info = jit_step_env(
            self.env, _key(self.np_random), self._state, np.asarray(action, np.float32)[None], self.params)
        info = {k: v[0] for k, v in _host(info).items()}
        if self._trails is not None:
            self._trails.update(self._state, restart=np.zeros(1, bool))
        return np.asarray(obs[0]), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        """An (H, W, 3) uint8 frame of the rally (None without ``render_mode``)."""
        if self._trails is None:
            return None
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        return self._trails.draw()[0]
