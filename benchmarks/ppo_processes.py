"""PPO training throughput per process count: ``ttsim train ppo`` of one config on 1 process and on
N processes (JAX's multi-process runtime on this machine, one command per process, the same total
environments), env-steps per second of training after the first chunk (compilation left out), in
one run (JSON out).

    python benchmarks/ppo_processes.py --processes 1,2 --devices 2 --envs 256 --chunks 4 --out benchmarks/results/ppo_processes_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PPO = """task = "return_ball"
[network]
hidden = [64, 64]
[ppo]
num_envs = {envs}
num_steps = 32
update_epochs = 4
num_minibatches = 4
learning_rate = 5e-4
[train]
total_env_steps = {steps}
time_limit_s = 3600.0
updates_per_chunk = {per_chunk}
eval_every_chunks = 0
eval_envs = 0
checkpoint_every_chunks = 1000
"""


def run(n: int, folder: Path, config: Path, devices: int = 1) -> dict:
    """Trains with ``n`` processes (one process: on ``devices`` host devices); the throughput from
    process 0's metrics."""
    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    cmd = [str(Path(sys.executable).parent / "ttsim"), "train", "ppo", "--config", str(config), "--out",
           str(folder / f"p{n}d{devices}"), "--force", "--quiet"]
    env = dict(os.environ)
    if devices > 1:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}").strip()
    t0 = time.perf_counter()
    procs = [subprocess.Popen(cmd + (["--coordinator", f"localhost:{port}", "--num-processes", str(n), "--process-id",
                                      str(i)] if n > 1 else []), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env=env)
             for i in range(n)]
    for p in procs:
        out, _ = p.communicate()
        if p.returncode:
            raise SystemExit(out[-3000:])
    wall = time.perf_counter() - t0
    h = json.loads((folder / f"p{n}d{devices}" / "metrics.json").read_text())
    steps = h[-1]["env_steps"] - h[0]["env_steps"]
    secs = h[-1]["time_s"] - h[0]["time_s"]
    return dict(processes=n, devices=n * devices, env_steps_per_s=steps / secs, chunks=len(h), wall_s=wall, first_chunk_s=h[0]["time_s"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--processes", default="1,2", help="process counts, comma-separated (default 1,2)")
    ap.add_argument("--devices", default="", help="also one process on each of these numbers of host devices, "
                    "comma-separated (e.g. 2; default none)")
    ap.add_argument("--envs", type=int, default=256, help="environments in all (default 256)")
    ap.add_argument("--chunks", type=int, default=4, help="chunks of updates (default 4; the first is left out)")
    ap.add_argument("--updates-per-chunk", type=int, default=2, help="updates per chunk (default 2)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/ppo_processes_cpu.json"), help="JSON to write")
    args = ap.parse_args(argv)
    folder = Path(tempfile.mkdtemp(prefix="ppo-processes-"))
    config = folder / "ppo.toml"
    config.write_text(PPO.format(envs=args.envs, steps=args.envs * 32 * args.updates_per_chunk * args.chunks,
                                 per_chunk=args.updates_per_chunk))
    result = dict(args={k: str(v) for k, v in vars(args).items()}, load_before=os.getloadavg(), rows=[])
    for n in (int(x) for x in args.processes.split(",")):
        row = run(n, folder, config)
        result["rows"].append(row)
        print(f"{n} process(es): {row['env_steps_per_s']:,.0f} env-steps/s ({row['wall_s']:.0f} s wall)", flush=True)
    for d in (int(x) for x in args.devices.split(",") if x):
        row = run(1, folder, config, devices=d)
        result["rows"].append(row)
        print(f"1 process on {d} host devices: {row['env_steps_per_s']:,.0f} env-steps/s ({row['wall_s']:.0f} s wall)",
              flush=True)
    result["load_after"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
