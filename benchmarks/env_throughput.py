"""Environment steps per second of the jitted ReturnBall vector environment (JSON out).

Each environment step is one policy command and ``substeps`` (10) kernel steps of 1 ms for every
environment; the timed call is the jitted ``step`` with the automatic reset, random actions drawn
outside the timing.

    python benchmarks/env_throughput.py --envs 1024 4096 --steps 50 --out benchmarks/results/env_throughput_cpu.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import ReturnBall, jit_reset, jit_step


def measure(num_envs: int, steps: int, repeats: int, task: str) -> dict:
    env = ReturnBall(load_task_config(task), num_envs)
    params = env.default_params()
    key = jax.random.PRNGKey(0)
    _, state = jit_reset(env, key, params)
    actions = jax.random.uniform(key, (steps, num_envs, env.action_dim), jnp.float32, -1.0, 1.0)
    t0 = time.perf_counter()
    out = jit_step(env, key, state, actions[0], params)
    jax.block_until_ready(out)
    compile_s = time.perf_counter() - t0
    state = out[1]
    runs = []
    for r in range(repeats):
        t0 = time.perf_counter()
        for i in range(steps):
            out = jit_step(env, jax.random.fold_in(key, r * steps + i), state, actions[i], params)
            state = out[1]
        jax.block_until_ready(out)
        runs.append(time.perf_counter() - t0)
    median = float(np.median(runs))
    return {"num_envs": num_envs, "steps": steps, "compile_s": compile_s, "run_s": runs, "median_s": median,
            "env_steps_per_s": num_envs * steps / median,
            "physics_ball_steps_per_s": num_envs * steps * env.substeps / median}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", type=int, nargs="+", default=[1024, 4096])
    p.add_argument("--steps", type=int, default=50, help="environment steps per timed run")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--task", default="return_ball")
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args()
    results = []
    for n in args.envs:
        r = measure(n, args.steps, args.repeats, args.task)
        print(f"{n:>7} envs: {r['env_steps_per_s']:>12,.0f} env-steps/s  (compile {r['compile_s']:.1f} s)", flush=True)
        results.append(r)
    doc = {"benchmark": "return_ball_env_throughput", "unit": "env-steps/s (one step: 10 kernel steps of 1 ms)",
           "task": args.task, "device": str(jax.devices()[0]), "platform": platform.platform(),
           "jax": jax.__version__, "results": results}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(doc, f, indent=2)


if __name__ == "__main__":
    main()
