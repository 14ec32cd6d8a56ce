"""The ``ttsim`` command: thin wrappers that parse options, call the library and print.

User errors never end in a traceback: option values are checked while parsing by the ``type=``
validators below (argparse then names the option and the value and exits with status 2), and the
library's user-error exceptions (bad config, dataset, checkpoint or path, :class:`UsageError`
from a command) are turned into one ``error: ...`` line and status 2 by :func:`main`. Any other
exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from ttsim_jax.sizes import require as require_memory


class UsageError(Exception):
    """A user error a command finds after parsing (refused overwrite, inconsistent options);
    :func:`main` prints ``error: MESSAGE`` and returns 2."""


def _user_errors() -> tuple:
    """The exceptions that report a user's mistake (their messages name the file, key or value)."""
    from ttsim_jax.data.errors import DataError
    from ttsim_jax.data.generator import GeneratorError
    from ttsim_jax.effects.base import EffectError
    from ttsim_jax.params import ConfigError
    from ttsim_jax.physics.residual import CheckpointError
    from ttsim_jax.physics.residual import ConfigError as ResidualConfigError
    from ttsim_jax.rl.checkpoint import CheckpointError as PolicyCheckpointError
    from ttsim_jax.sizes import SizeError

    return (UsageError, ConfigError, ResidualConfigError, CheckpointError, PolicyCheckpointError, DataError,
            GeneratorError, EffectError, SizeError,
            FileExistsError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)


# ---------------------------------------------------------------------------------------------
# argparse ``type=`` validators: each returns the converted value or raises ArgumentTypeError,
# which argparse reports as "argument OPTION: MESSAGE" (exit status 2).

