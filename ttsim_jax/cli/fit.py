"""The ``ttsim fit`` command: a model identified from one or several datasets, stage by stage.
Thin: parsing and printing; the work is in :func:`ttsim_jax.fit.pipeline.fit_dataset`.

    ttsim fit --data DATA [--data DATA ...] --out MODEL.toml [--stages aero,table,racket[,residual]]
              [--base conti2026] [--association averaged|v_eff] [--forms drag|magnus|drag,magnus]
              [--min-spin-conf C] [--max-rmse-mm R]
              [--folds K] [--lambda-rule 1se|min] [--epochs N] [--test-fraction F] [--seed S] [--force] [--quiet]
"""

from __future__ import annotations

import argparse
import sys

from ttsim_jax.cli.options import (UsageError, add_spin_option, existing_dir, finite_float, fraction,
                                   model_name_or_file, positive_float, positive_int, seed, writable_file)


def _stages(text: str) -> tuple:
    """Comma-separated stages of :data:`ttsim_jax.fit.choices.STAGES`, in the order they run."""
    from ttsim_jax.fit.choices import STAGES

    names = tuple(x.strip() for x in text.split(",") if x.strip())
    bad = [x for x in names if x not in STAGES]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(STAGES)}; got {text!r}")
    return tuple(x for x in STAGES if x in names)  # run in pipeline order


