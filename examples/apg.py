"""Analytic policy gradients through the environment, as brax's APG trains: the return of whole
episodes differentiated with respect to a policy's weights by ``jax.grad`` through every env step,
the tracker and the kernel's contacts, and followed by Adam.

    python examples/apg.py --iterations 40 --num-envs 16 --lr 0.001

The default task is the "accel" form, where the action is the racket's accelerations (fractions of
their limits). The policy is linear in the observation (normalised by the statistics of its
starting policy's own episodes) with a tanh. It starts (``--start tracker``) as a PD that drives
the face centre to the tracker's predicted hit point (the task's observation gets the tracker's
plan for it) and holds the face square: it meets two thirds of the balls but returns few. From
action 0 (``--start zero``) the racket stays at rest, meets almost no ball, and the gradient has
nothing to climb: before the first contact the return depends on the policy only through the
approach term, which telescopes to the distance between racket and ball at the contact or at the
episode's end. So the objective differentiated is the return minus ``--closest`` times the
closest distance between the ball and the racket's face before the contact [m], whose gradient
moves the racket to where the ball passes; what is reported is the task's own return,
legal-return and contact rates. Every ``--eval-every`` iterations the policy is scored on the
same held-out episodes (reset keys apart from training's). The gradient is that of the return
for the rally's sequence of events: the terms it can follow are the closest approach, the landing
point's distance to the target (a legal return's ``target`` reward) and the motion cost; a miss
becoming a hit, or a net ball becoming a legal return, is a jump it does not see
(docs/functional-env.md, "Gradients through the environment"). Each step's forward pass is
recomputed in the reverse pass (``jax.checkpoint``), so memory follows the episode's states, not
everything the steps computed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ttsim_jax.env import OUTCOME_NAMES, SingleReturnBall, load_task_config

LEGAL = OUTCOME_NAMES.index("legal")


def episodes(env: SingleReturnBall, params, stats, policy, keys, steps: int, truncate: int = 0):
    """(returns (B,), legal (B,), landing error (B,) [m] of a legal return (NaN otherwise), contact
    (B,): the racket met the ball, closest (B,) [m]: the ball-racket distance at its smallest before
    the contact) of one episode per reset key under the policy ``(W, b)``; the rewards after an
    episode's end are left out."""
    mean, scale = stats

    def one(key):
        obs, state = env.reset(key, params)

        @jax.checkpoint
        def body(carry, xs):
            k, i = xs
            obs, state, done, total, closest = carry
            if truncate:  # the gradient flows back at most ``truncate`` steps through the state
                cut = (i % truncate) == 0
                obs, state = jax.tree.map(lambda a: jnp.where(cut, jax.lax.stop_gradient(a), a), (obs, state))
            action = jnp.tanh(((obs - mean) / scale) @ policy[0] + policy[1])
            obs, state, reward, terminated, truncated, info = env.step_env(k, state, action, params)
            total = total + jnp.where(done, 0.0, reward)
            # the distance the step ends at, while the ball is still to be hit (it is frozen from the contact on)
            before = ~done & ~state.progress.hit
            closest = jnp.where(before, jnp.minimum(closest, state.distance), closest)
            return (obs, state, done | terminated | truncated, total, closest), (
                info["outcome"], info["landing_error"], info["contact"] & ~done)

        init = (obs, state, jnp.zeros((), bool), jnp.zeros((), jnp.float32), state.distance)
        (_, _, _, total, closest), (outcome, error, contact) = jax.lax.scan(
            body, init, (jax.random.split(jax.random.fold_in(key, 1), steps), jnp.arange(steps)))
        legal = outcome == LEGAL
        return (total, legal.any(), jnp.where(legal.any(), jnp.max(jnp.where(legal, error, 0.0)), jnp.nan),
                contact.any(), closest)

    return jax.vmap(one)(keys)


