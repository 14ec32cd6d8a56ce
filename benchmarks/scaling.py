"""Strong and weak scaling of the sharded rally kernel over forced host devices (CPU).

For each device count N the benchmark starts a fresh Python process with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (the flag is read once, when XLA starts) and
times :func:`ttsim_jax.kernel.sharding.sharded_rollout` on realistic shots with two tracking rackets:

* strong scaling: the same global batch (``--batch``) split over N devices;
* weak scaling: ``--batch`` balls per device, N times as many in all.

Speedup is throughput over that of one device; efficiency is speedup / N (strong) or throughput per
device over one device's (weak). Forced host devices share the machine's cores, so on a machine
with C cores no speedup beyond about C is possible: the JSON records the core count beside the
numbers. On a GPU node the same script with ``--platform gpu`` shards over the real devices.

    python benchmarks/scaling.py --devices 1,2,4 --out benchmarks/results/scaling_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

from report_json import emit  # the scripts' folder is on sys.path when run as a script

REPO = Path(__file__).resolve().parents[1]


def measure(n_devices: int, batch: int, n_steps: int, repeats: int, model_name: str) -> dict:
    """Runs in the child process: throughput of one sharded rollout configuration."""
    import jax
    import jax.numpy as jnp

    from ttsim_jax import init_state, load_model
    from ttsim_jax.kernel.sharding import ball_mesh, sharded_rollout
    from ttsim_jax.policies import tracking_rackets
    from ttsim_jax.shots import sample_shots
    from ttsim_jax.state import Ball

    devices = jax.devices()[:n_devices]
    if len(devices) < n_devices:
        raise SystemExit(f"--devices {n_devices}: only {len(devices)} devices are visible")
    mesh = ball_mesh(devices)
    shots, _ = sample_shots(batch, seed=batch)
    state = init_state(Ball(*(jnp.asarray(a) for a in (shots.pos, shots.vel, shots.spin))))
    model = load_model(model_name)
    rackets = tracking_rackets()

    def once():
        t0 = time.perf_counter()
        out_state, _ = sharded_rollout(model, state, n_steps, racket=rackets, mesh=mesh)
        jax.block_until_ready(out_state.ball.pos)
        return time.perf_counter() - t0

    first = once()
    times = [once() for _ in range(repeats)]
    med = statistics.median(times)
    return dict(devices=n_devices, batch=batch, n_steps=n_steps, run_s=times, median_s=med,
                compile_s=first - med, ball_steps_per_s=batch * n_steps / med)


def child(n_devices: int, batch: int, n_steps: int, repeats: int, model: str, platform_name: str) -> dict:
    env = dict(os.environ)
    if platform_name == "cpu":
        flags = env.get("XLA_FLAGS", "")
        env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n_devices}".strip()
        env["JAX_PLATFORMS"] = "cpu"
    code = (f"import json, sys; sys.path.insert(0, {str(REPO / 'benchmarks')!r}); import scaling; "
            f"print('RESULT', json.dumps(scaling.measure({n_devices}, {batch}, {n_steps}, {repeats}, {model!r})))")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=REPO)
    if proc.returncode:
        raise SystemExit(f"the run on {n_devices} devices failed:\n{proc.stderr[-3000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--devices", default="1,2,4", help="comma-separated device counts (default: %(default)s)")
    p.add_argument("--batch", type=int, default=16384,
                   help="global batch for strong scaling, batch per device for weak scaling (default: %(default)s)")
    p.add_argument("--steps", type=int, default=500, help="steps per timed rollout (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per configuration (default: %(default)s)")
    p.add_argument("--model", default="conti2026", help="bundled model (default: %(default)s)")
    p.add_argument("--platform", choices=("cpu", "gpu"), default="cpu",
                   help="cpu: forced host devices; gpu: the visible accelerators (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="write the JSON here (default: print only)")
    args = p.parse_args(argv)
    counts = [int(n) for n in args.devices.split(",")]
    if any(n < 1 for n in counts) or any(args.batch % n for n in counts):
        p.error(f"--batch {args.batch} must divide over every device count in --devices {args.devices}")

    rows = {"strong": [], "weak": []}
    for kind in ("strong", "weak"):
        for n in counts:
            batch = args.batch if kind == "strong" else args.batch * n
            r = child(n, batch, args.steps, args.repeats, args.model, args.platform)
            rows[kind].append(r)
            base = rows[kind][0]
            speedup = r["ball_steps_per_s"] / base["ball_steps_per_s"]
            r["speedup"] = speedup
            r["efficiency"] = speedup / (n / base["devices"])
            print(f"{kind:6s} {n:2d} devices, {batch:8d} balls: {r['ball_steps_per_s']:12,.0f} ball-steps/s "
                  f"(median of {args.repeats}), speedup {speedup:.2f}, efficiency {r['efficiency']:.2f}, "
                  f"compile {r['compile_s']:.1f} s", flush=True)
    report = dict(benchmark="sharded_scaling", unit="ball-steps/s", model=args.model, platform=args.platform,
                  cores=os.cpu_count(), host=platform.platform(), load_average=list(os.getloadavg()),
                  steps=args.steps, rackets="tracking_rackets (2)", **rows)
    emit(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
