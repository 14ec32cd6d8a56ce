"""Sim-to-real gap diagnosis (``ttsim diagnose``): where a model's errors lie by phase and regime,
which effect of the catalogue explains them, and how far the gap shrinks with it.

Modules: :mod:`~ttsim_jax.diagnose.phases` (the measured items), :mod:`~ttsim_jax.diagnose.stages`
(differentiable per-phase errors), :mod:`~ttsim_jax.diagnose.where`,
:mod:`~ttsim_jax.diagnose.candidates`, :mod:`~ttsim_jax.diagnose.residuals`,
:mod:`~ttsim_jax.diagnose.diagnosis` (the whole run), :mod:`~ttsim_jax.diagnose.report`;
``ttsim diagnose`` is :mod:`ttsim_jax.cli.diagnose`.
"""
