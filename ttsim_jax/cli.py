"""The ``ttsim`` command: thin wrappers that parse options, call the library and print."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def _simulate_command(sub):
    p = sub.add_parser(
        "simulate", help="simulate a spread of realistic shots and summarise them",
        description="Samples realistic shots (serves, topspin and backspin drives, pushes, blocks, smashes, "
                    "lobs; up to 35 m/s and 1000 rad/s), aims each through the model, simulates them and "
                    "prints the landing spread, bounce statistics and throughput.")
    p.add_argument("--model", default="conti2026",
                   help="bundled model name (conti2026, durr2026, nakashima2011) or path to a model .toml "
                        "(default: %(default)s)")
    p.add_argument("--shots", type=int, default=1000, help="number of shots to simulate (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the shot sampler (default: %(default)s)")
    p.add_argument("--types", default="all",
                   help="comma-separated shot types to draw from, or 'all' (default: %(default)s); known: "
                        "serve, topspin_drive, backspin_drive, push, block, smash, lob")
    p.add_argument("--duration", type=float, default=1.5, help="simulated time per shot [s] (default: %(default)s)")
    p.add_argument("--dt", type=float, default=1e-3, help="integration step [s] (default: %(default)s)")
    p.add_argument("--integrator", choices=["rk4", "rk2", "euler"], default="rk4",
                   help="flight integrator (default: %(default)s)")
    p.add_argument("--no-aim", action="store_true",
                   help="skip aiming each shot through the model (faster, more shots miss)")
    p.add_argument("--chunk", type=int, default=16384, help="balls simulated per call (default: %(default)s)")
    p.add_argument("--save", type=Path, default=None,
                   help="write the trajectories (every 5 ms) and event logs to this .npz file")
    p.add_argument("--plot", type=Path, default=None, help="write a PNG of sample trajectories over the table")
    p.set_defaults(func=cmd_simulate)


def cmd_simulate(args) -> int:
    import jax
    from tqdm import tqdm

    from ttsim_jax import load_model, simulate
    from ttsim_jax.evaluate.summary import summary_table
    from ttsim_jax.shots import SHOT_TYPES, sample_shots
    from ttsim_jax.state import Ball

    if args.shots <= 0 or args.duration <= 0 or args.dt <= 0 or args.chunk <= 0:
        print("error: --shots, --duration, --dt and --chunk must be positive", file=sys.stderr)
        return 2
    types = None if args.types == "all" else [t.strip() for t in args.types.split(",")]
    if types and set(types) - set(SHOT_TYPES):
        print(f"error: unknown shot types {sorted(set(types) - set(SHOT_TYPES))}; known: {list(SHOT_TYPES)}",
              file=sys.stderr)
        return 2
    model = load_model(args.model)
    n_steps = int(round(args.duration / args.dt))
    every = max(1, int(round(5e-3 / args.dt)))
    n_steps -= n_steps % every

    t0 = time.perf_counter()
    balls, labels = sample_shots(args.shots, seed=args.seed, types=types, model=None if args.no_aim else model)
    t_aim = time.perf_counter() - t0
    chunks = [slice(i, min(i + args.chunk, args.shots)) for i in range(0, args.shots, args.chunk)]
    results, t_sim, t_first = [], 0.0, 0.0
    for k, sl in enumerate(tqdm(chunks, desc="simulating", unit="chunk", disable=len(chunks) < 2)):
        chunk = Ball(*(np.asarray(a)[sl] for a in (balls.pos, balls.vel, balls.spin)))
        t1 = time.perf_counter()
        r = simulate(model, chunk, n_steps, args.dt, integrator=args.integrator,
                     record_every=every if (args.save or args.plot) else 0, max_events=8)
        jax.block_until_ready(r.final.pos)
        dt_call = time.perf_counter() - t1
        if k == 0:
            t_first = dt_call
        t_sim += dt_call
        results.append(jax.tree.map(np.asarray, r))
    cat = lambda get: np.concatenate([get(r) for r in results])  # noqa: E731
    kinds, pre, post_vel, status = (cat(lambda r: r.events.kind), cat(lambda r: r.events.pre.pos),
                                    cat(lambda r: r.events.post.vel), cat(lambda r: r.status))

    print(f"model {model.name}: {args.shots} shots, {n_steps} steps of {args.dt * 1e3:g} ms ({args.integrator})")
    print(summary_table(kinds, pre, post_vel, labels, status))
    if len(results) > 1:
        steady, steady_balls = t_sim - t_first, args.shots - chunks[0].stop
    else:  # one call: time it again, compiled, for an honest throughput
        t1 = time.perf_counter()
        jax.block_until_ready(simulate(model, chunk, n_steps, args.dt, integrator=args.integrator).final.pos)
        steady, steady_balls = time.perf_counter() - t1, args.shots
    print(f"aiming {t_aim:.1f} s; simulation {t_sim:.2f} s (first call {t_first:.2f} s, includes compilation); "
          f"throughput {steady_balls * n_steps / steady:,.0f} ball-steps/s (compiled)")
    if args.save:
        args.save.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.save, labels=labels, times=results[0].times,
                            pos=cat(lambda r: r.trajectory.pos), vel=cat(lambda r: r.trajectory.vel),
                            spin=cat(lambda r: r.trajectory.spin), event_kind=kinds, event_pos=pre,
                            event_time=cat(lambda r: r.events.time))
        print(f"trajectories written to {args.save}")
    if args.plot:
        from ttsim_jax.plots import plot_trajectories

        plot_trajectories(cat(lambda r: r.trajectory.pos), args.plot, labels=labels, events=(pre, kinds),
                          title=f"{model.name}: sample of {args.shots} shots")
        print(f"plot written to {args.plot}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from ttsim_jax.data import commands as data_commands
    from ttsim_jax.data import generator_cli
    from ttsim_jax.fit import commands as fit_commands

    parser = argparse.ArgumentParser(
        prog="ttsim", description="Differentiable table tennis ball physics in JAX: simulate shots, import, "
                                  "generate and inspect data, train and evaluate the racket residual network. World frame: origin at the centre of the table surface, x "
                                  "along the table, z up; SI units.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _simulate_command(sub)
    data_commands.register(sub)
    generator_cli.register(sub)
    fit_commands.register(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
