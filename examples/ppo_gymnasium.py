"""PPO over gymnasium's vector API, CleanRL style: ``gymnasium.make_vec("ttsim/ReturnBall-v0")``
under gymnasium's vector wrappers, a rollout loop on the host, one jitted update per iteration.

    python examples/ppo_gymnasium.py --num-envs 64 --total-timesteps 200000

This is how any gymnasium-based RL code sees the environment (next-step autoreset, numpy arrays).
The library's own trainer (``ttsim_jax.rl.train``, ``ttsim train ppo``) keeps the whole loop on the
device and trains far faster.
"""

from __future__ import annotations

import argparse
import time
import tomllib

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import optax
from gymnasium.wrappers import vector as wrappers

import ttsim_jax  # noqa: F401  (registers ttsim/ReturnBall-v0)
from ttsim_jax.rl.networks import ActorCritic, gaussian_log_prob
from ttsim_jax.rl.ppo import gae, ppo_loss
from ttsim_jax.rl.training import plot_curve


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="return_ball_unknown_rubber",
                   help="bundled task name or task .toml (default: the rubber the tracker does not know, where a "
                   "short run shows learning; return_ball: the default task, whose scripted stroke 200 k steps do not beat)")
    p.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                   help="task setting, TOML value (e.g. shots.bank=256); repeatable")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--total-timesteps", type=int, default=200_000)
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--num-steps", type=int, default=64, help="steps per environment per rollout")
    p.add_argument("--learning-rate", type=float, default=3e-4)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--gae-lambda", type=float, default=0.95)
    p.add_argument("--num-minibatches", type=int, default=4)
    p.add_argument("--update-epochs", type=int, default=4)
    p.add_argument("--clip-coef", type=float, default=0.2)
    p.add_argument("--ent-coef", type=float, default=0.0)
    p.add_argument("--vf-coef", type=float, default=0.5)
    p.add_argument("--max-grad-norm", type=float, default=0.5)
    p.add_argument("--eval-every", type=int, default=8, help="iterations between evaluations of the mean action "
                   "on held-out episodes (0: only before and after training)")
    p.add_argument("--eval-rounds", type=int, default=2,
                   help="episodes per environment in an evaluation (held-out seeds, the same every time)")
    p.add_argument("--plot", default="", metavar="PNG",
                   help="write the learning curve (held-out legal returns of the mean action beside the scripted "
                   "stroke's, the sampled actions' and their return, against env-steps) to this PNG file")
    return p.parse_args(argv)


def make_env(args):
    overrides = {}
    for item in args.override:
        key, _, value = item.partition("=")
        overrides[key] = tomllib.loads(f"v = {value}")["v"]
    env = gymnasium.make_vec("ttsim/ReturnBall-v0", num_envs=args.num_envs, task=args.task, overrides=overrides,
                             autoreset_mode=gymnasium.vector.AutoresetMode.NEXT_STEP)
    env = wrappers.FlattenObservation(env)
    env = wrappers.RecordEpisodeStatistics(env)
    env = wrappers.ClipAction(env)
    norm = env = wrappers.NormalizeObservation(env)
    env = wrappers.TransformObservation(env, lambda obs: np.clip(obs, -10, 10))
    env = wrappers.NormalizeReward(env, gamma=args.gamma)
    return wrappers.TransformReward(env, lambda reward: np.clip(reward, -10, 10)), norm


def evaluate(envs, norm, train_norm, policy, rounds: int, seed: int) -> float:
    """Legal-return rate of ``policy(obs) -> action`` over ``rounds`` episodes per environment of
    ``envs`` (its own environments, reset with held-out seeds: the same episodes every time), the
    observations normalised with the training statistics, frozen."""
    norm.obs_rms, norm.update_running_mean = train_norm.obs_rms, False
    legal = []
    for r in range(rounds):
        obs, _ = envs.reset(seed=seed + r)
        done = np.zeros(envs.num_envs, bool)
        while not done.all():
            obs, _, terminated, truncated, info = envs.step(np.asarray(policy(np.asarray(obs, np.float32))))
            ended = (terminated | truncated) & ~done
            if ended.any():
                legal += np.asarray(info["legal"])[ended].tolist()
            done |= terminated | truncated
    return float(np.mean(legal))


