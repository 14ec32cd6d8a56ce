"""``ttsim simulate``: a spread of realistic shots through the model, summarised (a thin wrapper
over :func:`ttsim_jax.shots.sample_shots` and :func:`ttsim_jax.simulate`)."""

from __future__ import annotations

import time

import numpy as np

from ttsim_jax.cli.options import (FIGURE_SUFFIXES, UsageError, file_of, model_name_or_file, positive_float, positive_int,
                                   seed)
from ttsim_jax.sizes import require as require_memory


def register(sub) -> None:
    """Adds ``simulate`` to an argparse subparsers object (``func``: :func:`cmd_simulate`)."""
    p = sub.add_parser(
        "simulate", help="simulate a spread of realistic shots and summarise them",
        description="Samples realistic shots (serves, topspin and backspin drives, pushes, blocks, smashes, "
                    "lobs; up to 35 m/s and 1000 rad/s), aims each through the model, simulates them and "
                    "prints the landing spread, bounce statistics and throughput.")
    p.add_argument("--model", default="conti2026", type=model_name_or_file,
                   help="bundled model name (conti2026, durr2026, nakashima2011) or path to a model .toml "
                        "(default: %(default)s)")
    p.add_argument("--shots", type=positive_int, default=1000, help="number of shots to simulate (default: %(default)s)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the shot sampler (default: %(default)s)")
    p.add_argument("--types", default="all",
                   help="comma-separated shot types to draw from, or 'all' (default: %(default)s); known: "
                        "serve, topspin_drive, backspin_drive, push, block, smash, lob")
    p.add_argument("--duration", type=positive_float, default=1.5,
                   help="simulated time per shot [s], at most 60 (default: %(default)s)")
    p.add_argument("--dt", type=positive_float, default=1e-3,
                   help="integration step [s], at most 0.01 (default: %(default)s)")
    p.add_argument("--integrator", choices=["rk4", "rk2", "euler"], default="rk4",
                   help="flight integrator (default: %(default)s)")
    p.add_argument("--no-aim", action="store_true",
                   help="skip aiming each shot through the model (faster, more shots miss)")
    p.add_argument("--chunk", type=positive_int, default=16384, help="balls simulated per call (default: %(default)s)")
    p.add_argument("--save", type=file_of(".npz", what="the trajectories file"), default=None,
                   help="write the trajectories (every 5 ms) and event logs to this .npz file")
    p.add_argument("--plot", type=file_of(*FIGURE_SUFFIXES, what="the figure"), default=None,
                   help="write a PNG (or another figure format by the name's suffix: pdf, svg, ...) of sample "
                        "trajectories over the table")
    p.set_defaults(func=cmd_simulate)


#: Largest step and duration ``ttsim simulate`` accepts [s].
MAX_DT, MAX_DURATION = 0.01, 60.0
#: Most steps per shot ``ttsim simulate`` takes (they run one after another: 1.5 s at 1 us is
#: 1.5 million); a step of 1e-9 s would set out on billions and run for days.
MAX_STEPS = 2_000_000
#: Event-log slots of each ``ttsim simulate`` shot.
SIMULATE_EVENTS = 8
#: Host memory of a shot's sampling and aiming (the numpy draws; the vmapped aiming flights keep
#: their forward-mode tangents over 90 steps of 20 ms, about 13 KiB per shot in float32) [bytes].
AIM_BYTES_PER_SHOT = 16 * 2**10


def simulate_bytes(shots: int, n_steps: int, record_every: int, *, chunk: int, aim: bool) -> int:
    """Memory ``ttsim simulate`` holds at once [bytes]: every shot's results on the host twice (the
    per-chunk arrays and their concatenation), the sampling and aiming of all shots, and one chunk's
    rollout (:func:`ttsim_jax.kernel.rollout.memory_bytes`)."""
    import numpy as np

    from ttsim_jax.kernel.rollout import memory_bytes

    per_shot = memory_bytes(1, n_steps, record_every, SIMULATE_EVENTS, np.float32)["total"]
    one_chunk = memory_bytes(min(chunk, shots), n_steps, record_every, SIMULATE_EVENTS, np.float32)["total"]
    return shots * (2 * per_shot + (AIM_BYTES_PER_SHOT if aim else 1024)) + one_chunk


