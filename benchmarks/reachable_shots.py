"""Share of a ReturnBall task's shot bank that no racket in the task's workspace can return: balls
whose centre, between their bounce on the agent's half and their next contact with anything (the
second bounce, the floor), never comes within reach of the face, i.e. never enters the workspace
(the ``[racket]`` box, with its floor raised to ``table_clearance`` over the table) widened by the
face's semi-axis plus the ball's radius. Flown through the task's nominal model, no racket, the
path sampled every 2 ms. A ceiling: the face reaching a ball with its rim counts as a return.

    python benchmarks/reachable_shots.py return_ball_accel return_ball
"""

from __future__ import annotations

import sys

import jax.numpy as jnp
import numpy as np

from ttsim_jax import Record, init_state, load_model, rollout
from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.bank import shot_bank
from ttsim_jax.physics import events as ev

DT, STEPS, EVERY = 1e-3, 2000, 2


def main(task: str) -> None:
    c = load_task_config(task)
    model = load_model(c.model, dtype=jnp.float32)
    bank, _ = shot_bank(model, c)
    _, out = rollout(model, init_state(bank), STEPS, DT, record=Record(max_events=6, every=EVERY))
    kind, pos, when = np.asarray(out.events.kind), np.asarray(out.events.pre.pos), np.asarray(out.events.time)
    count = np.asarray(out.events.count)
    slots = np.arange(kind.shape[1])[None]
    valid = slots < count[:, None]
    own = valid & (kind == ev.TABLE) & (pos[..., 0] > 0)
    first = np.where(own.any(1), np.argmax(own, 1), -1)  # slot of the bounce on the agent's half
    counted = first >= 0
    t_first = np.take_along_axis(when, np.maximum(first, 0)[:, None], 1)[:, 0]
    # the next event of any kind after that bounce (a second bounce, the floor, leaving play) ends the chance
    after = valid & (slots > first[:, None])
    t_end = np.where(after.any(1), np.take_along_axis(when, np.argmax(after, 1)[:, None], 1)[:, 0], np.inf)
    traj = np.asarray(out.trajectory.pos)  # (B, T, 3)
    times = np.asarray(out.times)  # (T,)
    r = c.racket
    m = max(r.face) + float(model.ball.radius)
    lo, hi = np.asarray(r.workspace_lo) - m, np.asarray(r.workspace_hi) + m
    inside = ((traj >= lo) & (traj <= hi)).all(-1)
    # over the table (x below its end, widened by m) the floor is the clearance, lowered by m
    over = traj[..., 0] < 0.5 * float(model.table.length) + m
    inside &= ~over | (traj[..., 2] >= r.table_clearance - m)
    window = (times[None] > t_first[:, None]) & (times[None] < t_end[:, None])
    reach = (inside & window).any(1)
    short = counted & ~reach
    share = short.sum() / counted.sum()
    print(f"{c.source}: {counted.sum()} shots reach the agent's half; {short.sum()} ({share:.3f}) "
          f"never come within {m:.3f} m (face semi-axis + ball radius) of the workspace {list(r.workspace_lo)} - "
          f"{list(r.workspace_hi)} (table_clearance {r.table_clearance}) before their next contact")


if __name__ == "__main__":
    for name in sys.argv[1:] or ["return_ball"]:
        main(name)
