"""Latent spin (``ttsim_jax.fit.latent_spin``) against measurement, on the public data.

* **SpinDOE** (Gossard et al. 2023, arXiv:2303.03879; spin measured by a dotted-ball vision
  method), its measured spin withheld from the fit: per flight segment, the latent spin's part
  across the direction of flight against the measured spin's part there (the angle between them and
  the magnitude error), by the measured spin's size, by the size of its component along the
  flight (which the positions do not show) and by segment length; and the spin check
  (``ttsim_jax.fit.spin_check``) of the measured spin against the latent one. And per table
  bounce whose incoming segment has a measured spin, the spin fitted across the bounce
  (``ttsim_jax.fit.bounce_spin``: both segments as one flight through the model's table law)
  against the measured one, beside the incoming segment's own latent spin.
* **MPI launcher recordings** (``intelligent-soft-robots/ball_prediction``, BSD-3-Clause; no spin
  measured): the latent spin's top/backspin component per file against the files' names
  (``mn5008_topspin``, ``mn5008_backspin``, ``mn5008_no_spin``), and the held-out flight error.
* **TT3D** (arXiv:2504.10035; no spin): the held-out flight error.

Held-out flight error: the latent spin and the initial state are fitted on the first
``--fit-fraction`` of a segment's samples; the model then predicts the rest from that state, and
the error is the RMSE over the remaining samples. Spin 0 gets the same treatment (its state fitted
on the same first samples, spin fixed at 0), so the two differ only in the spin.

Each dataset is read from ``--real`` at run time (see its SOURCES.md; cite the sources). Writes
``OUT/latent_spin.json`` and ``OUT/latent_spin.png``; prints Markdown tables.

    python benchmarks/latent_spin.py --out benchmarks/results
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


#: Trajectories per block of SpinDOE's files (in file order) in the table of sign disagreement by block.
BLOCK = 15


def evenness_p(blocks, permutations: int = 20000, seed: int = 0) -> float:
    """Permutation p-value of the blocks' counts of segments bent opposite to their measured spin
    under the hypothesis that those segments are spread evenly over the files (the chi-square of
    the counts against their shares, its flags shuffled over the segments)."""
    n = np.array([b["n"] for b in blocks])
    o = np.array([b["opposite"] for b in blocks])
    share = o.sum() / max(n.sum(), 1)
    if share in (0.0, 1.0):
        return 1.0
    expected = n * share

    def chi2(counts):
        return np.sum((counts - expected) ** 2 / (expected * (1.0 - share)), axis=-1)

    rng = np.random.default_rng(seed)
    flags = np.zeros((permutations, n.sum()), bool)
    flags[:, :o.sum()] = True
    flags = rng.permuted(flags, axis=1)
    counts = np.add.reduceat(flags, np.concatenate([[0], np.cumsum(n)[:-1]]), axis=1)
    return float((np.sum(chi2(counts) >= chi2(o)) + 1) / (permutations + 1))


def real_root() -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def segments(ds, min_samples):
    from ttsim_jax.fit.segment_batches import dataset_segments

    ids, times, positions, spins, conf = dataset_segments(ds, min_samples)
    session_of = dict(zip(np.asarray(ds.segments["segment_id"]).tolist(), np.asarray(ds.segments["session_id"]).tolist()))
    return ids, times, positions, spins, conf, np.array([session_of[int(i)] for i in ids])


def angle_deg(a, b):
    c = np.sum(a * b, 1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def topspin_component(spin, vel):
    """Spin along z x v_h (positive: topspin, negative: backspin) [rad/s]."""
    h = vel * np.array([1.0, 1.0, 0.0])
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-9)
    return np.sum(spin * np.cross(np.array([0.0, 0.0, 1.0]), h), 1)


def held_out_rmse(model, times, positions, fraction, spin_mode):
    """(S,) RMSE [m] over each segment's last samples, predicted from a state (and, with
    ``spin_mode="latent"``, a spin) fitted on its first ``fraction`` of samples."""
    import jax
    import jax.numpy as jnp

    from ttsim_jax.fit.latent_spin import fit_latent_spin
    from ttsim_jax.physics.aero import flight_step

    heads = [max(8, int(round(fraction * len(t)))) for t in times]
    head_t = [t[:k] for t, k in zip(times, heads)]
    head_p = [p[:k] for p, k in zip(positions, heads)]
    if spin_mode == "latent":
        ls = fit_latent_spin(head_t, head_p, model)
        p0, v0, w0 = ls.p0, ls.v0, ls.spin
    else:  # the state fitted with the spin held at 0: the latent fit with a spin prior of 1e-6 rad/s
        ls = fit_latent_spin(head_t, head_p, model, prior_along=1e-6, prior_any=1e-6)
        p0, v0, w0 = ls.p0, ls.v0, np.zeros_like(ls.spin)
    step = jax.jit(lambda p, v, w, h: flight_step(model.aero, model.ball.radius, model.ball.mass, p, v, w, 0.0, h,
                                                   model.effects))
    out = np.full(len(times), np.nan)
    for i, (t, p) in enumerate(zip(times, positions)):
        if not np.isfinite(p0[i]).all() or heads[i] >= len(t):
            continue
        y = (jnp.asarray(p0[i]), jnp.asarray(v0[i]), jnp.asarray(w0[i]))
        pred = [np.asarray(y[0])]
        for k in range(1, len(t)):
            n_sub = max(1, int(np.ceil((t[k] - t[k - 1]) / 1e-3)))
            h = (t[k] - t[k - 1]) / n_sub
            for _ in range(n_sub):
                y = step(*y, h)
            pred.append(np.asarray(y[0]))
        err = np.asarray(pred)[heads[i]:] - p[heads[i]:]
        out[i] = float(np.sqrt(np.mean(np.sum(err**2, 1))))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--real", type=Path, default=real_root(), help="folder of the public data (default: %(default)s)")
    p.add_argument("--model", default="conti2026", help="the flight model the spin is fitted under (default: %(default)s)")
    p.add_argument("--min-samples", type=int, default=20, help="shortest segment fitted (default: %(default)s)")
    p.add_argument("--fit-fraction", type=float, default=0.6,
                   help="share of a segment's samples the held-out flight error fits on (default: %(default)s)")
    p.add_argument("--max-segments", type=int, default=0, help="at most this many segments per dataset, 0: all")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="output folder (default: %(default)s)")
    args = p.parse_args(argv)
    if not args.real.is_dir():
        print(f"error: {args.real} is not a folder (the public data; --real)", file=sys.stderr)
        return 2

    import jax

    jax.config.update("jax_enable_x64", True)
    from ttsim_jax import load_model
    from ttsim_jax.data.importers import import_source
    from ttsim_jax.fit.bounce_spin import bounce_pairs, fit_bounce_spin
    from ttsim_jax.fit.latent_spin import fit_latent_spin
    from ttsim_jax.fit.spin_check import OPPOSITE_DEG, check_spin

    model = load_model(args.model)
    results, started = {}, time.time()
    cut = (lambda xs: xs[:args.max_segments]) if args.max_segments else (lambda xs: xs)

    # ------------------------------------------------------------------ SpinDOE: spin withheld
    print("SpinDOE: importing, fitting the latent spin ...", file=sys.stderr)
    ds = import_source(args.real / "spindoe", "spindoe")
    ids, times, positions, spins, conf, session = segments(ds, args.min_samples)
    keep = np.flatnonzero(conf >= 0.5)
    keep = cut(keep)
    times = [times[i] for i in keep]
    positions = [positions[i] for i in keep]
    measured = spins[keep]
    t0 = time.time()
    ls = fit_latent_spin(times, positions, model)
    fit_s = time.time() - t0
    along = ls.along
    meas_obs = measured - np.sum(measured * along, 1, keepdims=True) * along
    est = ls.observed
    ang = angle_deg(est, meas_obs)
    mag = np.linalg.norm(est, axis=1) / np.maximum(np.linalg.norm(meas_obs, axis=1), 1e-9) - 1.0
    w = np.linalg.norm(measured, axis=1)
    par = np.abs(np.sum(measured * along, 1))
    n = np.array([len(t) for t in times])
    ok = ls.ok

    def summary(sel):
        sel = sel & ok
        return dict(n=int(sel.sum()), median_angle_deg=float(np.median(ang[sel])) if sel.any() else None,
                    median_abs_magnitude_error=float(np.median(np.abs(mag[sel]))) if sel.any() else None,
                    median_signed_magnitude_error=float(np.median(mag[sel])) if sel.any() else None)

    spin_rows = {"|w| >= 100 rad/s": summary(w >= 100)}
    for lo, hi in ((100, 200), (200, 400), (400, 5000)):
        spin_rows[f"|w| {lo}-{hi}"] = summary((w >= lo) & (w < hi))
    for lo, hi in ((0, 50), (50, 150), (150, 5000)):
        spin_rows[f"|w| >= 100, along-flight part {lo}-{hi}"] = summary((w >= 100) & (par >= lo) & (par < hi))
    for lo, hi in ((20, 40), (40, 80), (80, 400)):
        spin_rows[f"|w| >= 100, {lo}-{hi} samples"] = summary((w >= 100) & (n >= lo) & (n < hi))
    check = check_spin(measured, ls)
    spin_rows["|w| >= 100 rad/s, size not flagged ambiguous"] = summary((w >= 100) & ~ls.ambiguous)
    # the files in recording order, in blocks of BLOCK trajectories: is the sign disagreement spread
    # evenly over the recording, or does it come in batches?
    file_of = dict(zip(np.asarray(ds.sessions["session_id"]).tolist(), [str(x) for x in np.asarray(ds.sessions["name"])]))
    files = np.array([file_of[int(x)] for x in session[keep]])
    order = np.argsort(files, kind="stable")
    blocks = []
    for start in range(0, len(order), BLOCK):
        rows = order[start:start + BLOCK]
        rows = rows[ok[rows]]
        if not len(rows):
            continue
        flipped = ang[rows] > OPPOSITE_DEG
        blocks.append(dict(first=files[rows[0]], last=files[rows[-1]], n=int(len(rows)), opposite=int(flipped.sum()),
                           median_angle_rest_deg=float(np.median(ang[rows][~flipped])) if (~flipped).any() else None,
                           median_spin=float(np.median(w[rows]))))
    results["spindoe"] = dict(segments=int(len(keep)), fitted=int(ok.sum()), fit_seconds=fit_s, rows=spin_rows,
                              by_file_block=blocks, by_file_block_evenness_p=evenness_p(blocks),
                              ambiguous_share=float(ls.ambiguous[ok].mean()), spin_check=check.to_json(),
                              spin_check_summary=check.summary(),
                              per_segment=dict(angle_deg=ang.round(2).tolist(), magnitude_error=mag.round(4).tolist(),
                                               spin=w.round(1).tolist(), along=par.round(1).tolist(), n=n.tolist()))

    # ------------------------------------------------- SpinDOE: across the bounce, spin withheld
    print("SpinDOE: fitting the spin across each bounce ...", file=sys.stderr)
    pairs = bounce_pairs(ds)
    conf_in = np.asarray(ds.segments["spin_conf"])[pairs["in_row"]]
    long_in = np.array([len(t) >= args.min_samples for t in pairs["times_in"]], bool)
    sel = cut(np.flatnonzero((conf_in >= 0.5) & long_in))
    t0 = time.time()
    bs = fit_bounce_spin([pairs["times_in"][i] for i in sel], [pairs["positions_in"][i] for i in sel],
                         [pairs["times_out"][i] for i in sel], [pairs["positions_out"][i] for i in sel],
                         pairs["t_contact"][sel], model)
    bounce_s = time.time() - t0
    measured_in = np.stack([np.asarray(ds.segments[f"spin_{a}"])[pairs["in_row"][sel]] for a in "xyz"], 1)
    u = bs.v0 / np.maximum(np.linalg.norm(bs.v0, axis=1, keepdims=True), 1e-9)
    across = lambda x: x - np.sum(x * u, 1, keepdims=True) * u  # noqa: E731
    w_in = np.linalg.norm(measured_in, axis=1)
    bounce_rows = {}
    for label, est in (("one segment", bs.single), ("across the bounce", bs.spin_in)):
        a = angle_deg(across(est), across(measured_in))
        m = np.linalg.norm(across(est), axis=1) / np.maximum(np.linalg.norm(across(measured_in), axis=1), 1e-9) - 1.0
        full = np.linalg.norm(est, axis=1) / np.maximum(w_in, 1e-9) - 1.0
        rows = {}
        for name, cond in (("|w| >= 100 rad/s", w_in >= 100), ("|w| 100-200", (w_in >= 100) & (w_in < 200)),
                           ("|w| 200-400", (w_in >= 200) & (w_in < 400)), ("|w| >= 400", w_in >= 400),
                           ("|w| >= 100, within 45 degrees", (w_in >= 100) & (a <= 45))):
            c = cond & bs.ok
            rows[name] = dict(n=int(c.sum()), median_angle_deg=float(np.median(a[c])) if c.any() else None,
                              median_abs_magnitude_error=float(np.median(np.abs(m[c]))) if c.any() else None,
                              median_signed_magnitude_error=float(np.median(m[c])) if c.any() else None,
                              median_abs_size_error=float(np.median(np.abs(full[c]))) if c.any() else None)
        bounce_rows[label] = rows
    results["spindoe_bounce"] = dict(pairs=int(len(sel)), fitted=int(bs.ok.sum()), fit_seconds=bounce_s,
                                     median_rmse_mm=float(np.nanmedian(bs.rmse) * 1e3), rows=bounce_rows)

    # ------------------------------------------------------------------ MPI and TT3D: no spin
    for name, folder, source in (("mpi", "mpi_ball_prediction", "mpi"), ("tt3d", "tt3d", "tt3d")):
        print(f"{name}: importing, fitting ...", file=sys.stderr)
        ds = import_source(args.real / folder, source)
        ids, times, positions, _, _, sessions = segments(ds, args.min_samples)
        sel = cut(np.arange(len(ids)))
        times = [times[i] for i in sel]
        positions = [positions[i] for i in sel]
        sessions = sessions[sel]
        ls = fit_latent_spin(times, positions, model)
        top = topspin_component(ls.spin, ls.v0)
        latent = held_out_rmse(model, times, positions, args.fit_fraction, "latent")
        zero = held_out_rmse(model, times, positions, args.fit_fraction, "zero")
        both = np.isfinite(latent) & np.isfinite(zero)
        row = dict(segments=int(len(times)), scored=int(both.sum()),
                   held_out_rmse_mm=dict(latent=float(np.median(latent[both]) * 1e3),
                                         zero=float(np.median(zero[both]) * 1e3)),
                   reduction_pct=float(100 * (1 - np.median(latent[both]) / np.median(zero[both]))))
        if name == "mpi":
            names = {int(s): str(nm) for s, nm in zip(ds.sessions["session_id"], ds.sessions["name"])}
            files = {}
            for s in np.unique(sessions):
                parts = names.get(int(s), "").split("/")  # "mpi/<file>/<launch>"
                f = parts[1] if len(parts) > 1 else parts[0]
                files.setdefault(f, []).extend(top[(sessions == s) & ls.ok].tolist())
            row["topspin_component_by_file"] = {f: dict(n=len(v), median=float(np.median(v)) if v else None)
                                                for f, v in files.items()}
        results[name] = row

    results["seconds"] = time.time() - started
    results["load"] = os.getloadavg()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "latent_spin.json").write_text(json.dumps(results, indent=1))

    print("| SpinDOE, spin withheld | segments | median angle | median magnitude error |\n|---|---|---|---|")
    for k, r in results["spindoe"]["rows"].items():
        if r["n"]:
            print(f"| {k} | {r['n']} | {r['median_angle_deg']:.1f} deg | {100 * r['median_abs_magnitude_error']:.0f} % |")
    print("\nSpinDOE " + results["spindoe"]["spin_check_summary"])
    print(f"\nSpinDOE by file, blocks of {BLOCK} trajectories in file order:\n"
          f"| files | segments | bent opposite to the measured spin (angle > {OPPOSITE_DEG:.0f}°) | median angle of the "
          "others | median spin |\n"
          "|---|---|---|---|---|")
    for b in results["spindoe"]["by_file_block"]:
        rest = "-" if b["median_angle_rest_deg"] is None else f"{b['median_angle_rest_deg']:.1f}°"
        print(f"| {b['first']} - {b['last']} | {b['n']} | {b['opposite']} | {rest} | {b['median_spin']:.0f} rad/s |")
    print(f"(evenly spread over the files: permutation p = {results['spindoe']['by_file_block_evenness_p']:.3f})")
    print("\nSpinDOE across the bounce (" + str(results["spindoe_bounce"]["pairs"]) + " bounces):")
    print("| fit | segments | n | median angle | median magnitude error across the flight (signed) | median size error |")
    print("|---|---|---|---|---|---|")
    for label, rows in results["spindoe_bounce"]["rows"].items():
        for k, r in rows.items():
            if r["n"]:
                print(f"| {label} | {k} | {r['n']} | {r['median_angle_deg']:.1f}° | "
                      f"{100 * r['median_abs_magnitude_error']:.0f} % ({100 * r['median_signed_magnitude_error']:+.0f} %) | "
                      f"{100 * r['median_abs_size_error']:.0f} % |")
    print("\n| data | segments | held-out RMSE, latent spin | spin 0 | less |\n|---|---|---|---|---|")
    for name in ("mpi", "tt3d"):
        r = results[name]
        print(f"| {name} | {r['scored']} | {r['held_out_rmse_mm']['latent']:.1f} mm | {r['held_out_rmse_mm']['zero']:.1f} mm "
              f"| {r['reduction_pct']:.0f} % |")
    print("\nMPI, top/backspin component per file (median, rad/s):",
          {f: r["median"] for f, r in results["mpi"]["topspin_component_by_file"].items()})

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    sp = results["spindoe"]["per_segment"]
    a, m_, wv = np.asarray(sp["angle_deg"]), np.asarray(sp["magnitude_error"]), np.asarray(sp["spin"])
    axes[0].scatter(wv, a, s=6)
    axes[0].set(xscale="log", xlabel="measured |w| [rad/s]", ylabel="angle error [deg]",
                title="SpinDOE: latent vs measured spin (across the flight)")
    axes[1].scatter(wv, 100 * m_, s=6)
    axes[1].axhline(0, color="k", lw=0.5)
    axes[1].set(xscale="log", xlabel="measured |w| [rad/s]", ylabel="magnitude error [%]", ylim=(-100, 200))
    fig.tight_layout()
    fig.savefig(args.out / "latent_spin.png", dpi=110)
    print(f"written to {args.out}: latent_spin.json, latent_spin.png", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
