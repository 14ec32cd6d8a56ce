"""benchmarks/interleaved.py: old and new trees run alternately, each run's figure kept, medians
and their ratio from those figures; the package each run imports is its own tree's."""

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

FAKE = '''
import argparse, json, os, pathlib, subprocess, sys
import fakepkg
with open(os.environ["ORDER_LOG"], "a") as f:
    f.write(f"{fakepkg.RATE}\\n")
p = argparse.ArgumentParser()
p.add_argument("--out")
a = p.parse_args()
# a child process, as diagnose_sample.py starts the CLI: it must import the same tree's package
child = float(subprocess.check_output([sys.executable, "-c", "import fakepkg; print(fakepkg.RATE)"]))
assert child == fakepkg.RATE, (child, fakepkg.RATE)
pathlib.Path(a.out).write_text(json.dumps({"results": [{"result": {"rate": fakepkg.RATE}},
                                                      {"result": {"rate": fakepkg.RATE + 2.0}}]}))
'''


def test_interleaved_runs_each_tree_and_takes_medians(tmp_path):
    for name, rate in (("old", 10.0), ("new", 30.0), ("caller", 99.0)):
        pkg = tmp_path / name / "fakepkg"
        pkg.mkdir(parents=True)
        (pkg / "__init__.py").write_text(f"RATE = {rate}\n")
        (tmp_path / name / "benchmarks").mkdir()
        (tmp_path / name / "benchmarks" / "bench.py").write_text(FAKE)
    out = tmp_path / "ab.json"
    subprocess.run([sys.executable, str(REPO / "benchmarks" / "interleaved.py"), "--old", str(tmp_path / "old"),
                    "--new", str(tmp_path / "new"), "--rounds", "2", "--metric", "result.rate", "--out", str(out), "--",
                    "benchmarks/bench.py"], check=True, capture_output=True, text=True, cwd=tmp_path / "caller",
                   env=dict(os.environ, ORDER_LOG=str(tmp_path / "order.log")))
    # old, new, then new, old
    assert (tmp_path / "order.log").read_text().split() == ["10.0", "30.0", "30.0", "10.0"]
    got = json.loads(out.read_text())
    # each run: the median of its two results (rate, rate + 2), read through the dotted path
    assert got["runs"] == {"old": [11.0, 11.0], "new": [31.0, 31.0]}
    assert got["median"] == {"old": 11.0, "new": 31.0}
    assert abs(got["ratio_new_over_old"] - 31.0 / 11.0) < 1e-12
    assert got["paired_ratios"] == [31.0 / 11.0] * 2 and got["paired_ratio_range"] == [31.0 / 11.0] * 2
