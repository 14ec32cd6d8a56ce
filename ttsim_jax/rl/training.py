"""A PPO training run: jitted chunks of updates, progress, periodic evaluation, atomic checkpoints,
resume, and the learning curve (PNG)."""

from __future__ import annotations

import functools
import json
import time
from pathlib import Path

import jax
import numpy as np

from ttsim_jax.env.config import load_task_config
from ttsim_jax.env.return_ball import ReturnBall
from ttsim_jax.files.atomic import atomic_write
from ttsim_jax.rl import distributed, ppo
from ttsim_jax.rl.checkpoint import read_checkpoint, restore_runner, save_checkpoint
from ttsim_jax.rl.config import PPOConfig, load_ppo_config, parse_ppo_config
from ttsim_jax.sizes import require as require_memory

CHECKPOINT = "checkpoint.msgpack"
CURVE = "learning_curve.png"
METRICS = "metrics.json"


def task_path(config: PPOConfig):
    """The task file of a PPO config: a path relative to the config's folder, or a bundled name."""
    task = Path(config.task)
    if config.source and task.suffix == ".toml" and not task.is_absolute():
        near = Path(config.source).parent / task
        if near.is_file():
            return near
    return config.task


def build(config: PPOConfig, num_envs: int, task=None, shots: dict | None = None):
    """(environment, its parameters) of a PPO config (or of another ``task``, with its ``[shots]``
    settings replaced by ``shots``, e.g. ``{"source": "measured", ...}``); the same environment
    object for the same task file, settings and size within a process, so its compiled programs are
    reused."""
    env = _task_env(config, num_envs, task, shots)
    return env, env.default_params()


def _task_env(config: PPOConfig, num_envs: int, task=None, shots: dict | None = None) -> ReturnBall:
    task = task or task_path(config)
    overrides = tuple(sorted((f"shots.{k}", tuple(v) if isinstance(v, list) else v) for k, v in (shots or {}).items()))
    return _env(str(Path(task).resolve()) if Path(task).is_file() else str(task), int(num_envs), overrides)


def memory_bytes(config: PPOConfig, num_envs: int, task=None) -> int:
    """What training (or evaluating) ``num_envs`` environments of a config holds at once [bytes],
    from the shapes of one environment's runner (``jax.eval_shape``: nothing is allocated): the
    environment state four times (a step's inputs, outputs and the kernel's temporaries) and the
    rollout buffer of ``num_steps`` transitions twice (the buffer and its shuffled minibatches). The
    shot bank is not drawn for it (:meth:`~ttsim_jax.env.return_ball.ReturnBall.sizing_params`)."""
    env = _task_env(config, 1, task)
    params = env.sizing_params()
    runner = jax.eval_shape(lambda k: ppo.init_runner(env, params, config, k), jax.random.PRNGKey(0))
    state = sum(int(np.prod(x.shape)) * x.dtype.itemsize for x in jax.tree.leaves(runner.env_state))
    transition = (env.obs_dim + 2 * env.action_dim + 6) * 4  # obs, action, its mean, reward, value, ...
    return int(num_envs) * (4 * state + 2 * config.ppo.num_steps * transition)


def require_envs(config: PPOConfig, num_envs: int, what: str, task=None) -> None:
    """Refuses a task whose shot bank's drawing (:func:`~ttsim_jax.env.bank.bank_bytes`), or
    ``num_envs`` environments whose memory (:func:`memory_bytes`), is above the budget, before either
    is built."""
    from ttsim_jax.env.bank import require_bank

    require_bank(_task_env(config, 1, task).config)
    require_memory(what, memory_bytes(config, num_envs, task), remedy="ask for fewer environments")


@functools.lru_cache(maxsize=8)
def _env(task: str, num_envs: int, overrides: tuple = ()) -> ReturnBall:
    # the overrides' lists travel as tuples (hashable, for the cache); the task file's reader takes lists
    return ReturnBall(load_task_config(task, {k: list(v) if isinstance(v, tuple) else v for k, v in overrides}), num_envs)


def _chunk_record(metrics: dict, env_steps: int, elapsed: float) -> dict:
    m = {k: np.asarray(v) for k, v in metrics.items()}
    episodes = float(m["episodes"].sum())
    legal = float(m["legal"].sum())
    return {"env_steps": env_steps, "time_s": round(elapsed, 2), "episodes": int(episodes),
            "train_legal_rate": legal / episodes if episodes else None,
            "train_return": float(m["return_sum"].sum()) / episodes if episodes else None,
            "train_landing_error_m": float(m["landing_error_sum"].sum()) / legal if legal else None,
            "entropy": float(m["entropy"].mean()), "value_loss": float(m["value_loss"].mean()),
            "reward_mean": float(m["reward_mean"].mean())}


