"""Part of the full withheld-effect selfcheck, at the full run's seeds: its four pairs, then chosen
single effects.

``ttsim diagnose selfcheck`` (full) runs every single effect, the pairs and the outside case in
about two hours on two cores; a change that concerns some cases only is checked here on those
cases, with the same datasets: case ``i`` of a selfcheck is seeded ``seed + 100 i``, so the pairs
(cases 10-13 of the full run) are run from seed 1000, and a single effect from 100 times its place
in the catalogue. Each part keeps its cases in ``OUT/<part>/cases`` (``--resume`` semantics: an
interrupted run continues) and writes ``OUT/<part>.json`` and its Markdown table to stdout.

    python benchmarks/selfcheck_subset.py --out runs/selfcheck_subset
    python benchmarks/selfcheck_subset.py --out runs/tilt --pairs spin_decay+table_tilt --singles ''
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def plan_parts(singles=(), pairs=None) -> list:
    """[(part name, plan, first seed)] of a subset: the pairs (``None``: all of them, as one part;
    otherwise one part per pair), then one part per single effect. A case's seed is its full run's:
    100 times its place in the full run's plan (``selfcheck`` seeds case ``i`` of a part ``first +
    100 i``)."""
    from ttsim_jax.diagnose import candidates as C
    from ttsim_jax.diagnose import selfcheck as SC

    full = SC.cases(C.candidate_names(), SC.PAIRS, SC.OUTSIDE)

    def part(name, plan):
        return name, plan, 100 * full.index(plan[0])

    if pairs is None:
        out = [part("pairs", SC.cases((), SC.PAIRS, None, control=False))]
    else:
        out = [part("pair_" + "+".join(q), SC.cases((), [tuple(q)], None, control=False)) for q in pairs]
    return out + [part(f"single_{n}", SC.cases((n,), (), None, control=False)) for n in singles]


def main(argv=None) -> int:
    from ttsim_jax.diagnose import candidates as C
    from ttsim_jax.diagnose import selfcheck as SC
    from ttsim_jax.diagnose.diagnosis import Settings
    from ttsim_jax.results import jsonable

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="run folder (cases, one JSON per part)")
    p.add_argument("--singles", default="worn_ball,buckling",
                   help="comma-separated single effects to run after the pairs, each at its full-run seed "
                        "(default: %(default)s; '' for none)")
    every_pair = ",".join("+".join(q) for q in SC.PAIRS)
    p.add_argument("--pairs", default=every_pair,
                   help="comma-separated pairs to run, each as a+b from the full run's pairs, each at its "
                        "full-run seed (default: all of them, as one part: %(default)s)")
    p.add_argument("--no-pairs", action="store_true", help="leave out the pairs")
    args = p.parse_args(argv)
    catalogue = C.candidate_names()
    singles = [n for n in args.singles.split(",") if n]
    unknown = [n for n in singles if n not in catalogue]
    if unknown:
        p.error(f"--singles: {unknown} not among the candidates {catalogue}")
    pairs = [tuple(q.split("+")) for q in args.pairs.split(",") if q]
    unknown = ["+".join(q) for q in pairs if q not in SC.PAIRS]
    if unknown:
        p.error(f"--pairs: {unknown} not among the full run's pairs {every_pair}")
    settings = Settings(landing=False, steps=Settings.quick().steps, max_segments=SC.SEGMENTS["full"])
    parts = plan_parts(singles, () if args.no_pairs else None if args.pairs == every_pair else pairs)
    # the full run's generators have all its effects switched on (the others at neutral): the same
    # compiled programs, so the same rounding and the same datasets, bit for bit
    present = {n for _, names in SC.cases(catalogue, SC.PAIRS, SC.OUTSIDE) for n in names}
    for name, plan, seed in parts:
        store = args.out / name
        res = SC.selfcheck(plan, settings, seed=seed, games=SC.GAMES["full"], store=store, present=present,
                           resume=bool(SC.stored_cases(store)), progress=lambda n: print("done", n, flush=True))
        (args.out / f"{name}.json").write_text(json.dumps(jsonable(res), indent=1))
        print(SC.table(res), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
