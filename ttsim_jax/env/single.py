"""One ReturnBall environment without a batch axis, as gymnax's environments are: the user vmaps it.

``env = SingleReturnBall("return_ball")``; ``obs, state = env.reset(key, params)`` gives one
observation (obs_dim,) and one state; ``env.step(key, state, action, params)`` takes one action (5,)
and returns a scalar reward and flags. ``jax.vmap(env.step, in_axes=(0, 0, 0, None))`` steps a
batch, each environment with its own key, and the whole training loop can sit in one ``jax.jit``
(``examples/functional_loop.py``). Underneath is the batched :class:`~ttsim_jax.env.return_ball.ReturnBall`
with one environment: the same physics, rewards and automatic reset, and under vmap each
environment follows its own key exactly as that one does.

Vmapped, the kernel cannot compact its batch to the balls near an event, so the batched form is
faster: 6,600 against 39,900 env-steps/s for 256 environments of the default task in the same
jitted loop on 2 CPU cores (7,900 with ``reference=False``, which compiles slower).
"""

from __future__ import annotations

import jax

from ttsim_jax.env.config import TaskConfig
from ttsim_jax.env.return_ball import EnvParams, EnvState, ReturnBall

# The kernel's clock: batch-wide scalars in a batched state, kept as they are.
_CLOCK = ("step", "t0", "dt")


def _map_per_env(fn, state: EnvState) -> EnvState:
    """``fn`` applied to every per-environment leaf of ``state`` (the kernel's clock left as it is)."""
    clock = {k: getattr(state.rally, k) for k in _CLOCK}
    bare = state.replace(rally=state.rally.replace(**dict.fromkeys(_CLOCK)))
    out = jax.tree.map(fn, bare)
    return out.replace(rally=out.rally.replace(**clock))


def unbatch(state: EnvState) -> EnvState:
    """The single environment of a batched state of one environment."""
    return _map_per_env(lambda a: a[0], state)


def batch(state: EnvState) -> EnvState:
    """A single environment's state as a batched state of one environment."""
    return _map_per_env(lambda a: a[None], state)


class SingleReturnBall:
    """One ReturnBall environment: pure ``reset`` / ``step`` without a batch axis (gymnax's shape).

    Arguments:
        config: a :class:`~ttsim_jax.env.config.TaskConfig`, a task file path or bundled task name
            (default ``return_ball``).
        reference: the kernel's reference step (default True: under ``vmap`` every environment
            runs the exact event detection, which batches without the lean step's compaction).

    Attributes:
        obs_dim, action_dim, max_steps, period, config: as :class:`~ttsim_jax.env.return_ball.ReturnBall`.
    """

    def __init__(self, config: TaskConfig | str | None = None, reference: bool = True):
        self.batched = ReturnBall(config, 1, reference=reference)
        self.config = self.batched.config
        self.obs_dim, self.action_dim = self.batched.obs_dim, self.batched.action_dim
        self.max_steps, self.period = self.batched.max_steps, self.batched.period

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and other.batched == self.batched

    def __hash__(self) -> int:
        return hash(("single", self.batched))

    def default_params(self) -> EnvParams:
        """The task file's parameters (shared with the batched form: the same shot bank)."""
        return self.batched.default_params()

    def observation_space(self, params: EnvParams | None = None):
        """The observation's Box (obs_dim,) (gymnax's signature: the same for any ``params``); its
        entries are named by :attr:`observation_names`."""
        from ttsim_jax.env.spaces import observation_space

        return observation_space(self.batched)

    def action_space(self, params: EnvParams | None = None):
        """The action's Box (5,) in [-1, 1] (gymnax's signature: the same for any ``params``)."""
        from ttsim_jax.env.spaces import action_space

        return action_space(self.batched)

    @property
    def observation_names(self) -> tuple:
        """The name of each observation entry (:attr:`~ttsim_jax.env.return_ball.ReturnBall.observation_fields`)."""
        return self.batched.observation_names

    def reset(self, key, params: EnvParams):
        """A fresh episode: (obs (obs_dim,) float32, :class:`~ttsim_jax.env.return_ball.EnvState`)."""
        obs, state = self.batched.reset(key, params)
        return obs[0], unbatch(state)

    def step_env(self, key, state: EnvState, action, params: EnvParams):
        """One control step, without the automatic reset; ``action`` (5,) in [-1, 1].

        Returns:
            (obs (obs_dim,), state, reward (), terminated (), truncated (), info of scalars), as
            :meth:`~ttsim_jax.env.return_ball.ReturnBall.step_env`.
        """
        return self._one(self.batched.step_env, key, state, action, params)

    def step(self, key, state: EnvState, action, params: EnvParams):
        """:meth:`step_env`, then a finished episode starts afresh (``info["final_obs"]`` holds its
        last observation), as :meth:`~ttsim_jax.env.return_ball.ReturnBall.step`."""
        return self._one(self.batched.step, key, state, action, params)

    def _one(self, step, key, state, action, params):
        action = jax.numpy.asarray(action)
        if action.shape != (self.action_dim,):
            raise ValueError(f"action of shape {action.shape}: expected ({self.action_dim},), one environment's "
                             "action (vmap the step for a batch)")
        obs, state, reward, terminated, truncated, info = step(key, batch(state), action[None], params)
        return (obs[0], unbatch(state), reward[0], terminated[0], truncated[0],
                {k: v[0] for k, v in info.items()})


#: The environments :func:`make` knows, by gymnax-style name.
ENV_IDS = ("ReturnBall-v0",)


def make(name: str = "ReturnBall-v0", *, task: TaskConfig | str | None = None, reference: bool = True):
    """gymnax's ``make``: ``env, params = make("ReturnBall-v0")``, then ``env.reset(key, params)``
    and ``env.step(key, state, action, params)`` (:class:`SingleReturnBall`; vmap them for a batch).

    Arguments:
        name: ``"ReturnBall-v0"`` (or gymnasium's ``"ttsim/ReturnBall-v0"``).
        task: a :class:`~ttsim_jax.env.config.TaskConfig`, a task file or a bundled task name
            (default ``return_ball``); reference: as :class:`SingleReturnBall`.

    Returns:
        (the environment, its default parameters).
    """
    bare = name.split("/", 1)[1] if name.startswith("ttsim/") else name
    if bare not in ENV_IDS:
        raise ValueError(f"unknown environment {name!r}; known: {', '.join(ENV_IDS)}")
    env = SingleReturnBall(task, reference=reference)
    return env, env.default_params()
