"""The functional environment as gymnax users know it: one environment's ``reset`` / ``step``,
vmapped over a batch by the user, and the whole rollout loop inside one ``jax.jit`` (``lax.scan``),
with no return to Python between steps.

    python examples/functional_loop.py --num-envs 256 --steps 200

A policy network, a PPO update and the loop around them go into the same jitted function the same
way (``ttsim_jax.rl.ppo`` does it for the batched form; ``ttsim_jax.rl.train(config)`` runs it).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.env import OUTCOME_NAMES, SingleReturnBall, load_task_config


def rollout(env: SingleReturnBall, params, key, num_envs: int, steps: int):
    """``steps`` control steps of ``num_envs`` environments under a uniformly random policy.

    Returns:
        (reward (steps, num_envs), done (steps, num_envs), outcome (steps, num_envs)).
    """
    reset = jax.vmap(env.reset, in_axes=(0, None))
    step = jax.vmap(env.step, in_axes=(0, 0, 0, None))  # with the automatic reset of finished episodes
    k_reset, k_run = jax.random.split(key)
    obs, state = reset(jax.random.split(k_reset, num_envs), params)

    def body(carry, key):
        obs, state = carry
        k_act, k_step = jax.random.split(key)
        action = jax.random.uniform(k_act, (num_envs, env.action_dim), minval=-1.0, maxval=1.0)
        obs, state, reward, terminated, truncated, info = step(jax.random.split(k_step, num_envs), state, action, params)
        return (obs, state), (reward, terminated | truncated, info["outcome"])

    _, out = jax.lax.scan(body, (obs, state), jax.random.split(k_run, steps))
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="return_ball", help="bundled task name or task .toml")
    p.add_argument("--bank", type=int, default=None, help="shots in the bank (default: the task's)")
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    overrides = {"shots.bank": args.bank, "shots.aim": False} if args.bank else None
    env = SingleReturnBall(load_task_config(args.task, overrides))
    params = env.default_params()
    run = jax.jit(rollout, static_argnums=(0, 3, 4))  # the environment is static: hashed by its settings
    key = jax.random.PRNGKey(args.seed)
    start = time.perf_counter()
    jax.block_until_ready(run(env, params, key, args.num_envs, args.steps))
    compiled = time.perf_counter() - start
    start = time.perf_counter()
    reward, done, outcome = jax.block_until_ready(run(env, params, jax.random.fold_in(key, 1), args.num_envs,
                                                      args.steps))
    elapsed = time.perf_counter() - start
    ended = np.asarray(outcome)[np.asarray(done)]
    shares = {name: float(np.mean(ended == i)) if ended.size else 0.0 for i, name in enumerate(OUTCOME_NAMES)}
    rate = args.num_envs * args.steps / elapsed
    print(f"{args.num_envs} environments x {args.steps} steps: first call {compiled:.1f} s (compiling), then "
          f"{rate:,.0f} env-steps/s; {ended.size} episodes ended under a random policy: "
          + ", ".join(f"{k} {v:.2f}" for k, v in shares.items() if v))
    return {"env_steps_per_s": rate, "episodes": int(ended.size), "outcomes": shares,
            "mean_reward": float(jnp.mean(reward))}


if __name__ == "__main__":
    main()
