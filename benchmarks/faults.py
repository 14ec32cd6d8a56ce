"""The fault table: a full disk under every writer, a flipped bit in every file kind, ``kill -9``
in every long job, each through the ``ttsim`` command a user types; what each leaves behind.

Every row is run, not asserted from the code: the command, its exit status, its last line of
error output, whether a traceback appeared, whether a temporary or a half-written file was left,
whether a previous output survived, and (for a killed job) whether running it again, with
``--resume`` where the job has one, finishes. The disk is a size-limited tmpfs mounted for the
run (needs root; without it those rows are skipped with the reason).

    python benchmarks/faults.py --out benchmarks/results     # faults.json and faults.md; about 15 min

The table in ``docs/getting-started.md`` (Faults) is this script's ``faults.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "ttsim_jax" / "data" / "sample" / "games"
TTSIM = [sys.executable, "-m", "ttsim_jax.cli"]

TASK = """
model = "conti2026"
[shots]
bank = 64
aim = false
"""
PPO = """
task = "task.toml"
[network]
hidden = [32, 32]
[ppo]
num_envs = 16
num_steps = 16
update_epochs = 2
num_minibatches = 2
[train]
total_env_steps = 20480
updates_per_chunk = 5
eval_every_chunks = 0
eval_envs = 0
checkpoint_every_chunks = 1
"""
RESIDUAL = """
[model]
n_inputs = 8
trunk = [16, 16]
dropout = 0.1
head_width = 8
n_clusters = 10
[attenuation]
a = 7.282
b = 12.899
c = 0.052
[training]
learning_rate = 3e-3
weight_decay = 5e-4
batch_size = 16
max_epochs = 400
patience = 400
kmeans_iters = 5
"""


def run(argv, timeout=900, cwd=None) -> dict:
    """``ttsim argv`` to its end: exit status, wall seconds, the last error line, a traceback?"""
    t = time.perf_counter()
    p = subprocess.run(TTSIM + [str(a) for a in argv], capture_output=True, text=True, timeout=timeout, cwd=cwd,
                       env=_env())
    err = [line for line in p.stderr.splitlines() if line.strip()]
    return dict(rc=p.returncode, seconds=round(time.perf_counter() - t, 1),
                error=next((line for line in reversed(err) if line.startswith("error:")), ""),
                error_lines=sum(line.startswith("error:") for line in err), traceback="Traceback" in p.stderr,
                stdout=p.stdout[-400:])


def _env() -> dict:
    return dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def temporaries(folder: Path) -> list[str]:
    """Temporaries of the atomic writers (``.NAME.<pid>.<random>.tmp``) anywhere under ``folder``."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name.endswith(".tmp"))


def command(argv) -> str:
    return "ttsim " + " ".join(str(a) for a in argv)


# ------------------------------------------------------------------------------------ set-up
def prepare(work: Path) -> dict:
    """The inputs the rows share: a CSV log, the task and PPO configs, a racket-contact dataset, a
    fitted model file, a PPO checkpoint."""
    sys.path.insert(0, str(REPO))
    from ttsim_jax.data import load, save
    from ttsim_jax.data.csvlog import write_csv
    from ttsim_jax.reality.synthetic import synthetic_contact_dataset

    files = dict(sample=SAMPLE)
    files["log"] = write_csv(load(SAMPLE), work / "log")
    (work / "task.toml").write_text(TASK)
    (work / "ppo.toml").write_text(PPO)
    (work / "residual.toml").write_text(RESIDUAL)
    files.update(task=work / "task.toml", ppo=work / "ppo.toml", residual=work / "residual.toml")
    ds, _ = synthetic_contact_dataset(100, seed=5, noise=0.0005)
    save(ds, work / "contacts")
    files["contacts"] = work / "contacts"
    files["model"] = work / "fitted.toml"
    r = run(["fit", "--data", SAMPLE, "--out", files["model"], "--stages", "aero", "--spin", "measured", "--quiet"])
    assert r["rc"] == 0, r
    files["policy"] = work / "ppo" / "checkpoint.msgpack"
    small = work / "ppo_small.toml"
    small.write_text(PPO.replace("total_env_steps = 20480", "total_env_steps = 2560"))
    r = run(["train", "ppo", "--config", small, "--out", work / "ppo", "--quiet"])
    assert r["rc"] == 0 and files["policy"].exists(), r
    return files


