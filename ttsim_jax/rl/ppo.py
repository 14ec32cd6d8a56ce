"""PPO in JAX (PureJaxRL style): rollouts, GAE, the clipped surrogate, value loss and entropy
bonus, all inside one jitted function that runs a chunk of updates (``lax.scan``) over the
batched functional environment.

A training run calls :func:`make_chunk`'s function repeatedly and reports, evaluates and
checkpoints between calls (:mod:`ttsim_jax.rl.training`); everything the run needs to resume lives in
the :class:`Runner` pytree.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from ttsim_jax.env.rally_rules import LEGAL, SHOT_FAULT
from ttsim_jax.env.return_ball import EnvParams, ReturnBall
from ttsim_jax.rl.config import PPOConfig
from ttsim_jax.rl.networks import ActorCritic, gaussian_entropy, gaussian_log_prob
from ttsim_jax.rl.normalise import RunningStats


@struct.dataclass
class Runner:
    """Everything a training run carries from one update to the next.

    Attributes:
        params: network parameters; opt_state: the optimiser's state; stats: observation
        :class:`~ttsim_jax.rl.normalise.RunningStats`; env_state: the environments' state; obs: their
        last observations (N, D); ep_return: (N,) return of the running episodes; key: PRNG key;
        update: () updates done.
    """

    params: Any
    opt_state: Any
    stats: RunningStats
    env_state: Any
    obs: jnp.ndarray
    ep_return: jnp.ndarray
    key: jnp.ndarray
    update: jnp.ndarray


def network(env: ReturnBall, config: PPOConfig) -> ActorCritic:
    """The actor-critic of ``config`` for ``env``."""
    return ActorCritic(action_dim=env.action_dim, hidden=tuple(config.hidden), init_log_std=config.ppo.init_log_std)


def optimizer(config: PPOConfig):
    """Adam with global gradient-norm clipping; with ``anneal_lr`` its step size falls linearly from
    ``learning_rate`` to zero over the minibatch steps of ``total_env_steps``.

    The schedule's count lives in the optimiser state, so a resumed run continues on the same line.
    A run cut short by ``time_limit_s`` stops before the step size reaches zero: set
    ``total_env_steps`` to what the machine trains in that time.
    """
    lr = config.ppo.learning_rate
    if config.ppo.anneal_lr:
        updates = max(config.train.total_env_steps // config.batch_size, 1)
        lr = optax.linear_schedule(lr, 0.0, updates * config.ppo.update_epochs * config.ppo.num_minibatches)
    return optax.chain(optax.clip_by_global_norm(config.ppo.max_grad_norm), optax.adam(lr, eps=1e-5))


def init_runner(env: ReturnBall, env_params: EnvParams, config: PPOConfig, key) -> Runner:
    """A fresh run: initial network, optimiser, statistics and environments."""
    k_net, k_env, key = jax.random.split(key, 3)
    obs, env_state = env.reset(k_env, env_params)
    params = network(env, config).init(k_net, jnp.zeros((1, env.obs_dim), jnp.float32))
    return Runner(params=params, opt_state=optimizer(config).init(params), stats=RunningStats.create(env.obs_dim),
                  env_state=env_state, obs=obs, ep_return=jnp.zeros(env.num_envs, jnp.float32), key=key,
                  update=jnp.zeros((), jnp.int32))


def gae(values, rewards, dones, last_value, gamma, lam):
    """Generalised advantage estimates and returns of a rollout.

    Arguments:
        values, rewards, dones: (T, N) per step (``dones[t]``: the episode ended at step t);
        last_value: (N,) value after the last step; gamma, lam: discount and GAE lambda.

    Returns:
        (advantages (T, N), returns (T, N)).
    """
    def body(carry, xs):
        adv, next_value = carry
        value, reward, done = xs
        live = 1.0 - done.astype(values.dtype)
        delta = reward + gamma * next_value * live - value
        adv = delta + gamma * lam * live * adv
        return (adv, value), adv

    _, advantages = jax.lax.scan(body, (jnp.zeros_like(last_value), last_value), (values, rewards, dones),
                                 reverse=True)
    return advantages, advantages + values


def ppo_loss(net, params, batch, clip_eps, vf_coef, ent_coef):
    """The PPO loss of a minibatch (dict of obs, action, log_prob, advantage, target, and optionally
    ``mask``: 1 for the transitions to learn from, 0 for those to leave out, such as the steps that
    only restart an environment under gymnasium's next-step autoreset) and its parts."""
    mask = batch.get("mask")
    average = jnp.mean if mask is None else lambda x: jnp.sum(x * mask) / jnp.maximum(jnp.sum(mask), 1.0)
    mean, log_std, value = net.apply(params, batch["obs"])
    log_prob = gaussian_log_prob(mean, log_std, batch["action"])
    ratio = jnp.exp(log_prob - batch["log_prob"])
    adv = batch["advantage"]
    centre = average(adv)
    spread = adv.std() if mask is None else jnp.sqrt(average((adv - centre) ** 2))
    adv = (adv - centre) / (spread + 1e-8)
    surrogate = jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * adv)
    policy_loss = -average(surrogate)
    value_loss = 0.5 * average((value - batch["target"]) ** 2)
    entropy = gaussian_entropy(log_std)
    total = policy_loss + vf_coef * value_loss - ent_coef * entropy
    return total, {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
                   "clip_fraction": average(jnp.abs(ratio - 1.0) > clip_eps)}


