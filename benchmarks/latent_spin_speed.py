"""Speed of the latent-spin fit against the flight fits it sits beside, on the same segments, one run.

``--segments`` flight segments of conti2026's physics (``reality.synthetic_segments``: 143 Hz,
0.3-0.6 s, 4-16 m/s, 50-500 rad/s, 2 mm of noise), fitted three ways in one process:

* **latent spin** (:func:`ttsim_jax.fit.latent_spin.fit_latent_spin`): (p0, v0, w) per segment
  under conti2026's flight (its C_D and C_M tables), two starts;
* **flight fit** (:func:`ttsim_jax.fit.flightfit.fit_segments`): (p0, v0, C_D, C_M) per segment
  with the measured spin, the identification's fit;
* **evaluate's flight fit** (:func:`ttsim_jax.fit.flight.flight_rmse`): v0 per segment under
  conti2026's flight with the measured spin, what ``ttsim evaluate --stages flight`` runs for a
  segment with a measured spin.

Each is timed cold (its first call in the process: tracing and compilation included) and warm
(median of ``--repeats`` further calls). Writes JSON with the load average before and after:
compare the ratios of one run on an idle machine, not times across runs.

    python benchmarks/latent_spin_speed.py --out benchmarks/results/latent_spin_speed_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--segments", type=int, default=2000, help="flight segments (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3, help="warm calls timed per fit (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the segments (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/latent_spin_speed_cpu.json"),
                   help="JSON to write (default: %(default)s)")
    args = p.parse_args(argv)

    import jax
    import numpy as np

    from ttsim_jax import load_model
    from ttsim_jax.fit.flightfit import fit_segments
    from ttsim_jax.reality.synthetic_segments import synthetic_segments
    from ttsim_jax.fit.flight import flight_rmse
    from ttsim_jax.fit.latent_spin import fit_latent_spin

    load_before = list(os.getloadavg())
    model = load_model("conti2026")
    times, positions, spins, _ = synthetic_segments(model.aero, model.ball.radius, model.ball.mass, args.segments,
                                                    seed=args.seed, coefficients=None)
    print(f"{args.segments} segments, {sum(len(t) for t in times)} samples; compiling and timing each fit ...",
          file=sys.stderr)
    fits = {"latent spin": lambda: fit_latent_spin(times, positions, model),
            "flight fit": lambda: fit_segments(times, positions, spins),
            "evaluate's flight fit": lambda: flight_rmse(model, times, positions, spins)}
    results, checks = {}, {}
    for name, fn in fits.items():
        t0 = time.perf_counter()
        out = fn()
        cold = time.perf_counter() - t0
        warm = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            fn()
            warm.append(time.perf_counter() - t0)
        results[name] = dict(cold_s=cold, warm_s=warm, warm_median_s=float(np.median(warm)))
        print(f"  {name}: cold {cold:.1f} s, warm median {np.median(warm):.1f} s", file=sys.stderr)
        if name == "latent spin":
            err = np.linalg.norm(out.observed - (spins - np.sum(spins * out.along, 1, keepdims=True) * out.along), axis=1)
            checks["latent_spin_ok_share"] = float(out.ok.mean())
            checks["latent_spin_median_rmse_mm"] = float(np.nanmedian(out.rmse) * 1e3)
            checks["latent_spin_median_error_across_rad_s"] = float(np.nanmedian(err))
        elif name == "flight fit":
            checks["flight_fit_median_rmse_mm"] = float(np.nanmedian(out.rmse) * 1e3)
        else:
            checks["evaluate_median_rmse_mm"] = float(np.nanmedian(out) * 1e3)
    lat = results["latent spin"]["warm_median_s"]
    ratios = {f"latent spin / {k}": lat / results[k]["warm_median_s"] for k in ("flight fit", "evaluate's flight fit")}
    ratios.update({f"latent spin / {k} (cold)": results["latent spin"]["cold_s"] / results[k]["cold_s"]
                   for k in ("flight fit", "evaluate's flight fit")})
    doc = dict(benchmark="latent-spin fit against the flight fits, same segments, one run",
               command="python benchmarks/latent_spin_speed.py " + " ".join(argv if argv is not None else sys.argv[1:]),
               segments=args.segments, samples=int(sum(len(t) for t in times)), results=results, ratios=ratios,
               checks=checks, load_average_before=load_before, load_average_after=list(os.getloadavg()),
               machine=dict(platform=platform.platform(), cpus=os.cpu_count(), jax=jax.__version__,
                            device=str(jax.devices()[0])))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps(dict(ratios=ratios, checks=checks), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
