"""Reinforcement-learning environments over the rally kernel.

:mod:`.return_ball` is the functional environment (pure ``reset`` / ``step`` over pytrees, batched,
jit- and vmap-able); :mod:`.gym` holds its gymnasium adapters; :mod:`.render` draws their frames
(``render_mode="rgb_array"``); :mod:`.registration` registers ``ttsim/ReturnBall-v0`` with
gymnasium (done when ``ttsim_jax`` is imported).
"""

from ttsim_jax.env.config import TaskConfig, load_task_config
from ttsim_jax.env.return_ball import OUTCOME_NAMES, EnvParams, EnvState, ReturnBall

__all__ = ["EnvParams", "EnvState", "OUTCOME_NAMES", "ReturnBall", "TaskConfig", "load_task_config"]
