"""Reinforcement-learning environments over the rally kernel.

:mod:`.return_ball` is the functional environment (pure ``reset`` / ``step`` over pytrees, batched,
jit- and vmap-able); :mod:`.single` the same for one environment, for the user to vmap (gymnax's
shape); :mod:`.gym` holds its gymnasium adapters; :mod:`.render` draws their frames
(``render_mode="rgb_array"``); :mod:`.registration` registers ``ttsim/ReturnBall-v0`` with
gymnasium (done when ``ttsim_jax`` is imported).
"""

from ttsim_jax.lazy import exports

_NAMES = {**dict.fromkeys(["TaskConfig", "load_task_config"], "ttsim_jax.env.config"),
          **dict.fromkeys(["EnvParams", "EnvState", "OUTCOME_NAMES", "ReturnBall"], "ttsim_jax.env.return_ball"),
          "SingleReturnBall": "ttsim_jax.env.single"}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = list(_NAMES)
