"""ttsim-jax: differentiable, vectorised table tennis ball physics in JAX.

World frame everywhere: origin at the centre of the table's playing surface, x along the table's
length, y across it, z up; SI units.

The public names below are imported on first use (:mod:`ttsim_jax.lazy`), so ``import ttsim_jax``
and the ``ttsim`` command's argument checks do not wait for JAX.
"""

from ttsim_jax.env.registration import register_envs
from ttsim_jax.lazy import exports

__version__ = "0.1.0"

_NAMES = {
    **dict.fromkeys(["ConfigError", "Model", "load_model", "stack_models"], "ttsim_jax.params"),
    **dict.fromkeys(["EventLog", "RacketPolicy", "RallyResult", "RallyState", "RolloutOutput", "init_state",
                     "per_ball_axes", "rollout", "simulate"], "ttsim_jax.kernel"),
    **dict.fromkeys(["Ball", "Racket"], "ttsim_jax.state"),
    "enable_compilation_cache": "ttsim_jax.cache",
}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = [*_NAMES, "__version__"]

register_envs()  # gymnasium only: the environment is named by a string entry point
