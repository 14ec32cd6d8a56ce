"""Error of each flight integrator against the step dt, in float64.

For a spread of realistic shots (conti2026, no rackets), the first bounce point and the position
0.6 s after launch are compared with a reference run (RK4, dt = 0.05 ms). Output: JSON with the
median and maximum error [m] per integrator and dt.

    python benchmarks/integrator_error.py --out benchmarks/results/integrator_error.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from ttsim_jax import Ball, load_model, simulate  # noqa: E402
from ttsim_jax.shots import sample_shots  # noqa: E402

T_END = 0.6


def run(model, balls, dt, integrator):
    n = int(round(T_END / dt))
    r = simulate(model, balls, n, dt, integrator=integrator)
    return np.asarray(r.events.pre.pos[:, 0]), np.asarray(r.final.pos), np.asarray(r.events.kind[:, 0])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shots", type=int, default=256, help="number of shots (default: %(default)s)")
    p.add_argument("--model", default="conti2026", help="model (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="write the JSON here")
    args = p.parse_args(argv)
    model = load_model(args.model, dtype=jnp.float64)
    shots, _ = sample_shots(args.shots, seed=7, types=["topspin_drive", "backspin_drive", "smash", "block", "lob"])
    balls = Ball(*(jnp.asarray(a, jnp.float64) for a in (shots.pos, shots.vel, shots.spin)))
    ref_bounce, ref_end, ref_kind = run(model, balls, 5e-5, "rk4")
    rows = []
    for integrator in ("rk4", "rk2", "euler"):
        for dt in (4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4):
            bounce, end, kind = run(model, balls, dt, integrator)
            same = (kind == ref_kind) & (ref_kind == 1)
            eb = np.linalg.norm(bounce - ref_bounce, axis=-1)[same]
            ee = np.linalg.norm(end - ref_end, axis=-1)[same]
            rows.append(dict(integrator=integrator, dt_s=dt, shots=int(same.sum()),
                             bounce_err_median_m=float(np.median(eb)), bounce_err_max_m=float(np.max(eb)),
                             pos_err_median_m=float(np.median(ee)), pos_err_max_m=float(np.max(ee))))
            print(f"{integrator:5s} dt {dt * 1e3:5.2f} ms: bounce point error median {np.median(eb) * 1e3:8.4f} mm, "
                  f"max {np.max(eb) * 1e3:8.4f} mm; position at {T_END} s median {np.median(ee) * 1e3:8.4f} mm, "
                  f"max {np.max(ee) * 1e3:8.4f} mm", flush=True)
    text = json.dumps(dict(benchmark="integrator_error", model=args.model, t_end_s=T_END,
                           reference="rk4, dt = 0.05 ms", results=rows), indent=2)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