def register(subparsers) -> None:
    """Adds ``fit`` to an argparse subparsers object (``func``: :func:`cmd_fit`)."""
    from ttsim_jax.fit.choices import ASSOCIATIONS, DEFAULT_FORMS, DEFAULT_STAGES

    p = subparsers.add_parser(
        "fit",
        help="identify a model (aerodynamics, table and racket contacts, optionally the racket residual network) "
        "from one or several datasets",
        description="Identify a model from DATA (several --data are merged), stage by stage, into ONE model config "
        "OUT (loadable with load_model / --model OUT) and a summary OUT.fit.json that holds the config's text "
        "(per stage: counts used and skipped by reason, fitted values with standard errors, the fitted model against "
        "the base on the held-out sessions, wall and CPU time). Without --stages, the stages "
        f"{','.join(DEFAULT_STAGES)} that the data supports run and the others are skipped with the reason; a stage "
        "named in --stages that the data cannot support is refused before any work. If a stage fails, the stages "
        "fitted before it are written and the exit status is 1. "
        "aero: C_D, C_M and the initial state per flight segment at its measured spin, or at its latent spin where "
        "none was measured (one compiled, batched Levenberg-Marquardt solver), segments above --max-rmse-mm dropped, "
        "the coefficients regressed into the "
        "paper's forms (the C_D breakpoint table over Re and Sp, C_M linear/quadratic in the spin rate per reference "
        "speed). table: states before and after each table bounce with a measured spin on both sides, e0 and e1 of "
        "the restitution law (held within [e_min, e_max]: no bounce gains energy) and the four local residual "
        "matrices by L1-regularised least squares (penalty by cross-validation; the sparsity pattern is reported). "
        "racket: the updated base model's e0, e1, et0, et1, e_s by least squares on the racket contacts' "
        "racket-frame states. residual: the racket residual network on what the fitted base model leaves (as 'ttsim "
        "train residual'), written to OUT's stem + .ttres. Parameters of stages not run, and entries without data, "
        "come from --base.",
    )
    p.add_argument("--data", required=True, action="append", metavar="DATA", type=existing_dir,
                   help="dataset directory (see docs/data_format.md; 'ttsim data import' converts the public datasets); "
                   "repeat it to fit several datasets together (merged, their ids renumbered)")
    p.add_argument("--out", required=True, metavar="OUT", type=writable_file,
                   help="model config to write, e.g. runs/fitted.toml ('.toml' is added if missing); the model's "
                   "name is the file's stem")
    p.add_argument("--stages", type=_stages, metavar="LIST",
                   help="comma-separated stages to run, of aero, table, racket, residual; each must be one the data "
                   f"supports (default: those of {','.join(DEFAULT_STAGES)} that the data supports; residual trains "
                   "the network, minutes)")
    p.add_argument("--base", default="conti2026", metavar="MODEL", type=model_name_or_file,
                   help="base model: ball, air, the forms' breakpoints, the values where data is missing, and every "
                   "parameter no stage fits (default: %(default)s)")
    p.add_argument("--association", choices=ASSOCIATIONS, default="averaged",
                   help="aero: how a segment's coefficient enters the forms: 'averaged', the force-weighted mean of "
                   "the form along the segment (default), or 'v_eff', the form at the paper's effective speed")
    p.add_argument("--forms", choices=("drag,magnus", "drag", "magnus"), default=",".join(DEFAULT_FORMS),
                   metavar="{drag,magnus | drag | magnus}",
                   help="aero: which forms to fit; the other keeps the base model's values (default: %(default)s, "
                   "which fits held-out measured flights best: see docs/measurements/fitting.md)")
    p.add_argument("--min-spin-conf", type=finite_float, default=0.5, metavar="C",
                   help="segments (aero) and contacts (table, racket: before and after) with a lower spin confidence "
                   "are not used (default: %(default)s)")
    p.add_argument("--max-rmse-mm", type=positive_float, default=20.0, metavar="R",
                   help="aero: segments whose constant-coefficient fit has a larger 3-D RMSE are dropped "
                   "(default: %(default)s)")
    p.add_argument("--folds", type=positive_int, default=5, metavar="K",
                   help="table: K of the cross-validation choosing the L1 penalty (default: %(default)s)")
    p.add_argument("--lambda-rule", choices=("1se", "min"), default="1se",
                   help="table: the penalty with the least CV error ('min') or the largest within one standard error "
                   "of it ('1se', sparser; default)")
    p.add_argument("--epochs", type=positive_int, metavar="N",
                   help="residual: maximum number of epochs (default: the bundled conti2026 residual config's)")
    p.add_argument("--test-fraction", type=fraction, default=0.0, metavar="F",
                   help="fraction of each dataset's sessions held out of every stage, listed in OUT.fit.json; the "
                   "fitted model is compared with the base on them (the same sessions as 'ttsim evaluate --split test' "
                   "with the same fraction and seed on that dataset; default: %(default)s)")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of the held-out draw and of the cross-validation folds (default: %(default)s)")
    add_spin_option(p, "spins of the flight segments: those the fitted and the base model are compared on, and "
                    "for aero's C_D those of the segments without a measured spin (auto, latent: their latent spin, "
                    "fitted under the base model; measured, zero: left out). C_M is fitted from measured spins only: a "
                    "latent spin is the one the base's C_M needs, and would return it")
    p.add_argument("--per-racket", action="store_true",
                   help="also fit each racket configuration the data name (rackets.config, as 'ttsim data import "
                   "--source tt_rackets' writes) on its own: the updated base model (and, with residual in --stages, "
                   "the residual network) on its contacts less a held-out --test-fraction of them (0.2 if not given), "
                   "scored held out against --base's constants and a model-free quadratic regression; written as "
                   "racket files OUT's stem + '.rackets/NAME.toml' (load_model(BASE, racket=FILE), a task's "
                   "racket_config)")
    p.add_argument("--force", action="store_true", help="overwrite OUT (and its network checkpoint) if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_fit)


class _Bars:
    """One progress bar per stage, for :func:`ttsim_jax.fit.pipeline.fit_dataset`'s ``progress``."""

    def __init__(self):
        self.bar, self.stage = None, None

    def __call__(self, stage: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if stage != self.stage:
            self.close()
            self.bar, self.stage = tqdm(total=total, desc=f"fit {stage}", file=sys.stderr), stage
        self.bar.total = total
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.bar, self.stage = None, None


def cmd_fit(args) -> int:
    """``fit``: identification of one or several datasets -> model config (+ checkpoint) + JSON summary."""
    from ttsim_jax.fit.pipeline import (FitError, FitSettings, StageFailed, fit_dataset, load_datasets, output_paths,
                                        write_fit)

    paths = output_paths(args.out)
    out = paths["toml"]
    wanted = [paths["toml"], paths["json"]] + ([paths["network"]] if args.stages and "residual" in args.stages else [])
    existing = [str(p) for p in wanted if p.exists()]
    if existing and not args.force:
        raise UsageError(f"--out {out}: the output already exists ({', '.join(existing)}); pass --force to "
                         "overwrite it")
    datasets, labels = load_datasets(args.data)
    for ds, label in zip(datasets, labels):
        print(f"loaded {label}: {len(ds.segments['segment_id'])} segments, {len(ds.observations['t'])} observations, "
              f"{len(ds.events['event_id'])} events")
    settings = FitSettings(association=args.association, forms=tuple(args.forms.split(",")),
                           min_spin_conf=args.min_spin_conf, max_rmse=args.max_rmse_mm / 1000.0, folds=args.folds,
                           lambda_rule=args.lambda_rule, epochs=args.epochs, test_fraction=args.test_fraction,
                           seed=args.seed, spin=args.spin)
    bars = _Bars()

    def log(text):
        bars.close()
        print(text)

    data = " ".join(f"--data {x}" for x in labels)
    try:
        result = fit_dataset(datasets, args.base, stages=args.stages, settings=settings, labels=labels, name=out.stem,
                             progress=None if args.quiet else bars, log=log)
    except FitError as e:
        bars.close()
        if e.problems:
            raise UsageError("; ".join(f"--stages {s}: {data}: {why}" for s, why in e.problems.items())
                             + f"; leave {','.join(e.problems)} out of --stages (without --stages, the stages the data "
                             "cannot fit are skipped)") from None
        raise UsageError(f"{data}: {e}") from None
    except StageFailed as e:
        bars.close()
        if not e.partial.fitted:
            raise e.cause from None
        written = write_fit(e.partial, out, force=args.force)
        print(f"stage {e.stage} failed (below); wrote what the stages before it fitted "
              f"({', '.join(e.partial.fitted)}) to {written['toml']} and {written['json']} (its 'failed' names the "
              "stage)", file=sys.stderr)
        raise e.cause from None
    bars.close()
    written = write_fit(result, out, force=args.force)
    for name, t in result.report["seconds"].items():
        print(f"{name}: {t['wall']:.1f} s wall, {t['cpu']:.1f} s CPU")
    extra = f" with --residual {written['network']}" if "network" in written else ""
    print(f"wrote {out} (load_model({str(out)!r}) or --model {out}){extra} and {written['json']}")
    if args.per_racket:
        _per_racket(args, datasets, labels, out)
    missed = [s for s in (args.stages or ()) if s in result.skipped]
    if missed:
        for s in missed:
            print(f"error: --stages {s}: skipped: {result.skipped[s]}", file=sys.stderr)
        return 1
    return 0


def _per_racket(args, datasets, labels, out) -> None:
    """``--per-racket``: :func:`ttsim_jax.fit.racket_configs.fit_configs` per dataset, the racket files
    beside OUT."""
    from ttsim_jax.fit.racket_configs import best, fit_configs, write_racket_file

    folder = out.with_suffix(".rackets")
    network = bool(args.stages and "residual" in args.stages)
    for ds, label in zip(datasets, labels):
        if not any(str(c) for c in ds.rackets["config"]):
            print(f"--per-racket: {label}: its racket states name no configuration (rackets.config); skipped")
            continue
        print(f"--per-racket: {label}: fitting each configuration" + (" (with its residual network)" if network else ""),
              flush=True)
        fits = fit_configs(ds, args.base, test_fraction=args.test_fraction or 0.2, seed=args.seed, network=network,
                           progress=(lambda s: None) if args.quiet else print)
        for f in fits:
            path = write_racket_file(f, folder, f"ttsim fit --per-racket on {label}", seed=args.seed)
            t = f.report["test"][best(f.report)]
            print(f"  {f.name}: wrote {path} (held out: |dv| {t['dv']:.3f} m/s, |dw| {t['dw']:.1f} rad/s; {f.report['form']})")
