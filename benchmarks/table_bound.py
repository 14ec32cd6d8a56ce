"""How often the table law's bounds change a bounce: on the public measured data and the generator's games.

The bounds (``ttsim_jax/physics/table.py``) on conti2026's residual matrices: the fade below 1 m/s
of horizontal speed and the energy bound (the contact creates no kinetic energy). For comparison,
the normal-speed cap the law had before (outgoing normal speed at most the incoming one, on top of
the energy bound) is computed here too; the simulator no longer applies it.

Each bounce's incoming state goes through the conti2026 law four ways: unbounded (the paper's
equations), faded (the fade only), bounded (the simulator's law: fade and energy bound) and capped
(the former law). Bounces:

- public data (SpinDOE, TT3D, MPI; read from ``--real`` at run time with the importers of
  ``ttsim data import``; cite the sources, see their SOURCES.md): the incoming state estimated from
  the observations around each table event as ``ttsim evaluate`` does
  (:func:`ttsim_jax.evaluate.stages.table_stage`: a quadratic per axis on each side; the segments'
  measured spin, 0 where none is measured);
- generator: the true incoming state of every table bounce on the playing surface of the bundled
  sample (``ttsim_jax/data/sample/games``) and of ``--games`` games generated here (every effect
  on, ``--seed``).

Per set and per bound: the share of bounces it changes (the residual's scale factor below
1 - 1e-6; for the fade, below 1 m/s of horizontal speed), the largest change of the outgoing
velocity (|dv| and dv_z) and spin, and of the position 0.3 s later (conti2026's flight from the
contact point); the same on the fast, flat bounces (impact angle 9-14 degrees). On the public data
also: the measured normal restitution against the impact angle, and, on the bounces where the cap
would act, the measured v_z+ minus each prediction (mean with a 95 % bootstrap interval).

    python benchmarks/table_bound.py --out benchmarks/results   # 3 CPU-minutes (8 min wall on a shared 2-core machine)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: make ``benchmarks`` importable
    sys.path.insert(0, str(REPO))

from benchmarks.real_flight_rmse import real_root  # noqa: E402

SOURCES = {"spindoe": "spindoe", "tt3d": "tt3d", "mpi": "mpi_ball_prediction"}
FLAT = (9.0, 14.0)  # impact angles [deg] of the fast, flat drives
CHANGED = 1e-6  # a scale factor below 1 - CHANGED counts as a change
FLIGHT_S = 0.3  # the outgoing flight compared [s]
ANGLE_BINS = (0.0, 10.0, 15.0, 20.0, 30.0, 90.0)


def public_bounces(real: Path, model) -> dict:
    """Set name -> (pos (N, 3), pre (N, 6), post (N, 6)) of the usable table bounces per source."""
    from ttsim_jax.data.importers import import_source
    from ttsim_jax.evaluate.stages import EvaluateSettings, table_stage

    out = {}
    for source, folder in SOURCES.items():
        ds = import_source(real / folder, source)
        r = table_stage(ds, [("conti2026", model)], EvaluateSettings())
        row_of = {int(e): i for i, e in enumerate(ds.events["event_id"])}
        rows = np.array([row_of[int(e)] for e in r.event_id], np.int64)
        pos = np.stack([np.asarray(ds.events[k], np.float64)[rows] for k in "xyz"], -1)
        out[source] = (pos, r.pre, r.post)
    return out


def truth_bounces(events: dict, model) -> tuple:
    """(pos, pre) of the true table bounces on the playing surface, moving down, of truth events."""
    kind = np.asarray(events["true_kind"]).astype(str)
    pre = np.stack([np.asarray(events[f"pre_{k}"], np.float64) for k in ("vx", "vy", "vz", "spin_x", "spin_y", "spin_z")], 1)
    pos = np.stack([np.asarray(events[f"pre_{k}"], np.float64) for k in "xyz"], 1)
    half = np.array([0.5 * float(model.table.length), 0.5 * float(model.table.width)])
    keep = (kind == "table") & np.all(np.abs(pos[:, :2]) <= half, axis=1) & (pre[:, 2] < 0.0)
    return pos[keep], pre[keep]


def responses(model, pre: np.ndarray) -> dict:
    """Outgoing (v, w) (N, 6) of the law without bounds (``unbounded``), with the fade only
    (``faded``), with both bounds (``bounded``, the simulator's) and with the former cap
    (``capped``); the fade and the energy bound's factor (N,)."""
    import jax
    import jax.numpy as jnp

    from ttsim_jax.physics import table as tbl

    t, r = model.table, model.ball.radius

    def one(v, w):
        base_v, base_w, dv, dw = tbl.residual_terms(t, r, v, w)
        lam = tbl.residual_bound(t.kappa, r, v, w, base_v, base_w, dv, dw)
        # the former cap: no more outgoing normal speed than the incoming one
        room = jnp.maximum(jnp.abs(v[2]) - base_v[2], 0.0)
        cap = jnp.minimum(lam, jnp.where(lam * dv[2] > room, room / jnp.where(dv[2] > 0.0, dv[2], 1.0), 1.0))
        bounded = jnp.concatenate(tbl.local_contact(t, r, v, w))
        return jnp.concatenate([base_v, base_w]), jnp.concatenate([dv, dw]), bounded, cap, tbl.residual_fade(v), lam

    base, d, bounded, cap, fade, lam = map(np.asarray, jax.jit(jax.vmap(one))(jnp.asarray(pre[:, :3]),
                                                                            jnp.asarray(pre[:, 3:])))
    # the residual before its fade; undefined for a vertical drop (no heading), kept faded there
    full = d / np.where(fade > 0.0, fade, 1.0)[:, None]
    return dict(unbounded=base + full, faded=base + d, bounded=bounded, capped=base + cap[:, None] * d, fade=fade,
                energy_factor=lam)


def positions_after(model, pos: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Ball positions FLIGHT_S after leaving ``pos`` (on the surface) with ``out`` = (v, w)."""
    from ttsim_jax import Ball, simulate

    start = np.concatenate([pos[:, :2], np.full((len(pos), 1), float(model.ball.radius) + 2e-4)], 1)
    r = simulate(model, Ball.create(start, out[:, :3], out[:, 3:]), int(round(FLIGHT_S / 1e-3)), 1e-3)
    return np.asarray(r.final.pos)


def change(a: np.ndarray, b: np.ndarray, pa: np.ndarray, pb: np.ndarray, sel: np.ndarray) -> dict:
    """Largest differences between two responses (and their positions FLIGHT_S later) over ``sel``."""
    if not sel.any():
        return dict(max_dv=0.0, max_dvz=0.0, max_dw=0.0, max_dpos_mm=0.0)
    d = (a - b)[sel]
    return dict(max_dv=float(np.linalg.norm(d[:, :3], axis=1).max()), max_dvz=float(np.abs(d[:, 2]).max()),
                max_dw=float(np.linalg.norm(d[:, 3:], axis=1).max()),
                max_dpos_mm=float(1e3 * np.linalg.norm((pa - pb)[sel], axis=1).max()))


def bootstrap_mean(x: np.ndarray, n_boot: int, seed: int = 0) -> list:
    rng = np.random.default_rng(seed)
    return np.percentile(x[rng.integers(0, len(x), (n_boot, len(x)))].mean(1), [2.5, 97.5]).tolist()


def summarise(pre: np.ndarray, res: dict, after: dict) -> dict:
    """Shares and largest changes of each bound over all bounces and over the flat ones."""
    speed = np.linalg.norm(pre[:, :3], axis=1)
    angle = np.degrees(np.arctan2(-pre[:, 2], np.linalg.norm(pre[:, :2], axis=1)))
    faded = res["fade"] < 1.0
    energy = res["energy_factor"] < 1.0 - CHANGED
    cap = np.any(np.abs(res["capped"] - res["bounded"]) > CHANGED, axis=1)
    flat = (angle >= FLAT[0]) & (angle <= FLAT[1])
    out = dict(n=len(pre), speed_m_s=dict(zip(("p5", "median", "p95"), np.percentile(speed, [5, 50, 95]).round(2).tolist())),
               impact_angle_deg=dict(zip(("min", "p5", "median", "p95"), np.percentile(angle, [0, 5, 50, 95]).round(1).tolist())),
               law_normal_restitution_above_1=int(np.sum(res["bounded"][:, 2] > -pre[:, 2])))
    for name, sub in (("all", np.ones(len(pre), bool)), (f"flat ({FLAT[0]:g}-{FLAT[1]:g} deg)", flat)):
        n = int(sub.sum())
        share = lambda m: float(np.mean(m[sub])) if n else 0.0  # noqa: E731
        out[name] = dict(
            n=n,
            fade=dict(share=share(faded), **change(res["unbounded"], res["faded"], after["unbounded"], after["faded"],
                                                  sub & faded)),
            energy_bound=dict(share=share(energy), **change(res["faded"], res["bounded"], after["faded"], after["bounded"],
                                                            sub & energy)),
            any_bound=dict(share=share(faded | energy), **change(res["unbounded"], res["bounded"], after["unbounded"],
                                                                 after["bounded"], sub & (faded | energy))),
            former_normal_cap=dict(share=share(cap), **change(res["capped"], res["bounded"], after["capped"], after["bounded"],
                                                              sub & cap)))
    return out


def measured(pre: np.ndarray, post: np.ndarray, res: dict, n_boot: int) -> dict:
    """Measured against predicted normal restitution by impact angle; the cap's bounces."""
    angle = np.degrees(np.arctan2(-pre[:, 2], np.linalg.norm(pre[:, :2], axis=1)))
    ratio, law = post[:, 2] / -pre[:, 2], res["bounded"][:, 2] / -pre[:, 2]
    bins = []
    for lo, hi in zip(ANGLE_BINS[:-1], ANGLE_BINS[1:]):
        s = (angle >= lo) & (angle < hi)
        if s.any():
            bins.append(dict(angle_deg=[lo, hi], n=int(s.sum()), measured_median=float(np.median(ratio[s])),
                             measured_iqr=np.percentile(ratio[s], [25, 75]).tolist(),
                             measured_share_above_1=float(np.mean(ratio[s] > 1.0)), law_median=float(np.median(law[s]))))
    cap = np.any(np.abs(res["capped"] - res["bounded"]) > CHANGED, axis=1)
    out = dict(normal_restitution_by_angle=bins, cap_bounces=int(cap.sum()))
    if cap.sum() >= 3:
        for name in ("bounded", "capped"):
            e = post[cap, 2] - res[name][cap, 2]
            out[f"measured_minus_{name}_vz"] = dict(mean=float(e.mean()), ci95=bootstrap_mean(e, n_boot),
                                                    rms=float(np.sqrt(np.mean(e * e))))
    e = post[:, 2] - res["bounded"][:, 2]
    out["measured_minus_bounded_vz_all"] = dict(mean=float(e.mean()), ci95=bootstrap_mean(e, n_boot))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--real", type=Path, default=real_root(), help="folder of the public data (default: %(default)s)")
    p.add_argument("--games", type=int, default=20, help="games generated beside the bundled sample, 0 for none "
                   "(default: %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="seed of the generated games (default: %(default)s)")
    p.add_argument("--bootstrap", type=int, default=4000, help="bootstrap draws (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="output folder (default: %(default)s)")
    args = p.parse_args(argv)
    if not args.real.is_dir():
        p.error(f"--real: {args.real} is not a folder (the public datasets, see its SOURCES.md)")
    if args.games < 0:
        p.error(f"--games {args.games}: must be >= 0")

    from ttsim_jax import load_model
    from ttsim_jax.reality import generate, load_truth, make_config

    t_start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    model = load_model("conti2026")
    sets, posts = {}, {}
    for name, (pos, pre, post) in public_bounces(args.real, model).items():
        sets[name], posts[name] = (pos, pre), post
    sets["generator: bundled sample"] = truth_bounces(load_truth(REPO / "ttsim_jax" / "data" / "sample" / "games").events, model)
    if args.games:
        gen = generate(make_config(games=args.games, seed=args.seed, effects="all"), progress=False)
        sets[f"generator: {args.games} games, seed {args.seed}"] = truth_bounces(gen.truth_events, model)

    # one response and one flight for every bounce of every set
    pos = np.concatenate([s[0] for s in sets.values()])
    pre = np.concatenate([s[1] for s in sets.values()])
    res = responses(model, pre)
    variants = ("unbounded", "faded", "bounded", "capped")
    flown = positions_after(model, np.concatenate([pos] * len(variants)), np.concatenate([res[k] for k in variants]))
    after = dict(zip(variants, np.split(flown, len(variants))))
    results, start = {}, 0
    for name, (_, p_set) in sets.items():
        sl = slice(start, start + len(p_set))
        start += len(p_set)
        r = {k: v[sl] for k, v in res.items()}
        results[name] = summarise(p_set, r, {k: v[sl] for k, v in after.items()})
        if name in posts:
            results[name]["measured"] = measured(p_set, posts[name], r, args.bootstrap)

    lines = ["| bounces | n | impact angle median [deg] | energy bound: share, max abs dv [m/s] | fade | any bound | "
             f"former normal cap: share, max abs dv [m/s], at {FLIGHT_S:g} s [mm] | cap at {FLAT[0]:g}-{FLAT[1]:g} deg |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        a, f = r["all"], r[f"flat ({FLAT[0]:g}-{FLAT[1]:g} deg)"]
        pct = lambda d: f"{100 * d['share']:.1f} %"  # noqa: E731
        lines.append(f"| {name} | {r['n']} | {r['impact_angle_deg']['median']:.1f} | {pct(a['energy_bound'])}, "
                     f"{a['energy_bound']['max_dv']:.3g} | {pct(a['fade'])} | {pct(a['any_bound'])} | "
                     f"{pct(a['former_normal_cap'])}, {a['former_normal_cap']['max_dv']:.3g}, "
                     f"{a['former_normal_cap']['max_dpos_mm']:.1f} | {pct(f['former_normal_cap'])} of {f['n']} |")
    table = "\n".join(lines)
    print(table)
    report = dict(benchmark="table law bounds on measured and generated bounces",
                  command="python benchmarks/table_bound.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                  model="conti2026", changed_threshold=CHANGED, flight_s=FLIGHT_S, flat_deg=list(FLAT),
                  sources="SpinDOE (Gossard et al., arXiv:2303.03879), TT3D (arXiv:2504.10035), MPI ball_prediction "
                          "(intelligent-soft-robots/ball_prediction); see the data's SOURCES.md",
                  sets=results, markdown=table, wall_s=round(time.perf_counter() - t_start, 1))
    (args.out / "table_bound.json").write_text(json.dumps(report, indent=1))
    print(f"wrote {args.out / 'table_bound.json'} ({report['wall_s']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