# -------------------------------------------------------------------------------- full disk
@contextlib.contextmanager
def full_disk(where: Path, size="8m"):
    """A tmpfs of ``size`` at ``where``, filled to its last byte by a file of its own."""
    where.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)], check=True,
                   capture_output=True)
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def fill(folder: Path) -> None:
    """Fills ``folder``'s filesystem to its last byte."""
    for name, chunk in ((".filler", 65536), (".filler_tail", 1)):
        with contextlib.suppress(OSError), open(folder / name, "wb", buffering=0) as f:
            while True:
                f.write(b"\0" * chunk)


def writers(f: dict, d: Path) -> list[tuple[str, list, Path]]:
    """(what is written, command, its output on the full disk ``d``)."""
    return [
        ("trajectories (NPZ)", ["simulate", "--shots", 16, "--save", d / "t.npz"], d / "t.npz"),
        ("figure (PNG)", ["simulate", "--shots", 16, "--plot", d / "shots.png"], d / "shots.png"),
        ("dataset (CSV import)", ["data", "import", "--source", "csv", f["log"], "--out", d / "imported"], d / "imported"),
        ("dataset (upgrade)", ["data", "upgrade", f["sample"], "--out", d / "upgraded"], d / "upgraded"),
        ("dataset (generate)", ["generate", "--games", 1, "--out", d / "generated", "--quiet"], d / "generated"),
        ("model file (fit)", ["fit", "--data", f["sample"], "--out", d / "fitted.toml", "--stages", "aero",
                              "--spin", "measured", "--quiet", "--force"], d / "fitted.toml"),
        ("evaluation report", ["evaluate", "--data", f["sample"], "--out", d / "evaluation", "--stages", "flight"],
         d / "evaluation"),
        ("diagnosis report", ["diagnose", "--data", f["sample"], "--out", d / "diagnosis", "--quick", "--no-landing"],
         d / "diagnosis"),
        ("animation (GIF)", ["play", "--episodes", 2, "--gif", d / "rally.gif"], d / "rally.gif"),
        ("sensitivity report", ["sensitivity", "--shots", 8, "--mode", "fwd", "--no-check", "--out", d / "sensitivity"],
         d / "sensitivity"),
        ("PPO checkpoint", ["train", "ppo", "--config", f["ppo"], "--out", d / "ppo", "--quiet"], d / "ppo"),
        ("racket network", ["train", "residual", "--data", f["contacts"], "--out", d / "net.ttres", "--config",
                            f["residual"], "--epochs", 2, "--quiet", "--force"], d / "net.ttres"),
    ]


def disk_rows(f: dict, work: Path, wanted=()) -> list[dict]:
    if os.geteuid() != 0:
        return [dict(fault="disk full", target="every writer", skipped="mounting a size-limited tmpfs needs root")]
    rows = []
    for what, argv, out in writers(f, work / "full"):
        if wanted and what not in wanted:
            continue
        with full_disk(work / "full") as d:
            old = None
            if out.suffix:  # a file: an earlier version of it must survive
                out.write_bytes(b"an earlier output")
                old = out.read_bytes()
            fill(d)
            r = run(argv)
            kept = None if old is None else (out.exists() and out.read_bytes() == old)
            new = sorted(str(p.relative_to(d)) for p in d.rglob("*") if not p.name.startswith(".filler")
                         and p != out)
            rows.append(dict(fault="disk full", target=what, command=command(argv).replace(str(work), "W"),
                             **{k: r[k] for k in ("rc", "seconds", "error", "error_lines", "traceback")},
                             temporaries=temporaries(d), earlier_output_kept=kept,
                             left=[n for n in new if not out.suffix or not n.startswith(out.name)]))
            print(json.dumps(rows[-1]), flush=True)
    return rows


