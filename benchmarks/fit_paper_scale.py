"""Time of the whole identification (``ttsim fit``) on a paper-scale dataset.

Runs ``ttsim fit --data DATA --out OUT --force --quiet`` (the default stages, aero, table and
racket, unless ``--stages`` is given) in a child process and records its wall time, its CPU time
(user + system, from the child's resource usage), its peak memory, the load average before, during
(sampled every 5 s) and after, and each stage's wall and CPU time and counts from the summary
``OUT.fit.json`` that the command writes.

The machine may be shared: wall times then grow with the load, CPU times much less. The JSON gives
two idle-machine estimates beside the measured wall time: the CPU time (the run is mostly one
thread, so an idle core takes about that long) and the CPU time over the machine's cores (the
bound if every core were busy with it).

    ttsim generate --preset paper --seed 0 --out runs/paper     # 277 games
    python benchmarks/fit_paper_scale.py --data runs/paper --out benchmarks/results/fit_paper_scale_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from report_json import emit  # noqa: E402


def _sample_load(stop: threading.Event, samples: list) -> None:
    while not stop.wait(5.0):
        samples.append(os.getloadavg()[0])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True,
                   help="dataset directory (e.g. from 'ttsim generate --preset paper')")
    p.add_argument("--model-out", type=Path, default=None,
                   help="model config the fit writes (default: a temporary folder's fitted.toml)")
    p.add_argument("--stages", default=None, help="passed to ttsim fit --stages (default: the command's default)")
    p.add_argument("--out", type=Path, default=None, help="write the JSON here (default: print it)")
    args = p.parse_args(argv)
    if not args.data.is_dir():
        p.error(f"--data {args.data}: not a directory")

    with tempfile.TemporaryDirectory() as tmp:
        model_out = args.model_out or Path(tmp) / "fitted.toml"
        cmd = [sys.executable, "-m", "ttsim_jax.cli", "fit", "--data", str(args.data), "--out", str(model_out),
               "--force", "--quiet"]
        if args.stages:
            cmd += ["--stages", args.stages]
        samples: list = []
        stop = threading.Event()
        sampler = threading.Thread(target=_sample_load, args=(stop, samples), daemon=True)
        load_before = os.getloadavg()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        sampler.start()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        stop.set()
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        load_after = os.getloadavg()
        if proc.returncode != 0:
            print(proc.stdout + proc.stderr, file=sys.stderr)
            return proc.returncode
        summary = json.loads(model_out.with_suffix(".fit.json").read_text())

    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    cores = os.cpu_count() or 1
    stages = {}
    for name, t in summary["seconds"].items():
        stages[name] = dict(t)
        part = summary.get(name, {})
        if "counts" in part:
            stages[name]["counts"] = part["counts"]
        if name == "aero":
            stages[name]["parts_wall"] = part["seconds"]  # select, fit, regress
    report = {
        "benchmark": "ttsim fit at the paper's scale",
        "command": "python benchmarks/fit_paper_scale.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "fit_command": " ".join(["ttsim"] + ["OUT" if a == str(model_out) and args.model_out is None else a
                                              for a in cmd[3:]]),
        "data": str(args.data),
        "wall_s": wall,
        "cpu_s": cpu,
        "idle_estimate_s": {"cpu_time": cpu, "cpu_time_over_cores": cpu / cores},
        "max_rss_mb": after.ru_maxrss / 1024.0,
        "stages": stages,
        "stdout": [line.replace(str(model_out.with_suffix("")), "OUT") for line in proc.stdout.splitlines()],
        "machine": {"platform": platform.platform(), "cpus": cores, "python": platform.python_version(),
                    "load_average_before": load_before, "load_average_after": load_after,
                    "load_average_1min_during": {"mean": sum(samples) / len(samples) if samples else None,
                                                 "max": max(samples) if samples else None, "samples": len(samples)}},
    }
    emit(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