def main(argv=None) -> dict:
    args = parse(argv)
    envs, train_norm = make_env(args)
    eval_envs, eval_norm = make_env(args)  # the same shapes: the programs compiled for training serve it
    n, t = args.num_envs, args.num_steps
    iterations = max(args.total_timesteps // (n * t), 1)
    net = ActorCritic(action_dim=envs.single_action_space.shape[0], hidden=(64, 64))
    key = jax.random.PRNGKey(args.seed)
    key, k_init = jax.random.split(key)
    params = net.init(k_init, jnp.zeros((1,) + envs.single_observation_space.shape, jnp.float32))
    tx = optax.chain(optax.clip_by_global_norm(args.max_grad_norm), optax.adam(args.learning_rate, eps=1e-5))
    opt_state = tx.init(params)

    @jax.jit
    def act(params, obs, key):
        mean, log_std, value = net.apply(params, obs)
        action = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
        return action, gaussian_log_prob(mean, log_std, action), value

    @jax.jit
    def mean_action(params, obs):
        return net.apply(params, obs)[0]

    def held_out(policy_params=None):
        policy = ((lambda obs: np.zeros((n,) + envs.single_action_space.shape, np.float32)) if policy_params is None
                  else (lambda obs: mean_action(policy_params, obs)))
        return evaluate(eval_envs, eval_norm, train_norm, policy, args.eval_rounds, held_out_seed)

    held_out_seed = held_out_seed_of(args)
    scripted = held_out()  # action 0: the task's scripted stroke alone
    print(f"held-out legal-return rate: scripted stroke (action 0) {scripted:.3f} over {args.eval_rounds * n} "
          "episodes", flush=True)
    curve = []

    @jax.jit
    def update(params, opt_state, data, key):
        def epoch(carry, k):
            perm = jax.random.permutation(k, n * t)
            batches = jax.tree.map(lambda a: a[perm].reshape((args.num_minibatches, -1) + a.shape[1:]), data)

            def minibatch(carry, batch):
                params, opt_state = carry
                (loss, _), grads = jax.value_and_grad(
                    lambda p: ppo_loss(net, p, batch, args.clip_coef, args.vf_coef, args.ent_coef), has_aux=True)(params)
                updates, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), loss

            return jax.lax.scan(minibatch, carry, batches)

        (params, opt_state), losses = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, args.update_epochs))
        return params, opt_state, losses.mean()

    obs, _ = envs.reset(seed=args.seed)
    restarting = np.zeros(n, bool)  # next-step autoreset: these environments' next step only restarts them
    returns, legal, start = [], [], time.perf_counter()
    history = [{"env_steps": 0, "time_s": 0.0, "train_legal_rate": None, "train_return": None,
                "eval_legal_rate": scripted}]  # the policy's curve starts from the scripted stroke's
    for iteration in range(1, iterations + 1):
        buffer = {k: [] for k in ("obs", "action", "log_prob", "value", "reward", "done", "mask")}
        for _ in range(t):
            key, k_act = jax.random.split(key)
            obs = np.asarray(obs, np.float32)  # the wrappers' statistics are float64
            action, log_prob, value = act(params, obs, k_act)
            next_obs, reward, terminated, truncated, info = envs.step(np.asarray(action))
            for k, v in (("obs", obs), ("action", action), ("log_prob", log_prob), ("value", value),
                         ("reward", np.float32(reward)), ("done", terminated | truncated), ("mask", ~restarting)):
                buffer[k].append(np.asarray(v))
            if "episode" in info:
                returns += info["episode"]["r"][info["_episode"]].tolist()
                legal += info["legal"][info["_episode"]].tolist()
            obs, restarting = next_obs, terminated | truncated
        data = {k: jnp.asarray(np.stack(v)) for k, v in buffer.items()}
        last_value = act(params, np.asarray(obs, np.float32), key)[2]
        advantages, targets = gae(data["value"], data["reward"], data["done"], last_value, args.gamma, args.gae_lambda)
        batch = {"obs": data["obs"], "action": data["action"], "log_prob": data["log_prob"],
                 "advantage": advantages, "target": targets, "mask": data["mask"].astype(jnp.float32)}
        key, k_update = jax.random.split(key)
        params, opt_state, loss = update(params, opt_state, jax.tree.map(lambda a: a.reshape((n * t,) + a.shape[2:]),
                                                                          batch), k_update)
        recent = slice(-100, None)
        line = (f"iteration {iteration}/{iterations}  steps {iteration * n * t:,}  "
                f"SPS {iteration * n * t / (time.perf_counter() - start):,.0f}  loss {float(loss):+.3f}  "
                f"episodes {len(returns)}")
        if returns:  # the sampled actions' episodes ended so far (none yet: nothing to show, not NaN)
            line += f"  return {np.mean(returns[recent]):+.3f}  legal (sampled actions) {np.mean(legal[recent]):.2f}"
        history.append({"env_steps": iteration * n * t, "time_s": time.perf_counter() - start,
                        "train_legal_rate": np.mean(legal[recent]) if legal else None,
                        "train_return": np.mean(returns[recent]) if returns else None})
        if iteration == iterations or (args.eval_every and iteration % args.eval_every == 0):
            curve.append((iteration * n * t, held_out(params)))
            history[-1]["eval_legal_rate"] = curve[-1][1]
            line += f"  held-out legal (mean action) {curve[-1][1]:.3f} (scripted stroke {scripted:.3f})"
        print(line, flush=True)
    envs.close()
    eval_envs.close()
    if args.plot:
        plot_curve(history, args.plot, baseline=("scripted stroke (action 0), held out", scripted),
                   title=f"{args.task}, {args.eval_rounds * n} held-out episodes, seed {args.seed}")
        print(f"wrote {args.plot}", flush=True)
    return {"iterations": iterations, "episodes": len(returns), "returns": returns, "loss": float(loss),
            "scripted_legal": scripted, "held_out_legal": curve}


def held_out_seed_of(args) -> int:
    """The first seed of the evaluation's resets, far from the training's (``args.seed``)."""
    return args.seed + 10_000


if __name__ == "__main__":
    main()
