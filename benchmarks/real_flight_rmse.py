"""Flight-segment position error on the public measured data, with a model fitted on a training split.

1. Imports SpinDOE (measured spin), TT3D and the MPI launcher recordings from ``--real`` (read
   at run time; see their SOURCES.md and cite them).
2. Splits SpinDOE's trajectories (sessions) into training and test (``--test-fraction``, ``--seed``)
   and identifies the aerodynamics on the training split (``ttsim_jax.fit.identify``, as
   ``ttsim fit`` does); the fitted configs are written next to the JSON.
3. On the test split, and on every segment of TT3D and MPI (no measured spin: spin 0, so these
   compare drag only and no model saw them), evaluates nakashima2011, durr2026, conti2026 and the
   fitted models (C_D table and C_M form fitted; C_D table only, C_M from conti2026): per segment, the initial position is the first observation, the initial velocity
   is fitted, the spin is the measured one, and the error is the 3-D position RMSE. Segments are
   those the paper would keep: at least 5 samples, spin confidence >= 0.5 where spin is measured,
   and a constant-coefficient fit within 20 mm (segmentation errors).

Writes ``OUT/real_flight_rmse.json`` (every number), ``OUT/real_flight_rmse.png`` (violins) and
prints Markdown tables (median and 75th percentile per model and dataset; a second table with
the initial position fitted too, as the identification does, instead of the first observation).

    python benchmarks/real_flight_rmse.py --out benchmarks/results
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

MODELS = ("nakashima2011", "durr2026", "conti2026")


def real_root() -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def kept_segments(ds, sessions=None, need_spin=True):
    """Segments of ``ds`` the paper would keep, optionally only from ``sessions``."""
    from ttsim_jax.fit.flightfit import fit_segments
    from ttsim_jax.fit.segment_batches import dataset_segments

    ids, times, positions, spins, conf = dataset_segments(ds, min_samples=5)
    session_of = dict(zip(ds.segments["segment_id"], ds.segments["session_id"]))
    keep = np.ones(len(ids), bool)
    if need_spin:
        keep &= conf >= 0.5
    if sessions is not None:
        keep &= np.isin([session_of[i] for i in ids], sessions)
    times = [t for t, k in zip(times, keep) if k]
    positions = [p for p, k in zip(positions, keep) if k]
    spins = spins[keep] if need_spin else np.zeros((int(keep.sum()), 3))
    fit = fit_segments(times, positions, spins, batch=64)
    ok = fit.rmse <= 0.02
    return ([t for t, k in zip(times, ok) if k], [p for p, k in zip(positions, ok) if k], spins[ok],
            dict(candidates=len(times), kept=int(ok.sum())))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--real", type=Path, default=real_root(), help="folder of the public data (default: %(default)s)")
    p.add_argument("--test-fraction", type=float, default=0.3, help="SpinDOE sessions held out (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the split (default: %(default)s)")
    p.add_argument("--association", default="averaged", help="see ttsim fit --association (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="output folder (default: %(default)s)")
    args = p.parse_args(argv)

    from ttsim_jax import load_model
    from ttsim_jax.data.importers import import_source
    from ttsim_jax.fit.flight import flight_rmse
    from ttsim_jax.fit.identify import identify_aero, write_model

    t_start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    spindoe = import_source(args.real / "spindoe", "spindoe")
    models = {name: load_model(name) for name in MODELS}
    fitted = {}
    for label, forms in (("fitted", ("drag", "magnus")), ("fitted, drag only", ("drag",))):
        ident = identify_aero(spindoe, "conti2026", association=args.association, test_fraction=args.test_fraction,
                              seed=args.seed, forms=forms)
        print(ident.summary(), file=sys.stderr)
        stem = "spindoe_fitted" + ("" if len(forms) == 2 else "_drag")
        path = write_model(ident, args.out / f"{stem}.toml", name=stem,
                           source=f"{' and '.join(forms)} fitted on the SpinDOE training split (seed {args.seed}, "
                           f"{ident.counts['used']} segments) over conti2026")
        models[label] = load_model(path)
        fitted[label] = dict(config=str(path), counts=ident.counts, seconds=ident.seconds,
                             cd=ident.drag.values["cd"].tolist(),
                             magnus={k: v.tolist() for k, v in ident.magnus.values.items()})

    sets = {"spindoe (test split)": kept_segments(spindoe, ident.test_sessions)}
    sets["tt3d (spin 0)"] = kept_segments(import_source(args.real / "tt3d", "tt3d"), need_spin=False)
    sets["mpi (spin 0)"] = kept_segments(import_source(args.real / "mpi_ball_prediction", "mpi"), need_spin=False)

    results = {}
    for set_name, (times, positions, spins, counts) in sets.items():
        rows = {}
        for name, model in models.items():
            rmse = flight_rmse(model, times, positions, spins, batch=64)
            free = flight_rmse(model, times, positions, spins, batch=64, fit_position=True)
            rows[name] = dict(median_mm=float(np.nanmedian(rmse) * 1e3), p75_mm=float(np.nanpercentile(rmse, 75) * 1e3),
                              rmse_mm=(rmse * 1e3).round(3).tolist(),
                              position_fitted=dict(median_mm=float(np.nanmedian(free) * 1e3),
                                                   p75_mm=float(np.nanpercentile(free, 75) * 1e3)))
        base = rows["nakashima2011"]
        for r in rows.values():
            r["median_reduction_vs_nakashima_pct"] = 100 * (1 - r["median_mm"] / base["median_mm"])
            r["p75_reduction_vs_nakashima_pct"] = 100 * (1 - r["p75_mm"] / base["p75_mm"])
        results[set_name] = dict(segments=counts, models=rows)

    lines = ["| data (segments) | " + " | ".join(models) + " |", "|---|" + "---|" * len(models)]
    for set_name, res in results.items():
        cells = [f"{r['median_mm']:.1f} / {r['p75_mm']:.1f}" for r in res["models"].values()]
        lines.append(f"| {set_name} ({res['segments']['kept']}) | " + " | ".join(cells) + " |")
    lines += ["", "initial position fitted too:", "", lines[0], lines[1]]
    for set_name, res in results.items():
        cells = [f"{r['position_fitted']['median_mm']:.1f} / {r['position_fitted']['p75_mm']:.1f}"
                 for r in res["models"].values()]
        lines.append(f"| {set_name} ({res['segments']['kept']}) | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    print(table)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(4.5 * len(results), 4), squeeze=False)
    for ax, (set_name, res) in zip(axes[0], results.items()):
        data = [np.asarray(r["rmse_mm"])[np.isfinite(r["rmse_mm"])] for r in res["models"].values()]
        ax.violinplot(data, showmedians=True)
        ax.set_xticks(range(1, len(models) + 1), list(models), rotation=20)
        ax.set_title(f"{set_name}, {res['segments']['kept']} segments")
        ax.set_ylabel("flight RMSE [mm]")
        ax.set_ylim(0, max(np.percentile(d, 95) for d in data) * 1.3)
    fig.tight_layout()
    fig.savefig(args.out / "real_flight_rmse.png", dpi=120)

    report = dict(benchmark="flight RMSE on public measured data",
                  command="python benchmarks/real_flight_rmse.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                  split=dict(test_fraction=args.test_fraction, seed=args.seed, test_sessions=ident.test_sessions,
                             association=args.association),
                  identification=fitted, results=results, table=table,
                  wall_s=time.perf_counter() - t_start)
    (args.out / "real_flight_rmse.json").write_text(json.dumps(report, indent=1, default=int) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
