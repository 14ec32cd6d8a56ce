"""`ttsim fit` on the three public datasets together, scored on held-out sessions over several seeds.

For each seed, :func:`ttsim_jax.fit.pipeline.fit_dataset` (what ``ttsim fit --data A --data B
--data C`` runs) fits SpinDOE, TT3D and the MPI launcher recordings together, with
``--test-fraction`` of each dataset's sessions held out, once per aerodynamic variant (forms x
association). The stages the public data cannot support are skipped (table: no bounce has a
measured spin on both sides; racket: no racket states). Only SpinDOE has measured spins: its
training segments place C_D and C_M, and TT3D's and MPI's (and SpinDOE's without a confident
spin) enter the C_D table at their latent spin (``ttsim fit --spin auto``, the default; before
it, SpinDOE's C_D alone made MPI 5-45 % worse).

Every model is then scored as ``ttsim evaluate --split test`` scores it
(:func:`ttsim_jax.evaluate.stages.flight_stage`): per held-out flight segment, the 3-D position
RMSE with the first observation as the initial position, the initial velocity fitted and the
spin ``ttsim evaluate`` flies by default (``--spin auto``): SpinDOE's measured spin where confident,
elsewhere, and on every TT3D and MPI segment, the latent spin each model fits from the segment's own
samples (:mod:`ttsim_jax.fit.latent_spin`; before it, TT3D and MPI were scored at spin 0, where a
C_D fitted on SpinDOE's spinning balls made MPI 9-24 % worse on every seed). Per seed: median and 75th percentile of each
model, and each fitted variant's reduction against conti2026 and nakashima2011 with a 95 % paired
bootstrap interval over the segments; across seeds: mean, minimum and maximum. Also per seed, on
SpinDOE's held-out segments: the error a per-segment constant C_D and C_M leaves (the floor of any
coefficient form; initial position fitted, as the identification fits it) beside conti2026's and
the fitted models' with the initial position fitted too.

    nice python benchmarks/fit_real.py --out benchmarks/results/fit_real.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

BASELINES = ("nakashima2011", "durr2026", "conti2026")
#: (label, forms, association) of the fitted variants.
VARIANTS = (("fit drag", ("drag",), "averaged"), ("fit drag+magnus", ("drag", "magnus"), "averaged"),
            ("fit magnus", ("magnus",), "averaged"), ("fit drag (v_eff)", ("drag",), "v_eff"),
            ("fit drag+magnus (v_eff)", ("drag", "magnus"), "v_eff"))
SOURCES = (("spindoe", "spindoe"), ("tt3d", "tt3d"), ("mpi", "mpi_ball_prediction"))


def real_root() -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def _stats(rmse_m) -> dict:
    e = np.asarray(rmse_m, np.float64) * 1e3
    e = e[np.isfinite(e)]
    return dict(n=int(len(e)), median_mm=float(np.median(e)), p75_mm=float(np.percentile(e, 75)))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--real", type=Path, default=real_root(), help="folder of the public data (default: %(default)s)")
    p.add_argument("--seeds", type=int, default=5, help="seeds 0 .. N-1 of the held-out draw (default: %(default)s)")
    p.add_argument("--test-fraction", type=float, default=0.3,
                   help="fraction of each dataset's sessions held out (default: %(default)s)")
    p.add_argument("--variants", default=",".join(v[0] for v in VARIANTS),
                   help="comma-separated fitted variants to run (default: all: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/fit_real.json"),
                   help="JSON to write (default: %(default)s)")
    args = p.parse_args(argv)

    from ttsim_jax.files.cache import enable_compilation_cache

    enable_compilation_cache()  # as the ttsim command does
    from ttsim_jax import load_model
    from ttsim_jax.fit.flightfit import fit_segments
    from ttsim_jax.data.importers import import_source
    from ttsim_jax.fit.segment_batches import dataset_segments
    from ttsim_jax.evaluate.report import reduction, reduction_ci
    from ttsim_jax.evaluate.stages import EvaluateSettings, flight_stage
    from ttsim_jax.fit.flight import flight_rmse
    from ttsim_jax.fit.identify import split_sessions
    from ttsim_jax.fit.pipeline import FitSettings, fit_dataset

    wanted = [v for v in VARIANTS if v[0] in args.variants.split(",")]
    t_start = time.perf_counter()
    datasets = {name: import_source(args.real / folder, name) for name, folder in SOURCES}
    baselines = [(name, load_model(name)) for name in BASELINES]
    seeds = {}
    for seed in range(args.seeds):
        t_seed = time.perf_counter()
        fitted, fits = [], {}
        for label, forms, association in wanted:
            t0 = time.perf_counter()
            result = fit_dataset(list(datasets.values()), "conti2026", labels=list(datasets), name=label.replace(" ", "_"),
                                 settings=FitSettings(forms=forms, association=association,
                                                      test_fraction=args.test_fraction, seed=seed))
            fitted.append((label, result.model))
            aero = result.report["aero"]
            fits[label] = dict(fitted=result.fitted, skipped=result.skipped, seconds=time.perf_counter() - t0,
                               segments_used=aero["counts"]["used"], held_out=aero["counts"]["held_out"],
                               cd=aero["drag"]["values"]["cd"],
                               magnus={k: v for k, v in aero["magnus"]["values"].items()},
                               comparison=result.report["comparison"])
        models = baselines + fitted
        scores = {}
        for name, ds in datasets.items():
            test = split_sessions(ds.segments["session_id"], args.test_fraction, seed)
            out = flight_stage(ds, models, EvaluateSettings(sessions=tuple(int(s) for s in test)))
            rmse = out.rmse
            per = {m: _stats(rmse[m]) for m, _ in models}
            for label, _ in fitted:
                for ref in ("conti2026", "nakashima2011"):
                    for key, q in (("median", 50), ("p75", 75)):
                        per[label][f"{key}_reduction_vs_{ref}_pct"] = reduction(per[ref][f"{key}_mm"],
                                                                                per[label][f"{key}_mm"])
                        per[label][f"{key}_reduction_vs_{ref}_ci95"] = reduction_ci(rmse[ref], rmse[label], q,
                                                                                    seed=seed)
            for ref in ("conti2026", "durr2026"):
                per[ref]["median_reduction_vs_nakashima2011_pct"] = reduction(per["nakashima2011"]["median_mm"],
                                                                              per[ref]["median_mm"])
                per[ref]["median_reduction_vs_nakashima2011_ci95"] = reduction_ci(rmse["nakashima2011"], rmse[ref], 50,
                                                                                  seed=seed)
            scores[name] = dict(segments=int(len(out.segment_id)), spin_measured=bool(out.spin_measured),
                                test_sessions=int(len(test)), models=per)
        # the floor of any coefficient form on SpinDOE's held-out segments: a constant C_D, C_M per segment
        ds = datasets["spindoe"]
        test = split_sessions(ds.segments["session_id"], args.test_fraction, seed)
        ids, times, positions, spins, conf = dataset_segments(ds, 5)
        session_of = dict(zip(ds.segments["segment_id"].tolist(), ds.segments["session_id"].tolist()))
        keep = (conf >= 0.5) & np.isin([session_of[int(i)] for i in ids], test)
        times = [t for t, k in zip(times, keep) if k]
        positions = [q for q, k in zip(positions, keep) if k]
        floor = dict(per_segment_constant_coefficients=_stats(fit_segments(times, positions, spins[keep]).rmse))
        for name, model in models:
            if name in ("conti2026", "nakashima2011") or name in (v[0] for v in wanted[:2]):
                floor[name] = _stats(flight_rmse(model, times, positions, spins[keep], fit_position=True))
        seeds[seed] = dict(fits=fits, scores=scores, spindoe_position_fitted=floor,
                           wall_s=time.perf_counter() - t_seed)
        s = scores["spindoe"]["models"]
        print(f"seed {seed}: spindoe ({scores['spindoe']['segments']}) median mm: "
              + ", ".join(f"{m} {s[m]['median_mm']:.2f}" for m, _ in models)
              + f"; {time.perf_counter() - t_seed:.0f} s", file=sys.stderr)

    summary = {}
    for name in datasets:
        summary[name] = {}
        for m in list(BASELINES) + [v[0] for v in wanted]:
            med = np.array([seeds[s]["scores"][name]["models"][m]["median_mm"] for s in seeds])
            p75 = np.array([seeds[s]["scores"][name]["models"][m]["p75_mm"] for s in seeds])
            row = dict(median_mm_mean=float(med.mean()), median_mm_min=float(med.min()), median_mm_max=float(med.max()),
                       p75_mm_mean=float(p75.mean()), p75_mm_min=float(p75.min()), p75_mm_max=float(p75.max()))
            if m not in BASELINES:
                red = np.array([seeds[s]["scores"][name]["models"][m]["median_reduction_vs_conti2026_pct"]
                                for s in seeds])
                lo = [seeds[s]["scores"][name]["models"][m]["median_reduction_vs_conti2026_ci95"][0] for s in seeds]
                hi = [seeds[s]["scores"][name]["models"][m]["median_reduction_vs_conti2026_ci95"][1] for s in seeds]
                row.update(median_reduction_vs_conti2026_pct=red.tolist(),
                           seeds_better_than_conti2026=[int(s) for s, r in zip(seeds, red) if r > 0],
                           seeds_significantly_better=[int(s) for s, a in zip(seeds, lo) if a > 0],
                           seeds_significantly_worse=[int(s) for s, b in zip(seeds, hi) if b < 0])
            summary[name][m] = row
    lines = ["| model | " + " | ".join(f"{n} median / p75 [mm], mean (min-max) over {len(seeds)} seeds" for n in datasets)
             + " |", "|---|" + "---|" * len(datasets)]
    for m in list(BASELINES) + [v[0] for v in wanted]:
        cells = [f"{r['median_mm_mean']:.2f} ({r['median_mm_min']:.2f}-{r['median_mm_max']:.2f}) / "
                 f"{r['p75_mm_mean']:.2f}" for r in (summary[n][m] for n in datasets)]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    print(table)
    import jax

    report = dict(benchmark="ttsim fit on SpinDOE + TT3D + MPI, held-out flight RMSE over seeds",
                  command="python benchmarks/fit_real.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                  data=dict(spindoe="Gossard et al., arXiv:2303.03879", tt3d="arXiv:2504.10035",
                            mpi="intelligent-soft-robots/ball_prediction"),
                  test_fraction=args.test_fraction, variants=[dict(label=v[0], forms=list(v[1]), association=v[2])
                                                              for v in wanted],
                  seeds={str(k): v for k, v in seeds.items()}, summary=summary, table=table,
                  machine=dict(platform=platform.platform(), python=platform.python_version(), jax=jax.__version__,
                               device=str(jax.devices()[0])),
                  wall_s=time.perf_counter() - t_start)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