def make_update(env: ReturnBall, config: PPOConfig, step=None):
    """``update(runner, env_params) -> (runner, metrics)``: one rollout of ``num_steps`` steps of every
    environment and ``update_epochs`` passes of minibatch PPO over it (pure; jit it).

    ``step``: the environment step over the whole batch (default ``env.step``; over several devices
    :func:`ttsim_jax.rl.distributed.per_shard`)."""
    net, tx, p = network(env, config), optimizer(config), config.ppo
    step = step or env.step

    def env_step(carry, _):
        runner, env_params = carry
        key, k_act, k_env = jax.random.split(runner.key, 3)
        nobs = runner.stats.normalise(runner.obs)
        mean, log_std, value = net.apply(runner.params, nobs)
        action = mean + jnp.exp(log_std) * jax.random.normal(k_act, mean.shape)
        log_prob = gaussian_log_prob(mean, log_std, action)
        obs, env_state, reward, terminated, truncated, info = step(k_env, runner.env_state, action, env_params)
        # a truncated episode is not over for the value: bootstrap from its final observation
        final_value = net.apply(runner.params, runner.stats.normalise(info["final_obs"]))[2]
        learn_reward = reward + p.gamma * jnp.where(truncated & ~terminated, final_value, 0.0)
        done = terminated | truncated
        ep_return = runner.ep_return + reward
        counted = done & (info["outcome"] != SHOT_FAULT)
        legal = info["outcome"] == LEGAL
        episode = {"episodes": jnp.sum(counted), "return_sum": jnp.sum(jnp.where(counted, ep_return, 0.0)),
                   "legal": jnp.sum(counted & legal), "contacts": jnp.sum(info["contact"]),
                   "landing_error_sum": jnp.sum(jnp.where(counted & legal, info["landing_error"], 0.0)),
                   "shot_faults": jnp.sum(done & (info["outcome"] == SHOT_FAULT))}
        runner = runner.replace(env_state=env_state, obs=obs, ep_return=jnp.where(done, 0.0, ep_return), key=key)
        transition = {"obs": nobs, "action": action, "log_prob": log_prob, "value": value, "reward": learn_reward,
                      "done": done}
        return (runner, env_params), (transition, episode, obs)

    def update(runner: Runner, env_params: EnvParams):
        (runner, _), (traj, episode, raw_obs) = jax.lax.scan(env_step, (runner, env_params), None, length=p.num_steps)
        last_value = net.apply(runner.params, runner.stats.normalise(runner.obs))[2]
        advantages, targets = gae(traj["value"], traj["reward"], traj["done"], last_value, p.gamma, p.gae_lambda)
        data = {"obs": traj["obs"], "action": traj["action"], "log_prob": traj["log_prob"], "advantage": advantages,
                "target": targets}
        data = jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), data)
        n = data["advantage"].shape[0]

        def epoch(carry, _):
            params, opt_state, key = carry
            key, k_perm = jax.random.split(key)
            perm = jax.random.permutation(k_perm, n)
            batches = jax.tree.map(lambda a: a[perm].reshape((p.num_minibatches, -1) + a.shape[1:]), data)

            def minibatch(carry, batch):
                params, opt_state = carry
                grads, parts = jax.grad(lambda q: ppo_loss(net, q, batch, p.clip_eps, p.vf_coef, p.ent_coef),
                                        has_aux=True)(params)
                updates, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), parts

            (params, opt_state), parts = jax.lax.scan(minibatch, (params, opt_state), batches)
            return (params, opt_state, key), parts

        key, k_epochs = jax.random.split(runner.key)
        (params, opt_state, _), parts = jax.lax.scan(epoch, (runner.params, runner.opt_state, k_epochs), None,
                                                      length=p.update_epochs)
        runner = runner.replace(params=params, opt_state=opt_state, stats=runner.stats.update(raw_obs), key=key,
                                update=runner.update + 1)
        metrics = jax.tree.map(jnp.sum, episode)
        metrics.update(jax.tree.map(jnp.mean, parts))
        metrics["reward_mean"] = jnp.mean(traj["reward"])
        return runner, metrics

    return update


