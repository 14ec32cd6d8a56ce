"""Peak memory of drawing a task's shot bank, aimed through the model: the measurement behind
``ttsim_jax.env.bank.AIM_BYTES_PER_SHOT``.

Each bank size is drawn in a process of its own (``[shots] bank = N``, the default task, the cache
bypassed), and its peak resident memory above the process's after imports and model loading
(``ru_maxrss``) is reported; the slope between the smallest and the largest size is the memory per
shot (the compiled programs and JAX's own allocations are the intercept). JSON out:

    python benchmarks/bank_memory.py --sizes 512 4096 --out benchmarks/results/bank_memory_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = """
import json, resource, sys, time
import jax.numpy as jnp
from ttsim_jax import load_model
from ttsim_jax.env import load_task_config
from ttsim_jax.env.bank import shot_bank
n = int(sys.argv[1])
cfg = load_task_config("return_ball", {"shots.bank": n})
model = load_model(cfg.model, dtype=jnp.float32)
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
shots, types = shot_bank(model.replace(residual=None), cfg, cache=False)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps(dict(bank=n, base_mib=base / 1024, peak_mib=peak / 1024, above_mib=(peak - base) / 1024,
                      seconds=time.perf_counter() - t, drawn=int(len(types)))))
"""


def measure(n: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", CHILD, str(n)], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 4096], help="bank sizes (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="JSON file to write (default: print only)")
    args = p.parse_args(argv)
    runs = []
    for n in sorted(args.sizes):
        print(f"drawing an aimed bank of {n} shots ...", flush=True)
        runs.append(measure(n))
        print(json.dumps(runs[-1]), flush=True)
    lo, hi = runs[0], runs[-1]
    per_shot = (hi["above_mib"] - lo["above_mib"]) * 2**20 / (hi["bank"] - lo["bank"]) if len(runs) > 1 else None
    from ttsim_jax.env.bank import AIM_BYTES_PER_SHOT

    result = dict(runs=runs, bytes_per_shot=per_shot, estimate_bytes_per_shot=AIM_BYTES_PER_SHOT,
                  machine=platform.processor() or platform.machine(), cpus=os.cpu_count(),
                  load=os.getloadavg())
    print(f"memory per aimed shot: {per_shot / 1e6:.3f} MB (the estimate: {AIM_BYTES_PER_SHOT / 1e6:.3f} MB)"
          if per_shot else "one size: no slope")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
