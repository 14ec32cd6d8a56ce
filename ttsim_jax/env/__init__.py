"""Reinforcement-learning environments over the rally kernel.

:mod:`.return_ball` is the functional environment (pure ``reset`` / ``step`` over pytrees, batched,
jit- and vmap-able; :mod:`.rally_rules` its outcomes and how a rally moves on); :mod:`.single` the same for one environment, for the user to vmap (gymnax's
shape); :mod:`.gym` holds its gymnasium adapters; :mod:`.brax_env` its brax ``Env`` (brax installed); :mod:`.render` draws their frames
(``render_mode="rgb_array"``). ``ttsim/ReturnBall-v0`` is registered with gymnasium by
:mod:`ttsim_jax.registration` when gymnasium is imported after (or before) ``ttsim_jax``.
"""

from ttsim_jax.lazy import exports

_NAMES = {**dict.fromkeys(["TaskConfig", "load_task_config"], "ttsim_jax.env.config"),
          **dict.fromkeys(["EnvParams", "EnvState", "ReturnBall"], "ttsim_jax.env.return_ball"),
          "OUTCOME_NAMES": "ttsim_jax.env.rally_rules",
          **dict.fromkeys(["SingleReturnBall", "make"], "ttsim_jax.env.single")}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = list(_NAMES)