def plot_curve(history: list, path, *, baseline: tuple | None = None, title: str = "PPO on ReturnBall") -> None:
    """Writes the learning curve (legal-return rate and return against env steps) as a PNG, atomically.

    Arguments:
        history: one dict per point, with ``env_steps``, ``time_s``, ``train_legal_rate`` and
            ``train_return`` (None where no episode ended yet) and, where evaluated,
            ``eval_legal_rate``.
        path: the PNG file.
        baseline: optional ``(label, legal-return rate)`` drawn as a dashed line (e.g. the scripted
            stroke's).
        title: the figure's title, before the training time.
    """
    from ttsim_jax.plots import pyplot, save_figure

    steps = np.array([h["env_steps"] for h in history], float)
    get = lambda k: np.array([np.nan if h.get(k) is None else h[k] for h in history], float)  # noqa: E731
    fig, (ax1, ax2) = pyplot().subplots(2, 1, figsize=(8, 7), sharex=True)
    ax1.plot(steps, get("train_legal_rate"), label="training episodes (sampled actions)")
    ev = [h for h in history if "eval_legal_rate" in h]
    if ev:
        ax1.plot([h["env_steps"] for h in ev], [h["eval_legal_rate"] for h in ev], "o-", label="evaluation (mean action)")
    if baseline is not None:
        ax1.axhline(baseline[1], color="grey", ls="--", label=baseline[0])
    ax1.set(ylabel="legal-return rate", ylim=(0, 1))
    ax1.grid(alpha=0.3)
    ax1.legend()
    ax2.plot(steps, get("train_return"), label="training episode return")
    ax2.set(xlabel="environment steps", ylabel="return")
    ax2.grid(alpha=0.3)
    times = get("time_s")
    ax1.set_title(f"{title} ({times[-1]:.0f} s of training)" if len(times) else title)
    save_figure(fig, path)


