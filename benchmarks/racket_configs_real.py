"""The racket contact fitted per racket configuration on tt_rackets' measured bounces, held out.

tt_rackets (github.com/gossardt/tt_rackets, MIT licence; T. Gossard, "Learning Racket-Ball Bounce
Dynamics Across Diverse Rubbers for Robotic Table Tennis", arXiv:2604.11349, 2026), train split:
6,490 bounces on 10 configurations. :func:`ttsim_jax.fit.racket_configs.fit_configs` per
configuration and held-out split:

* ``random``: 20 % of each configuration's bounces held out (seed 0; the upstream test split is not
  in the shared folder, so this is a split of the given data);
* ``tilt 20``: every bounce at the rig's 20 degree tilt held out, the fits on 0 and 10 degrees (a
  region of incidence angles the fits never saw).

Models on the held-out bounces: conti2026's updated base with the paper's constants, the fitted
updated base, the fitted base + the residual network trained on the configuration, and a quadratic
least-squares regression of the outgoing state on the incoming one (model-free). With
``--write-configs`` the random split's fits are written as the bundled racket files
``configs/rackets/racket_NN.toml`` (+ ``.ttres``), which ``load_model("conti2026", racket="racket_NN")``
and a task's ``racket_config`` load.

    nice python benchmarks/racket_configs_real.py --out benchmarks/results/racket_configs_real.json --write-configs
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "real" / "tt_rackets",
                   help="the tt_rackets folder (default: ../shared/data/real/tt_rackets)")
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    p.add_argument("--seed", type=int, default=0, help="seed of the random split and the networks (default 0)")
    p.add_argument("--no-network", action="store_true", help="skip the residual networks (about 10 s per configuration)")
    p.add_argument("--few", default="racket_01", help="the configuration refitted on fewer training bounces "
                   "(50, 100, 200, 400), the same held-out ones (default racket_01; '' for none)")
    p.add_argument("--write-configs", action="store_true",
                   help="write the random split's fits as configs/rackets/racket_NN.toml and .ttres")
    args = p.parse_args(argv)

    from ttsim_jax.data import import_source
    from ttsim_jax.fit.racket_configs import best, fit_configs, write_racket_file

    t0 = time.time()
    ds = import_source(args.data, "tt_rackets")
    out = dict(data=str(args.data), host=platform.node(), seed=args.seed, splits={})
    for split, kw in (("random", dict(test_fraction=0.2)), ("tilt 20", dict(hold_tilt=20.0))):
        print(f"split {split}:", flush=True)
        fits = fit_configs(ds, "conti2026", seed=args.seed, network=not args.no_network, progress=print, **kw)
        rows = {}
        for f in fits:
            rows[f.name] = dict(description=f.description, values=f.values, stderr=f.stderr, bounds=f.bounds,
                                best=best(f.report), **f.report)
        out["splits"][split] = rows
        if split == "random" and args.write_configs:
            folder = REPO / "configs" / "rackets"
            for f in fits:
                write_racket_file(f, folder, "tt_rackets train split (MIT licence, (c) 2026 Thomas Gossard; "
                                  "arXiv:2604.11349), 80 % of the configuration's bounces: "
                                  "benchmarks/racket_configs_real.py", seed=args.seed)
            print(f"wrote {len(fits)} racket files to {folder}")
    if args.few and not args.no_network:
        print(f"fewer bounces, {args.few}:", flush=True)
        out["few"] = {}
        for n in (50, 100, 200, 400):
            f = fit_configs(ds, "conti2026", seed=args.seed, configs=[args.few], max_train=n, progress=print)[0]
            out["few"][str(n)] = dict(n_train=f.report["n_train"], test=f.report["test"])
    out["wall_s"] = time.time() - t0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out} ({out['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
