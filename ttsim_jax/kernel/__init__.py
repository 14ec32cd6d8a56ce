"""The rally kernel: state, one step, the event log, racket plans and the resumable rollout.

Modules, in the order the data flows: :mod:`.state` (``RallyState``, ``init_state``),
:mod:`.plans` (racket schedules and policies), :mod:`.ball_step` (one ball's stages of a step),
:mod:`.step` (one step for a batch), :mod:`.eventlog` (what happened), :mod:`.axes` (per-ball
parameters: ``per_ball_axes``), :mod:`.rollout` (``rollout``, ``simulate``) and
:mod:`.record` (``Record``: what a rollout records), :mod:`.execution` (``Execution``: how a
rollout runs, same results); :mod:`.fused` (the Pallas
flight path for accelerators), :mod:`.sharding` (the ball axis over devices).
"""

from ttsim_jax.kernel.axes import per_ball_axes
from ttsim_jax.kernel.eventlog import EventLog
from ttsim_jax.kernel.execution import Execution
from ttsim_jax.kernel.plans import RacketPolicy
from ttsim_jax.kernel.record import Record
from ttsim_jax.kernel.rollout import RallyResult, RolloutOutput, rollout, simulate
from ttsim_jax.kernel.state import RallyState, init_state
from ttsim_jax.kernel.ball_step import ball_properties

__all__ = ["EventLog", "Execution", "RacketPolicy", "RallyResult", "RolloutOutput", "RallyState", "Record",
           "ball_properties", "init_state", "per_ball_axes", "rollout", "simulate"]
