"""ReturnBall on real rubbers: legal returns of a policy with the generic racket and with tt_rackets'
fitted configurations, and of a policy trained on one rubber played with the others.

Each case is one ``ttsim play --json`` (1,024 episodes, mean action) on a task file written here:
``return_ball.toml`` with ``racket_config`` set (the rally's racket contact: the fitted base +
its residual network of ``configs/rackets/``), and ``[intercept] racket_known`` true (the tracker
plans its stroke with the rubber's fitted coefficients: a robot calibrated on its racket) or false
(it plans with conti2026's own racket: a robot that does not know its rubber). Policies: the bundled
one (trained on the generic racket) and, with ``--train NAME``, one trained here with
``ttsim train ppo`` on the bundled policy's small config, the task with rubber NAME.

    nice python benchmarks/racket_rl.py --out benchmarks/results/racket_rl.json --work runs/racket_rl --train racket_05
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RACKETS = ("racket_01", "racket_05", "racket_07", "racket_08", "racket_10")  # one per rubber type (01: inverted)


def task_file(folder: Path, racket: str | None, known: bool) -> Path:
    """The default task with ``racket_config = racket`` (None: the generic racket) and ``racket_known``."""
    text = (REPO / "configs" / "tasks" / "return_ball.toml").read_text()
    text = text.replace("racket_known = true ", f"racket_known = {'true' if known else 'false'} ")
    name = "generic" if racket is None else f"{racket}_{'known' if known else 'unknown'}"
    path = folder / f"return_ball_{name}.toml"
    path.write_text((f'racket_config = "{racket}"\n' if racket else "") + text)
    return path


def play(policy: str | None, task: Path, episodes: int) -> dict:
    cmd = [sys.executable, "-m", "ttsim_jax.cli", "play", "--json", "--episodes", str(episodes), "--task", str(task)]
    if policy:
        cmd += ["--policy", policy]
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(done.stdout)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    p.add_argument("--work", type=Path, default=REPO / "runs" / "racket_rl",
                   help="folder for the task files and the trained policy (default: runs/racket_rl)")
    p.add_argument("--episodes", type=int, default=1024, help="episodes per case (default 1024)")
    p.add_argument("--train", default=None, help="also train a policy on this rubber (e.g. racket_05) and play it")
    p.add_argument("--plot", type=Path, default=None,
                   help="draw the legal-return rates per racket, policy and planning (PNG); with --replot only that")
    p.add_argument("--replot", action="store_true", help="draw --plot from an existing --out JSON, play nothing")
    args = p.parse_args(argv)
    if args.replot:
        return plot(json.loads(args.out.read_text()), args.plot)
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    policies = {"bundled (generic racket)": None}
    out = dict(episodes=args.episodes, rackets=list(RACKETS), cases=[])
    if args.train:
        task = task_file(work, args.train, True)
        ppo = (REPO / "configs" / "ppo" / "return_ball_small.toml").read_text()
        ppo = ppo.replace('task = "return_ball"', f'task = "{task}"')
        (work / "ppo_small.toml").write_text(ppo)
        run = work / f"ppo_{args.train}"
        t = time.time()
        subprocess.run([sys.executable, "-m", "ttsim_jax.cli", "train", "ppo", "--config", str(work / "ppo_small.toml"),
                        "--out", str(run), "--force", "--quiet"], check=True)
        out["train_seconds"] = time.time() - t
        policies[f"trained on {args.train}"] = str(run / "checkpoint.msgpack")
    for label, policy in policies.items():
        cases = [(None, True)] + [(r, k) for r in RACKETS for k in (True, False)]
        for racket, known in cases:
            s = play(policy, task_file(work, racket, known), args.episodes)
            row = dict(policy=label, racket=racket or "generic", racket_known=known, legal_rate=s["legal_rate"],
                       outcomes=s["outcomes"], landing_error_m=s["landing_error_m"])
            out["cases"].append(row)
            print(f"{label:28s} {row['racket']:10s} known={known!s:5s} legal {s['legal_rate']:.3f}", flush=True)
    out["wall_s"] = time.time() - t0
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out} ({out['wall_s']:.0f} s)")
    return plot(out, args.plot) if args.plot else 0


def plot(out: dict, path: Path) -> int:
    """Grouped bars: per racket, the legal-return rate of each (policy, planning) pair."""
    import numpy as np

    from ttsim_jax.plots import pyplot, save_figure

    plt = pyplot()
    rackets = ["generic"] + list(out["rackets"])
    series = {}
    for c in out["cases"]:
        key = f"{c['policy']}, " + ("stroke planned with the rubber" if c["racket_known"] else "rubber unknown to the tracker")
        series.setdefault(key, {})[c["racket"]] = c["legal_rate"]
    fig, ax = plt.subplots(figsize=(10, 4.2))
    width = 0.8 / len(series)
    for k, (label, values) in enumerate(series.items()):
        x = np.arange(len(rackets)) + (k - (len(series) - 1) / 2) * width
        ax.bar(x, [values.get(r, np.nan) for r in rackets], width, label=label)
    ax.set_xticks(range(len(rackets)), rackets)
    ax.set_ylabel("legal-return rate")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2)
    ax.set_title(f"ReturnBall on tt_rackets' fitted rubbers ({out['episodes']} episodes per bar)")
    save_figure(fig, path)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
