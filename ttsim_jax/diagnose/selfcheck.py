"""Withheld-effect validation of the diagnosis (``ttsim diagnose selfcheck``).

For each simulator effect of a list, the reality generator makes a dataset with conti2026 plus
that effect at a random magnitude (its ``sample`` draw: a realistic range) and position noise; the
diagnosis runs with the effect hidden from the model, and the case is scored:

* *rank 1*: the true effect is the first candidate and significant;
* *phase*: the first candidate is significant and its best held-out phase is one the true effect
  acts in;
* *shrink*: the held-out RMS reduction the diagnosis found in that phase, as a fraction of the
  oracle's (the model given the true effect with its true parameters, on the same held-out split;
  the oracle's best phase when nothing is significant, the diagnosis then recovering 0).

The generator's truth is read here, and only here: the diagnosis itself never sees it.
"""

from __future__ import annotations

import math
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import effects as fx
from ttsim_jax.diagnose import candidates as C
from ttsim_jax.diagnose import stages as S

#: Effects of ``--quick`` (one per phase, and one that acts in a narrow regime).
QUICK = ("spin_decay", "air_flow", "table_tilt", "buckling")
#: Tries of successive seeds when the generator refuses its own data.
TRIES = 4


def oracle_scores(pb, model, name: str, truth: dict) -> dict:
    """Held-out scores (:func:`ttsim_jax.diagnose.candidates.score`) of the model with the true
    effect ``name`` at its true parameters (``truth``: the generator's ``truth.json`` dict)."""
    cls = fx.effect_class(name)
    per_session = cls.SCOPE == "session"
    sp = C.Spec(name, cls, tuple(cls.PARAMS), per_session)
    consts = dict(start={k: np.zeros(p.shape) for k, p in cls.PARAMS.items()},
                  scale={k: np.float64(1.0) for k in cls.PARAMS})
    if per_session:
        values = [truth["sessions"][int(s)]["effects"][name] for s in pb.sessions]
    else:
        values = [truth["effects"][name]["params"]]
    u = ({k: jnp.asarray(np.stack([np.broadcast_to(np.asarray(v[k], np.float64), p.shape) for v in values]), jnp.float32)
          for k, p in cls.PARAMS.items()},)
    phases = tuple(p for p in pb.phases if p in sp.phases)
    errors, _ = C.evaluate(model, (sp,), (consts,), u, pb, S.GN_START, phases)
    return C.score(pb, errors)


def run_case(name: str, seed: int, settings, games: int = 2, rallies: int = 6) -> dict:
    """One withheld-effect case (see the module docstring)."""
    from ttsim_jax import load_model
    from ttsim_jax.data import generator as G
    from ttsim_jax.data.errors import DataError
    from ttsim_jax.diagnose.diagnosis import diagnose

    gen, error = None, ""
    for k in range(TRIES):
        cfg = G.make_config(games=games, rallies_per_game=(rallies, rallies), seed=seed + k, effects=[name, "position_noise"],
                            max_flight_time=1.5, truth_observations=False)
        try:
            gen = G.generate(cfg, progress=False)
            break
        except DataError as e:  # the generator refuses its own data for some seeds
            error = str(e)
    if gen is None:
        return dict(effect=name, error=f"generator refused {TRIES} seeds: {error}")
    model = load_model("conti2026", dtype=jnp.float32)
    keep = {}
    out = diagnose(gen.dataset, model, settings, keep=keep)
    pb = keep["problem"]
    top = out["candidates"][0] if out["candidates"] else None
    true_phases = C.phases_of(fx.effect_class(name))
    oracle = oracle_scores(pb, model, name, gen.truth)
    located = top is not None and top["significant"]
    phase = max(top["heldout"], key=lambda p: top["heldout"][p]["pct"]) if located else None
    found = top["heldout"][phase]["pct"] if located and top["name"] == name else 0.0
    best_oracle = max(oracle, key=lambda p: oracle[p]["pct"])
    ref = oracle[phase if phase in oracle else best_oracle]["pct"]
    return dict(effect=name, seed=int(cfg.seed), rank1=bool(located and top["name"] == name),
                top=top["name"] if located else "none significant", phase=phase, phase_right=bool(phase in true_phases),
                found_pct=found, oracle_pct=ref, shrink=found / ref if ref and ref > 0 else math.nan,
                seconds=out["seconds"])


def selfcheck(names=QUICK, settings=None, seed: int = 0, progress: Callable | None = None, **case) -> dict:
    """Every case of ``names`` and the summary: rank-1 rate, located-phase rate, median shrink."""
    from ttsim_jax.diagnose.diagnosis import Settings

    settings = settings or Settings.quick()
    t0 = time.perf_counter()
    rows = []
    for i, name in enumerate(names):
        rows.append(run_case(name, seed + 100 * i, settings, **case))
        if progress:
            progress(name)
        jax.clear_caches()  # every case compiles its own shapes
    ok = [r for r in rows if "error" not in r]
    shrink = [r["shrink"] for r in ok if math.isfinite(r["shrink"])]
    return dict(cases=rows, rank1_rate=float(np.mean([r["rank1"] for r in ok])) if ok else math.nan,
                phase_rate=float(np.mean([r["phase_right"] for r in ok])) if ok else math.nan,
                median_shrink=float(np.median(shrink)) if shrink else math.nan, seconds=time.perf_counter() - t0)


def table(result: dict) -> str:
    """The per-effect Markdown table of a selfcheck."""
    lines = ["| effect | top candidate | rank 1 | phase | found [%] | oracle [%] | shrink recovered |",
             "|---|---|---|---|---|---|---|"]
    for r in result["cases"]:
        if "error" in r:
            lines.append(f"| {r['effect']} | {r['error'][:60]} | | | | | |")
            continue
        phase = f"{r['phase']} ({'right' if r['phase_right'] else 'wrong'})" if r["phase"] else "-"
        lines.append(f"| {r['effect']} | {r['top']} | {'yes' if r['rank1'] else 'no'} | {phase} | {r['found_pct']:.1f} | "
                     f"{r['oracle_pct']:.1f} | {r['shrink']:.2f} |")
    lines.append(f"\nrank-1 rate {result['rank1_rate']:.2f}, located phase {result['phase_rate']:.2f}, median shrink "
                 f"recovered {result['median_shrink']:.2f}; {result['seconds']:.0f} s")
    return "\n".join(lines)