def train(config: PPOConfig | str | Path | None = None, out="runs/ppo", resume: bool = False, progress=print,
          overrides: dict | None = None) -> dict:
    """Trains PPO on the config's task, checkpointing into ``out``: what ``ttsim train ppo`` runs,
    callable from Python (``ttsim_jax.rl.train``).

    Arguments:
        config: a :class:`~ttsim_jax.rl.config.PPOConfig`, a PPO .toml path, or None for the bundled
            ``configs/ppo/return_ball.toml`` (on resume, the checkpoint's own config is used, with
            this one's ``total_env_steps`` and ``time_limit_s``).
        out: run folder (``checkpoint.msgpack``, ``metrics.json``, ``learning_curve.png``).
        resume: continue from ``out/checkpoint.msgpack``.
        progress: called with one line of text after each chunk (None: silent).
        overrides: ``{"section.key": value}`` on top of a config read from a file
            (``{"train.total_env_steps": 1_000_000}``).

    Returns:
        The last history record (with the final evaluation); the policy is in
        ``out/checkpoint.msgpack`` (``ttsim play --policy``).
    """
    if not isinstance(config, PPOConfig):
        config = load_ppo_config(config, overrides)
    elif overrides:
        raise ValueError("overrides apply to a config read from a file; change a PPOConfig with dataclasses.replace")
    out = Path(out)
    history, elapsed = [], 0.0
    payload = None
    if resume:
        payload = read_checkpoint(out / CHECKPOINT)
        limits = config.train
        config = parse_ppo_config(payload["config"], payload["config_source"])
        import dataclasses

        config = dataclasses.replace(config, train=dataclasses.replace(
            config.train, total_env_steps=limits.total_env_steps, time_limit_s=limits.time_limit_s))
        history, elapsed = payload["history"], payload["elapsed_s"]
    t = config.train
    require_envs(config, config.ppo.num_envs + t.eval_envs,
                 f"{config.source or 'the PPO config'}: [ppo] num_envs = {config.ppo.num_envs} "
                 f"(and [train] eval_envs = {t.eval_envs})")
    env, env_params = build(config, config.ppo.num_envs)
    eval_env, eval_params = build(config, t.eval_envs) if t.eval_envs else (None, None)
    init = lambda k: ppo.init_runner(env, env_params, config, k)  # noqa: E731
    # several devices (one process's, or several processes' joined by distributed.initialize): the environments
    # split over all of them, each stepping its own; everything else replicated, partitioned by XLA
    split = distributed.sharded()
    if split:
        distributed.check_envs(config.ppo.num_envs, "[ppo] num_envs")
        mesh = distributed.mesh()
        env_params = distributed.replicate(env_params, mesh)
        if eval_params is not None:
            eval_params = distributed.replicate(eval_params, mesh)
        layout = distributed.shardings(jax.eval_shape(init, jax.random.PRNGKey(0)), config.ppo.num_envs, mesh)
    host = (lambda tree: distributed.to_host(tree, mesh)) if split else (lambda tree: tree)  # noqa: E731
    seed_key = (lambda k: distributed.replicate(k, mesh)) if split else (lambda k: k)  # noqa: E731
    runner = (jax.jit(init, out_shardings=layout) if split else jax.jit(init))(seed_key(jax.random.PRNGKey(t.seed)))
    if payload is not None:
        runner = restore_runner(runner, payload, out / CHECKPOINT)
        if split:
            runner = distributed.put(runner, layout)
        # derived state, absent from older checkpoints: made again from the rest
        runner = runner.replace(env_state=runner.env_state.replace(plan=jax.jit(env.plan)(runner.env_state, env_params)))
    chunk = ppo.make_chunk(env, config, mesh if split else None)
    evaluate = ppo.make_evaluate(eval_env, config) if eval_env else None
    per_chunk = config.batch_size * t.updates_per_chunk
    writer = jax.process_index() == 0  # one process writes the run's files and prints

    def run_eval(record):
        key = jax.random.fold_in(jax.random.PRNGKey(t.seed + 1), int(host(runner.update)))
        s = ppo.summarise(host(evaluate(runner.params, runner.stats, eval_params, seed_key(key))))
        record.update(eval_legal_rate=s["legal_rate"], eval_landing_error_m=s["landing_error_m"],
                      eval_return=s["return_mean"], eval_outcomes=s["outcomes"])
        return s

    def save():
        state = host(runner)  # every process takes part in the gathering; one writes
        if not writer:
            return
        save_checkpoint(out / CHECKPOINT, state, config, history, elapsed)
        atomic_write(out / METRICS, json.dumps(history, indent=1).encode())
        if history:
            plot_curve(history, out / CURVE)

    progress = progress if writer else None
    if progress:  # nothing else is printed until the first chunk of updates is compiled and done
        progress(f"compiling the PPO update of {config.ppo.num_envs} environments (a few minutes the first time, "
                 "cached afterwards) ...")
    n_chunk = 0
    start = time.perf_counter() - elapsed

    def clock():
        """Training time so far; with several processes, process 0's (every process stops after
        the same chunk, or the others would wait for it in the next one's collectives)."""
        now = time.perf_counter() - start
        if not split or jax.process_count() == 1:
            return now
        from jax.experimental import multihost_utils

        return float(multihost_utils.broadcast_one_to_all(np.float64(now)))
    env_steps = int(host(runner.update)) * config.batch_size
    while env_steps < t.total_env_steps and elapsed < t.time_limit_s:
        runner, metrics = chunk(runner, env_params)
        metrics = host(metrics)
        jax.block_until_ready(metrics)
        env_steps += per_chunk
        elapsed = clock()
        record = _chunk_record(metrics, env_steps, elapsed)
        n_chunk += 1
        if evaluate and t.eval_every_chunks and n_chunk % t.eval_every_chunks == 0:
            run_eval(record)
            elapsed = clock()
        history.append(record)
        if progress:
            rate = record["train_legal_rate"]
            line = f"steps {env_steps:>11,}  time {elapsed:7.1f} s  "
            line += f"legal (train) {'-' if rate is None else f'{rate:.3f}'}  return {record['train_return'] or 0:+.3f}"
            if "eval_legal_rate" in record:
                line += f"  legal (eval) {record['eval_legal_rate']:.3f}  landing error {record['eval_landing_error_m']:.3f} m"
            progress(line)
        if n_chunk % t.checkpoint_every_chunks == 0:
            save()
    if evaluate and history and "eval_legal_rate" not in history[-1]:
        s = run_eval(history[-1])
        if progress:
            progress(f"final evaluation: legal-return rate {s['legal_rate']:.3f}, landing error "
                     f"{s['landing_error_m']:.3f} m, return {s['return_mean']:+.3f} over {s['episodes']} episodes")
    save()
    return history[-1] if history else {}