def cmd_simulate(args) -> int:
    """``simulate``: sample and aim the shots, simulate them in chunks, print the summary and throughput."""
    import jax
    from tqdm import tqdm

    from ttsim_jax import Record, load_model, simulate
    from ttsim_jax.evaluate.summary import summary_table
    from ttsim_jax.shots import SHOT_TYPES, sample_shots
    from ttsim_jax.state import Ball

    types = None if args.types == "all" else [t.strip() for t in args.types.split(",")]
    if types and set(types) - set(SHOT_TYPES):
        raise UsageError(f"--types {args.types}: unknown shot types {sorted(set(types) - set(SHOT_TYPES))}; "
                         f"known: {list(SHOT_TYPES)}")
    if args.dt > MAX_DT:
        raise UsageError(f"--dt {args.dt:g}: above {MAX_DT:g} s a ball at 35 m/s moves more than 35 cm per step "
                         "(twice the net's height) and the flight error grows with dt^4; use a smaller step")
    if args.duration > MAX_DURATION:
        raise UsageError(f"--duration {args.duration:g}: a shot is in play for a few seconds; at most "
                         f"{MAX_DURATION:g} s is simulated")
    n_steps = int(round(args.duration / args.dt))
    every = max(1, int(round(5e-3 / args.dt)))
    n_steps -= n_steps % every
    if n_steps < 1:
        raise UsageError(f"--duration {args.duration:g} with --dt {args.dt:g}: less than one step "
                         f"(at least {every * args.dt:g} s are needed)")
    if n_steps > MAX_STEPS:
        raise UsageError(f"--duration {args.duration:g} with --dt {args.dt:g}: {n_steps:,} steps per shot, taken one "
                         f"after another; at most {MAX_STEPS:,} are simulated (a step of {args.duration / MAX_STEPS:.2g} s "
                         "or more; the flight error at 1e-4 s is already below a micrometre)")
    record_every = every if (args.save or args.plot) else 0
    require_memory(f"--shots {args.shots}" + (" with --save/--plot" if record_every else ""),
                   simulate_bytes(args.shots, n_steps, record_every, chunk=args.chunk, aim=not args.no_aim),
                   remedy="ask for fewer shots")
    model = load_model(args.model)

    t0 = time.perf_counter()
    if not args.no_aim:  # the aiming flights compile once per model and batch shape (cached across runs)
        print(f"aiming {args.shots} shots through {model.name} (the first run compiles the aiming flights: "
              "up to a minute) ...", flush=True)
    balls, labels = sample_shots(args.shots, seed=args.seed, types=types, model=None if args.no_aim else model)
    t_aim = time.perf_counter() - t0
    chunks = [slice(i, min(i + args.chunk, args.shots)) for i in range(0, args.shots, args.chunk)]
    results, t_sim, t_first = [], 0.0, 0.0
    print(f"simulating {args.shots} shots for {n_steps} steps (the first call compiles the kernel: up to a "
          "minute) ...", flush=True)
    for k, sl in enumerate(tqdm(chunks, desc="simulating", unit="chunk", disable=len(chunks) < 2)):
        chunk = Ball(*(np.asarray(a)[sl] for a in (balls.pos, balls.vel, balls.spin)))
        t1 = time.perf_counter()
        r = simulate(model, chunk, n_steps, args.dt, integrator=args.integrator,
                     record=Record(every=record_every, max_events=SIMULATE_EVENTS))
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
    else:  # one call: time it again with the same arguments (the same compiled program) for an honest throughput
        t1 = time.perf_counter()
        jax.block_until_ready(simulate(model, chunk, n_steps, args.dt, integrator=args.integrator,
                                       record=Record(every=record_every, max_events=SIMULATE_EVENTS)).final.pos)
        steady, steady_balls = time.perf_counter() - t1, args.shots
    print(f"aiming {t_aim:.1f} s; simulation {t_sim:.2f} s (first call {t_first:.2f} s, includes compilation); "
          f"throughput {steady_balls * n_steps / steady:,.0f} ball-steps/s (compiled)")
    if args.save:
        import io

        from ttsim_jax.files.atomic import atomic_write

        buf = io.BytesIO()
        np.savez_compressed(buf, labels=labels, times=results[0].times,
                            pos=cat(lambda r: r.trajectory.pos), vel=cat(lambda r: r.trajectory.vel),
                            spin=cat(lambda r: r.trajectory.spin), event_kind=kinds, event_pos=pre,
                            event_time=cat(lambda r: r.events.time))
        atomic_write(args.save, buf.getvalue(), "the trajectories")
        print(f"trajectories written to {args.save}")
    if args.plot:
        from ttsim_jax.plots import plot_trajectories

        plot_trajectories(cat(lambda r: r.trajectory.pos), args.plot, labels=labels, events=(pre, kinds),
                          title=f"{model.name}: {args.shots} simulated shots")
        print(f"plot written to {args.plot}")
    return 0
