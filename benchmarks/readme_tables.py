"""Renders the peers benchmark's JSON files as the throughput tables of the docs
(``docs/measurements/performance.md``) and of ``benchmarks/README.md``, so that a table is always
the numbers of one run and never typed by hand.

    python benchmarks/readme_tables.py                      # print the tables
    python benchmarks/readme_tables.py --write docs/measurements/performance.md benchmarks/README.md

One table per entry of :data:`TABLES`: the CPU run (``results/peers_cpu.json``) between the lines
``<!-- peers-table:start -->`` and ``<!-- peers-table:end -->``, the GPU runs
(``results/peers_gpu.json``, ``results/peers_gpu_fused.json``) between
``<!-- peers-gpu-table:start -->`` / ``<!-- peers-gpu-fused-table:start -->`` and their end lines,
the CPU run with the residual network (``results/peers_cpu_network.json``) between
``<!-- peers-network-table:start -->`` and its end line.
``--write`` replaces those blocks in each file (a file without them is an error).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT = REPO / "benchmarks" / "results" / "peers_cpu.json"
# marker name -> the benchmark JSON its table is written from
TABLES = {"peers-table": DEFAULT, "peers-gpu-table": REPO / "benchmarks" / "results" / "peers_gpu.json",
          "peers-gpu-fused-table": REPO / "benchmarks" / "results" / "peers_gpu_fused.json",
          "peers-gpu-lean-table": REPO / "benchmarks" / "results" / "peers_gpu_lean.json",
          "peers-gpu-now-table": REPO / "benchmarks" / "results" / "peers_gpu_61ba2cf.json",
          "peers-gpu-d0605a4-table": REPO / "benchmarks" / "results" / "peers_gpu_d0605a4.json",
          "peers-gpu-be0ffe5-table": REPO / "benchmarks" / "results" / "peers_gpu_be0ffe5.json",
          "peers-network-table": REPO / "benchmarks" / "results" / "peers_cpu_network.json",
          "peers-cpu-fused-table": REPO / "benchmarks" / "results" / "peers_cpu_fused_xla.json",
          "peers-cpu-fused-long-table": REPO / "benchmarks" / "results" / "peers_cpu_fused_xla_1000.json"}
PEERS = ("kernel", "kernel_fused", "plain_scan", "numba", "numba_lean", "numba_cuda", "numba_cuda_lean", "mujoco", "mjx")


def markers(name: str = "peers-table") -> tuple[str, str]:
    """The start and end lines of the block named ``name``."""
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


START, END = markers()


def _rate(x: float) -> str:
    if x >= 1e9:
        return f"{x / 1e9:.2f} G"
    return f"{x / 1e6:.2f} M" if x >= 1e5 else f"{x / 1e3:.1f} k"


def render(result: dict, source: str) -> str:
    """The Markdown table (with a line naming its source and run) of a peers JSON ``result``."""
    configs = result["configs"]
    shown = [p for p in PEERS if any(p in r["peers"] for c in configs.values() for r in c["results"])]
    lines = [f"Ball-steps/s and ratio to the kernel, medians of {result['repeats']} "
             f"({result['model']}, {result['dtype']}, {result['integrator']} at {result['dt_s'] * 1e3:g} ms; "
             f"{result.get('device_kind', result['device'])}, {result['cpu_count']} CPU cores; "
             f"from `{source}`):", "",
             "| config | batch x steps | " + " | ".join(shown) + " |",
             "|---|---|" + "---|" * len(shown)]
    for name, c in configs.items():
        for r in c["results"]:
            cells = []
            for p in shown:
                v = r["peers"].get(p)
                if v is None or "ball_steps_per_s" not in v:  # not run for this batch (see "skipped")
                    cells.append("–")
                elif p == "kernel":
                    cells.append(_rate(v["ball_steps_per_s"]))
                else:
                    cells.append(f"{_rate(v['ball_steps_per_s'])} ({v['ratio_to_kernel']:.2f})")
            lines.append(f"| {name} | {r['batch']:,} x {r['n_steps']:,} | " + " | ".join(cells) + " |")
    skipped = {f"{p}: {why}" for c in configs.values() for p, why in c.get("skipped", {}).items()}
    skipped |= {f"{p} at batch {r['batch']:,}: {v['skipped']}" for c in configs.values() for r in c["results"]
                for p, v in r["peers"].items() if "skipped" in v}
    skipped = sorted(skipped)
    # peers.py's kernel / numba's and / the lean loop's flight + table, per configuration
    targets = [(row, "numba's") for row in result.get("targets", [])]
    targets += [(row, "the lean loop's") for row in result.get("targets_lean", [])]
    lines += [""] if targets else []
    for row, base in targets:
        lines.append(f"- the kernel over {base} flight + table at batch {row['batch']:,}: "
                     + ", ".join(f"{cfg} {v:.2f}" for cfg, v in row.items() if cfg != "batch"))
    if skipped:
        lines += [""] + [f"- not run, {s}" for s in skipped]
    return "\n".join(lines)


def replace_block(text: str, block: str, name: str, marker: str = "peers-table") -> str:
    """``text`` (of the file ``name``) with the lines between the ``marker`` lines replaced by ``block``."""
    start, end = markers(marker)
    pattern = re.compile(re.escape(start) + r"\n.*?" + re.escape(end), re.S)
    if not pattern.search(text):
        raise ValueError(f"{name}: no '{start}' ... '{end}' block to write the table into")
    return pattern.sub(lambda _: f"{start}\n{block}\n{end}", text, count=1)


def block_of(text: str, marker: str = "peers-table") -> str | None:
    """The table now between the ``marker`` lines of ``text`` (None without them)."""
    start, end = markers(marker)
    m = re.search(re.escape(start) + r"\n(.*?)\n" + re.escape(end), text, re.S)
    return None if m is None else m.group(1)


def source_of(path: Path) -> str:
    """``path`` as the tables name it: relative to the repository when inside it."""
    return path.resolve().relative_to(REPO).as_posix() if path.resolve().is_relative_to(REPO) else str(path)


def rendered() -> dict[str, str]:
    """marker -> the table of its committed JSON."""
    return {marker: render(json.loads(path.read_text()), source_of(path)) for marker, path in TABLES.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--write", type=Path, nargs="*", default=[],
                   help="Markdown files whose table blocks (one per benchmark JSON: "
                        + ", ".join(f"{m} <- {source_of(j)}" for m, j in TABLES.items())
                        + ") are replaced (default: print only)")
    args = p.parse_args(argv)
    try:
        blocks = rendered()
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not args.write:
        print("\n\n".join(blocks.values()))
    for path in args.write:
        try:
            text = path.read_text()
            for marker, block in blocks.items():
                text = replace_block(text, block, str(path), marker)
            path.write_text(text)
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"wrote the tables into {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
