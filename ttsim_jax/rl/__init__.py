"""Reinforcement learning on the environments of :mod:`ttsim_jax.env`: PPO in JAX.

``ttsim_jax.rl.train(config, out)`` trains a policy from Python, as ``ttsim train ppo`` does
(``load_ppo_config`` reads a PPO file, ``PPOConfig`` is what it returns).

:mod:`.config` (the PPO TOML), :mod:`.networks` (actor-critic), :mod:`.normalise` (running
observation statistics), :mod:`.ppo` (the jitted training updates and the evaluation),
:mod:`.checkpoint` (atomic checkpoints), :mod:`.training` (the training run: progress, evaluation,
checkpoints, learning curve; ``ttsim train ppo`` and ``ttsim play`` are :mod:`ttsim_jax.cli.rl`),
``policies/`` (a small trained policy, ``ttsim play``'s default).
"""

from ttsim_jax.lazy import exports

_NAMES = {"train": "ttsim_jax.rl.training",
          **dict.fromkeys(["PPOConfig", "load_ppo_config"], "ttsim_jax.rl.config")}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = list(_NAMES)
