"""``python -m ttsim_jax.effects``: prints the effect catalogue with every parameter."""

from . import describe

print(describe())
