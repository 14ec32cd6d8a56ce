"""Wall time of ``ttsim diagnose`` on the bundled sample (JSON out), as a user runs it: a fresh
process, the compilation cache as it is, the verdict's headline kept to compare runs.

    python benchmarks/diagnose_sample.py --out sample_diagnosis.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="JSON file to write")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "ttsim_jax.cli", "diagnose", "--data",
                        str(ROOT / "ttsim_jax" / "data" / "sample" / "games"), "--model", "conti2026", "--out", tmp],
                       check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        out = json.loads((Path(tmp) / "diagnosis.json").read_text())
    verdict = out["verdict"]
    result = {"wall_s": wall, "diagnosis_s": out.get("seconds"), "timings": out.get("timings"),
              "verdict": {k: verdict.get(k) for k in ("level", "effects")}}
    Path(args.out).write_text(json.dumps({"benchmark": "diagnose_sample", "results": [result]}, indent=1))
    print(f"{wall:.1f} s wall, diagnosis {result['diagnosis_s']}", flush=True)


if __name__ == "__main__":
    main()