# -------------------------------------------------------------------------------- bit flips
def flipped_copy(src: Path, dst: Path, rng: random.Random, file: Path | None = None) -> tuple[str, int]:
    """``src`` copied to ``dst`` with one bit of one file flipped (``file``, or one drawn)."""
    if src.is_dir():
        shutil.copytree(src, dst)
        victim = dst / (file or rng.choice(sorted(p.name for p in src.iterdir() if p.is_file())))
    else:
        shutil.copy(src, dst)
        victim = dst
    data = bytearray(victim.read_bytes())
    at = rng.randrange(len(data))
    data[at] ^= 1 << rng.randrange(8)
    victim.write_bytes(bytes(data))
    return victim.name, at


def flip_rows(f: dict, work: Path, per_kind: int, wanted=()) -> list[dict]:
    rng = random.Random(0)
    policy = next(iter(sorted((REPO / "ttsim_jax" / "rl" / "policies").glob("*.msgpack"))), None)
    network = next(iter(sorted((REPO / "configs" / "rackets").glob("*.ttres"))), None)
    kinds = [(f"dataset: {name}", f["sample"], name, lambda p: ["data", "info", p])
             for name in sorted(p.name for p in SAMPLE.iterdir() if p.is_file())]
    kinds += [("model file (fitted)", f["model"], None, lambda p: ["simulate", "--model", p, "--shots", 4]),
              ("PPO checkpoint", f["policy"], None, lambda p: ["play", "--policy", p, "--episodes", 2])]
    if policy is not None:
        kinds.append(("bundled policy", policy, None, lambda p: ["play", "--policy", p, "--episodes", 2]))
    if network is not None:
        kinds.append(("racket network", network, None,
                      lambda p: ["evaluate", "residual", "--data", f["contacts"], "--checkpoint", p]))
    rows = []
    for k, (what, src, name, door) in enumerate(kinds):
        if wanted and what not in wanted:
            continue
        for i in range(per_kind):
            dst = work / "flips" / f"{k}_{i}" / src.name
            dst.parent.mkdir(parents=True)
            victim, at = flipped_copy(src, dst, rng, name)
            r = run(door(dst))
            rows.append(dict(fault="bit flip", target=what, file=victim, offset=at,
                             command=command(door(dst)).replace(str(work), "W"),
                             **{k: r[k] for k in ("rc", "seconds", "error", "error_lines", "traceback")},
                             names_file=victim in r["error"]))
            print(json.dumps(rows[-1]), flush=True)
    return rows


# ---------------------------------------------------------------------------------- kill -9
def start(argv) -> subprocess.Popen:
    return subprocess.Popen(TTSIM + [str(a) for a in argv], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, env=_env(), start_new_session=True)


def kill_when(p: subprocess.Popen, ready, timeout=600) -> float | None:
    """SIGKILL ``p`` once ``ready()`` holds (polled every few milliseconds: a small dataset's
    temporary directory lives for a tenth of a second); the seconds it ran, or None when it
    finished first."""
    t = time.perf_counter()
    while not ready():
        if p.poll() is not None:
            return None
        if time.perf_counter() - t > timeout:
            break
        time.sleep(0.005)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    return time.perf_counter() - t


def after(seconds: float):
    """A ``ready`` for :func:`kill_when` that holds ``seconds`` from its first call."""
    t0 = []
    return lambda: (t0.append(time.perf_counter()) if not t0 else None) or time.perf_counter() - t0[0] >= seconds