def observation_stats(env, params, key, n: int, linear=None):
    """Mean and spread of the observations of ``n`` episodes of action 0, or of the action
    ``tanh(obs @ coef + const)`` with ``linear = (coef, const)``."""
    def one(k):
        obs, state = env.reset(k, params)

        def body(carry, kk):
            obs, state = carry
            action = jnp.zeros(env.action_dim) if linear is None else jnp.tanh(obs @ linear[0] + linear[1])
            obs2, state, *_ = env.step_env(kk, state, action, params)
            return (obs2, state), obs

        return jax.lax.scan(body, (obs, state), jax.random.split(k, env.max_steps))[1]

    obs = jax.vmap(one)(jax.random.split(key, n)).reshape(-1, env.obs_dim)
    return obs.mean(0), jnp.maximum(obs.std(0), 1e-3)


def tracker_gains(env: SingleReturnBall, params, omega: float = 12.0, omega_angle: float = 20.0):
    """``(coef, const)``: the linear map of the raw observation whose tanh is a critically damped PD of natural frequency ``omega`` [rad/s] driving the face centre to
    the tracker's predicted hit point (the observation's plan; the rest position where none exists)
    and one of ``omega_angle`` holding the face's angles at 0: a start that already meets some balls,
    so the gradient has contacts to improve (from action 0 the racket stays at rest and meets almost
    none). The command is a fraction of the racket's acceleration limits, and the observation holds
    velocities / 10: hence the factors."""
    names = env.observation_names
    limits = params.limits
    coef = np.zeros((env.obs_dim, env.action_dim), np.float32)
    const = np.zeros(env.action_dim, np.float32)
    accel = np.broadcast_to(np.asarray(limits.max_accel), (3,))
    accel_angle = np.broadcast_to(np.asarray(limits.max_angle_accel), (2,))
    start = np.asarray(params.start)
    for k, axis in enumerate("xyz"):
        kp, kd = omega ** 2 / accel[k], 2 * omega / accel[k]
        coef[names.index(f"plan.hit_pos.{axis}"), k] = kp
        coef[names.index(f"racket.pos.{axis}"), k] = -kp
        coef[names.index(f"racket.vel.{axis}"), k] = -10 * kd
        # the rest position where no hit is predicted: kp * (1 - exists) * start, linear in exists
        coef[names.index("plan.exists"), k] = -kp * start[k]
        const[k] = kp * start[k]
    for k, angle in enumerate(("pitch", "yaw")):
        coef[names.index(f"racket.{angle}"), 3 + k] = -omega_angle ** 2 / accel_angle[k]
        coef[names.index(f"racket.{angle}_rate"), 3 + k] = -10 * 2 * omega_angle / accel_angle[k]
    return jnp.asarray(coef), jnp.asarray(const)


