"""The ``ttsim evaluate`` command: models compared on a dataset, as in the paper's Results section.

    ttsim evaluate --data DATA --models nakashima2011,durr2026,conti2026[,MODEL.toml] --out DIR
                   [--split all|test] [--test-fraction F] [--seed S] [--stages flight,table,racket,landing]
                   [--horizon S] [--float64] [--quiet]

The work is in :mod:`ttsim_jax.evaluate.stages` and :mod:`ttsim_jax.evaluate.report`. ``ttsim evaluate residual`` (the residual
network on its own, :mod:`ttsim_jax.cli.residual`) stays a subcommand of the same group.
"""

from __future__ import annotations

import argparse

from ttsim_jax.cli.options import (UsageError, add_spin_option, command_group, existing_dir, fraction,
                                   model_name_or_file, positive_float, seed, writable_dir)

DEFAULT_MODELS = "nakashima2011,durr2026,conti2026"


def model_list(text: str) -> list[str]:
    """Comma-separated bundled model names or model ``.toml`` paths (each checked to exist)."""
    items = [t.strip() for t in text.split(",")]
    if not all(items):
        raise argparse.ArgumentTypeError(f"{text!r}: an empty model name; expected names or .toml paths separated by commas")
    for item in items:
        try:
            model_name_or_file(item)
        except argparse.ArgumentTypeError as e:
            raise argparse.ArgumentTypeError(f"{item!r}: {e}") from None
    if len(set(items)) != len(items):
        raise argparse.ArgumentTypeError(f"{text!r}: a model is given twice")
    return items


def stage_list(text: str) -> list[str]:
    """Comma-separated stages of :data:`ttsim_jax.evaluate.report.STAGES`."""
    from ttsim_jax.evaluate.stages import STAGES

    items = [t.strip() for t in text.split(",")]
    unknown = [t for t in items if t not in STAGES]
    if unknown:
        raise argparse.ArgumentTypeError(f"{text!r}: unknown stage(s) {unknown}; stages: {','.join(STAGES)}")
    return items


def register(subparsers) -> None:
    """Adds the model comparison to the ``evaluate`` group (created here if no other module did)."""
    description = ("Compare models on a dataset as in the paper's Results section: flight-segment 3-D position RMSE "
                   "(violin plot, median, 75th percentile, reductions against nakashima2011), table-contact errors "
                   "per component, racket-contact errors by contact-distance band (0-5, 5-8, > 8 cm) and the "
                   "landing-position error of rollouts from the last observation before each racket contact. "
                   "Writes PNG figures, report.md, metrics.json (every number) and samples.npz (per-item values) "
                   "to --out. Stages the dataset has no data for are skipped, with the reason in the report.")
    sub = command_group(subparsers, "evaluate", "evaluate models on measured data", description)
    parser = subparsers.choices["evaluate"]
    parser.description = description + " 'ttsim evaluate residual' evaluates a residual network alone."
    sub.required = False
    sub.metavar = "[residual]"  # optional: without it, the models are evaluated
    parser.add_argument("--data", metavar="DATA", type=existing_dir, help="dataset directory (required)")
    parser.add_argument("--models", metavar="MODELS", type=model_list,
                        help=f"comma-separated bundled model names or model .toml files (default: {DEFAULT_MODELS})")
    parser.add_argument("--out", metavar="DIR", type=writable_dir, help="output directory (required)")
    parser.add_argument("--split", choices=("all", "test"), default="all",
                        help="evaluate every session (default) or only the held-out sessions of "
                        "'ttsim fit --test-fraction F --seed S' (same F and S)")
    parser.add_argument("--test-fraction", type=fraction, default=None, metavar="F",
                        help="with --split test (required there): the fraction of sessions held out, as given to "
                        "'ttsim fit'")
    parser.add_argument("--seed", type=seed, default=0, help="with --split test: seed of the draw (default: %(default)s)")
    parser.add_argument("--stages", type=stage_list, default=None, metavar="STAGES",
                        help="comma-separated subset of flight,table,racket,landing (default: all)")
    parser.add_argument("--horizon", type=positive_float, default=1.5, metavar="S",
                        help="longest landing rollout [s] (default: %(default)s)")
    add_spin_option(parser, "flight segments' spin, and so the spin a bounce or a racket contact receives (a "
                    "racket contact after a bounce: the spin leaving it, both segments fitted as one flight; with "
                    "'measured' a bounce without a measured spin takes spin 0 and a racket contact without one is "
                    "skipped)")
    parser.add_argument("--float64", action="store_true", help="simulate in float64 (default: float32)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=cmd_evaluate)


def cmd_evaluate(args) -> int:
    """``evaluate``: every stage for every model -> report, figures and numbers in --out."""
    from ttsim_jax.data import load
    from ttsim_jax.evaluate.report import write_report
    from ttsim_jax.evaluate.stages import STAGES, EvaluateSettings, evaluate_models
    from ttsim_jax.fit.identify import split_sessions

    missing = [opt for opt, v in (("--data", args.data), ("--out", args.out)) if v is None]
    if missing:
        raise UsageError(f"ttsim evaluate: {' and '.join(missing)} required (or a subcommand: 'ttsim evaluate "
                         "residual'); see 'ttsim evaluate --help'")
    ds = load(args.data)
    sessions = None
    if args.split == "test":
        if args.test_fraction is None:
            raise UsageError("--split test: give --test-fraction F (and --seed S) as given to 'ttsim fit', so that the "
                             "same sessions are held out")
        sessions = tuple(int(s) for s in split_sessions(ds.segments["session_id"], args.test_fraction, args.seed))
        if not sessions:
            raise UsageError(f"--split test: --test-fraction {args.test_fraction:g} of the "
                             f"sessions of {args.data} holds out none")
    settings = EvaluateSettings(horizon=args.horizon, sessions=sessions, float64=args.float64, spin=args.spin)
    models = args.models or DEFAULT_MODELS.split(",")
    result = evaluate_models(ds, models, settings, stages=args.stages or STAGES, progress=not args.quiet)
    paths = write_report(result, args.out, data=str(args.data))
    print(paths["report"].read_text())
    print(f"written to {args.out}: " + ", ".join(p.name for p in paths.values()))
    return 0
