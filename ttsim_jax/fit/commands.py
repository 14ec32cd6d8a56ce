"""The ``ttsim fit``, ``ttsim train residual`` and ``ttsim evaluate residual`` commands. Thin:
parsing and printing; the work is in :mod:`ttsim_jax.fit.pipeline` (the stages of ``fit``), which
calls :mod:`ttsim_jax.fit.identify`, :mod:`ttsim_jax.fit.table` and :mod:`ttsim_jax.fit.racket`,
and :mod:`ttsim_jax.fit.contacts` and :mod:`ttsim_jax.fit.residual`.

``ttsim_jax/cli.py`` calls :func:`register` with its subparsers object; every command sets
``func`` on the parsed namespace to a callable ``func(args) -> int`` (the exit status); user
errors are raised (the library's errors, :class:`ttsim_jax.cli.UsageError`) and reported by
:func:`ttsim_jax.cli.main` with status 2.

    ttsim fit --data DATA [--data DATA ...] --out MODEL.toml [--stages aero,table,racket[,residual]]
              [--base conti2026] [--association averaged|v_eff] [--forms drag|magnus|drag,magnus]
              [--min-spin-conf C] [--max-rmse-mm R]
              [--folds K] [--lambda-rule 1se|min] [--epochs N] [--test-fraction F] [--seed S] [--force] [--quiet]
    ttsim train residual --data DATA --out CHECKPOINT [--model conti2026|durr2026]
                         [--config configs/residual/NAME.toml] [--epochs N] [--seed S]
                         [--clusters K] [--resume | --force]
    ttsim evaluate residual --data DATA --checkpoint CHECKPOINT [--model NAME] [--split all|test]
                            [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import tomllib
from pathlib import Path

from ttsim_jax.cli import (UsageError, existing_dir, existing_file, finite_float, model_name_or_file, positive_float,
                           positive_int, seed, text_file, writable_file)
from ttsim_jax.fit.pipeline import bundled_config

MODELS = ("conti2026", "durr2026")


def _bundled_values(table: str, key: str) -> str:
    """'1000 for conti2026, 500 for durr2026': a setting of the bundled configs, for --help."""
    values = []
    for model in MODELS:
        with open(bundled_config(model), "rb") as f:
            values.append(f"{tomllib.load(f)[table][key]} for {model}")
    return ", ".join(values)


def _group(subparsers, name: str, help: str, description: str):
    """The sub-subparsers of the top-level command ``name``, created if no other module did."""
    parser = subparsers.choices.get(name) if hasattr(subparsers, "choices") else None
    if parser is not None:
        for action in parser._actions:  # another module registered the group: extend it
            if isinstance(action, argparse._SubParsersAction):
                return action
    parser = subparsers.add_parser(name, help=help, description=description)
    sub = parser.add_subparsers(dest=f"{name}_command", metavar="WHAT")
    sub.required = True
    return sub


def _fraction(text: str) -> float:
    value = finite_float(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1), got {text!r}")
    return value


def _stages(text: str) -> tuple:
    from ttsim_jax.fit.choices import STAGES

    names = tuple(x.strip() for x in text.split(",") if x.strip())
    bad = [x for x in names if x not in STAGES]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(STAGES)}; got {text!r}")
    return tuple(x for x in STAGES if x in names)  # run in pipeline order


def _register_fit(subparsers) -> None:
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
        "aero: C_D, C_M and the initial state per flight segment with a measured spin (one compiled, batched "
        "Levenberg-Marquardt solver), segments above --max-rmse-mm dropped, the coefficients regressed into the "
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
    p.add_argument("--test-fraction", type=_fraction, default=0.0, metavar="F",
                   help="fraction of each dataset's sessions held out of every stage, listed in OUT.fit.json; the "
                   "fitted model is compared with the base on them (the same sessions as 'ttsim evaluate --split test' "
                   "with the same fraction and seed on that dataset; default: %(default)s)")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of the held-out draw and of the cross-validation folds (default: %(default)s)")
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
                           seed=args.seed)
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
    missed = [s for s in (args.stages or ()) if s in result.skipped]
    if missed:
        for s in missed:
            print(f"error: --stages {s}: skipped: {result.skipped[s]}", file=sys.stderr)
        return 1
    return 0


def register(subparsers) -> None:
    """Adds ``fit``, ``train residual`` and ``evaluate residual`` to an argparse subparsers object.

    Arguments:
        subparsers: what ``ArgumentParser.add_subparsers()`` returned. If a ``train`` or
            ``evaluate`` command already exists there, ``residual`` is added to it.
    """
    _register_fit(subparsers)
    train = _group(subparsers, "train", "fit model components to measured data",
                   "Fit model components to measured data.")
    p = train.add_parser(
        "residual",
        help="train the racket residual network on a dataset's racket contacts",
        description="Convert DATA's racket contacts into racket-frame training arrays, train the residual network "
        "(80/10/10 split by contact, early stopping, population batch-norm statistics, sigma calibration on the "
        "validation split) and write CHECKPOINT. Ends with the test split's errors against the base model by "
        "contact-distance band.",
    )
    p.add_argument("--data", required=True, metavar="DATA", type=existing_dir,
                   help="dataset directory (see docs/data_format.md; the bundled sample is ttsim_jax/data/sample/games)")
    p.add_argument("--out", required=True, metavar="CHECKPOINT", type=writable_file,
                   help="residual checkpoint to write (e.g. runs/net.ttres); the training state goes to "
                   "CHECKPOINT.state while it runs and is removed when it finishes")
    p.add_argument("--model", choices=MODELS, default="conti2026",
                   help="simulator model whose racket base model the network corrects (default conti2026: 8 inputs; "
                   "durr2026: 6 inputs, racket spin ignored)")
    p.add_argument("--config", metavar="TOML", type=text_file,
                   help="residual config with [model], [attenuation], [training] "
                   "(default: the bundled configs/residual/MODEL.toml)")
    p.add_argument("--epochs", type=positive_int, metavar="N",
                   help="maximum number of epochs (default: the config's max_epochs, "
                   f"{_bundled_values('training', 'max_epochs')})")
    p.add_argument("--seed", type=seed, metavar="S",
                   help="seed of split, initialisation and shuffling (default: the config's seed, "
                   f"{_bundled_values('training', 'seed')})")
    p.add_argument("--clusters", type=positive_int, metavar="K",
                   help="k-means centres of the attenuation (default: the config's n_clusters, "
                   f"{_bundled_values('model', 'n_clusters')}); lowered, with a message, to the number of "
                   "training contacts when there are fewer")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true",
                      help="continue an interrupted run from CHECKPOINT.state (same data and settings)")
    mode.add_argument("--force", action="store_true",
                      help="discard an existing CHECKPOINT.state and overwrite CHECKPOINT")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train_residual)

    evaluate = _group(subparsers, "evaluate", "evaluate model components on measured data",
                      "Evaluate model components on measured data.")
    e = evaluate.add_parser(
        "residual",
        help="errors of a trained residual network against its base model on a dataset",
        description="Convert DATA's racket contacts like 'train residual' and print the errors of the base model "
        "and of base + residual, by contact-distance band, and the fraction inside one predicted sigma.",
    )
    e.add_argument("--data", required=True, metavar="DATA", type=existing_dir, help="dataset directory")
    e.add_argument("--checkpoint", required=True, metavar="CKPT", type=existing_file,
                   help="residual checkpoint written by 'train residual'")
    e.add_argument("--model", choices=MODELS,
                   help="base model (default: the one the checkpoint was trained for; another is refused)")
    e.add_argument("--split", choices=("all", "test"), default="all",
                   help="evaluate all usable contacts (default) or only the test split of training "
                   "(same data, split and seed as stored in the checkpoint)")
    e.add_argument("--json", action="store_true", help="print the results as JSON")
    e.set_defaults(func=cmd_evaluate_residual)


# ----------------------------------------------------------------------------------------------


def _convert(ds, model_name: str, n_inputs: int, stream=None):
    from ttsim_jax.fit.contacts import contact_arrays

    arrays = contact_arrays(ds, model_name, n_inputs=n_inputs)
    print(arrays.summary(), file=stream or sys.stdout)
    return arrays


def format_band_table(bands: list[dict], title: str) -> str:
    """A text table of :func:`ttsim_jax.fit.residual.evaluate_by_band` results: one row per
    quantity, one column per band; cells 'base -> residual' median absolute errors."""
    units = dict(v_x="m/s", v_y="m/s", v_z="m/s", w_x="rad/s", w_y="rad/s", w_z="rad/s")
    units["|v|"], units["|w|"] = "m/s", "rad/s"

    def cell(b, q):
        if b["n"] == 0:
            return "-"
        fmt = "{:.3f}" if units[q] == "m/s" else "{:.1f}"
        return f"{fmt.format(b['base'][q])} -> {fmt.format(b['residual'][q])}"

    heads = [f"{b['band']} (n={b['n']})" for b in bands]
    rows = [[q, units[q]] + [cell(b, q) for b in bands] for q in units]
    rows.append(["inside 1 sigma", ""]
                + ["-" if b["n"] == 0 else f"{100 * b['within_one_sigma']:.1f} %" for b in bands])
    widths = [max(len(r[0]) for r in rows + [["quantity"]]), 5]
    widths += [max(len(h), *(len(r[2 + i]) for r in rows)) for i, h in enumerate(heads)]
    def line(cells):
        return "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    out = [title, line(["quantity", "unit"] + heads), line(["-" * w for w in widths])]
    out += [line(r) for r in rows]
    out.append("median absolute errors in the racket frame, base model -> base + residual; |v|, |w|: errors of the "
               "speed and spin magnitudes")
    return "\n".join(out)


def _bands_with_total(model, x, y_base, y_obs, distance):
    from ttsim_jax.fit.residual import evaluate_by_band

    bands = evaluate_by_band(model, x, y_base, y_obs, distance)
    total = evaluate_by_band(model, x, y_base, y_obs, distance, edges=())[0]
    total["band"] = "all"
    return bands + [total]


def cmd_train_residual(args) -> int:
    """``train residual``: convert, train, save, report on the test split."""
    from ttsim_jax.data import load
    from ttsim_jax.fit import residual as F
    from ttsim_jax.physics.residual import save_residual

    config_path = args.config or bundled_config(args.model)
    config, tcfg = F.load_train_config(config_path)
    if args.epochs is not None:
        tcfg = dataclasses.replace(tcfg, max_epochs=args.epochs)
    if args.seed is not None:
        tcfg = dataclasses.replace(tcfg, seed=args.seed)
    if args.clusters is not None:
        config = dataclasses.replace(config, n_clusters=args.clusters)
    out = Path(args.out)
    state = Path(str(out) + ".state")
    if not args.resume and not args.force and state.exists():
        raise UsageError(f"--out {out}: the training state {state} of an unfinished run exists: pass --resume to "
                         "continue it, or --force to start over")
    if not args.resume and not args.force and out.exists():
        raise UsageError(f"--out {out}: already exists; pass --force to overwrite it")
    if args.resume and not state.exists():
        if out.exists():
            raise UsageError(f"--resume: {out} is a finished run (no training state {state} left): nothing to "
                             "resume; pass --force to train again")
        raise UsageError(f"--resume: no training state {state} to continue")
    ds = load(args.data)
    arrays = _convert(ds, args.model, config.n_inputs)
    if len(arrays) < 3:
        raise UsageError(f"--data {args.data}: only {len(arrays)} usable racket contacts; at least 3 are needed "
                         "(train / validation / test)")
    n_train = len(F.split_by_contact(len(arrays), tcfg.split, tcfg.seed)[0])
    if config.n_clusters > n_train:
        print(f"{n_train} training contacts: the attenuation's k-means centres lowered from {config.n_clusters} "
              f"to {n_train} (--clusters sets them)")
        config = dataclasses.replace(config, n_clusters=n_train)
    if args.force and state.exists():
        state.unlink()
    try:
        model, report = F.train_residual(arrays.x, arrays.y_base, arrays.y_obs, config, tcfg, checkpoint=state,
                                         resume=args.resume, progress=not args.quiet)
    except KeyboardInterrupt:
        print("error: interrupted; the last completed epoch is saved: rerun with --resume", file=sys.stderr)
        return 1
    meta = {k: v for k, v in report.items() if k != "history"}
    meta.update(model=args.model, data=str(args.data), config_file=str(config_path), train_config=tcfg.to_dict(),
                contacts=dict(used=len(arrays), total=arrays.n_contacts, skipped=arrays.counts()))
    save_residual(out, model, metadata=meta)
    state.unlink(missing_ok=True)  # finished: a state left behind would only make the next run ask for --resume

    _, _, test = F.split_by_contact(len(arrays), tcfg.split, tcfg.seed)
    bands = _bands_with_total(model, arrays.x[test], arrays.y_base[test], arrays.y_obs[test], arrays.distance[test])
    cal = report["sigma_calibration"]
    print(f"trained {report['epochs']} epochs (best {report['best_epoch']}, validation loss "
          f"{report['best_val_loss']:.4g}); wrote {out}")
    print(f"sigma calibration ({cal['mode']}): factors "
          + ", ".join(f"{k} {v:.3g}" for k, v in cal["factors"].items())
          + f"; test split inside one sigma {100 * report['within_one_sigma_overall']:.1f} % "
          f"(uncalibrated {100 * report['within_one_sigma_uncalibrated_overall']:.1f} %)")
    print(format_band_table(bands, f"test split ({len(test)} contacts), model {args.model}:"))
    return 0


def cmd_evaluate_residual(args) -> int:
    """``evaluate residual``: base vs base + residual on a dataset, by contact-distance band."""
    from ttsim_jax.data import load
    from ttsim_jax.fit import residual as F
    from ttsim_jax.physics.residual import checkpoint_metadata, load_residual

    model = load_residual(args.checkpoint)
    meta = checkpoint_metadata(args.checkpoint)
    name = meta.get("model") or ("conti2026" if model.config.n_inputs == 8 else "durr2026")
    if args.model and args.model != name:
        raise UsageError(f"--checkpoint {args.checkpoint} was trained for the {name} base model "
                         f"({model.config.n_inputs} inputs); it cannot correct --model {args.model}")
    ds = load(args.data)
    arrays = _convert(ds, name, model.config.n_inputs, sys.stderr if args.json else None)
    rows = slice(None)
    if args.split == "test":
        tc = meta.get("train_config")
        if not tc:
            raise UsageError(f"--checkpoint {args.checkpoint}: no training configuration stored; use --split all")
        _, _, rows = F.split_by_contact(len(arrays), tuple(tc["split"]), int(tc["seed"]))
    if len(arrays.x[rows]) == 0:
        raise UsageError(f"--data {args.data}: no usable racket contacts")
    x, yb, yo, dist = arrays.x[rows], arrays.y_base[rows], arrays.y_obs[rows], arrays.distance[rows]
    overall = F.evaluate_residual(model, x, yb, yo)
    bands = _bands_with_total(model, x, yb, yo, dist)
    if args.json:
        clean = lambda v: None if isinstance(v, float) and not math.isfinite(v) else v  # noqa: E731
        bands = [{k: ({q: clean(e) for q, e in v.items()} if isinstance(v, dict) else clean(v)) for k, v in b.items()}
                 for b in bands]
        print(json.dumps(dict(model=name, checkpoint=str(args.checkpoint), split=args.split, overall=overall,
                              bands=bands), indent=2))
        return 0
    print(f"inside one sigma: {100 * overall['within_one_sigma_overall']:.1f} %; median velocity error "
          f"{overall['median_vel_error_base']:.3f} -> {overall['median_vel_error_residual']:.3f} m/s, spin "
          f"{overall['median_spin_error_base']:.1f} -> {overall['median_spin_error_residual']:.1f} rad/s")
    print(format_band_table(bands, f"{args.split} contacts of {os.fspath(args.data)} ({len(x)}), model {name}:"))
    return 0
