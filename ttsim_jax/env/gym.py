"""Gymnasium adapters of the functional :class:`~ttsim_jax.env.return_ball.ReturnBall`.

:class:`ReturnBallVectorEnv` steps all its environments in one jitted call; finished environments
restart as gymnasium's ``autoreset_mode`` says (``NEXT_STEP``, gymnasium's default, which its
vector wrappers expect, or ``SAME_STEP``, declared in ``metadata``). :class:`ReturnBallEnv` is one
environment (gymnasium's ``Env``, no automatic reset). Both return numpy arrays. Environments with
equal settings share their compiled programs within a process (and, through the compilation
cache, across processes).

Actions are checked on the host before the jitted step: a wrong shape is refused naming the action
space, a NaN or infinite entry is refused naming the environment (:class:`ActionError`); finite
values outside [-1, 1] are clipped by the racket's limits.

Both render with ``render_mode="rgb_array"`` (:mod:`.render`: the ball's path this episode and the
racket face over the table, from above and from the side): ``render()`` returns an (H, W, 3) uint8
frame, a tuple of them from the vector environment (its first ``render_envs`` environments), so
gymnasium's ``RecordVideo`` and ``HumanRendering`` wrappers work on the single environment.
"""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

import jax

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import RESET_INFO, ReturnBall, jit_reset, jit_select, jit_step, jit_step_env
from ttsim_jax.env.spaces import action_space, observation_space
from ttsim_jax.errors import UserError


def _key(rng: np.random.Generator):
    """A raw PRNG key (uint32 pair) drawn on the host: no device call beside the step itself."""
    return rng.integers(0, 2**32, size=2, dtype=np.uint32)


def _host(tree):
    """Writable numpy copies of device arrays (gymnasium's wrappers write into what they are given)."""
    return jax.tree.map(np.array, jax.device_get(tree))


class ActionError(UserError, ValueError):
    """An action the environment cannot take: of the wrong shape, or not finite."""


def checked_action(action, space) -> np.ndarray:
    """``action`` as a float32 array of ``space``'s shape; raises :class:`ActionError` naming the
    space for another shape, and the environments whose action holds a NaN or an infinity."""
    raw = np.asarray(action)
    if raw.shape != space.shape:
        raise ActionError(f"action of shape {raw.shape}: the action space is {space} (shape {space.shape})")
    if not np.issubdtype(raw.dtype, np.number) and raw.dtype != bool:
        raise ActionError(f"action of dtype {raw.dtype}: the action space is {space}")
    bad = ~np.isfinite(raw)
    if bad.any():
        if raw.ndim > 1:
            rows = np.flatnonzero(bad.any(-1))
            more = " ..." if len(rows) > 8 else ""
            raise ActionError(f"the action of environment(s) {rows[:8].tolist()}{more} holds NaN or infinite values "
                              f"(first: {raw[rows[0]].tolist()})")
        raise ActionError(f"the action holds NaN or infinite values: {raw.tolist()}")
    # float32 overflow would make a huge finite action infinite; the racket clips it to its limits anyway
    return np.clip(raw, -1e30, 1e30).astype(np.float32)


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

    def update(self, state, restart=None, hold=None):
        """Appends the balls of ``state``; environments where ``restart`` (N,) is set (all when None)
        start a new path; those where ``hold`` is set keep their path and frame as they are (an
        ended episode whose new one is not shown yet).

        Drawn from the environments' state, the frame of an episode's last step under
        ``NEXT_STEP`` is its step before (the state already holds the next episode).
        """
        n = self.n
        first = lambda tree: jax.tree.map(lambda a: a[:n], tree)  # noqa: E731
        ball, rk, progress, t = jax.device_get(first((state.rally.ball.pos, state.racket, state.progress, state.t)))
        now = (rk.pos, self.rotations(rk.angle), progress, t)
        keep = np.zeros(n, bool) if hold is None or self.now is None else np.asarray(hold[:n])
        for i in np.flatnonzero(~keep):
            if restart is None or restart[i]:
                self.paths[i] = []
            self.paths[i].append(ball[i])
        if keep.any():
            now = jax.tree.map(lambda new, old: np.where(keep.reshape((-1,) + (1,) * (new.ndim - 1)), old, new),
                               now, self.now)
        self.now = now

    def draw(self):
        from ttsim_jax.env.render import progress_text

        pos, rot, p, t = self.now
        return tuple(self.frames.frame(np.stack(self.paths[i]), pos[i], rot[i],
                                       progress_text(float(t[i]) * self.env.period, bool(p.bounced[i]),
                                                     bool(p.hit[i]), int(p.outcome[i])))
                     for i in range(self.n))