def _number(text: str, kind, what: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (counts: shots, games, epochs, clusters)."""
    value = _number(text, int, "a positive integer")
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def seed(text: str) -> int:
    """A random seed: an integer in [0, 2**32)."""
    value = _number(text, int, "an integer seed in [0, 2**32)")
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"expected an integer seed in [0, 2**32), got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A finite number (not nan or inf)."""
    return _number(text, float, "a finite number")


def positive_float(text: str) -> float:
    """A finite number > 0 (durations, steps, tolerances)."""
    value = _number(text, float, "a positive finite number")
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return value


def existing_file(text: str) -> Path:
    """A file that exists (not a directory)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: is a directory, expected a file")
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    return path


def text_file(text: str) -> Path:
    """An existing UTF-8 text file (TOML configs and models): a binary file is refused here."""
    path = existing_file(text)
    try:
        path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise argparse.ArgumentTypeError(f"{text}: not a text file (byte {e.start} is not UTF-8)") from None
    except OSError as e:
        raise argparse.ArgumentTypeError(f"{text}: cannot be read: {e.strerror}") from None
    return path


def existing_dir(text: str) -> Path:
    """A directory that exists (datasets)."""
    path = Path(text)
    if path.is_file():
        raise argparse.ArgumentTypeError(f"{text}: is a file, expected a directory")
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no such directory")
    return path


def existing_path(text: str) -> Path:
    """A file or directory that exists (an importer's input)."""
    if not Path(text).exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file or directory")
    return Path(text)


def _check_creatable(path: Path, text: str) -> None:
    """Refuses a path whose nearest existing ancestor is not a directory in which a file can be
    created (tried with a probe file), so that an output the command would only write at the end
    is checked before the work starts."""
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: cannot be created, {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: cannot be created, {parent} is not writable")
    from ttsim_jax.io_atomic import probe_writable

    reason = probe_writable(parent)
    if reason is not None:
        raise argparse.ArgumentTypeError(f"{text}: cannot be created, no file can be made in {parent} ({reason})")


def writable_file(text: str) -> Path:
    """An output file: not a directory, writable if it exists, else creatable (missing parent
    directories are created when it is written)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: is a directory, expected a file name")
    if path.exists() and not os.access(path, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: is not writable")
    _check_creatable(path, text)
    return path


def writable_dir(text: str) -> Path:
    """An output directory: a writable directory if it exists, else creatable."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: exists and is not a directory")
    if path.is_dir() and not os.access(path, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: is not writable")
    _check_creatable(path, text)
    return path


def memory_size(text: str) -> int:
    """A memory size such as 512M, 16G or 2.5GiB, in bytes."""
    from ttsim_jax.sizes import parse_size

    try:
        return parse_size(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def model_name_or_file(text: str) -> str:
    """A bundled model name or the path of a model TOML file."""
    from ttsim_jax.params import ConfigError, resolve_model_path

    try:
        path = resolve_model_path(text)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    if path == Path(text):  # a file given by path, not a bundled name
        text_file(text)
    return text


def _simulate_command(sub):
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
    p.add_argument("--save", type=writable_file, default=None,
                   help="write the trajectories (every 5 ms) and event logs to this .npz file")
    p.add_argument("--plot", type=writable_file, default=None, help="write a PNG of sample trajectories over the table")
    p.set_defaults(func=cmd_simulate)


#: Largest step and duration ``ttsim simulate`` accepts [s].
MAX_DT, MAX_DURATION = 0.01, 60.0
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
    import jax
    from tqdm import tqdm

    from ttsim_jax import load_model, simulate
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
        r = simulate(model, chunk, n_steps, args.dt, integrator=args.integrator, record_every=record_every,
                     max_events=SIMULATE_EVENTS)
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
                                       record_every=record_every, max_events=SIMULATE_EVENTS).final.pos)
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
                          title=f"{model.name}: {args.shots} simulated shots")
        print(f"plot written to {args.plot}")
    return 0


def _sensitivity_command(sub):
    p = sub.add_parser(
        "sensitivity", help="Jacobians of where shots land against every parameter and input; error budgets",
        description="For a batch of returns (sampled by shot type, or a dataset's racket contacts), the Jacobian "
                    "of a target (landing point, landing time, net clearance, speed after the bounce) against "
                    "every model parameter, the ball's state before the contact and the racket's state at it, by "
                    "jax.jacrev through the rally kernel; flags gradients that hold only locally; propagates "
                    "the racket-state and spin-estimate uncertainties (and a parameter covariance) to the "
                    "landing point. Writes sensitivity.json, report.md, heatmaps.png and budget.png to --out.")
    p.add_argument("--model", default="conti2026", type=model_name_or_file,
                   help="bundled model name or path to a model .toml (default: %(default)s)")
    p.add_argument("--residual", type=existing_file, default=None,
                   help="racket residual network checkpoint (.ttres) to include (its weights are one group)")
    p.add_argument("--data", type=existing_dir, default=None,
                   help="dataset whose racket contacts (with racket states) are the shots")
    p.add_argument("--shots", type=positive_int, default=None,
                   help="number of sampled shots (default 256; with --data: at most this many contacts)")
    p.add_argument("--types", default="all", help="comma-separated shot types to sample, or 'all' (default: %(default)s)")
    p.add_argument("--target", choices=["landing", "landing_time", "net_clearance", "bounce_speed"], default="landing",
                   help="what to differentiate (default: %(default)s); the error budget is for 'landing'")
    p.add_argument("--seed", type=seed, default=0, help="seed of the shot sampler (default: %(default)s)")
    p.add_argument("--dt", type=positive_float, default=1e-3,
                   help="integration step [s], at most 0.01 (default: %(default)s)")
    p.add_argument("--horizon", type=positive_float, default=1.5,
                   help="flight simulated after the contact [s]; shots landing later count as not landing "
                        "(default: %(default)s)")
    p.add_argument("--chunk", type=positive_int, default=512, help="shots per compiled call (default: %(default)s)")
    p.add_argument("--mode", choices=["rev", "fwd"], default="rev", help="reverse or forward mode (default: %(default)s)")
    p.add_argument("--no-check", action="store_true",
                   help="skip the local-gradient check (finite differences at two steps per input group)")
    p.add_argument("--monte-carlo", type=positive_int, default=None, metavar="N",
                   help="also propagate the budget's sources by N samples per shot through the simulator")
    p.add_argument("--racket-pos-std", type=finite_float, default=0.008, help="racket position error, RMS length [m] (default: %(default)s)")
    p.add_argument("--racket-vel-std", type=finite_float, default=0.2, help="racket velocity error, RMS length [m/s] (default: %(default)s)")
    p.add_argument("--racket-rot-std", type=finite_float, default=0.7, help="racket orientation error, RMS angle [deg] (default: %(default)s)")
    p.add_argument("--spin-rel-std", type=finite_float, default=0.05, help="relative spin-estimate noise (default: %(default)s)")
    p.add_argument("--spin-abs-std", type=finite_float, default=10.0, help="spin-estimate noise per axis [rad/s] (default: %(default)s)")
    p.add_argument("--param-cov", type=existing_file, default=None,
                   help='JSON {"parameters": [names], "covariance": [[...]]}: a fitted parameter covariance')
    p.add_argument("--float64", action="store_true", help="compute in float64")
    p.add_argument("--out", type=writable_dir, required=True, help="output directory")
    p.set_defaults(func=cmd_sensitivity)


def cmd_sensitivity(args) -> int:
    from ttsim_jax.sensitivity.study import StudyConfig, run_study
    from ttsim_jax.shots import SHOT_TYPES

    types = None if args.types == "all" else tuple(t.strip() for t in args.types.split(","))
    if types and set(types) - set(SHOT_TYPES):
        raise UsageError(f"--types {args.types}: unknown shot types {sorted(set(types) - set(SHOT_TYPES))}; "
                         f"known: {list(SHOT_TYPES)}")
    if args.dt > MAX_DT:
        raise UsageError(f"--dt {args.dt:g}: at most {MAX_DT:g} s (see ttsim simulate --help)")
    if args.horizon > MAX_DURATION:
        raise UsageError(f"--horizon {args.horizon:g}: at most {MAX_DURATION:g} s")
    for opt in ("racket_pos_std", "racket_vel_std", "racket_rot_std", "spin_rel_std", "spin_abs_std"):
        if getattr(args, opt) < 0:
            raise UsageError(f"--{opt.replace('_', '-')} {getattr(args, opt):g}: must be >= 0")
    cfg = StudyConfig(model=args.model, residual=None if args.residual is None else str(args.residual),
                      data=None if args.data is None else str(args.data), shots=args.shots or 256, types=types,
                      seed=args.seed, target=args.target, dt=args.dt, horizon=args.horizon, chunk=args.chunk,
                      mode=args.mode, check=not args.no_check, monte_carlo=args.monte_carlo or 0,
                      racket_pos=args.racket_pos_std, racket_vel=args.racket_vel_std, racket_rot_deg=args.racket_rot_std,
                      spin_rel=args.spin_rel_std, spin_abs=args.spin_abs_std,
                      param_cov=None if args.param_cov is None else str(args.param_cov), float64=args.float64)
    try:
        summary = run_study(cfg, args.out)
    except ValueError as e:  # a parameter covariance file that cannot be used
        if args.param_cov is not None and str(args.param_cov) in str(e):
            raise UsageError(str(e)) from None
        raise
    print(summary["markdown"])
    for name, path in summary["paths"].items():
        print(f"{name} written to {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from ttsim_jax import __version__
    from ttsim_jax.data import commands as data_commands
    from ttsim_jax.data import generator_cli
    from ttsim_jax.diagnose import commands as diagnose_commands
    from ttsim_jax.evaluate import commands as evaluate_commands
    from ttsim_jax.fit import commands as fit_commands
    from ttsim_jax.rl import commands as rl_commands

    parser = argparse.ArgumentParser(
        prog="ttsim", description="Differentiable table tennis ball physics in JAX: simulate shots, import, "
                                  "generate and inspect data, fit aerodynamics, compare models on data, diagnose the sim-to-real gap, train and evaluate the racket "
                                  "residual network, train and play a racket policy (PPO). "
                                  "World frame: origin at the centre of the table surface, x along the table, z "
                                  "up; SI units.")
    parser.add_argument("--version", action="version", version=f"ttsim-jax {__version__}")
    parser.add_argument("--memory-budget", type=memory_size, default=None, metavar="SIZE",
                        help="memory a command may plan to use, e.g. 16G (default: the TTSIM_MEMORY_BUDGET "
                             "variable, else half the memory available when it starts); a job whose sizes "
                             "(shots, games, environments, episodes) need more is refused before it starts")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _simulate_command(sub)
    _sensitivity_command(sub)
    data_commands.register(sub)
    generator_cli.register(sub)
    fit_commands.register(sub)
    evaluate_commands.register(sub)  # after fit_commands: adds to its 'evaluate' group
    diagnose_commands.register(sub)
    rl_commands.register(sub)
    _everywhere(parser, next(a for a in parser._actions if "--memory-budget" in a.option_strings))
    return parser


def _everywhere(parser: argparse.ArgumentParser, action: argparse.Action) -> None:
    """Lets a global option also follow the subcommand (``ttsim generate ... --memory-budget 32G``):
    every subparser gets a copy whose default leaves the global value in place."""
    option = action.option_strings[0]
    for sub in (a for a in parser._actions if isinstance(a, argparse._SubParsersAction)):
        for child in sub.choices.values():
            _everywhere(child, action)
            if option not in child._option_string_actions:
                child.add_argument(option, type=action.type, default=argparse.SUPPRESS, metavar=action.metavar,
                                   help=action.help)


def main(argv=None) -> int:
    """Runs ``ttsim ARGV``.

    Arguments:
        argv: the arguments after ``ttsim`` (default: ``sys.argv[1:]``).

    Returns:
        The exit status: 0 done, 2 a user error (bad option, file or value; reported in one
        ``error:`` line naming it), otherwise what the command returns.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help and --version (0), or argparse's usage error (2), already printed
        return int(e.code or 0)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from ttsim_jax.cache import enable_compilation_cache

    enable_compilation_cache()  # a command run again loads its compiled programs
    from ttsim_jax.sizes import ENV

    before = os.environ.get(ENV)
    if args.memory_budget is not None:  # the library's size checks read it (ttsim_jax.sizes)
        os.environ[ENV] = str(args.memory_budget)
    from ttsim_jax.data.errors import DataWarning

    shown = warnings.showwarning

    def show(message, category, *where):  # a warning about the user's data: one 'warning:' line
        if issubclass(category, DataWarning):
            print(f"warning: {message}", file=sys.stderr)
        else:
            shown(message, category, *where)

    warnings.showwarning = show
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return status
    except _user_errors() as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except MemoryError as e:  # an allocation the size checks did not foresee: still no traceback
        what = str(e).split(" for an array")[0] or "an allocation failed"  # numpy: "Unable to allocate 8 GiB"
        print(f"error: ttsim {args.command}: out of memory ({what}); ask for fewer shots, games, environments "
              "or episodes, or run it where more memory is free", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader went away (``ttsim data info DIR | head``): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    finally:
        warnings.showwarning = shown
        if args.memory_budget is not None:
            if before is None:
                os.environ.pop(ENV, None)
            else:
                os.environ[ENV] = before


if __name__ == "__main__":
    sys.exit(main())