def kill_rows(f: dict, work: Path, wanted=()) -> list[dict]:
    k = work / "killed"
    k.mkdir()
    sc = k / "selfcheck"
    jobs = [  # (job, command, when to kill, how to continue, what must hold after)
        ("train ppo", ["train", "ppo", "--config", f["ppo"], "--out", k / "ppo", "--quiet"],
         lambda: (k / "ppo" / "checkpoint.msgpack").exists(), ["--resume"],
         lambda: (k / "ppo" / "checkpoint.msgpack").exists()),
        ("train residual", ["train", "residual", "--data", f["contacts"], "--out", k / "net.ttres", "--config",
                            f["residual"], "--quiet"],
         lambda: (k / "net.ttres.state").exists(), ["--resume"],
         lambda: (k / "net.ttres").exists() and not (k / "net.ttres.state").exists()),
        ("diagnose selfcheck", ["diagnose", "selfcheck", "--quick", "--effects", "spin_decay", "--games", 2,
                                "--out", sc, "--quiet"],
         lambda: any((sc / "cases").glob("*.json")) if (sc / "cases").exists() else False, ["--resume"],
         lambda: (sc / "selfcheck.md").exists()),
        ("generate", ["generate", "--games", 4, "--out", k / "generated", "--quiet"],
         lambda: any(k.glob(".generated.*.tmp")), [], lambda: (k / "generated" / "metadata.json").exists()),
        ("data import", ["data", "import", "--source", "csv", f["log"], "--out", k / "imported"],
         lambda: any(k.glob(".imported.*.tmp")), [], lambda: (k / "imported" / "metadata.json").exists()),
        # no output until the end: killed in the middle of the work
        ("fit", ["fit", "--data", f["sample"], "--out", k / "fitted.toml", "--stages", "aero,table", "--spin",
                 "measured", "--quiet"], after(4.0), [], lambda: (k / "fitted.toml").exists()),
        ("diagnose", ["diagnose", "--data", f["sample"], "--out", k / "diagnosis", "--quick", "--no-landing"],
         after(20.0), [], lambda: (k / "diagnosis" / "report.md").exists()),
    ]
    rows = []
    for job, argv, ready, again, done in jobs:
        if wanted and job not in wanted:
            continue
        p = start(argv)
        ran = kill_when(p, ready)
        if ran is None:
            rows.append(dict(fault="kill -9", target=job, command=command(argv), skipped="finished before the kill"))
            print(json.dumps(rows[-1]), flush=True)
            continue
        left = temporaries(k)
        r = run(argv + again)
        rows.append(dict(fault="kill -9", target=job, command=command(argv).replace(str(work), "W"),
                         killed_after_s=round(ran, 1), temporaries_after_kill=left,
                         rerun=command(argv + again).replace(str(work), "W"),
                         **{key: r[key] for key in ("rc", "seconds", "error", "traceback")},
                         finished=bool(done()), temporaries_after_rerun=temporaries(k)))
        print(json.dumps(rows[-1]), flush=True)
    return rows


# ------------------------------------------------------------------------------------ report
def markdown(rows: list[dict]) -> str:
    out = ["| fault | what | command | exit | what the user reads | left behind |", "|---|---|---|---|---|---|"]
    for r in rows:
        if "skipped" in r:
            out.append(f"| {r['fault']} | {r['target']} | | | skipped: {r['skipped']} | |")
            continue
        if r["fault"] == "kill -9":
            said = (f"killed after {r['killed_after_s']:.0f} s; `{r['rerun'].replace('ttsim ', '', 1)}` "
                    f"{'finishes' if r['finished'] and r['rc'] == 0 else 'FAILS'} (exit {r['rc']})")
            left = ", ".join(r["temporaries_after_kill"]) or "nothing"
            left = f"after the kill: {left}; after the rerun: {', '.join(r['temporaries_after_rerun']) or 'nothing'}"
        else:
            said = ("TRACEBACK" if r["traceback"] else r["error"].replace("|", "\\|")[:160])
            left = ", ".join(r.get("temporaries", []) + r.get("left", [])) or "nothing"
            if r.get("earlier_output_kept") is not None:
                left += "; the earlier output kept" if r["earlier_output_kept"] else "; the earlier output LOST"
        target = r["target"] + (f" ({r['file']}, byte {r['offset']})" if r["fault"] == "bit flip" else "")
        out.append(f"| {r['fault']} | {target} | `{r['command']}` | {r['rc']} | {said} | {left} |")
    return "\n".join(out) + "\n"


