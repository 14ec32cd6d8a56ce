"""The fused path against the reference path where the fused path flies the reference flight step
(effects acting in flight, per-ball effect parameters), where it samples the residual, where the
table and air parameters are drawn per ball, and where a racket policy moves the rackets (two
tracking rackets, with the same per-ball parameters),
alternated in one process (JSON out). This is what ``fused="auto"`` decides on for these models.

    python benchmarks/fused_effects.py --batch 65536 --steps 300 --out benchmarks/results/fused_effects_cpu.json
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
from ttsim_jax import Execution, effects as fx, init_state, load_model, rollout  # noqa: E402
from ttsim_jax.fit.network_config import load_residual_config  # noqa: E402
from ttsim_jax.kernel import per_ball_axes  # noqa: E402
from ttsim_jax.physics.network import init_model  # noqa: E402
from ttsim_jax.policies import tracking_rackets  # noqa: E402


def cases(b: int, rng) -> dict:
    """name -> (model, model_axes, whether the residual is sampled, racket): the rollouts the comparison runs."""
    base = load_model(peers.MODEL, dtype=jnp.float32)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    effects = (fx.make("spin_decay", dtype=jnp.float32).replace(rate=f32(rng.uniform(0.0, 0.3, b))),
               fx.make("air_flow", dtype=jnp.float32).replace(wind=f32(rng.uniform(-0.5, 0.5, (b, 3)))))
    hooked = base.replace(effects=effects)
    net = init_model(load_residual_config(REPO / "configs" / "residual" / f"{peers.MODEL}.toml"), jax.random.PRNGKey(0))
    drawn = base.replace(table=base.table.replace(e0=f32(rng.uniform(0.85, 0.95, b))),
                         aero=base.aero.replace(rho_air=f32(rng.uniform(1.1, 1.3, b))))
    return {"effects_in_flight": (hooked, per_ball_axes(hooked, "effects.0.rate", "effects.1.wind"), False, None),
            "sampled_residual": (base.replace(residual=net), per_ball_axes(base), True, None),
            "per_ball_parameters": (drawn, per_ball_axes(drawn, "table.e0", "aero.rho_air"), False, None),
            "racket_policy": (drawn, per_ball_axes(drawn, "table.e0", "aero.rho_air"), False, tracking_rackets())}


def compare(name: str, model, axes, sample: bool, racket, balls, n: int, repeats: int) -> dict:
    """The fused and the reference path's rollouts of ``balls`` over ``n`` steps, compiled, then timed
    ``repeats`` times each, alternated; their final positions compared. Returns the case's JSON."""
    b = balls.pos.shape[0]

    def run(fused):
        def final(m, x):  # the event log is an output, as for a user who reads it (else XLA drops it)
            state, out = rollout(m, init_state(x), n, peers.DT, racket, model_axes=axes,
                                 sample_key=jax.random.PRNGKey(1) if sample else None,
                                 execution=Execution(fused=fused))
            return state.ball.pos, out.events
        return jax.jit(final)

    paths = {"fused": run(True), "reference": run(False)}
    compile_s = {}
    for k, fn in paths.items():
        print(f"{name}: compiling the {k} path ...", flush=True)
        t0 = time.perf_counter()
        jax.block_until_ready(fn(model, balls))
        compile_s[k] = time.perf_counter() - t0
    runs = {k: [] for k in paths}
    for r in range(repeats):
        for k, fn in paths.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(model, balls))
            runs[k].append(time.perf_counter() - t0)
        print(f"  repeat {r + 1}/{repeats} done", flush=True)
    rate = {k: b * n / float(np.median(v)) for k, v in runs.items()}
    # float32: a ball that grazes an edge may take the other side of it on the other path
    gap = np.asarray(jnp.max(jnp.abs(paths["fused"](model, balls)[0] - paths["reference"](model, balls)[0]), axis=-1))
    apart = float(np.mean(gap > 1e-3))
    print(f"{name}: fused {rate['fused']:,.0f} ball-steps/s, reference {rate['reference']:,.0f}: "
          f"{rate['fused'] / rate['reference']:.2f}x; final positions: median difference {np.median(gap):.1e} m, "
          f"{apart:.2%} of the balls more than 1 mm apart", flush=True)
    return {"run_s": runs, "compile_s": compile_s, "ball_steps_per_s": rate,
            "fused_over_reference": rate["fused"] / rate["reference"],
            "median_position_difference_m": float(np.median(gap)), "fraction_more_than_1mm_apart": apart}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=65536, help="balls (default: %(default)s)")
    p.add_argument("--steps", type=int, default=300, help="steps of 1 ms per timed run (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs of each path, alternated (default: %(default)s)")
    p.add_argument("--cases", default="effects_in_flight,sampled_residual,per_ball_parameters,racket_policy",
                   help="comma-separated: effects_in_flight (spin decay and wind, drawn per ball), "
                        "sampled_residual (an untrained network, no rackets), per_ball_parameters (table.e0 "
                        "and aero.rho_air drawn per ball, no rackets), racket_policy (the same with two "
                        "tracking rackets) (default: %(default)s)")
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    args = p.parse_args()
    b, n = args.batch, args.steps
    balls, _ = peers._shots(b)
    all_cases = cases(b, np.random.default_rng(0))
    doc = {"benchmark": "fused_effects", "batch": b, "steps": n, "cases": {}}
    for name in args.cases.split(","):
        model, axes, sample, racket = all_cases[name]
        doc["cases"][name] = compare(name, model, axes, sample, racket, balls, n, args.repeats)
    doc.update(load_average=list(os.getloadavg()), device=str(jax.devices()[0]), platform=platform.platform(),
               jax=jax.__version__)
    args.out.write_text(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
