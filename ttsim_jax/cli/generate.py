"""The ``ttsim generate`` command: synthetic measured data with a known truth.

Thin: parses options, calls :mod:`ttsim_jax.reality`, prints a summary.
"""

from __future__ import annotations

import argparse
import json

from ttsim_jax.cli.options import UsageError, positive_int, seed, text_file, writable_dir


def register(subparsers) -> argparse.ArgumentParser:
    """Adds ``generate`` to an argparse subparsers object; sets ``func`` to :func:`cmd_generate`.

    Arguments:
        subparsers: what ``ArgumentParser.add_subparsers()`` returned.

    Returns:
        The ``generate`` parser.
    """
    p = subparsers.add_parser(
        "generate",
        help="generate synthetic measured data (games of robot vs opponent) with known effects and ground truth",
        description="Simulate games between a robot and an opponent with a truth model (conti2026 plus effects from "
                    "the effect catalogue), and write them as a dataset directory in the measured-data format, "
                    "with the ground truth beside it (truth.json, truth_events.parquet, truth_rackets.parquet, "
                    "truth_observations.parquet). Deterministic for a seed and configuration. The effects of the "
                    "catalogue: 'python -m ttsim_jax.effects' lists and describes them.",
    )
    p.add_argument("--out", required=True, metavar="DIR", type=writable_dir, help="dataset directory to write")
    p.add_argument("--preset", choices=["sample", "paper"], default=None,
                   help="starting configuration: 'sample' (3 games of 6 rallies, the bundled sample dataset) or 'paper' "
                        "(277 games, the scale of the paper's dataset); default: the generator's defaults (4 games)")
    p.add_argument("--config", metavar="FILE", default=None, type=text_file,
                   help="TOML file with [generator] settings and [effects] (enabled = [...], [effects.NAME] fixed "
                        "parameter values); applied after --preset, before the options below")
    p.add_argument("--games", type=positive_int, default=None, metavar="N", help="number of games (sessions) to generate")
    p.add_argument("--seed", type=seed, default=None, metavar="S", help="seed of every random stream (default 0)")
    p.add_argument("--effects", default=None, metavar="LIST",
                   help="effects that are on: comma-separated names, 'all' (default) or 'none'")
    p.add_argument("--lanes", type=positive_int, default=None, metavar="L", help="games simulated in parallel (default 256)")
    p.add_argument("--no-truth-observations", action="store_true",
                   help="do not write truth_observations.parquet (the noise-free state of every observation)")
    p.add_argument("--force", action="store_true", help="overwrite DIR if it holds a dataset")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=cmd_generate)
    return p


def cmd_generate(args) -> int:
    """``generate``: build the configuration, generate, write, print a summary."""
    from ttsim_jax.reality import generate, make_config, write

    out = args.out
    if out.exists() and any(out.iterdir()) and not args.force:
        raise UsageError(f"--out {out}: exists and is not empty; pass --force to overwrite it")
    from ttsim_jax.data.io import kept_entries

    kept_entries(out, overwrite=True)  # a folder that is no dataset is refused before the generation, not after
    cfg = make_config(args.preset, args.config, games=args.games, seed=args.seed, effects=args.effects,
                      lanes=args.lanes, truth_observations=False if args.no_truth_observations else None)
    gen = generate(cfg, progress=not args.quiet)
    write(gen, out, overwrite=True)
    summary = summarise(gen.truth, out, gen.wall_time_s)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


def summarise(truth: dict, out, wall_time_s: float = 0.0) -> dict:
    """The printed summary: where, counts, wall time, effects and their true parameters."""
    effects = {}
    for name, info in truth["effects"].items():
        if info["scope"] == "dataset":
            effects[name] = {"scope": "dataset", "params": info["params"], "units": info["units"]}
        else:
            per = [s["effects"][name] for s in truth["sessions"]]
            effects[name] = {"scope": "session", "params_game0": per[0] if per else {}, "units": info["units"],
                             "games": len(per)}
    return {"out": str(out), "seed": truth["seed"], "model": truth["model"], "counts": truth["counts"],
            "wall_time_s": round(wall_time_s, 2), "effects": effects}


def _fmt(v) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def format_summary(s: dict) -> str:
    """Human-readable text of :func:`summarise`'s dict."""
    c = s["counts"]
    ev = ", ".join(f"{k} {n}" for k, n in c["events"].items())
    bands = ", ".join(f"{k} {n}" for k, n in c["robot_contact_bands"].items())
    shots = ", ".join(f"{k} {n}" for k, n in c["shots"].items())
    lines = [
        f"wrote {s['out']} (seed {s['seed']}, truth model {s['model']} + effects) in {s['wall_time_s']:.1f} s",
        f"games:          {c['games']} ({c['rallies']} rallies)",
        f"observations:   {c['observations']}",
        f"segments:       {c['segments']} ({c['segments_with_spin_conf>=0.5']} with spin confidence >= 0.5)",
        f"events:         {ev}",
        f"table contacts: {c['table_contacts']}",
        f"racket:         robot {c['robot_racket_contacts']} (with racket states), opponent {c['opponent_racket_contacts']}",
        f"robot contacts by distance from the face centre: {bands}",
        f"shots:          {shots}",
        "effects (true parameters; per-game effects shown for game 0, all games in truth.json):",
    ]
    if not s["effects"]:
        lines.append("  none")
    for name, e in s["effects"].items():
        params = e.get("params", e.get("params_game0", {}))
        units = e["units"]
        body = ", ".join(f"{k}={_fmt(v)} {units[k]}" for k, v in params.items())
        lines.append(f"  {name} ({e['scope']}): {body}")
    return "\n".join(lines)