class _TaskTimeLimit:
    """The ``spec`` of an environment that truncates its episodes itself, at the task's
    ``max_steps``: gymnasium's ``make`` gives it a spec without ``max_episode_steps`` (no time limit
    registered: the task sets it, and a TimeLimit wrapper would duplicate the environment's own), and
    this fills in the task's, which wrappers and trainers read (``env.spec.max_episode_steps``)."""

    @property
    def spec(self):
        return self.__dict__.get("_spec")

    @spec.setter
    def spec(self, value):
        if value is not None and value.max_episode_steps is None:
            value = dataclasses.replace(value, max_episode_steps=self.env.max_steps)
        self._spec = value


class ReturnBallVectorEnv(_TaskTimeLimit, gymnasium.vector.VectorEnv):
    """``num_envs`` ReturnBall environments stepped by one jitted call.

    Arguments:
        num_envs: number of environments.
        task: task file or bundled task name (default ``return_ball``).
        overrides: ``{"section.key": value}`` on top of the task file (e.g. ``{"shots.bank": 256}``).
        block_size: the kernel's block size (default: its own choice).
        autoreset_mode: ``AutoresetMode.NEXT_STEP`` (default, as gymnasium's own vector
            environments: the step that ends an episode returns its last observation, the next step
            ignores that environment's action and returns the first observation of a new episode,
            reward 0, not terminated, not truncated) or ``SAME_STEP`` (the new episode's first
            observation comes in the ending step itself, the last one in ``info["final_obs"]``); the
            mode or its name (``"NextStep"``, ``"SameStep"``).
        render_mode: None or ``"rgb_array"``: :meth:`render` returns a frame of each of the first
            ``render_envs`` environments (a finished environment's path starts afresh with its new
            episode).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"]}

    def __init__(self, num_envs: int = 1, task=None, overrides: dict | None = None, block_size: int | None = None,
                 render_mode: str | None = None, render_envs: int = 1,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP):
        try:
            mode = AutoresetMode(autoreset_mode)
        except ValueError:
            mode = None
        if mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
            raise ValueError(f"autoreset_mode must be AutoresetMode.NEXT_STEP or SAME_STEP, got {autoreset_mode!r}")
        self.env = ReturnBall(load_task_config(task, overrides), num_envs, block_size)
        self.params = self.env.default_params()
        self.render_mode = _render_mode(render_mode, self.metadata["render_modes"])
        self.metadata = dict(self.metadata, autoreset_mode=mode, render_fps=self.env.config.control.rate_hz)
        if not 1 <= render_envs <= self.env.num_envs:
            raise ValueError(f"render_envs must be in [1, num_envs={self.env.num_envs}], got {render_envs}")
        self._trails = _Trails(self.env, self.params, render_envs) if self.render_mode else None
        self.num_envs = self.env.num_envs
        self.single_observation_space = observation_space(self.env)
        self.single_action_space = action_space(self.env)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._state = None
        # NEXT_STEP: the environments whose episode ended in the last step; the step's observations (the
        # new episodes' first ones there)
        self._restart = np.zeros(self.num_envs, bool)
        self._first_obs = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Starts every environment afresh; returns (obs (N, D), info)."""
        if seed is not None:
            self._np_random, self._np_random_seed = seeding.np_random(seed)
            self.action_space.seed(seed)
        obs, self._state = jit_reset(self.env, _key(self.np_random), self.params)
        self._restart[:] = False
        if self._trails is not None:
            self._trails.update(self._state)
        return _host(obs), {}

    def step(self, actions):
        """One control step of every environment; finished ones restart as ``autoreset_mode`` says.

        Arguments:
            actions: (N, 5) in [-1, 1] (checked: :func:`checked_action`).

        Returns:
            (obs, reward, terminated, truncated, info) as numpy arrays; info holds ``outcome``,
            ``legal``, ``contact``, ``landing_error`` and ``shot_type`` (N,)
            (:meth:`~ttsim_jax.env.return_ball.ReturnBall.step_env`); in ``SAME_STEP`` mode also
            ``final_obs`` (N, D), the last observation of the environments that finished
            (``info["_final_obs"]``).
        """
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        actions = checked_action(actions, self.action_space)
        before = self._state
        obs, self._state, reward, terminated, truncated, info = jit_step(
            self.env, _key(self.np_random), before, actions, self.params)
        obs, reward, terminated, truncated, info = _host((obs, reward, terminated, truncated, info))
        if self.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP:
            done = terminated | truncated
            info["_final_obs"] = done
            if self._trails is not None:
                self._trails.update(self._state, restart=done)
            return obs, reward, terminated, truncated, info
        # NEXT_STEP: the ending step shows the episode's last observation; its state already holds the
        # new episode, which waits, unstepped, until the next step shows its first observation
        first, last = obs, info.pop("final_obs")
        restart = self._restart
        if restart.any():
            self._state = jit_select(restart, before, self._state)
            last = np.where(restart[:, None], self._first_obs, last)
            reward = np.where(restart, 0.0, reward).astype(np.float32)
            terminated, truncated = terminated & ~restart, truncated & ~restart
            for k, fill in RESET_INFO.items():
                info[k] = np.where(restart, fill, info[k]).astype(info[k].dtype)
        self._restart, self._first_obs = terminated | truncated, first
        if self._trails is not None:
            self._trails.update(self._state, restart=restart, hold=self._restart)
        return last, reward, terminated, truncated, info

    def render(self):
        """A tuple of (H, W, 3) uint8 frames of the first ``render_envs`` environments (None
        without ``render_mode``)."""
        if self._trails is None:
            return None
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        return self._trails.draw()


