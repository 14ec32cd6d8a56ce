"""The ``ttsim diagnose`` command: where a model's sim-to-real gap lies and which effect causes it.

    ttsim diagnose --data DATA --model MODEL --out DIR [--effects all|NAME,...] [--quick]
                   [--steps N] [--test-fraction F] [--seed S] [--max-segments N] [--no-landing] [--quiet]

The work is in :mod:`ttsim_jax.diagnose.diagnosis` and :mod:`ttsim_jax.diagnose.report`.
"""

from __future__ import annotations

import argparse
import sys

from ttsim_jax.cli.options import (UsageError, add_spin_option, existing_dir, model_name_or_file, open_fraction,
                                   positive_int, seed, writable_dir)

#: Most Adam steps per candidate ``--steps`` takes (the default converges in 100).
MAX_STEPS = 100_000


def effect_list(text: str) -> tuple:
    """Simulator effects of the catalogue: ``all`` or comma-separated names."""
    from ttsim_jax import effects as fx

    try:
        names = fx.parse_names(text)
    except fx.EffectError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    record = [n for n in names if fx.effect_class(n).WHERE != "simulator"]
    if record and text.strip() not in ("all", "*"):
        raise argparse.ArgumentTypeError(f"{', '.join(record)}: act on the record, not in the simulator; they are sized "
                                         "in every report, not fitted (choose among: "
                                         f"{', '.join(fx.names('simulator'))})")
    names = [n for n in names if fx.effect_class(n).WHERE == "simulator"]
    if not names:
        raise argparse.ArgumentTypeError(f"{text!r}: no simulator effect chosen")
    return tuple(names)


