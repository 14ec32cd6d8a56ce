"""Reinforcement learning on the environments of :mod:`ttsim_jax.env`: PPO in JAX.

:mod:`.config` (the PPO TOML), :mod:`.networks` (actor-critic), :mod:`.normalise` (running
observation statistics), :mod:`.ppo` (the jitted training updates and the evaluation),
:mod:`.checkpoint` (atomic checkpoints), :mod:`.train` (the training run: progress, evaluation,
checkpoints, learning curve), :mod:`.commands` (``ttsim train ppo``, ``ttsim play``).
"""