def _program_key(config: PPOConfig) -> PPOConfig:
    """The config without what does not change a compiled program (its file name and text, limits;
    ``total_env_steps`` stays when it sets the learning-rate schedule)."""
    steps = config.train.total_env_steps if config.ppo.anneal_lr else 1
    return dataclasses.replace(config, source="", text="", train=dataclasses.replace(
        config.train, total_env_steps=steps, time_limit_s=1.0, seed=0, eval_every_chunks=0, checkpoint_every_chunks=1))


def make_chunk(env: ReturnBall, config: PPOConfig, mesh=None):
    """A jitted ``chunk(runner, env_params) -> (runner, metrics)`` running ``updates_per_chunk``
    updates; metrics are (updates_per_chunk,) arrays. The same function for the same environment
    and settings within a process (compiled once). ``mesh``: the devices the environments are split
    over, each stepping its own (:func:`ttsim_jax.rl.distributed.per_shard`), or None."""
    return _make_chunk(env, _program_key(config), mesh)


@functools.lru_cache(maxsize=8)
def _make_chunk(env: ReturnBall, config: PPOConfig, mesh):
    step = None
    if mesh is not None:
        from ttsim_jax.rl.distributed import per_shard

        step = per_shard(env.resized(env.num_envs // mesh.size), mesh)
    update = make_update(env, config, step)
    n = config.train.updates_per_chunk

    @jax.jit
    def chunk(runner, env_params):
        return jax.lax.scan(lambda r, _: update(r, env_params), runner, None, length=n)

    return chunk


def make_evaluate(env: ReturnBall, config: PPOConfig, record: int = 0):
    """A jitted ``evaluate(params, stats, env_params, key) -> dict`` playing one episode in each of
    ``env.num_envs`` environments with the policy's mean action.

    The dict holds (N,) ``outcome``, ``return``, ``landing_error`` (-1 unless legal), ``shot_type``
    and, with ``record`` > 0, of the first ``record`` environments after every control step: ``ball``
    and ``racket`` positions (T, record, 3), the racket's ``angle`` (T, record, 2) and the rally's
    ``progress`` (T, record, 3): bounced, hit, outcome (what a frame of
    :mod:`ttsim_jax.env.render` shows).
    """
    return _make_evaluate(env, _program_key(config), int(record))


@functools.lru_cache(maxsize=8)
def _make_evaluate(env: ReturnBall, config: PPOConfig, record: int):
    net = network(env, config)
    run = episode_runner(env, lambda policy, obs: net.apply(policy[0], policy[1].normalise(obs))[0], record)
    return jax.jit(lambda params, stats, env_params, key: run((params, stats), env_params, key))


def episode_runner(env: ReturnBall, act, record: int = 0):
    """``run(policy, env_params, key) -> dict``: one episode in each of ``env.num_envs`` environments,
    actions from ``act(policy, obs) -> (N, action_dim)``, where ``policy`` is any pytree (network
    parameters, a constant action); traceable, so the caller jits it.

    The dict holds what :func:`make_evaluate` describes.
    """

    def run(policy, env_params, key):
        k_reset, key = jax.random.split(key)
        obs, state = env.reset(k_reset, env_params)
        b = env.num_envs

        def body(carry, k):
            obs, state, finished, ret, outcome, error = carry
            obs, state, reward, terminated, truncated, info = env.step_env(k, state, act(policy, obs), env_params)
            ret = ret + jnp.where(finished, 0.0, reward)
            # an episode's outcome is read at its end; finished environments step on unrecorded
            newly = (terminated | truncated) & ~finished
            outcome = jnp.where(newly, info["outcome"], outcome)
            error = jnp.where(newly, info["landing_error"], error)
            p = state.progress
            rec = (state.rally.ball.pos[:record], state.racket.pos[:record], state.racket.angle[:record],
                   jnp.stack([p.bounced[:record].astype(jnp.int32), p.hit[:record].astype(jnp.int32),
                              p.outcome[:record]], -1)) if record else None
            return (obs, state, finished | newly, ret, outcome, error), rec

        init = (obs, state, jnp.zeros(b, bool), jnp.zeros(b, jnp.float32), jnp.zeros(b, jnp.int32),
                jnp.full(b, -1.0, jnp.float32))
        (_, state, _, ret, outcome, error), rec = jax.lax.scan(body, init, jax.random.split(key, env.max_steps))
        out = {"outcome": outcome, "return": ret, "landing_error": error, "shot_type": env_params.shot_type[state.shot]}
        if record:
            out["ball"], out["racket"], out["angle"], out["progress"] = rec
        return out

    return run


def summarise(result: dict, shot_types=None) -> dict:
    """Legal-return rate (shots the opponent missed left out), mean landing error [m] of the legal
    returns, mean return and the share of each outcome, from :func:`make_evaluate`'s result; with
    ``shot_types`` (the task's ``[shots] types``, which ``shot_type`` indexes) also ``by_type``:
    per shot type its episodes, the counted ones' legal-return rate and the share the opponent
    missed."""
    import numpy as np

    from ttsim_jax.env.rally_rules import OUTCOME_NAMES

    outcome = np.asarray(result["outcome"])
    counted = outcome != SHOT_FAULT
    legal = outcome == LEGAL
    error = np.asarray(result["landing_error"])
    out = {"episodes": int(counted.sum()),
           "legal_rate": float(legal.sum() / max(counted.sum(), 1)),
           "landing_error_m": float(error[legal].mean()) if legal.any() else float("nan"),
           "return_mean": float(np.asarray(result["return"])[counted].mean()) if counted.any() else float("nan"),
           "outcomes": {name: float((outcome == i).mean()) for i, name in enumerate(OUTCOME_NAMES)}}
    if shot_types is not None:
        kind = np.asarray(result["shot_type"])
        out["by_type"] = {}
        for i, name in enumerate(shot_types):
            k = kind == i
            n = int((k & counted).sum())
            out["by_type"][name] = {"episodes": n, "legal_rate": float((k & legal).sum() / n) if n else None,
                                    "opponent_missed": float((k & ~counted).sum() / k.sum()) if k.any() else None}
    return out