def register(subparsers) -> None:
    """Adds ``diagnose`` to the ``ttsim`` command."""
    from types import SimpleNamespace

    from ttsim_jax.diagnose import defaults
    from ttsim_jax.diagnose.defaults import FLAG_RATIO, MIN_REDUCTION

    d = SimpleNamespace(steps=defaults.STEPS, max_segments=defaults.MAX_SEGMENTS, test_fraction=defaults.TEST_FRACTION,
                        seed=0)
    q = SimpleNamespace(**{**vars(d), **defaults.QUICK})
    description = (
        "Diagnose the sim-to-real gap of a model on a dataset. WHERE: the model's errors per phase (flight "
        "segments, table contacts, racket contacts, landing of rollouts after racket contacts) binned by regime "
        "(speed, spin, spin ratio, spin axis, impact angle, contact distance, table position, time since the last "
        f"contact) with bootstrap intervals; a bin is flagged when its interval lies above {FLAG_RATIO} x the phase's "
        "mean. WHICH EFFECT: every simulator effect of the catalogue ('python -m ttsim_jax.effects') is fitted by "
        "gradient descent through the phase it acts in on a training split and scored by the reduction of the "
        f"held-out RMS error (significant: 95 % interval above {MIN_REDUCTION:g} % and a fall above the phase's "
        "resolution, and no phase it acts in materially worse); effects on the record (noise, "
        "missing frames, racket-state error) are sized instead. A fit that needs parameters beyond their plausible "
        "range (a 1-degree table tilt, an 8 cm/s indoor updraft) is reported, never accepted; candidates whose "
        "changes of the errors are nearly alike are reported as indistinguishable, with what data would separate "
        "them. HOW FAR: forward selection: each further significant effect is fitted together with those accepted "
        "before it and kept only when it adds significantly on top of them; the accepted effects fitted together, "
        "before and after (--quick: no joint fits). NOISE FLOOR: per phase, the error a perfect model would reach "
        "on this record (from its own position noise) and the removable gap above it; a model-free correction per "
        "phase measures how far the gap could shrink and names the variables that carry it. VERDICT: 'explained' "
        "only when the accepted effects close 70 % or more of the removable gap in every phase they act in; "
        "'partly explained' says how much each closes and where the rest lies; 'unexplained' when nothing "
        "plausible is significant; 'no gap' when, besides, every phase lies at its noise floor and nothing stands "
        "out. Writes report.md, diagnosis.json and PNG figures to --out.")
    p = subparsers.add_parser("diagnose", help="where the sim-to-real gap lies and which effect causes it",
                              description=description)
    p.add_argument("--data", metavar="DATA", type=existing_dir, help="dataset directory (required)")
    p.add_argument("--model", metavar="MODEL", type=model_name_or_file, default="conti2026",
                   help="bundled model name or model .toml file (default: %(default)s)")
    p.add_argument("--out", metavar="DIR", type=writable_dir, help="output directory (required)")
    p.add_argument("--effects", metavar="NAMES", type=effect_list, default=None,
                   help="candidate effects: 'all' (default: every simulator effect) or comma-separated names")
    p.add_argument("--quick", action="store_true",
                   help=f"a faster, coarser run: {q.steps} descent steps per candidate instead of {d.steps}, at most "
                   f"{q.max_segments} flight segments instead of every one, no landing rollouts, "
                   "no forward selection (every significant effect reported; none fitted together), no spin check "
                   "of the record")
    p.add_argument("--steps", type=positive_int, default=None, metavar="N",
                   help=f"Adam steps per candidate (default: {d.steps}, with --quick {q.steps})")
    p.add_argument("--test-fraction", type=open_fraction, default=d.test_fraction, metavar="F",
                   help="share of the segments and contacts held out for scoring (default: %(default)s)")
    p.add_argument("--seed", type=seed, default=d.seed, help="seed of the split, the segment subset and the "
                   "bootstraps (default: %(default)s)")
    p.add_argument("--max-segments", type=positive_int, default=None, metavar="N",
                   help="flight segments used at most, a seeded random subset of more, for speed (default: every "
                   f"segment; with --quick {q.max_segments})")
    p.add_argument("--no-landing", action="store_true", help="skip the landing rollouts (the slowest part)")
    p.add_argument("--no-spin-correction", action="store_true",
                   help="report the spin check only: without this, where it finds the record's measured spin off (a "
                   "sign, an axis, a scale), its correction is tried on the flight segments and, where it lowers the "
                   "held-out flight error significantly, every candidate is fitted with the corrected spin")
    add_spin_option(p, "flight segments' spin (latent: fitted under --model from the segment's own samples, which "
                    "then takes up any force across the flight)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_diagnose)
    sub = p.add_subparsers(dest="diagnose_command", metavar="[selfcheck]")
    sub.required = False
    s = sub.add_parser("selfcheck", help="withheld-effect validation of the diagnosis",
                       description="Generate data with each effect in turn, with pairs of effects, and with an effect "
                       "the candidates lack (conti2026 plus the effects at random magnitudes in the upper part of their "
                       "realistic range, plus paper-like position noise), hide them from the model, diagnose, and score: "
                       "the true effect ranked first and significant, the located phase, and the fraction of the "
                       "oracle's held-out error reduction (the model given the true effects) that the diagnosis "
                       "recovers; cases the oracle itself cannot resolve are reported apart as undetectable. Prints the "
                       "per-case table.")
    s.add_argument("--effects", metavar="NAMES", type=effect_list, default=None,
                   help="single effects to withhold in turn (default: every simulator effect; with --quick "
                   "spin_decay,air_flow,table_tilt,buckling)")
    s.add_argument("--quick", action="store_true", help="four single effects and the outside case, on smaller "
                   "datasets, diagnosed with 'ttsim diagnose --quick' on at most 384 flight segments "
                   "(default: every effect, four pairs and the outside case, every flight segment, the full diagnosis "
                   "without landing, with --quick's descent steps)")
    s.add_argument("--outside", action="store_true", help="run the suite outside the catalogue instead: each of "
                   "its effects generated and withheld from the candidates, some cases recorded as a tracker's raw "
                   "multi-throw log (no labelled events, imported through the CSV path) and in one direction only; "
                   "diagnosed at the user's default settings without the landing rollouts. Right: never 'explained' "
                   "(the cause is not a candidate) and the gap located in a phase the effect acts in")
    s.add_argument("--games", type=positive_int, default=None, help="games per generated dataset (default: 14, with "
                   "--quick 8)")
    s.add_argument("--seed", type=seed, default=0, help="seed of the generated datasets (default: %(default)s)")
    s.add_argument("--out", metavar="DIR", type=writable_dir, default=None,
                   help="also write selfcheck.md, selfcheck.json and selfcheck.png (found against the "
                   "oracle, per case) here, and each case as it finishes to DIR/cases/ (see --resume)")
    mode = s.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="continue an interrupted run in --out DIR: the cases "
                      "stored in DIR/cases/ are taken as they are (they must have been run with the same options), "
                      "the others are run")
    mode.add_argument("--force", action="store_true", help="discard the cases stored in --out DIR/cases/ and run "
                      "every case again")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_selfcheck)


