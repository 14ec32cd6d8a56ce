"""ttsim-jax: differentiable, vectorised table tennis ball physics in JAX.

World frame everywhere: origin at the centre of the table's playing surface, x along the table's
length, y across it, z up; SI units.

The public names below are imported on first use (:mod:`ttsim_jax.lazy`), so ``import ttsim_jax``
and the ``ttsim`` command's argument checks do not wait for JAX.
"""

from ttsim_jax.lazy import exports
from ttsim_jax.registration import register_when_imported

__version__ = "0.1.0"

_NAMES = {
    **dict.fromkeys(["ConfigError", "UserError"], "ttsim_jax.errors"),
    **dict.fromkeys(["Model", "load_model", "stack_models"], "ttsim_jax.params"),
    **dict.fromkeys(["EventLog", "Execution", "RacketPolicy", "RallyResult", "RallyState", "Record", "RolloutOutput",
                     "init_state", "per_ball_axes", "rollout", "simulate"], "ttsim_jax.kernel"),
    **dict.fromkeys(["Ball", "Racket"], "ttsim_jax.state"),
    "enable_compilation_cache": "ttsim_jax.files.cache",
}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = [*_NAMES, "__version__"]

register_when_imported()  # neither gymnasium nor the environment package is imported here
