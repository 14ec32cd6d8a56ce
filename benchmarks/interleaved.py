"""Old code against new code, interleaved: one benchmark run alternately from two source trees, so
that a change of the machine's speed during the comparison (other jobs, thermal limits, a shared
host) falls on both alike. Each run is a fresh process (its own compilation; a benchmark keeps
compilation out of its timed repeats) and writes its JSON; the summary holds every run's figure
and the median per tree.

    git worktree add /tmp/old <commit>      # or: git clone . /tmp/old && git -C /tmp/old checkout <commit>
    python benchmarks/interleaved.py --old /tmp/old --new . --rounds 3 \\
        --metric env_steps_per_s --out benchmarks/results/env_throughput_ab_cpu.json -- \\
        benchmarks/env_throughput.py --envs 4096 --repeats 3

Each tree runs its own copy of the benchmark script (a path relative to the trees' roots), with
``PYTHONPATH`` at that tree's root and the tree's root as its working folder: a script that puts
its own repository first on ``sys.path`` (``peers.py`` does), or starts ``python -m ttsim_jax.cli``
(``diagnose_sample.py`` does), then still imports its tree's package. Its ``--out`` is added here.
``--metric`` names the key read from each entry of the JSON's ``results``, or a dotted path into
a nested entry (``result.ball_steps_per_s`` for ``throughput.py``); the median over all of them
when there are several, e.g. one per batch: pass one batch.

Rounds run old then new, and new then old in the next (so that a steady drift of the machine's
speed over two rounds falls on both trees alike); besides the ratio of the medians, the summary
holds each round's ratio new / old (``paired_ratios``), their median and range: the range shows
how far one round can be trusted on this machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_once(tree: Path, script: list, metric: str, log) -> float:
    """The benchmark ``script`` (its path relative to the tree's root, then its arguments) run once
    from ``tree``: the median of ``metric`` over its results."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run.json"
        env = dict(os.environ, PYTHONPATH=str(tree.resolve()))
        cmd = [sys.executable, str((tree / script[0]).resolve()), *script[1:], "--out", str(out)]
        log(f"[{time.strftime('%H:%M:%S')}] {tree}: {' '.join(cmd[1:])}")
        # from the tree's root: a child the benchmark starts as `python -m` or `-c` puts its working
        # folder first on sys.path, ahead of PYTHONPATH, and would import the caller's package
        subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, cwd=tree.resolve())
        values = [read_metric(r, metric) for r in json.loads(out.read_text())["results"]]
    return float(statistics.median(values))


def read_metric(entry: dict, metric: str) -> float:
    """``metric`` of one entry of a benchmark's results: a key, or a dotted path into nested
    entries (``result.ball_steps_per_s`` for ``throughput.py``)."""
    for key in metric.split("."):
        entry = entry[key]
    return float(entry)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--old", type=Path, required=True, help="source tree of the old code (its root folder)")
    p.add_argument("--new", type=Path, required=True, help="source tree of the new code (its root folder)")
    p.add_argument("--rounds", type=int, default=3, help="runs per tree: old then new, then new then old, and so on (default: %(default)s)")
    p.add_argument("--metric", required=True,
                   help="key of each entry of the JSON's results, e.g. env_steps_per_s, or a dotted path into a "
                        "nested entry, e.g. result.ball_steps_per_s")
    p.add_argument("--out", type=Path, required=True, help="summary JSON")
    p.add_argument("script", nargs=argparse.REMAINDER,
                   help="-- then the benchmark script (its path relative to each tree's root) and its arguments")
    args = p.parse_args(argv)
    script = [a for a in args.script if a != "--"]
    if not script:
        p.error("give the benchmark after --, e.g. -- benchmarks/env_throughput.py --envs 4096")
    runs = {"old": [], "new": []}
    for k in range(args.rounds):
        # old, new, then new, old: a drift of the machine's speed across a pair of rounds falls on
        # both trees alike
        for name in ("old", "new") if k % 2 == 0 else ("new", "old"):
            runs[name].append(run_once(getattr(args, name), script, args.metric, print))
    med = {k: statistics.median(v) for k, v in runs.items()}
    paired = [n / o for n, o in zip(runs["new"], runs["old"])]
    summary = dict(benchmark="interleaved", metric=args.metric, script=script,
                   old=str(args.old), new=str(args.new), rounds=args.rounds, runs=runs, median=med,
                   ratio_new_over_old=med["new"] / med["old"], paired_ratios=paired,
                   paired_ratio_median=statistics.median(paired), paired_ratio_range=[min(paired), max(paired)],
                   load_average=list(os.getloadavg()))
    for name in ("old", "new"):
        head = subprocess.run(["git", "-C", str(getattr(args, name)), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True)
        summary[f"{name}_commit"] = head.stdout.strip() or None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(dict(median=med, ratio_new_over_old=summary["ratio_new_over_old"],
                          paired_ratio_median=summary["paired_ratio_median"]), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
