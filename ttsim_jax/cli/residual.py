"""The ``ttsim train residual`` and ``ttsim evaluate residual`` commands: the racket residual
network trained on, and evaluated on, a dataset's racket contacts. Thin: parsing and printing; the
work is in :mod:`ttsim_jax.fit.racket_arrays` and :mod:`ttsim_jax.fit.network_training`.

    ttsim train residual --data DATA --out CHECKPOINT [--model conti2026|durr2026]
                         [--config configs/residual/NAME.toml] [--epochs N] [--seed S]
                         [--clusters K] [--resume | --force]
    ttsim evaluate residual --data DATA --checkpoint CHECKPOINT [--model NAME] [--split all|test]
                            [--json]
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import tomllib
from pathlib import Path

from ttsim_jax.cli.options import (UsageError, command_group, existing_dir, existing_file, positive_int, seed,
                                   text_file, writable_file)
from ttsim_jax.fit.pipeline import bundled_config

MODELS = ("conti2026", "durr2026")


def _bundled_values(table: str, key: str) -> str:
    """'1000 for conti2026, 500 for durr2026': a setting of the bundled configs, for --help."""
    values = []
    for model in MODELS:
        with open(bundled_config(model), "rb") as f:
            values.append(f"{tomllib.load(f)[table][key]} for {model}")
    return ", ".join(values)


def register(subparsers) -> None:
    """Adds ``train residual`` and ``evaluate residual`` to an argparse subparsers object.

    Arguments:
        subparsers: what ``ArgumentParser.add_subparsers()`` returned. If a ``train`` or
            ``evaluate`` command already exists there, ``residual`` is added to it.
    """
    train = command_group(subparsers, "train", "fit model components to measured data",
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

    evaluate = command_group(subparsers, "evaluate", "evaluate model components on measured data",
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
    from ttsim_jax.fit.racket_arrays import contact_arrays

    arrays = contact_arrays(ds, model_name, n_inputs=n_inputs)
    print(arrays.summary(), file=stream or sys.stdout)
    return arrays


def format_band_table(bands: list[dict], title: str) -> str:
    """A text table of :func:`ttsim_jax.fit.network_evaluation.evaluate_by_band` results: one row per
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
    from ttsim_jax.fit.network_evaluation import evaluate_by_band

    bands = evaluate_by_band(model, x, y_base, y_obs, distance)
    total = evaluate_by_band(model, x, y_base, y_obs, distance, edges=())[0]
    total["band"] = "all"
    return bands + [total]


def cmd_train_residual(args) -> int:
    """``train residual``: convert, train, save, report on the test split."""
    from ttsim_jax.data import load
    from ttsim_jax.fit.network_config import load_train_config
    from ttsim_jax.fit.network_training import split_by_contact, train_residual
    from ttsim_jax.physics.network_checkpoint import save_residual

    config_path = args.config or bundled_config(args.model)
    config, tcfg = load_train_config(config_path)
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
    n_train = len(split_by_contact(len(arrays), tcfg.split, tcfg.seed)[0])
    if config.n_clusters > n_train:
        print(f"{n_train} training contacts: the attenuation's k-means centres lowered from {config.n_clusters} "
              f"to {n_train} (--clusters sets them)")
        config = dataclasses.replace(config, n_clusters=n_train)
    if args.force and state.exists():
        state.unlink()
    try:
        model, report = train_residual(arrays.x, arrays.y_base, arrays.y_obs, config, tcfg, checkpoint=state,
                                       resume=args.resume, progress=not args.quiet)
    except KeyboardInterrupt:
        print("error: interrupted; the last completed epoch is saved: rerun with --resume", file=sys.stderr)
        return 1
    meta = {k: v for k, v in report.items() if k != "history"}
    meta.update(model=args.model, data=str(args.data), config_file=str(config_path), train_config=tcfg.to_dict(),
                contacts=dict(used=len(arrays), total=arrays.n_contacts, skipped=arrays.counts()))
    save_residual(out, model, metadata=meta)
    state.unlink(missing_ok=True)  # finished: a state left behind would only make the next run ask for --resume

    _, _, test = split_by_contact(len(arrays), tcfg.split, tcfg.seed)
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
    from ttsim_jax.fit.network_evaluation import evaluate_residual
    from ttsim_jax.fit.network_training import split_by_contact
    from ttsim_jax.physics.network_checkpoint import checkpoint_metadata, load_residual

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
        _, _, rows = split_by_contact(len(arrays), tuple(tc["split"]), int(tc["seed"]))
    if len(arrays.x[rows]) == 0:
        raise UsageError(f"--data {args.data}: no usable racket contacts")
    x, yb, yo, dist = arrays.x[rows], arrays.y_base[rows], arrays.y_obs[rows], arrays.distance[rows]
    overall = evaluate_residual(model, x, yb, yo)
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
