"""Rally-kernel throughput: ball-steps per second against batch size, per model family.

Each configuration is compiled once (timed apart), then run ``--repeats`` times; the JSON gives the
median and every repeat. Balls are realistic shots (``ttsim_jax.shots``), played by two tracking
rackets (``ttsim_jax.policies``) so that table and racket contacts happen at a realistic rate.
With ``--residual`` the models that have a racket residual network (conti2026, durr2026) are also
run with an (untrained, same-cost) network, giving the network-on / network-off ratio.

    python benchmarks/throughput.py --out benchmarks/results/throughput_cpu.json
    python benchmarks/throughput.py --quick          # batches 1, 1024, 65536 only
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from ttsim_jax import Record, load_model, simulate
from ttsim_jax.fit.network_config import load_residual_config
from ttsim_jax.physics.network import init_model
from ttsim_jax.policies import tracking_rackets
from ttsim_jax.shots import sample_shots
from ttsim_jax.state import Ball

from report_json import emit  # the scripts' folder is on sys.path when run as a script

REPO = Path(__file__).resolve().parents[1]


def steps_for(batch: int, budget: float) -> int:
    """Steps per run so that a run is about ``budget`` ball-steps (at least 200, at most 2000)."""
    return int(min(2000, max(200, budget // batch)))


def run(variants, balls, n_steps, repeats, rackets):
    """Times each (tag, model) variant; repeats are interleaved so machine drift hits all alike."""
    def once(model):
        t0 = time.perf_counter()
        jax.block_until_ready(simulate(model, balls, n_steps, racket=rackets, record=Record(max_events=8)).final.pos)
        return time.perf_counter() - t0

    first = {tag: once(model) for tag, model in variants}
    times = {tag: [] for tag, _ in variants}
    for _ in range(repeats):
        for tag, model in variants:
            times[tag].append(once(model))
    out = {}
    for tag, _ in variants:
        med = statistics.median(times[tag])
        out[tag] = dict(compile_s=first[tag] - med, run_s=times[tag], median_s=med,
                        ball_steps_per_s=balls.pos.shape[0] * n_steps / med)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default="nakashima2011,durr2026,conti2026",
                   help="comma-separated bundled models (default: %(default)s)")
    p.add_argument("--batches", default="1,16,256,1024,4096,16384,65536,262144",
                   help="comma-separated batch sizes (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="only batches 1, 1024 and 65536")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per configuration (default: %(default)s)")
    p.add_argument("--budget", type=float, default=2e7,
                   help="ball-steps per timed run; sets the step count per batch (default: %(default)g)")
    p.add_argument("--residual", action="store_true",
                   help="also run models with a residual network, for the network-on/off ratio")
    p.add_argument("--no-rackets", action="store_true", help="flight and table only, no rackets")
    p.add_argument("--out", type=Path, default=None, help="write the JSON here (default: print only)")
    args = p.parse_args(argv)

    batches = [1, 1024, 65536] if args.quick else [int(b) for b in args.batches.split(",")]
    rackets = None if args.no_rackets else tracking_rackets()
    results = []
    for name in args.models.split(","):
        variants = [("off", load_model(name))]
        cfg_path = REPO / "configs" / "residual" / f"{name}.toml"
        if args.residual and cfg_path.exists():
            net = init_model(load_residual_config(cfg_path), jax.random.PRNGKey(0))
            variants.append(("on", load_model(name, residual=net)))
        for batch in batches:
            shots, _ = sample_shots(batch, seed=batch)
            balls = Ball(*(jnp.asarray(a) for a in (shots.pos, shots.vel, shots.spin)))
            n_steps = steps_for(batch, args.budget)
            row = dict(model=name, batch=batch, n_steps=n_steps)
            timed = run(variants, balls, n_steps, args.repeats, rackets)
            for tag, _ in variants:
                r = timed[tag]
                row[f"network_{tag}" if len(variants) > 1 else "result"] = r
                print(f"{name:14s} batch {batch:7d} network {tag:3s}: {r['ball_steps_per_s']:12,.0f} ball-steps/s "
                      f"(median of {args.repeats}, compile {r['compile_s']:.1f} s)", flush=True)
            if len(variants) > 1:
                row["ratio_on_off"] = row["network_on"]["ball_steps_per_s"] / row["network_off"]["ball_steps_per_s"]
                print(f"{'':14s} network on/off ratio {row['ratio_on_off']:.3f}", flush=True)
            results.append(row)
    report = dict(benchmark="rally_kernel_throughput", unit="ball-steps/s", dt_s=1e-3, integrator="rk4",
                  rackets=None if args.no_rackets else "tracking_rackets (2)",
                  device=str(jax.devices()[0]), platform=platform.platform(), jax=jax.__version__,
                  results=results)
    emit(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
