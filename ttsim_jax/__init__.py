"""ttsim-jax: differentiable, vectorised table tennis ball physics in JAX.

World frame everywhere: origin at the centre of the table's playing surface, x along the table's
length, y across it, z up; SI units.
"""

from ttsim_jax.params import ConfigError, Model, load_model, stack_models
from ttsim_jax.kernel import (EventLog, RacketPolicy, RallyResult, RallyState, RolloutOutput, init_state, per_ball_axes,
                              rollout, simulate)
from ttsim_jax.state import Ball, Racket
from ttsim_jax.env.registration import register_envs

register_envs()

__version__ = "0.1.0"

__all__ = ["Ball", "Racket", "Model", "ConfigError", "load_model", "stack_models", "init_state", "rollout",
           "simulate", "per_ball_axes", "RallyState", "RolloutOutput", "RacketPolicy", "RallyResult", "EventLog",
           "__version__"]