def cmd_diagnose(args) -> int:
    """``diagnose``: the diagnosis -> report.md, diagnosis.json and figures in --out."""
    import jax.numpy as jnp
    from tqdm import tqdm

    from ttsim_jax.data import load
    from ttsim_jax.diagnose.diagnosis import NoData, Settings, diagnose, work_units
    from ttsim_jax.diagnose.report import write_report
    from ttsim_jax.params import load_model

    missing = [opt for opt, v in (("--data", args.data), ("--out", args.out)) if v is None]
    if missing:
        raise UsageError(f"ttsim diagnose: {' and '.join(missing)} required (or 'ttsim diagnose selfcheck'); see "
                         "'ttsim diagnose --help'")
    if args.steps is not None and args.steps > MAX_STEPS:
        raise UsageError(f"--steps {args.steps:,}: Adam steps per candidate, each a pass over every segment and "
                         f"contact; at most {MAX_STEPS:,} are taken (the default {Settings().steps} converges)")
    ds = load(args.data)
    model = load_model(args.model, dtype=jnp.float32)
    changes = dict(effects=args.effects, test_fraction=args.test_fraction, seed=args.seed, spin=args.spin)
    if args.steps is not None:
        changes["steps"] = args.steps
    if args.max_segments is not None:
        changes["max_segments"] = args.max_segments
    if args.no_landing:
        changes["landing"] = False
    if args.no_spin_correction:
        changes["spin_correct"] = False
    settings = Settings.quick(**changes) if args.quick else Settings(**changes)
    with tqdm(total=work_units(settings), desc="diagnose", unit="step", disable=args.quiet) as bar:
        def tick(what, n=1):
            bar.set_postfix_str(what)
            bar.update(n)

        try:
            out = diagnose(ds, model, settings, progress=tick)
        except NoData as e:
            raise UsageError(f"{args.data}: {e}") from None
    paths = write_report(out, args.out, data=str(args.data), model=str(args.model))
    print(out.verdict.text)
    print(f"written to {args.out}: " + ", ".join(p.name for p in paths.values()))
    return 0


def cmd_selfcheck(args) -> int:
    """``diagnose selfcheck``: the withheld-effect cases and their table."""
    import json

    from tqdm import tqdm

    from ttsim_jax.diagnose.candidates import candidate_names
    from ttsim_jax.diagnose.diagnosis import Settings
    from ttsim_jax.results import jsonable
    from ttsim_jax.diagnose.outside import outside_cases
    from ttsim_jax.diagnose.selfcheck import (GAMES, PAIRS, QUICK, SEGMENTS, ResumeError, cases, plot, selfcheck,
                                              stored_cases, table)
    from ttsim_jax.files.atomic import atomic_write

    if (args.resume or args.force) and args.out is None:
        raise UsageError("ttsim diagnose selfcheck: --resume and --force need --out DIR")
    stored = stored_cases(args.out) if args.out is not None else []
    if stored and not (args.resume or args.force):
        raise UsageError(f"--out {args.out}: {len(stored)} cases of an earlier run are stored in "
                         f"{args.out / 'cases'}: pass --resume to continue that run, or --force to run every case again")
    if args.resume and not stored:
        raise UsageError(f"--resume: no stored cases in {args.out / 'cases'} to continue")
    if args.force:
        for path in stored:
            path.unlink()
    size = "quick" if args.quick else "full"
    if args.outside:
        plan = outside_cases()
        settings = Settings.quick(max_segments=SEGMENTS[size]) if args.quick else Settings(landing=False)
    elif args.quick:
        plan = cases(args.effects or QUICK)
        settings = Settings.quick(max_segments=SEGMENTS[size])
    else:
        plan = cases(args.effects or candidate_names(), PAIRS)
        settings = Settings(landing=False, steps=Settings.quick().steps, max_segments=SEGMENTS[size])
    with tqdm(total=len(plan), desc="selfcheck", unit="case", disable=args.quiet) as bar:
        try:
            result = selfcheck(plan, settings, seed=args.seed, progress=lambda name: bar.update(1),
                               games=args.games or GAMES[size], store=args.out, resume=args.resume)
        except ResumeError as e:
            raise UsageError(str(e)) from None
        except KeyboardInterrupt:
            if args.out is None:
                raise
            print(f"error: interrupted; the finished cases are stored in {args.out / 'cases'}: rerun with --resume",
                  file=sys.stderr)
            return 1
    text = table(result)
    print(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write(args.out / "selfcheck.md", (text + "\n").encode(), "the selfcheck's table")
        atomic_write(args.out / "selfcheck.json", json.dumps(jsonable(result), indent=1).encode(), "the selfcheck")
        plot(result, args.out / "selfcheck.png")
    return 0
