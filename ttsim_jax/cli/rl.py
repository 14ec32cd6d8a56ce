"""``ttsim train ppo`` and ``ttsim play``: thin wrappers over :mod:`ttsim_jax.rl.training`."""

from __future__ import annotations

import json
from pathlib import Path

from ttsim_jax.cli.options import (FIGURE_SUFFIXES, UsageError, command_group, existing_dir, existing_file, file_of,
                                   positive_float, positive_int, seed, text_file, writable_dir)


def register(subparsers) -> None:
    """Adds ``train ppo`` (to the ``train`` group) and ``play`` to an argparse subparsers object."""
    train = command_group(subparsers, "train", "fit model components to measured data", "Fit model components to "
                          "measured data, or train a policy.")
    p = train.add_parser(
        "ppo", help="train a racket policy with PPO on the ReturnBall environment",
        description="Trains a policy with PPO (JAX, jitted) on the batched ReturnBall environment "
                    "(ttsim/ReturnBall-v0), shows progress, evaluates periodically (legal-return rate, landing "
                    "error to the target), checkpoints atomically to OUT/checkpoint.msgpack and draws "
                    "OUT/learning_curve.png.")
    p.add_argument("--config", type=text_file, default=None, metavar="TOML",
                   help="PPO config (default: the bundled configs/ppo/return_ball.toml)")
    p.add_argument("--out", type=writable_dir, default=Path("runs/ppo"), metavar="DIR",
                   help="run folder (default: %(default)s)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="continue the run in OUT from its checkpoint")
    mode.add_argument("--force", action="store_true", help="start afresh even if OUT holds a checkpoint")
    p.add_argument("--total-env-steps", type=positive_int, default=None, metavar="N",
                   help="stop after this many environment steps in all (default: the config's)")
    p.add_argument("--time-limit", type=positive_float, default=None, metavar="S",
                   help="stop after this many seconds of training, a resumed run's earlier time included "
                        "(default: the config's)")
    p.add_argument("--seed", type=seed, default=None, help="seed (default: the config's)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    d = p.add_argument_group("training across processes (JAX's multi-process runtime; one command per process, "
                             "the same config and --out for all; process 0 writes the files)")
    d.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="address of process 0, which coordinates the run (e.g. localhost:12355)")
    d.add_argument("--num-processes", type=positive_int, default=None, metavar="N", help="processes in the run")
    d.add_argument("--process-id", type=int, default=None, metavar="I", help="this process's index, 0 to N-1")
    p.set_defaults(func=cmd_train_ppo)

    q = subparsers.add_parser(
        "play", help="evaluate a PPO checkpoint (default: the bundled policy) on ReturnBall",
        description="Plays one episode in each of N environments with the checkpoint's policy (mean action) and "
                    "prints the legal-return rate, the landing error to the target and the share of each outcome; "
                    "optionally draws sample rallies.")
    q.add_argument("--policy", default=None, type=existing_file, metavar="CKPT",
                   help="checkpoint written by 'ttsim train ppo' (OUT/checkpoint.msgpack; default: the bundled "
                        "policy, a small one trained on the default task for a few minutes)")
    q.add_argument("--task", default=None, metavar="TASK",
                   help="bundled task name (return_ball, return_ball_pro, return_ball_real (measured shots: set "
                        "TTSIM_REAL_DATA); return_ball_accel, return_ball_pro_accel for an accel policy) or task .toml "
                        "(default: the checkpoint's)")
    q.add_argument("--episodes", type=positive_int, default=1024, help="episodes (default: %(default)s)")
    q.add_argument("--seed", type=seed, default=0, help="seed (default: %(default)s)")
    q.add_argument("--real-shots", type=existing_dir, default=None, metavar="DIR",
                   help="play the held-out split of measured shots instead of the task's bank: a folder of "
                        "Google DeepMind's post-hit ball states (serves.json, rallies.json of "
                        "google-deepmind/competitive_robot_table_tennis, CC-BY-4.0); the rates are also given "
                        "per shot type (serve, rally)")
    q.add_argument("--split", choices=("test", "train", "all"), default="test",
                   help="with --real-shots: which split of the states (default: %(default)s, the held-out one)")
    q.add_argument("--plot", type=file_of(*FIGURE_SUFFIXES, what="the figure"), default=None, metavar="PNG",
                   help="draw sample rallies to this PNG (or another figure format by the name's suffix)")
    q.add_argument("--gif", type=file_of(".gif", what="the animation"), default=None, metavar="GIF",
                   help="animate the first episode (top and side views of the ball's path and the racket face, "
                        "in real time, every second control step) to this GIF")
    q.add_argument("--json", action="store_true", help="print the results as JSON")
    q.set_defaults(func=cmd_play)


def cmd_train_ppo(args) -> int:
    """``train ppo``: train (or resume) a policy into the run folder, then print where it went."""
    import dataclasses

    from ttsim_jax.rl.config import load_ppo_config
    from ttsim_jax.rl.training import CHECKPOINT, train

    given = [x is not None for x in (args.coordinator, args.num_processes, args.process_id)]
    if any(given) and not all(given):
        raise UsageError("--coordinator, --num-processes and --process-id go together (one command per process)")
    if all(given):
        if not 0 <= args.process_id < args.num_processes:
            raise UsageError(f"--process-id {args.process_id}: must be within 0..{args.num_processes - 1}")
        from ttsim_jax.rl.distributed import initialize

        initialize(args.coordinator, args.num_processes, args.process_id)
    config = load_ppo_config(args.config)
    t = config.train
    config = dataclasses.replace(config, train=dataclasses.replace(
        t, total_env_steps=args.total_env_steps or t.total_env_steps, time_limit_s=args.time_limit or t.time_limit_s,
        seed=t.seed if args.seed is None else args.seed))
    if args.resume and not (args.out / CHECKPOINT).is_file():
        raise UsageError(f"--resume: {args.out / CHECKPOINT} does not exist")
    if not args.resume and not args.force and (args.out / CHECKPOINT).exists():
        raise UsageError(f"--out {args.out}: holds a checkpoint; continue it with --resume or replace it with --force")
    last = train(config, args.out, resume=args.resume, progress=None if args.quiet else lambda s: print(s, flush=True))
    print(f"checkpoint {args.out / CHECKPOINT}; learning curve {args.out / 'learning_curve.png'}")
    if last:
        print(f"legal-return rate {last.get('eval_legal_rate', float('nan')):.3f} (evaluation), "
              f"{last['env_steps']:,} environment steps in {last['time_s']:.0f} s")
    return 0


def cmd_play(args) -> int:
    """``play``: one episode per environment with the checkpoint's policy; print (and draw) the outcomes."""
    import jax
    import numpy as np

    from ttsim_jax.env.config import load_task_config
    from ttsim_jax.rl import ppo
    from ttsim_jax.rl.checkpoint import BUNDLED_POLICY, read_checkpoint, restore_runner
    from ttsim_jax.rl.config import parse_ppo_config
    from ttsim_jax.rl.training import build, require_envs, task_path

    if args.real_shots is not None:  # a wrong folder is refused before the task's bank is built
        from ttsim_jax.data.post_hit_states import read_post_hit_states

        read_post_hit_states(args.real_shots)
    if args.policy is None:
        args.policy = BUNDLED_POLICY
    payload = read_checkpoint(args.policy)
    config = parse_ppo_config(payload["config"], payload["config_source"])
    trained = load_task_config(task_path(config)).control.action
    asked = load_task_config(args.task).control.action if args.task else trained
    if trained != asked:
        raise UsageError(f"--task {args.task}: its [control] action = {asked!r}, but {args.policy} was trained with "
                         f"action = {trained!r} (for the professional shots of an intercept policy: "
                         "--task return_ball_pro; of an accel policy: --task return_ball_pro_accel)")
    require_envs(config, args.episodes, f"--episodes {args.episodes}", args.task)
    train_env, train_params = build(config, config.ppo.num_envs, args.task)
    runner = restore_runner(jax.eval_shape(lambda k: ppo.init_runner(train_env, train_params, config, k),
                                           jax.random.PRNGKey(0)), payload, args.policy)
    shots = None if args.real_shots is None else dict(source="measured", measured=str(args.real_shots.resolve()),
                                                      split=args.split, types=["serve", "rally"])
    env, params = (train_env, train_params) if args.episodes == train_env.num_envs and shots is None else build(
        config, args.episodes, args.task, shots=shots)
    record = min(args.episodes, 12) if args.plot else 1 if args.gif else 0
    result = ppo.make_evaluate(env, config, record=record)(runner.params, runner.stats, params,
                                                          jax.random.PRNGKey(args.seed))
    s = ppo.summarise(result, env.config.shots.types)
    s["task"] = env.config.source
    s["shots"] = (f"measured ({args.split} split of {args.real_shots})" if shots else
                  f"{env.config.shots.source} (the task's bank)")
    s["env_steps_trained"] = payload["history"][-1]["env_steps"] if payload["history"] else 0
    if args.json:
        print(json.dumps(s, indent=1))
    else:
        print(f"task {s['task']}: {s['episodes']} episodes (shots the opponent missed left out)")
        print(f"legal-return rate {s['legal_rate']:.3f}; landing error to the target {s['landing_error_m']:.3f} m; "
              f"mean return {s['return_mean']:+.3f}")
        print("outcomes: " + ", ".join(f"{k} {v:.3f}" for k, v in s["outcomes"].items()))
        print(f"shots: {s['shots']}; legal-return rate by shot type: " + ", ".join(
            f"{k} {v['legal_rate']:.3f} ({v['episodes']})" if v["legal_rate"] is not None else f"{k} - (0)"
            for k, v in s["by_type"].items()))
    if args.plot:
        from ttsim_jax.env.rally_rules import OUTCOME_NAMES
        from ttsim_jax.plots import plot_trajectories

        ball = np.swapaxes(np.asarray(result["ball"]), 0, 1)
        labels = np.array([OUTCOME_NAMES[i] for i in np.asarray(result["outcome"])[:record]])
        plot_trajectories(ball, args.plot, labels=labels, title=f"sample rallies of {args.policy}")
        print(f"plot written to {args.plot}")
    if args.gif:
        from ttsim_jax.env.render import RallyFrames, episode_frames, save_gif

        table = params.model.table
        frames = RallyFrames(np.asarray(params.limits.face), float(table.length), float(table.width))
        every = 2
        shots = episode_frames(frames, *(np.asarray(result[k])[:, 0] for k in ("ball", "racket", "angle", "progress")),
                               period=env.period, every=every)
        save_gif(shots, args.gif, every * env.period)
        print(f"animation of the first episode ({len(shots)} frames) written to {args.gif}")
    return 0
