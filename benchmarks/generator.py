"""Reality-generator wall time at the scale of the paper's dataset.

Generates the ``paper`` preset (277 games; the paper reports about 58,000 flight segments, 25,000
table contacts and 11,000 robot racket contacts) with every effect on, and prints JSON: the wall
time of the generation (``wall_s``, after a one-game warm-up that compiles most kernels and is
timed apart; kernels for larger batches still compile inside the run), the counts and the
machine. Optionally writes the dataset.

    python benchmarks/generator.py --out-json benchmarks/results/generator_cpu.json
    python benchmarks/generator.py --games 20            # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax

from ttsim_jax.reality import generate, make_config, write

PAPER = {"games": 277, "segments": 58000, "table_contacts": 25000, "robot_racket_contacts": 11000}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", choices=["paper", "sample"], default="paper", help="generator preset (default: %(default)s)")
    p.add_argument("--games", type=int, default=None, help="override the preset's number of games")
    p.add_argument("--seed", type=int, default=0, help="seed (default: %(default)s)")
    p.add_argument("--effects", default="all", help="effects that are on: names, 'all' or 'none' (default: %(default)s)")
    p.add_argument("--lanes", type=int, default=None, help="games simulated in parallel (default: the generator's)")
    p.add_argument("--no-warmup", action="store_true", help="skip the one-game warm-up that measures compilation apart")
    p.add_argument("--out", type=Path, default=None, help="also write the dataset (and truth files) to this directory")
    p.add_argument("--out-json", type=Path, default=None, help="write the JSON result to this file too")
    p.add_argument("--progress", action="store_true", help="show the generator's progress bar")
    args = p.parse_args(argv)

    cfg = make_config(args.preset, games=args.games, seed=args.seed, effects=args.effects, lanes=args.lanes)
    warm = None
    if not args.no_warmup:
        t0 = time.perf_counter()
        generate(cfg.replace(games=1, rallies_per_game=(1, 1)), progress=False)
        warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    gen = generate(cfg, progress=args.progress)
    wall = time.perf_counter() - t0
    t_write = None
    if args.out is not None:
        t1 = time.perf_counter()
        write(gen, args.out, overwrite=True)
        t_write = time.perf_counter() - t1
    c = gen.truth["counts"]
    result = {
        "benchmark": "reality generator",
        "command": "python benchmarks/generator.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "preset": args.preset, "seed": args.seed, "effects": list(cfg.effects), "lanes": cfg.lanes,
        "wall_s": round(wall, 2), "warmup_one_game_s": None if warm is None else round(warm, 2),
        "write_s": None if t_write is None else round(t_write, 2),
        "counts": {k: c[k] for k in ("games", "rallies", "observations", "segments", "table_contacts",
                                     "robot_racket_contacts", "opponent_racket_contacts", "events", "shots",
                                     "robot_contact_bands", "simulated_ball_steps", "chunks")},
        "paper": PAPER,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "jax": jax.__version__,
                    "device": str(jax.devices()[0])},
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out_json is not None:
        args.out_json.parent.mkdir(parents=True, exist_ok=True)
        args.out_json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
