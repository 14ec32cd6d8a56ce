"""Renders the peers benchmark's JSON as the README's throughput table, so that the table is
always the numbers of one run and never typed by hand.

    python benchmarks/readme_tables.py                      # print the table of results/peers_cpu.json
    python benchmarks/readme_tables.py --write README.md benchmarks/README.md

``--write`` replaces what lies between the lines ``<!-- peers-table:start -->`` and
``<!-- peers-table:end -->`` in each file (a file without them is an error).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT = REPO / "benchmarks" / "results" / "peers_cpu.json"
START, END = "<!-- peers-table:start -->", "<!-- peers-table:end -->"
PEERS = ("kernel", "kernel_fused", "plain_scan", "numba", "numba_cuda", "mujoco", "mjx")


def _rate(x: float) -> str:
    return f"{x / 1e6:.2f} M" if x >= 1e5 else f"{x / 1e3:.1f} k"


def render(result: dict, source: str) -> str:
    """The Markdown table (with a line naming its source and run) of a peers JSON ``result``."""
    configs = result["configs"]
    shown = [p for p in PEERS if any(p in r["peers"] for c in configs.values() for r in c["results"])]
    lines = [f"Ball-steps/s and ratio to the kernel, medians of {result['repeats']} "
             f"({result['model']}, {result['dtype']}, {result['integrator']} at {result['dt_s'] * 1e3:g} ms; "
             f"{result['device']}, {result['cpu_count']} cores; from `{source}`):", "",
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
    if skipped:
        lines += [""] + [f"- not run, {s}" for s in skipped]
    return "\n".join(lines)


def replace_block(text: str, block: str, name: str) -> str:
    """``text`` with the lines between the markers replaced by ``block``."""
    pattern = re.compile(re.escape(START) + r"\n.*?" + re.escape(END), re.S)
    if not pattern.search(text):
        raise ValueError(f"{name}: no '{START}' ... '{END}' block to write the table into")
    return pattern.sub(lambda _: f"{START}\n{block}\n{END}", text, count=1)


def block_of(text: str) -> str | None:
    """The table now between the markers of ``text`` (None without markers)."""
    m = re.search(re.escape(START) + r"\n(.*?)\n" + re.escape(END), text, re.S)
    return None if m is None else m.group(1)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", type=Path, default=DEFAULT, help="peers benchmark JSON (default: %(default)s)")
    p.add_argument("--write", type=Path, nargs="*", default=[],
                   help="Markdown files whose peers-table block is replaced (default: print only)")
    args = p.parse_args(argv)
    try:
        result = json.loads(args.json.read_text())
    except (OSError, ValueError) as e:
        print(f"error: {args.json}: {e}", file=sys.stderr)
        return 2
    source = args.json.resolve().relative_to(REPO).as_posix() if args.json.resolve().is_relative_to(REPO) \
        else str(args.json)
    block = render(result, source)
    if not args.write:
        print(block)
    for path in args.write:
        try:
            path.write_text(replace_block(path.read_text(), block, str(path)))
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"wrote the table into {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
