"""A tracker's raw logs through the user's door: launcher throws simulated independently of the
package (numpy, its own flight and bounce laws), written as CSV the way a tracker writes them (many
throws per session, unrecorded pauses between them, dropped frames, no labelled events), imported
with ``ttsim data import --source csv`` and diagnosed with ``ttsim diagnose``; the same throws also
written one session per throw. Records the segment counts of both imports against the throws' true
flights, and both verdicts.

The simulation: flight with drag and Magnus forces of constant coefficients (C_D, C_M) in still air
of density ``rho``, RK4 at 0.1 ms; a table bounce with normal restitution ``e`` and Coulomb friction
``mu`` on the contact point's slip (sliding, or rolling once the slip would reverse); the ball is
followed until it leaves the table's far end or falls below the surface. ``--friction-scale`` (a
table whose friction is lower or higher) and ``--clock-rate`` (a tracker clock running fast) make
realities whose cause the catalogue may not hold.

Usage: python benchmarks/tracker_sessions.py [--sessions 10 --throws 100] [--friction-scale 0.7]
       [--clock-rate 0.004] [--out benchmarks/results/tracker_sessions.json] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

R, M, RHO, G = 0.02, 0.0027, 1.2, 9.81
AREA = np.pi * R**2


def accel(v, w, cd, cm, rho, wind=(0.0, 0.0, 0.0)):
    """Drag and Magnus accelerations of balls with velocity v (N, 3) and spin w (N, 3) in air that
    moves at ``wind`` (m/s, world frame): both act on the velocity relative to the air."""
    v = v - np.asarray(wind, float)
    speed = np.linalg.norm(v, axis=1, keepdims=True)
    k = 0.5 * rho * AREA / M
    magnus = np.cross(w, v) / np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-9) * speed
    return -k * cd * speed * v + k * cm * magnus * (np.linalg.norm(w, axis=1, keepdims=True) > 0) + [0.0, 0.0, -G]


def bounce(v, w, e, mu):
    """Post-bounce velocity and spin on a level table (normal +z): restitution e, Coulomb friction mu
    on the contact point's slip, capped where the slip would reverse (rolling: the sphere's
    moment of inertia 2/3 m r^2)."""
    vn = v[:, 2]
    slip = v[:, :2] + R * np.stack([w[:, 1], -w[:, 0]], 1)  # contact point at -r z: v + w x (-r z)
    s = np.linalg.norm(slip, axis=1, keepdims=True)
    jn = (1.0 + e) * np.abs(vn)[:, None]  # normal impulse per unit mass
    jt = np.minimum(mu * jn, 0.4 * s)  # 2/5 of the slip removed is rolling for a thin shell (1 / (1 + 3/2))
    dirn = slip / np.maximum(s, 1e-12)
    dv = -jt * dirn
    v2 = np.concatenate([v[:, :2] + dv, -e * vn[:, None]], 1)
    # angular impulse r x J about the centre, J = (dv, jn) at r = -R z: dw = (3 / (2 R)) (-z x dv)
    dw = 1.5 / R * np.stack([dv[:, 1], -dv[:, 0], np.zeros(len(v))], 1)
    return v2, w + dw


def throws(n, rng, *, cd=0.45, cm=0.25, rho=RHO, e=0.88, mu=0.25, h=1e-4, rate=150.0, wind=(0.0, 0.0, 0.0)):
    """``n`` launcher throws: (t, pos, spin, n_bounces) per throw, sampled at ``rate`` with 2 % of
    the frames dropped and 1.5 mm of noise on the positions (the spin as the tracker would estimate
    it without error: the true spin of each sample), in a steady ``wind``."""
    p = np.stack([np.full(n, -1.6), rng.normal(0, 0.15, n), rng.uniform(0.2, 0.35, n)], 1)
    v = np.stack([rng.uniform(4.0, 7.0, n), rng.normal(0, 0.3, n), rng.uniform(0.0, 1.5, n)], 1)
    w = np.stack([rng.normal(0, 20, n), rng.choice([-1.0, 1.0], n) * rng.uniform(30, 150, n), rng.normal(0, 20, n)], 1)
    every = int(round(1.0 / (rate * h)))
    alive = np.ones(n, bool)
    out_t, out_p, out_w = [[] for _ in range(n)], [[] for _ in range(n)], [[] for _ in range(n)]
    bounces = np.zeros(n, int)
    for k in range(int(1.2 / h)):
        if k % every == 0:
            for i in np.flatnonzero(alive):
                out_t[i].append(k * h)
                out_p[i].append(p[i].copy())
                out_w[i].append(w[i].copy())
        f = lambda vv: accel(vv, w, cd, cm, rho, wind)  # noqa: E731
        k1v = f(v)
        k2v = f(v + 0.5 * h * k1v)
        k3v = f(v + 0.5 * h * k2v)
        k4v = f(v + h * k3v)
        p_new = p + h * (v + h / 6.0 * (k1v + k2v + k3v))
        v_new = v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        hit = alive & (p_new[:, 2] < R) & (v_new[:, 2] < 0) & (np.abs(p_new[:, 0]) < 1.37) & (np.abs(p_new[:, 1]) < 0.7625)
        if hit.any():
            v_new[hit], w[hit] = bounce(v_new[hit], w[hit], e, mu)
            p_new[hit, 2] = 2 * R - p_new[hit, 2]
            bounces[hit] += 1
        p, v = np.where(alive[:, None], p_new, p), np.where(alive[:, None], v_new, v)
        alive &= (p[:, 0] < 1.7) & (p[:, 2] > -0.3)
        if not alive.any():
            break
    res = []
    for i in range(n):
        t, pos, spin = np.asarray(out_t[i]), np.asarray(out_p[i]), np.asarray(out_w[i])
        keep = rng.random(len(t)) > 0.02
        keep[:3] = keep[-3:] = True
        res.append((t[keep], pos[keep] + rng.normal(0, 0.0015, pos[keep].shape), spin[keep], int(bounces[i])))
    return res


def sessions(n_sessions, n_throws, rng, **throw_options):
    """``n_sessions`` tracker sessions of ``n_throws`` throws each (:func:`throws` with
    ``throw_options``), 2-6 s apart: (multi, single, flights): each session's (t, pos, spin) with
    its throws one after the other, every throw as a session of its own, and the true flights."""
    multi, single, flights = [], [], 0
    for _ in range(n_sessions):
        t0 = 0.0
        T, P, S = [], [], []
        for t, pos, spin, nb in throws(n_throws, rng, **throw_options):
            T.append(t + t0)
            P.append(pos)
            S.append(spin)
            single.append((t, pos, spin))
            flights += nb + 1
            t0 = T[-1][-1] + rng.uniform(2.0, 6.0)
        multi.append((np.concatenate(T), np.concatenate(P), np.concatenate(S)))
    return multi, single, flights


def write(path: Path, sessions, *, clock_rate=0.0):
    """observations.csv: one (t, pos, spin) block per session, spin with confidence 0.8."""
    path.mkdir(parents=True, exist_ok=True)
    lines = ["session_id,t,x,y,z,spin_x,spin_y,spin_z,spin_conf"]
    for sid, (t, pos, spin) in enumerate(sessions):
        for a, p, s in zip(t * (1.0 + clock_rate), pos, spin):
            lines.append(f"{sid},{float(a)!r}," + ",".join(repr(float(x)) for x in (*p, *s)) + ",0.8")
    (path / "observations.csv").write_text("\n".join(lines) + "\n")


def run(cmd, log: Path):
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT)
    if rc:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed ({rc}); see {log}")
    return time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sessions", type=int, default=10, help="tracker sessions (default 10)")
    ap.add_argument("--throws", type=int, default=100, help="throws per session (default 100)")
    ap.add_argument("--friction-scale", type=float, default=1.0, help="table friction times this (default 1)")
    ap.add_argument("--clock-rate", type=float, default=0.0, help="the tracker's clock runs this much fast (default 0)")
    ap.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    ap.add_argument("--quick", action="store_true", help="diagnose with --quick")
    ap.add_argument("--work", type=Path, default=Path("/tmp/tracker_sessions"), help="working folder (default /tmp/tracker_sessions)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/tracker_sessions.json"), help="JSON to write")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    multi, single, flights = sessions(args.sessions, args.throws, rng, mu=0.25 * args.friction_scale)
    result = dict(args={k: str(v) for k, v in vars(args).items()}, throws=args.sessions * args.throws, true_flights=flights,
                  load_before=os.getloadavg())
    ttsim = [str(Path(sys.executable).parent / "ttsim")]
    for name, logs in (("multi", multi), ("single", single)):
        folder = args.work / name
        write(folder / "csv", logs, clock_rate=args.clock_rate)
        secs = run(ttsim + ["data", "import", str(folder / "csv"), "--source", "csv", "--out", str(folder / "ds"), "--force"],
                   folder / "import.log")
        from ttsim_jax.data import load

        ds = load(folder / "ds")
        diag = ttsim + ["diagnose", "--data", str(folder / "ds"), "--out", str(folder / "report"), "--quiet", "--no-landing"]
        dsecs = run(diag + (["--quick"] if args.quick else []), folder / "diagnose.log")
        d = json.loads((folder / "report" / "diagnosis.json").read_text())
        result[name] = dict(sessions=len(ds.sessions["session_id"]), segments=len(ds.segments["segment_id"]),
                            table_bounces=int(np.sum(ds.events["kind"] == "table")), import_seconds=secs,
                            diagnose_seconds=dsecs, level=d["verdict"].get("level"), effects=d["verdict"]["effects"],
                            verdict=d["verdict"]["text"], floor=d.get("floor"),
                            import_report=(folder / "import.log").read_text().splitlines()[:6])
        print(name, result[name]["segments"], "segments;", result[name]["verdict"][:300], flush=True)
    result["segments_within_1pct"] = abs(result["multi"]["segments"] - flights) <= 0.01 * flights
    result["same_verdict"] = (result["multi"]["level"], result["multi"]["effects"]) == (result["single"]["level"],
                                                                                        result["single"]["effects"])
    result["load_after"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=str))
    print(f"true flights {flights}; multi {result['multi']['segments']}, single {result['single']['segments']}; "
          f"same verdict: {result['same_verdict']}; written to {args.out}")


if __name__ == "__main__":
    main()