def normalised(linear, stats):
    """The policy ``(W, b)`` on observations normalised by ``stats`` with the same action as the
    raw linear map ``(coef, const)``: coef . obs + const = W . (obs - mean) / scale + b."""
    (coef, const), (mean, scale) = linear, stats
    return coef * scale[:, None], const + mean @ coef


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--task", default="return_ball_accel",
                   help="bundled task name or task .toml (the default commands the racket's accelerations)")
    p.add_argument("--bank", type=int, default=256, help="shots in the task's bank")
    p.add_argument("--num-envs", type=int, default=8, help="episodes per gradient step")
    p.add_argument("--iterations", type=int, default=30, help="gradient steps")
    p.add_argument("--lr", type=float, default=0.003, help="Adam's learning rate")
    p.add_argument("--max-grad-norm", type=float, default=1.0, help="gradients are clipped to this global norm")
    p.add_argument("--closest", type=float, default=2.0,
                   help="weight [1/m] of the closest ball-racket distance before the contact in the objective "
                        "(0: the task's return alone)")
    p.add_argument("--truncate", type=int, default=0,
                   help="the gradient flows back through at most this many steps of the state (0: the whole "
                        "episode), as brax's APG truncates: over a whole episode it grows with the dynamics' chaos")
    p.add_argument("--eval-every", type=int, default=10, help="score the policy every N iterations")
    p.add_argument("--eval-episodes", type=int, default=64, help="held-out episodes per score")
    p.add_argument("--start", choices=("zero", "tracker"), default="tracker",
                   help="the policy's start: action 0 (on an accel task the racket at rest), or a PD driving the "
                        "racket to the predicted hit point (accel tasks; their observation gets the tracker's plan)")
    p.add_argument("--seed", type=int, default=0, help="seed of the training episodes (the held-out ones are apart)")
    p.add_argument("--out", type=Path, default=None, help="write the curve here as JSON")
    args = p.parse_args(argv)

    overrides = {"shots.bank": args.bank}
    if args.start == "tracker":
        if load_task_config(args.task).control.action != "accel":
            raise SystemExit("error: --start tracker drives the racket itself: it needs an accel task "
                             "(the intercept tasks' action 0 is their tracker's stroke: use --start zero)")
        overrides["observation.plan"] = True
    env = SingleReturnBall(load_task_config(args.task, overrides))
    params = env.default_params()
    steps = env.max_steps
    key = jax.random.PRNGKey(args.seed)
    held_out = jax.random.split(jax.random.PRNGKey(10_000 + args.seed), args.eval_episodes)
    print("preparing the observation statistics and the episodes' gradient: compiling takes about 4 minutes on "
          "two CPU cores", file=sys.stderr, flush=True)
    # statistics of the starting policy's own observations: normalised by those of a racket at rest,
    # its moving racket's velocities would read in thousands
    linear = tracker_gains(env, params) if args.start == "tracker" else None
    stats = jax.jit(observation_stats, static_argnums=(0, 3))(env, params, jax.random.fold_in(key, 7), 32, linear)
    policy = (normalised(linear, stats) if linear is not None else
              (jnp.zeros((env.obs_dim, env.action_dim), jnp.float32), jnp.zeros(env.action_dim, jnp.float32)))

    def loss(policy, keys):
        returns, legal, _, _, closest = episodes(env, params, stats, policy, keys, steps, args.truncate)
        return -(returns - args.closest * closest).mean(), (returns, legal)

    opt = optax.chain(optax.clip_by_global_norm(args.max_grad_norm), optax.adam(args.lr))
    state = opt.init(policy)

    @jax.jit
    def update(policy, state, keys):
        (value, (returns, legal)), grads = jax.value_and_grad(loss, has_aux=True)(policy, keys)
        upd, state = opt.update(grads, state, policy)
        return optax.apply_updates(policy, upd), state, returns.mean(), legal.mean(), optax.global_norm(grads)

    score = jax.jit(lambda policy: episodes(env, params, stats, policy, held_out, steps))
    curve = []

    def evaluate(it, elapsed):
        returns, legal, error, contact, closest = jax.device_get(score(policy))
        row = dict(iteration=it, episodes=int(it * args.num_envs), wall_s=round(elapsed, 1),
                   heldout_return=float(np.mean(returns)), heldout_legal=float(np.mean(legal)),
                   heldout_contact=float(np.mean(contact)), heldout_closest_m=float(np.mean(closest)),
                   heldout_landing_error_m=float(np.nanmean(error)) if np.isfinite(error).any() else None)
        curve.append(row)
        print(f"iteration {it:4d}  held-out return {row['heldout_return']:+.3f}  closest {row['heldout_closest_m']:.3f} m"
              f"  contact {row['heldout_contact']:.3f}"
              f"  legal {row['heldout_legal']:.3f}"
              f"  landing {row['heldout_landing_error_m'] or float('nan'):.3f} m from the target  ({elapsed:.0f} s)",
              flush=True)

    start = time.perf_counter()
    evaluate(0, 0.0)
    for it in range(1, args.iterations + 1):
        keys = jax.random.split(jax.random.fold_in(key, it), args.num_envs)
        policy, state, ret, legal, gnorm = update(policy, state, keys)
        if not np.isfinite(float(gnorm)):
            raise SystemExit(f"error: the gradient at iteration {it} is not finite")
        if it % args.eval_every == 0 or it == args.iterations:
            evaluate(it, time.perf_counter() - start)
    result = dict(task=args.task, start=args.start, num_envs=args.num_envs, iterations=args.iterations, lr=args.lr,
                  closest=args.closest, truncate=args.truncate, curve=curve)
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
