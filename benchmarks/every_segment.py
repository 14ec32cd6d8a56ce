"""What every flight segment buys: a withheld flight effect in a tracker's log of about 2,000
flight segments, diagnosed twice on the same split: on 128 flight segments (the default before
every segment was) and on every one (today's default).

Two sources (``--source``):

* ``games`` (default): the package's generator (conti2026, paper-like position noise, 14 games)
  with one effect at a fixed size (``--effect``, ``--params``), written as a tracker's CSV log and
  imported through the CSV path (multi-throw sessions, no labelled events:
  :func:`ttsim_jax.diagnose.selfcheck.as_tracker_log`), or with ``--labelled`` as the generator
  labels them. The model is the truth but for the effect.
* ``throws``: launcher throws in a steady wind simulated independently of the package
  (``tracker_sessions.py``'s numpy flight and bounce laws: constant drag and Magnus coefficients,
  which differ from the paper's tables, so the wind is a part of the flight gap, not all of it),
  written as CSV and imported with ``ttsim data import --source csv``.

For each diagnosis the JSON records the flight segments used, the effect's candidate held-out
reduction of the flight error with its interval, significance and rank, its detection limit, the
verdict, and the *oracle*: the held-out reduction that the model with the true effect gives on the
same split (:func:`ttsim_jax.diagnose.selfcheck.oracle_scores`): how much of the flight error the
effect is.

Usage: python benchmarks/every_segment.py [--source games] [--effect air_flow --params '{"wind": [0, 0.1, 0]}']
       [--source throws --sessions 10 --throws 100 --wind 0,0.15,0] [--out FILE] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tracker_sessions import run, sessions, write  # noqa: E402  (the independent simulation)

#: Flight segments of the diagnosis before every segment counted.
BEFORE = 128


def wind_truth(session_ids, wind) -> dict:
    """The generator-style truth (``truth.json``'s shape) of a steady ``wind`` in every session:
    what :func:`~ttsim_jax.diagnose.selfcheck.oracle_scores` reads."""
    from ttsim_jax import effects as fx

    cls = fx.effect_class("air_flow")
    params = {k: np.broadcast_to(p.neutral, p.shape).tolist() for k, p in cls.PARAMS.items()}
    params["wind"] = [float(x) for x in wind]
    return {"sessions": {int(s): {"effects": {"air_flow": params}} for s in session_ids}}


def games_log(name: str, params: dict, games: int, seed: int, log: bool = True):
    """(dataset, truth) of ``games`` generated games with effect ``name`` at ``params`` (its other
    parameters neutral) and paper-like position noise: as a tracker's log, or (``log=False``) the
    labelled dataset as ``ttsim generate`` writes it."""
    from ttsim_jax import effects as fx
    from ttsim_jax import reality
    from ttsim_jax.diagnose.selfcheck import NOISE, as_tracker_log

    cls = fx.effect_class(name)
    values = {k: np.broadcast_to(p.neutral, p.shape).tolist() for k, p in cls.PARAMS.items()}
    values.update(params)
    cfg = reality.make_config(games=games, seed=seed, effects=[name, "position_noise"], max_flight_time=1.5,
                              effect_params={name: values, "position_noise": {"std": list(NOISE)}},
                              truth_observations=False)
    gen = reality.generate(cfg, progress=False)
    return (as_tracker_log(gen.dataset) if log else gen.dataset), gen.truth


def one(ds, model, max_segments, name, truth) -> dict:
    """The diagnosis at ``max_segments`` and the oracle of effect ``name``, as the JSON row."""
    from ttsim_jax.diagnose.diagnosis import Settings, diagnose
    from ttsim_jax.diagnose.limits import describe
    from ttsim_jax.diagnose.candidates import significant
    from ttsim_jax.diagnose.selfcheck import oracle_scores

    keep = {}
    t0 = time.perf_counter()
    out = diagnose(ds, model, Settings(landing=False, max_segments=max_segments), keep=keep)
    seconds = time.perf_counter() - t0
    oracle = oracle_scores(keep["problem"], model, (name,), truth)["flight"]
    ranked = [c["name"] for c in out.candidates]
    cand = next(c for c in out.candidates if c["name"] == name)
    flight = cand["heldout"]["flight"]
    limit = out.limits["candidates"].get(name, {}).get("flight")
    return dict(max_segments=max_segments, counts=out.counts, seconds=seconds, load=os.getloadavg(),
                oracle_pct=oracle["pct"], oracle_ci95=oracle["ci95"],
                oracle_significant=significant("flight", oracle),
                candidate=dict(name=name, pct=flight["pct"], ci95=flight["ci95"], significant=bool(cand["significant"]),
                               rank=ranked.index(name) + 1, params=cand.get("params")),
                accepted=out.verdict.effects, level=out.verdict.level, gaps=out.verdict.gaps,
                limit=None if limit is None else dict(limit, text=describe(name, limit)),
                verdict=out.verdict.text)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", choices=("games", "throws"), default="games",
                    help="generated games written as a tracker's log, or independently simulated throws (default: games)")
    ap.add_argument("--effect", default="air_flow", help="games: the withheld effect (default air_flow)")
    ap.add_argument("--params", default='{"wind": [0.0, 0.1, 0.0]}',
                    help="games: the effect's parameter values as JSON, the others neutral (default: a wind of 0.1 m/s across)")
    ap.add_argument("--labelled", action="store_true", help="games: diagnose the labelled games (events and racket "
                    "states as the generator writes them) instead of their tracker's log")
    ap.add_argument("--games", type=int, default=14, help="games: games generated (default 14: about 2,000 flight segments)")
    ap.add_argument("--sessions", type=int, default=10, help="throws: tracker sessions (default 10)")
    ap.add_argument("--throws", type=int, default=100, help="throws: throws per session (default 100)")
    ap.add_argument("--wind", default="0,0.15,0", help="throws: steady wind vx,vy,vz in m/s, world frame (default 0,0.15,0: across the table)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the games or throws (default 0)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/every_segment"), help="throws: working folder (default /tmp/every_segment)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/every_segment.json"), help="JSON to write")
    args = ap.parse_args(argv)

    import jax.numpy as jnp

    from ttsim_jax import load_model
    from ttsim_jax.data import load

    result = dict(args={k: str(v) for k, v in vars(args).items()}, load_before=os.getloadavg(), runs=[])
    if args.source == "throws":
        wind = [float(x) for x in args.wind.split(",")]
        if len(wind) != 3:
            ap.error(f"--wind {args.wind!r}: give three components vx,vy,vz")
        multi, _, flights = sessions(args.sessions, args.throws, np.random.default_rng(args.seed), wind=wind)
        write(args.work / "csv", multi)
        ttsim = [str(Path(sys.executable).parent / "ttsim")]
        result["import_seconds"] = run(ttsim + ["data", "import", str(args.work / "csv"), "--source", "csv", "--out",
                                                str(args.work / "ds"), "--force"], args.work / "import.log")
        ds = load(args.work / "ds")
        name, truth = "air_flow", wind_truth(ds.sessions["session_id"], wind)
        result.update(throws=args.sessions * args.throws, true_flights=flights)
    else:
        name = args.effect
        ds, truth = games_log(name, json.loads(args.params), args.games, args.seed, log=not args.labelled)
    result["segments"] = len(ds.segments["segment_id"])
    model = load_model("conti2026", dtype=jnp.float32)
    for max_segments in (BEFORE, None):
        row = one(ds, model, max_segments, name, truth)
        result["runs"].append(row)
        c = row["candidate"]
        print(f"max_segments {max_segments}: flight {row['counts']['flight']}, oracle {row['oracle_pct']:.1f} % "
              f"(significant {row['oracle_significant']}), {name} {c['pct']:.1f} % {np.round(c['ci95'], 1).tolist()} "
              f"significant {c['significant']} rank {c['rank']}; {row['level']} {row['accepted']}; {row['seconds']:.0f} s",
              flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=str))
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
