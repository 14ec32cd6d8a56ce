"""Legal-return rate of the "intercept" mode's scripted tracker alone: constant actions (action 0, a
grid over the return's flight time and the pitch offset, and random constant actions), one episode
per environment against the task's shot bank (JSON out).

    python benchmarks/intercept_tracker.py --envs 512 --random 16 --out benchmarks/results/intercept_tracker_cpu.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
import tomllib

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import ReturnBall
from ttsim_jax.rl.ppo import episode_runner, summarise


def make_play(env: ReturnBall):
    """A jitted ``play(action (5,), env_params, key) -> dict`` (as :func:`ttsim_jax.rl.ppo.make_evaluate`)
    holding one constant action in every environment for one episode."""
    return jax.jit(episode_runner(env, lambda action, obs: jnp.broadcast_to(action, (obs.shape[0], env.action_dim))))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="return_ball")
    p.add_argument("--envs", type=int, default=512)
    p.add_argument("--swing", type=float, nargs="*", default=[-1.0, -0.5, 0.0, 0.5, 1.0],
                   help="grid of action[0] (return flight time)")
    p.add_argument("--pitch", type=float, nargs="*", default=[-1.0, -0.5, 0.0, 0.5, 1.0],
                   help="grid of action[3] (pitch offset)")
    p.add_argument("--random", type=int, default=0, help="random constant actions besides the grid")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE", help="task overrides (TOML values)")
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args()
    overrides = {k: tomllib.loads(f"v = {v}")["v"] for k, v in (kv.split("=", 1) for kv in args.set)}
    env = ReturnBall(load_task_config(args.task, {"control.action": "intercept", **overrides}), args.envs)
    params = env.default_params()
    play = make_play(env)
    key = jax.random.PRNGKey(args.seed)
    actions = [np.zeros(5)] + [np.array([s, 0.0, 0.0, q, 0.0]) for s, q in itertools.product(args.swing, args.pitch)]
    actions += list(np.random.default_rng(args.seed).uniform(-1.0, 1.0, (args.random, 5)))
    rows = []
    t0 = time.perf_counter()
    for a in actions:
        s = summarise(play(jnp.asarray(a, jnp.float32), params, key))
        rows.append({"action": [round(float(x), 3) for x in a], **s})
        print(f"action {rows[-1]['action']}: legal {s['legal_rate']:.3f}  "
              + " ".join(f"{k} {v:.2f}" for k, v in s["outcomes"].items()), flush=True)
    best = max(rows, key=lambda r: r["legal_rate"])
    out = {"benchmark": "intercept_tracker", "task": env.config.source, "envs": args.envs,
           "wall_time_s": round(time.perf_counter() - t0, 1), "action_zero": rows[0], "best": best, "rows": rows}
    print(f"action 0: legal {rows[0]['legal_rate']:.3f}; best {best['action']}: legal {best['legal_rate']:.3f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
