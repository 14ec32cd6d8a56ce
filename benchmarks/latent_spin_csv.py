"""A tracker's CSV log without spin columns, through the user's door: flight RMSE with the latent
spin against the same log with its spin.

1. ``ttsim generate`` games of the paper's physics (conti2026 with the record's noise only:
   ``--effects position_noise,spin_noise,missing_frames``), written as a tracker-style multi-throw CSV log (``ttsim_jax.data.write_csv``: no events,
   no racket states), once with its spin columns and once without them.
2. ``ttsim data import --source csv`` of each log (segments found by the importer, not given).
3. ``ttsim evaluate --stages flight --models conti2026`` of each, with ``--spin auto`` (the default:
   the measured spin where the log has one, the latent spin elsewhere) and, for the log without
   spin, ``--spin zero`` (what the evaluation did before the latent spin).

Writes ``OUT/latent_spin_csv.json`` and prints the medians and their ratios.

    python benchmarks/latent_spin_csv.py --out benchmarks/results
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


def ttsim(*args) -> None:
    done = subprocess.run([sys.executable, "-m", "ttsim_jax.cli", *args], capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"ttsim {' '.join(args)} failed:\n{done.stderr[-3000:]}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--games", type=int, default=4, help="games generated (default: %(default)s)")
    p.add_argument("--seed", type=int, default=7, help="seed of the games (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="output folder (default: %(default)s)")
    args = p.parse_args(argv)

    from ttsim_jax.data import io, write_csv

    work = Path(tempfile.mkdtemp(prefix="latent-spin-csv-"))
    print(f"generating {args.games} games in {work} ...", file=sys.stderr)
    ttsim("generate", "--out", str(work / "games"), "--games", str(args.games), "--seed", str(args.seed),
          "--effects", "position_noise,spin_noise,missing_frames", "--quiet")
    ds = io.load(work / "games")
    with_spin = write_csv(ds, work / "csv_spin").parent
    without = work / "csv_nospin"
    without.mkdir()
    for f in Path(with_spin).iterdir():
        text = f.read_text().splitlines()
        if f.name.startswith("observations"):
            head = text[0].split(",")
            keep = [i for i, c in enumerate(head) if not c.startswith("spin")]
            text = [",".join(line.split(",")[i] for i in keep) for line in text]
        (without / f.name).write_text("\n".join(text) + "\n")
    results = {}
    for name, folder, modes in (("with spin", Path(with_spin), ("auto",)), ("without spin", without, ("auto", "zero"))):
        print(f"importing and evaluating the log {name} ...", file=sys.stderr)
        ttsim("data", "import", "--source", "csv", str(folder), "--out", str(work / f"ds_{folder.name}"))
        for mode in modes:
            out = work / f"eval_{folder.name}_{mode}"
            ttsim("evaluate", "--data", str(work / f"ds_{folder.name}"), "--models", "conti2026", "--stages", "flight",
                  "--spin", mode, "--out", str(out), "--quiet")
            flight = json.loads((out / "metrics.json").read_text())["flight"]
            results[f"{name}, --spin {mode}"] = dict(median_mm=1e3 * flight["models"]["conti2026"]["median"],
                                                     n=flight["n_segments"], spin_sources=flight.get("spin_sources"))
    ref = results["with spin, --spin auto"]["median_mm"]
    for r in results.values():
        r["ratio_to_with_spin"] = r["median_mm"] / ref
    results["load"] = os.getloadavg()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "latent_spin_csv.json").write_text(json.dumps(results, indent=1))
    for k, r in results.items():
        if k != "load":
            print(f"{k}: median flight RMSE {r['median_mm']:.2f} mm over {r['n']} segments "
                  f"({r['ratio_to_with_spin']:.2f}x the log with its spin; spins {r['spin_sources']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
