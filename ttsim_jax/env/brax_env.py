"""ReturnBall behind brax's ``Env`` contract, so that ``brax.training``'s agents train it unmodified.

``env = BraxReturnBall()``; ``state = env.reset(rng)`` and ``env.step(state, action)`` take and give
brax's :class:`brax.envs.base.State` (``obs``, ``reward``, ``done``, ``metrics``, ``info``; the
environment's :class:`~ttsim_jax.env.return_ball.EnvState` as ``pipeline_state``), one environment
without a batch axis as brax's environments are; ``observation_size``, ``action_size`` and
``backend`` as brax reads them. PPO::

    from brax.training.agents.ppo import train as ppo
    from ttsim_jax.env.brax_env import BraxReturnBall, wrap_for_training

    env = BraxReturnBall()
    make_policy, params, metrics = ppo.train(environment=env, num_timesteps=1_000_000, num_envs=256,
                                             episode_length=env.max_steps, wrap_env_fn=wrap_for_training)

Episodes and resets. ``done`` is the environment's termination (the rally's outcome is decided);
the time limit is brax's ``episode_length`` (pass ``env.max_steps``, the task's own). brax's
default training wrapper (:func:`brax.envs.training.wrap`) restarts a finished environment from the
state its ``reset`` gave, so each environment would replay its first incoming shot for the whole
run; :func:`wrap_for_training` (as ``wrap_env_fn``) is the same wrapper but for that: a finished
environment starts a new episode with a new shot from the bank, drawn from its own key (kept in
``info["rng"]``). ``metrics`` hold ``legal`` (1 at the step a legal return lands) and ``contact``
(1 at the racket's hit), so brax's episode metrics (their sums over an episode) are the legal-return
rate and the hit rate.

brax vmaps the single environment; vmapped, the kernel cannot compact its batch to the balls near
an event, so this runs at about a sixth of the batched :class:`~ttsim_jax.env.return_ball.ReturnBall`'s
env-steps per second (:mod:`ttsim_jax.env.single`). brax is not a dependency of ttsim-jax
(``pip install brax``; brax 0.14.2's PPO needs a JAX older than 0.10 (tested: 0.8.3) and float32: no ``jax_enable_x64``).
"""

from __future__ import annotations

try:
    from brax.envs import base as _brax
    from brax.envs.wrappers import training as _brax_training
except ImportError as e:  # pragma: no cover - the message is the point
    raise ImportError("ttsim_jax.env.brax_env needs brax, which is not a dependency of ttsim-jax: "
                      "pip install brax") from e

import jax
import jax.numpy as jnp

from ttsim_jax.env.config import TaskConfig
from ttsim_jax.env.return_ball import EnvParams
from ttsim_jax.env.single import SingleReturnBall

#: The per-step metrics, summed by brax over an episode.
METRICS = ("legal", "contact")


def _float(x) -> jax.Array:
    """``x`` in JAX's default float (float32; float64 under ``jax_enable_x64``): the dtype brax's
    wrappers create their episode counters in, so that their scans keep one type."""
    return jnp.asarray(x, jnp.result_type(float))


class BraxReturnBall(_brax.Env):
    """One ReturnBall environment as a brax ``Env``.

    Arguments:
        task: a :class:`~ttsim_jax.env.config.TaskConfig`, a task file or a bundled task name
            (default ``return_ball``).
        params: the :class:`~ttsim_jax.env.return_ball.EnvParams` to run with (default: the task
            file's); they are constants of every program brax compiles.
        reference: as :class:`~ttsim_jax.env.single.SingleReturnBall` (default True).

    Attributes:
        single: the :class:`~ttsim_jax.env.single.SingleReturnBall` underneath; max_steps: the
            task's episode length in control steps (brax's ``episode_length``);
            observation_names: the name of each observation entry.
    """

    def __init__(self, task: TaskConfig | str | None = None, *, params: EnvParams | None = None,
                 reference: bool = True):
        self.single = SingleReturnBall(task, reference=reference)
        self.params = self.single.default_params() if params is None else params
        self.max_steps = self.single.max_steps
        self.observation_names = self.single.observation_names

    def reset(self, rng: jax.Array) -> _brax.State:
        """A fresh episode from PRNG key ``rng`` (one environment)."""
        rng, key = jax.random.split(rng)
        obs, state = self.single.reset(key, self.params)
        zero = _float(0.0)
        return _brax.State(pipeline_state=state, obs=obs, reward=zero, done=zero,
                           metrics=dict.fromkeys(METRICS, zero), info={"rng": rng})

    def step(self, state: _brax.State, action: jax.Array) -> _brax.State:
        """One control step (``action`` (5,) in [-1, 1]), without a reset: brax's wrappers reset."""
        rng, key = jax.random.split(state.info["rng"])
        obs, nxt, reward, terminated, _, info = self.single.step_env(key, state.pipeline_state, action, self.params)
        metrics = dict(state.metrics, **{k: _float(info[k]) for k in METRICS})  # keeps those brax's agents add
        return state.replace(pipeline_state=nxt, obs=obs, reward=_float(reward), done=_float(terminated),
                             metrics=metrics, info={**state.info, "rng": rng})

    @property
    def observation_size(self) -> int:
        return self.single.obs_dim

    @property
    def action_size(self) -> int:
        return self.single.action_dim

    @property
    def backend(self) -> str:
        return "ttsim"


class NewShotAutoReset(_brax.Wrapper):
    """brax's ``AutoResetWrapper``, but a finished environment starts a new episode from a fresh
    ``reset`` (a new shot, drawn from the key in its ``info["rng"]``) instead of replaying the state
    its first reset gave. Wraps a batched env (brax's ``VmapWrapper`` and ``EpisodeWrapper``)."""

    def step(self, state: _brax.State, action: jax.Array) -> _brax.State:
        if "steps" in state.info:  # as brax's: a finished episode's step count starts again
            state.info.update(steps=jnp.where(state.done, jnp.zeros_like(state.info["steps"]), state.info["steps"]))
        state = self.env.step(state.replace(done=jnp.zeros_like(state.done)), action)
        keys = jax.vmap(jax.random.split)(state.info["rng"])  # (n, 2, key)
        fresh = self.env.reset(keys[:, 1])

        def where_done(new, old):
            return jnp.where(state.done.reshape(state.done.shape + (1,) * (old.ndim - 1)) > 0, new, old)

        return state.replace(pipeline_state=jax.tree.map(where_done, fresh.pipeline_state, state.pipeline_state),
                             obs=where_done(fresh.obs, state.obs), info={**state.info, "rng": keys[:, 0]})


def wrap_for_training(env: _brax.Env, episode_length: int = 1000, action_repeat: int = 1,
                      randomization_fn=None) -> _brax.Wrapper:
    """brax's training wrapper (vmap, episode length and metrics, automatic reset) with
    :class:`NewShotAutoReset` for the reset: pass it to brax's trainers as ``wrap_env_fn``.

    Arguments:
        env: a :class:`BraxReturnBall`; episode_length, action_repeat: as brax's
            ``envs.training.wrap`` (pass ``env.max_steps``); randomization_fn: not supported (the
            environment's own randomisation lives in its task file).

    Returns:
        The wrapped, batched environment.
    """
    if randomization_fn is not None:
        raise ValueError("randomization_fn is not supported by ReturnBall: its randomised model values are set "
                         "in the task file ([randomisation])")
    env = _brax_training.VmapWrapper(env)
    env = _brax_training.EpisodeWrapper(env, episode_length, action_repeat)
    return NewShotAutoReset(env)
