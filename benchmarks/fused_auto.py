"""Where the fused path pays for flight + table: the fused and the reference path over a grid of
batches and rollout lengths, alternated in one process for each (JSON out). This is what sets
``rollout.FUSED_AUTO_MIN_BATCH_CPU`` and ``FUSED_AUTO_MIN_STEPS_CPU``, where ``fused="auto"`` starts
taking the fused path on a CPU.

    python benchmarks/fused_auto.py --batches 1024,8192,65536 --steps 100,300,1000 \\
        --out benchmarks/results/fused_auto_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import peers  # noqa: E402
from fused_effects import compare  # noqa: E402
from ttsim_jax import load_model  # noqa: E402


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",")]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=_ints, default=[1024, 8192, 65536],
                   help="comma-separated balls per rollout (default: 1024,8192,65536)")
    p.add_argument("--steps", type=_ints, default=[100, 300, 1000],
                   help="comma-separated steps of 1 ms per rollout (default: 100,300,1000)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs of each path, alternated (default: %(default)s)")
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    args = p.parse_args()
    model = load_model(peers.MODEL, dtype=jnp.float32)
    doc = {"benchmark": "fused_auto", "model": peers.MODEL, "dtype": "float32", "dt_s": peers.DT,
           "what": "flight + table, shared parameters, no rackets; sample_shots", "load_average_before":
           list(os.getloadavg()), "runs": []}
    for b in args.batches:
        balls, _ = peers._shots(b)
        for n in args.steps:
            doc["runs"].append({"batch": b, "steps": n,
                                **compare(f"{b:,} balls x {n} steps", model, None, False, None, balls, n,
                                          args.repeats)})
            args.out.write_text(json.dumps(doc, indent=2))  # what a run cut short leaves
    doc.update(load_average_after=list(os.getloadavg()), device=str(jax.devices()[0]), platform=platform.platform(),
               jax=jax.__version__)
    args.out.write_text(json.dumps(doc, indent=2))
    print("fused / reference:")
    for r in doc["runs"]:
        print(f"  {r['batch']:>8,} x {r['steps']:>5}: {r['fused_over_reference']:.2f}")


if __name__ == "__main__":
    main()
