"""``ttsim sensitivity``: Jacobians of where shots land, and error budgets (a thin wrapper over
:func:`ttsim_jax.sensitivity.study.run_study`)."""

from __future__ import annotations

from ttsim_jax.cli.options import (UsageError, existing_dir, existing_file, finite_float, model_name_or_file,
                                   positive_float, positive_int, seed, writable_dir)
from ttsim_jax.cli.simulate import MAX_DT, MAX_DURATION


def register(sub) -> None:
    """Adds ``sensitivity`` to an argparse subparsers object (``func``: :func:`cmd_sensitivity`)."""
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
    """``sensitivity``: check the options, run the study, print its report and the files written."""
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
