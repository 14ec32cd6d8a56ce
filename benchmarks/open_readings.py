"""The paper's open readings, settled on the public measured data: flight RMSE of conti2026 and
of each variant that reads the paper the other way, with paired bootstrap intervals.

Readings (each a bundled model variant, ``configs/models/``):

- ``conti2026_cd_blended``: C_D between reference speeds with blended breakpoints (the authors'
  code) instead of the two rows evaluated at the same Sp.
- ``conti2026_cm_values``: C_M interpolated as values between reference speeds instead of its
  coefficients (the authors' code interpolates the coefficients).
- ``conti2026_rho1184``: air density 1.184 kg/m^3 (the Nakashima baseline's) instead of 1.204.

No reading is fitted, so every kept segment is test data. Segments and the RMSE protocol are
``benchmarks/real_flight_rmse.py``'s (first observation as the initial position, initial velocity
fitted, measured spin; TT3D and MPI have no spin, so only the air density can matter there). The
racket contact point, the fourth open reading, needs racket states, which no public dataset has.

    python benchmarks/open_readings.py --out benchmarks/results

Writes ``OUT/open_readings.json`` (every per-segment RMSE, medians, 75th percentiles, the paired
bootstrap intervals) and ``OUT/open_readings.png``; prints the Markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: make ``benchmarks`` importable
    sys.path.insert(0, str(REPO))

from benchmarks.real_flight_rmse import kept_segments, real_root  # noqa: E402

BASE = "conti2026"
VARIANTS = ("conti2026_cd_blended", "conti2026_cm_values", "conti2026_rho1184")
WHAT = {"conti2026_cd_blended": "C_D: blended breakpoints", "conti2026_cm_values": "C_M: values interpolated",
        "conti2026_rho1184": "rho_air 1.184"}


def bootstrap_ci(values, stat, n_boot: int, seed: int = 0) -> list:
    """95 % bootstrap interval of ``stat`` (e.g. ``np.mean``) of ``values`` (per-segment paired
    differences, so resampling them is the paired bootstrap)."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(values), (n_boot, len(values)))
    return np.percentile(stat(values[idx], axis=1), [2.5, 97.5]).tolist()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--real", type=Path, default=real_root(), help="folder of the public data (default: %(default)s)")
    p.add_argument("--bootstrap", type=int, default=2000, help="bootstrap draws (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="output folder (default: %(default)s)")
    args = p.parse_args(argv)
    if not args.real.is_dir():
        p.error(f"--real: {args.real} is not a folder (the public datasets, see its SOURCES.md)")

    from ttsim_jax import load_model
    from ttsim_jax.data.importers import import_source
    from ttsim_jax.fit.flight import flight_rmse
    from ttsim_jax.evaluate.report import reduction_ci

    t_start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    sets = {"spindoe": kept_segments(import_source(args.real / "spindoe", "spindoe")),
            "tt3d (spin 0)": kept_segments(import_source(args.real / "tt3d", "tt3d"), need_spin=False),
            "mpi (spin 0)": kept_segments(import_source(args.real / "mpi_ball_prediction", "mpi"), need_spin=False)}
    names = (BASE,) + VARIANTS
    models = {n: load_model(n) for n in names}
    results = {}
    for set_name, (times, positions, spins, counts) in sets.items():
        rmse = {n: flight_rmse(models[n], times, positions, spins, batch=64) for n in names}
        rows = {}
        for n in names:
            ok = np.isfinite(rmse[n]) & np.isfinite(rmse[BASE])
            d = (rmse[n] - rmse[BASE])[ok]
            rows[n] = dict(median_mm=float(np.median(rmse[n][ok]) * 1e3),
                           p75_mm=float(np.percentile(rmse[n][ok], 75) * 1e3),
                           reduction_median_pct=float(100 * (1 - np.median(rmse[n][ok]) / np.median(rmse[BASE][ok]))),
                           reduction_median_ci95=reduction_ci(rmse[BASE], rmse[n], 50, args.bootstrap),
                           reduction_p75_ci95=reduction_ci(rmse[BASE], rmse[n], 75, args.bootstrap),
                           better_share=float(np.mean(d < -1e-6)) if n != BASE else None,
                           median_paired_difference_um=float(np.median(d) * 1e6),
                           median_paired_difference_ci95_um=np.multiply(bootstrap_ci(d, np.median, args.bootstrap),
                                                                        1e6).tolist(),
                           mean_paired_difference_um=float(np.mean(d) * 1e6),
                           mean_paired_difference_ci95_um=np.multiply(bootstrap_ci(d, np.mean, args.bootstrap),
                                                                      1e6).tolist(),
                           affected_share=float(np.mean(np.abs(d) > 1e-6)) if n != BASE else None,
                           rmse_mm=(rmse[n] * 1e3).round(4).tolist())
        results[set_name] = dict(segments=counts, models=rows)

    # cells: median / 75th percentile RMSE [mm]; for a variant also the mean of its per-segment
    # RMSE minus conti2026's (negative: the variant fits better) with its 95 % interval (medians
    # of the differences are 0 where most segments are untouched), the share of segments it fits
    # better and the share it changes by more than 1 µm
    head = "| reading | " + " | ".join(f"{s} ({r['segments']['kept']})" for s, r in results.items()) + " |"
    lines = [head, "|---|" + "---|" * len(results)]
    for n in names:
        cells = []
        for res in results.values():
            r = res["models"][n]
            cell = f"{r['median_mm']:.2f} / {r['p75_mm']:.2f}"
            if n != BASE:
                lo, hi = r["mean_paired_difference_ci95_um"]
                cell += (f"; {r['mean_paired_difference_um']:+.0f} µm [{lo:+.0f}, {hi:+.0f}]; "
                         f"{100 * r['better_share']:.0f} % better, {100 * r['affected_share']:.0f} % changed")
            cells.append(cell)
        lines.append(f"| {n if n == BASE else WHAT[n]} | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    print(table)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.8))
    width = 0.8 / len(results)
    for i, (set_name, res) in enumerate(results.items()):
        xs = np.arange(len(VARIANTS)) + (i - (len(results) - 1) / 2) * width
        mid = [res["models"][n]["mean_paired_difference_um"] for n in VARIANTS]
        ci = np.array([res["models"][n]["mean_paired_difference_ci95_um"] for n in VARIANTS])
        ax.bar(xs, mid, width, label=f"{set_name} ({res['segments']['kept']} segments)",
               yerr=[np.subtract(mid, ci[:, 0]), np.subtract(ci[:, 1], mid)], capsize=3)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xticks(range(len(VARIANTS)), [WHAT[n] for n in VARIANTS])
    ax.set_ylabel(f"mean per-segment RMSE change\nagainst {BASE} [µm] (95 % CI)")
    ax.set_title("The paper's open readings on measured flights (negative: the variant fits better)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "open_readings.png", dpi=120)

    report = dict(benchmark="open readings of the paper on public measured flights",
                  command="python benchmarks/open_readings.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                  base=BASE, variants={n: WHAT[n] for n in VARIANTS}, bootstrap=args.bootstrap,
                  results=results, table=table, wall_s=time.perf_counter() - t_start)
    (args.out / "open_readings.json").write_text(json.dumps(report, indent=1, default=int) + "\n")
    print(f"written {args.out / 'open_readings.json'} and open_readings.png ({time.perf_counter() - t_start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