class ReturnBallEnv(_TaskTimeLimit, gymnasium.Env):
    """One ReturnBall environment (gymnasium ``Env``); arguments as :class:`ReturnBallVectorEnv`
    (``render_mode="rgb_array"``: :meth:`render` returns one frame)."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, task=None, overrides: dict | None = None, render_mode: str | None = None):
        self.env = ReturnBall(load_task_config(task, overrides), 1)
        self._params = None
        self.render_mode = _render_mode(render_mode, self.metadata["render_modes"])
        self.metadata = dict(self.metadata, render_fps=self.env.config.control.rate_hz)
        self._trails = _Trails(self.env, self.params, 1) if self.render_mode else None
        self.observation_space = observation_space(self.env)
        self.action_space = action_space(self.env)
        self._state = None

    @property
    def params(self):
        """The task's :class:`~ttsim_jax.env.return_ball.EnvParams`, made on first use: an
        environment only made and closed (as gymnasium's ``AsyncVectorEnv`` does in its own
        process, for the spaces, before it forks its workers) starts no JAX backend, whose
        threads a forked worker would deadlock on."""
        if self._params is None:
            self._params = self.env.default_params()
        return self._params

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, self._state = jit_reset(self.env, _key(self.np_random), self.params)
        if self._trails is not None:
            self._trails.update(self._state)
        return _host(obs)[0], {}

    def step(self, action):
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        action = checked_action(action, self.action_space)
        obs, self._state, reward, terminated, truncated, info = jit_step_env(
            self.env, _key(self.np_random), self._state, action[None], self.params)
        obs, reward, terminated, truncated, info = _host((obs, reward, terminated, truncated, info))
        if self._trails is not None:
            self._trails.update(self._state, restart=np.zeros(1, bool))
        return (obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]),
                {k: v[0] for k, v in info.items()})

    def render(self):
        """An (H, W, 3) uint8 frame of the rally (None without ``render_mode``)."""
        if self._trails is None:
            return None
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        return self._trails.draw()[0]
