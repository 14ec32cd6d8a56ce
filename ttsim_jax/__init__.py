"""ttsim-jax: differentiable, vectorised table tennis ball physics in JAX.

World frame everywhere: origin at the centre of the table's playing surface, x along the table's
length, y across it, z up; SI units.
"""

from ttsim_jax.params import ConfigError, Model, load_model, stack_models
from ttsim_jax.rally import EventLog, RacketPolicy, RallyResult, simulate
from ttsim_jax.state import Ball, Racket

__version__ = "0.1.0"

__all__ = ["Ball", "Racket", "Model", "ConfigError", "load_model", "stack_models", "simulate",
           "RacketPolicy", "RallyResult", "EventLog", "__version__"]