def summary(rows: list[dict]) -> str:
    """One line per fault and target, for the docs: what a user reads and what is left."""
    out = ["| fault | what | command | result |", "|---|---|---|---|"]
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["fault"], r["target"]), []).append(r)
    for (fault, target), rs in groups.items():
        r = rs[0]
        if "skipped" in r:
            out.append(f"| {fault} | {target} | | skipped: {r['skipped']} |")
            continue
        if fault == "kill -9":
            ok = r["rc"] == 0 and r["finished"] and not r["temporaries_after_rerun"]
            left = ", ".join(r["temporaries_after_kill"]) or "nothing"
            result = (f"killed after {r['killed_after_s']:.0f} s, leaving {left}; "
                      + ("`--resume` " if r["rerun"].endswith("--resume") else "the same command ")
                      + ("finishes, nothing left" if ok else f"FAILS (exit {r['rc']})"))
        else:
            clear = sum(x["rc"] == 2 and x["error_lines"] == 1 and not x["traceback"] for x in rs)
            clean = sum(not x.get("temporaries") and not x.get("left") and x.get("earlier_output_kept") is not False
                        for x in rs)
            what = (f"{clear} of {len(rs)} refused in one `error:` line naming the file" if fault == "bit flip" else
                    "one `error:` line" if clear == len(rs) else "NOT one error line")
            result = what + ("" if fault == "bit flip" else
                             ", nothing half-written" + ("" if clean == len(rs) else " NOT: see faults.md")
                             + (", the earlier output kept" if r.get("earlier_output_kept") else ""))
        cmd = r["command"].replace("|", "\\|")
        out.append(f"| {fault} | {target} | `{cmd}` | {result} |")
    return "\n".join(out) + "\n"


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=None, help="folder for faults.json and faults.md (default: print)")
    p.add_argument("--flips", type=int, default=2, help="bit flips per file kind (default: %(default)s)")
    p.add_argument("--only", default="disk,flips,kill", help="which faults: any of disk, flips, kill (the rows of "
                   "the others already in --out's faults.json are kept)")
    p.add_argument("--targets", default="", help="only these rows' targets, comma-separated (e.g. 'generate,fit', "
                   "'model file (fit)'); default: all")
    args = p.parse_args(argv)
    only = set(args.only.split(","))
    wanted = tuple(j for j in args.targets.split(",") if j)
    with tempfile.TemporaryDirectory(prefix="ttsim-faults-") as tmp:
        work = Path(tmp)
        print("preparing the inputs (a CSV log, a fitted model, a short PPO run) ...", flush=True)
        files = prepare(work)
        rows = []
        if "disk" in only:
            rows += disk_rows(files, work, wanted)
        if "flips" in only:
            rows += flip_rows(files, work, args.flips, wanted)
        if "kill" in only:
            rows += kill_rows(files, work, wanted)
        # the run's own folder as W, the repository's files relative to it, as the commands name them
        rows = json.loads(json.dumps(rows).replace(str(work), "W").replace(str(REPO) + "/", ""))
    kept = []
    if args.out is not None and (args.out / "faults.json").exists():  # rows of faults not run again
        new = {(r["fault"], r["target"]) for r in rows}
        kept = [r for r in json.loads((args.out / "faults.json").read_text())["rows"]
                if (r["fault"], r["target"]) not in new]
    order = {"disk full": 0, "bit flip": 1, "kill -9": 2}
    rows = sorted(kept + rows, key=lambda r: order[r["fault"]])  # stable: each fault's rows keep their order
    doc = dict(machine=platform.platform(), load=os.getloadavg(), rows=rows)
    text = markdown(rows)
    print(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "faults.json").write_text(json.dumps(doc, indent=1) + "\n")
        (args.out / "faults.md").write_text(text)
        (args.out / "faults_summary.md").write_text(summary(rows))
    return rows


if __name__ == "__main__":
    main()
