"""Share of a ReturnBall task's shot bank that no racket in the task's workspace can return: balls
whose second bounce on the agent's half lies before x = workspace_lo x - face semi-axis - ball
radius (flown through the task's nominal model, no racket).

    python benchmarks/reachable_shots.py return_ball
"""

from __future__ import annotations

import sys

import jax.numpy as jnp
import numpy as np

from ttsim_jax import init_state, load_model, rollout
from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import shot_bank
from ttsim_jax.physics import events as ev


def main(task: str) -> None:
    c = load_task_config(task)
    model = load_model(c.model, dtype=jnp.float32)
    bank, _ = shot_bank(model, c)
    _, out = rollout(model, init_state(bank), 2000, 1e-3, max_events=6)
    kind, pos = np.asarray(out.events.kind), np.asarray(out.events.pre.pos)
    count = np.asarray(out.events.count)
    valid = np.arange(kind.shape[1])[None] < count[:, None]
    own = valid & (kind == ev.TABLE) & (pos[..., 0] > 0)
    n_own = own.sum(1)
    reach = c.racket.workspace_lo[0] - c.racket.face[0] - float(model.ball.radius)
    second = np.argsort(~own, 1, kind="stable")[:, 1:2]  # slot of the second bounce on the agent's half
    second_x = np.where(n_own >= 2, np.take_along_axis(pos[..., 0], second, 1)[:, 0], np.inf)
    counted = n_own >= 1
    short = counted & (second_x < reach)
    print(f"{c.source}: {counted.sum()} shots reach the agent's half; {short.sum()} ({short.sum() / counted.sum():.3f}) "
          f"bounce twice there before x = {reach:.3f} m (workspace_lo x - face semi-axis - ball radius)")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "return_ball")
