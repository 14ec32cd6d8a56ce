"""The kernel with what an RL environment runs (two tracking rackets, the racket residual network,
and per-ball table.e0, racket.e0 and aero.rho_air, drawn as the default task's domain
randomisation draws them) against the lean hand-written numba loop of flight + table, alternated in
one process (JSON out).

    python benchmarks/peers_per_ball.py --batch 65536 --steps 100 --out benchmarks/results/peers_per_ball_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import peers  # noqa: E402
import peers_numba  # noqa: E402
from ttsim_jax import Record, init_state, load_model, rollout  # noqa: E402
from ttsim_jax.fit.network_config import load_residual_config  # noqa: E402
from ttsim_jax.kernel import per_ball_axes  # noqa: E402
from ttsim_jax.physics.network import init_model  # noqa: E402
from ttsim_jax.policies import tracking_rackets  # noqa: E402

# the default task's randomised parameters and ranges (configs/tasks/return_ball.toml)
RANGES = {"table.e0": (0.94, 0.99), "racket.e0": (0.84, 0.90), "aero.rho_air": (1.15, 1.25)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=65536, help="balls (default: %(default)s)")
    p.add_argument("--steps", type=int, default=100, help="steps of 1 ms per timed run (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs of each, alternated (default: %(default)s)")
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    args = p.parse_args()
    b, n = args.batch, args.steps
    balls, _ = peers._shots(b)
    net = init_model(load_residual_config(REPO / "configs" / "residual" / f"{peers.MODEL}.toml"), jax.random.PRNGKey(0))
    model = load_model(peers.MODEL, dtype=jnp.float32, residual=net)
    rng = np.random.default_rng(0)
    for path, (lo, hi) in RANGES.items():
        head, leaf = path.split(".")
        part = getattr(model, head).replace(**{leaf: jnp.asarray(rng.uniform(lo, hi, b), jnp.float32)})
        model = model.replace(**{head: part})
    axes = per_ball_axes(model, *RANGES)
    policy = tracking_rackets()
    kernel = jax.jit(lambda m, x: rollout(m, init_state(x), n, peers.DT, policy, model_axes=axes,
                                          record=Record(max_events=8))[0].ball.pos)
    params = peers_numba.pack_params(load_model(peers.MODEL, dtype=jnp.float32), policy.params)

    def lean(x):
        return peers_numba.rollout_cpu(params, x, n, peers.DT, False, lean=True)

    print("compiling the kernel ...", flush=True)
    t0 = time.perf_counter()
    jax.block_until_ready(kernel(model, balls))
    compile_s = time.perf_counter() - t0
    lean(balls)
    runs = {"kernel": [], "numba_lean": []}
    for r in range(args.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(kernel(model, balls))
        runs["kernel"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        lean(balls)
        runs["numba_lean"].append(time.perf_counter() - t0)
        print(f"  repeat {r + 1}/{args.repeats} done", flush=True)
    rate = {k: b * n / float(np.median(v)) for k, v in runs.items()}
    ratio = rate["kernel"] / rate["numba_lean"]
    print(f"kernel (2 rackets, network, per-ball parameters) {rate['kernel']:,.0f} ball-steps/s; lean numba "
          f"flight + table {rate['numba_lean']:,.0f}: {ratio:.3f}x", flush=True)
    doc = {"benchmark": "peers_per_ball", "batch": b, "steps": n, "per_ball": list(RANGES),
           "rackets": "tracking_rackets() (2)", "residual_network": f"configs/residual/{peers.MODEL}.toml, untrained",
           "run_s": runs, "ball_steps_per_s": rate, "kernel_over_numba_lean": ratio, "compile_s": compile_s,
           "load_average": list(os.getloadavg()), "device": str(jax.devices()[0]), "platform": platform.platform(),
           "jax": jax.__version__}
    args.out.write_text(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
