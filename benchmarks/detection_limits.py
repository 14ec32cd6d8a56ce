"""Are the diagnosis's detection limits right? Effects generated at 0.5 and 1.5 times the limit
that the diagnosis reports on the same games without them, found how often?

Per seed (the selfcheck's games: conti2026 plus paper-like position noise, ``--games`` games):

1. the games without the effect (the effect present at neutral, so that all three datasets share
   the generator's programs and draws), diagnosed with conti2026 and the one candidate
   (``Settings.quick(effects=(NAME,))``, every flight segment unless ``--max-segments``): its detection limit in typical sizes, in the phase
   where it is smallest (``diagnosis["limits"]``);
2. the same games with the effect generated at 0.5 and at 1.5 times that limit (its typical
   parameter values times the size: :func:`ttsim_jax.diagnose.limits.direction`), each diagnosed
   the same way: found when the candidate is significant with plausible parameters.

A right limit is found in >= 80 % of seeds at 1.5 x and in <= 20 % at 0.5 x. Writes
``OUT/detection_limits.json`` (per seed and effect: the limit, the found flags, the held-out
reductions) and prints the rates. Resumable: each finished seed is kept in ``OUT/detection_limits/``.

    python benchmarks/detection_limits.py --effects table_friction --seeds 10 --max-segments 96 --out benchmarks/results
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def games(name: str, size: float, seed: int, n_games: int):
    """The games of ``seed`` with effect ``name`` at ``size`` typical sizes (0: neutral)."""
    from ttsim_jax import effects as fx
    from ttsim_jax import reality
    from ttsim_jax.diagnose.selfcheck import NOISE

    cls = fx.effect_class(name)
    values = {k: (np.asarray(p.neutral, np.float64) + size * (np.asarray(p.typical, np.float64) - np.asarray(p.neutral, np.float64))
                  if k in _stepped(name) else np.broadcast_to(np.asarray(p.neutral, np.float64), p.shape)).tolist()
              for k, p in cls.PARAMS.items()}
    params = {name: values, "position_noise": {"std": list(NOISE)}}
    cfg = reality.make_config(games=n_games, seed=seed, effects=[name, "position_noise"], effect_params=params,
                              max_flight_time=1.5, truth_observations=False)
    return reality.generate(cfg, progress=False).dataset, values


def _stepped(name: str) -> set:
    """The parameters the diagnosis's limit scales (its direction)."""
    from ttsim_jax.diagnose import candidates
    from ttsim_jax.diagnose.limits import direction

    sp, const = candidates.spec(name)
    return set(direction(sp, const))


def diagnosed(ds, name: str, max_segments):
    import jax.numpy as jnp

    from ttsim_jax import load_model
    from ttsim_jax.diagnose.diagnosis import Settings, diagnose

    out = diagnose(ds, load_model("conti2026", dtype=jnp.float32), Settings.quick(effects=(name,), max_segments=max_segments))
    c = next(c for c in out.candidates if c["name"] == name)
    return out, c


def one_seed(name: str, seed: int, n_games: int, max_segments) -> dict:
    ds, _ = games(name, 0.0, seed, n_games)
    out, _ = diagnosed(ds, name, max_segments)
    per = out.limits["candidates"].get(name, {})
    shown = {p: e for p, e in per.items() if e["size"] is not None}
    if not shown:
        return dict(seed=seed, limit=None, phase=None)
    phase, lim = min(shown.items(), key=lambda kv: kv[1]["size"])
    row = dict(seed=seed, phase=phase, limit=lim["size"], limit_params=lim["params"], share_pct=lim["share_pct"],
               limit_reduction_pct=lim["reduction_pct"], segments=out.counts)
    for factor in (0.5, 1.5):
        ds, values = games(name, factor * lim["size"], seed, n_games)
        res, c = diagnosed(ds, name, max_segments)
        row[f"x{factor}"] = dict(found=bool(c["significant"] and not c.get("implausible")),
                                 heldout={p: dict(pct=h["pct"], ci95=h["ci95"]) for p, h in c["heldout"].items()},
                                 generated={k: values[k] for k in _stepped(name)})
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--effects", default="table_friction", help="comma-separated candidate names (default: %(default)s)")
    p.add_argument("--seeds", type=int, default=10, help="seeds per effect (default: %(default)s)")
    p.add_argument("--games", type=int, default=4, help="games per dataset (default: %(default)s)")
    p.add_argument("--max-segments", type=int, default=None, help="flight segments diagnosed (default: every one; "
                   "fewer for speed where the effect acts on contacts only)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="output folder (default: %(default)s)")
    args = p.parse_args(argv)
    store = args.out / "detection_limits"
    store.mkdir(parents=True, exist_ok=True)
    results, t0 = {}, time.time()
    for name in args.effects.split(","):
        rows = []
        for seed in range(args.seeds):
            f = store / f"{name}_{seed}.json"
            if f.exists():
                rows.append(json.loads(f.read_text()))
                continue
            print(f"{name}, seed {seed}: generating and diagnosing 3 datasets ...", file=sys.stderr, flush=True)
            row = one_seed(name, seed, args.games, args.max_segments)
            tmp = f.with_suffix(".tmp")
            tmp.write_text(json.dumps(row, indent=1))
            tmp.replace(f)
            rows.append(row)
        valid = [r for r in rows if r.get("limit") is not None]
        rates = {k: float(np.mean([r[k]["found"] for r in valid])) if valid else float("nan") for k in ("x0.5", "x1.5")}
        results[name] = dict(rows=rows, found_rate_at_0_5=rates["x0.5"], found_rate_at_1_5=rates["x1.5"],
                             n=len(valid), median_limit=float(np.median([r["limit"] for r in valid])) if valid else None)
        print(f"{name}: limit median {results[name]['median_limit']} typical sizes over {len(valid)} seeds; found at "
              f"0.5 x: {rates['x0.5']:.0%}, at 1.5 x: {rates['x1.5']:.0%}")
    results["seconds"] = time.time() - t0
    results["load"] = os.getloadavg()
    (args.out / "detection_limits.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
