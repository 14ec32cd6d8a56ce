"""The files of a diagnosis: ``report.md``, ``diagnosis.json`` and PNG figures.

Figures (:data:`FIGURES`): the gap by phase and regime (mean error per regime bin with its 95 %
interval, flagged bins in red, the phase's mean as a line), the ranked candidates' held-out
reductions with their intervals, and the held-out error distributions before / after the
significant effects.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ttsim_jax.results import jsonable
from ttsim_jax.diagnose.phases import REGIMES
from ttsim_jax.diagnose.result import Diagnosis
from ttsim_jax.diagnose.spin_record import text as correction_text
from ttsim_jax.diagnose.where import FLAG_RATIO, SHOWN, UNITS
from ttsim_jax.files.atomic import atomic_write

FIGURES = {"where": "gap_by_regime.png", "effects": "effects.png", "before_after": "before_after.png"}


def _show(phase):
    return SHOWN[UNITS[phase]]


def params_text(params: dict, name: str = "", limit: int = 200) -> str:
    """A candidate's fitted parameters as the report's table shows them: ``key = value`` with
    three significant digits, the effect's own name left off the keys, parameters fitted to zero
    everywhere (unused gust terms) left out, and at most about ``limit`` characters (then a count
    of the rest; every value is in diagnosis.json)."""
    items = []

    def walk(key, value):
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{key}.{k}" if key else str(k), v)
            return
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            items.append(f"{key} = {value}")
            return
        if a.size and not np.any(a):
            return
        text = (f"{a.item():.3g}" if a.ndim == 0 else
                np.array2string(a, separator=", ", max_line_width=10**6, formatter={"float_kind": lambda x: f"{x:.3g}"}))
        parts = key.split(".")
        sessions = [k for k in parts if k.isdigit()]  # per-session fits are keyed by the session's index
        label = ".".join(k for k in parts if not k.isdigit()) + (f" (session {', '.join(sessions)})" if sessions else "")
        items.append(f"{label} = {text.replace(chr(10), '')}")

    walk("", jsonable(params.get(name, params) if set(params) == {name} else params))
    shown_items, length = [], 0
    for item in items:
        if shown_items and length + len(item) > limit:
            return "; ".join(shown_items) + f"; {len(items) - len(shown_items)} more in diagnosis.json"
        shown_items.append(item)
        length += len(item) + 2
    return "; ".join(shown_items) or "none"


def plot_where(where: dict, path, columns: int = 4) -> Path:
    """Mean error per regime bin and phase: for each phase, its regimes in rows of ``columns``
    panels (a grid wide enough for every regime was unreadable at any page width)."""
    from matplotlib.patches import Patch

    from ttsim_jax.plots import pyplot, save_figure

    plt = pyplot()
    panels = [(p, r) for p in where for r in REGIMES if where[p]["regimes"].get(r)]
    rows_of = {p: -(-sum(1 for q, _ in panels if q == p) // columns) for p in where}
    n_rows = max(1, sum(rows_of.values()))
    fig, axes = plt.subplots(n_rows, columns, figsize=(3.6 * columns, 2.9 * n_rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    row = 0
    for p in where:
        unit, f = _show(p)
        mine = [r for q, r in panels if q == p]
        for k, r in enumerate(mine):
            ax = axes[row + k // columns, k % columns]
            ax.axis("on")
            rows = where[p]["regimes"][r]
            m = np.array([b["mean"] for b in rows]) * f
            lo = np.array([b["ci95"][0] for b in rows]) * f
            hi = np.array([b["ci95"][1] for b in rows]) * f
            colours = ["#d62728" if b["flag"] else "#1f77b4" for b in rows]
            x = np.arange(len(rows))
            ax.bar(x, m, color=colours, alpha=0.8)
            ax.errorbar(x, m, yerr=[np.maximum(m - lo, 0), np.maximum(hi - m, 0)], fmt="none", ecolor="k", lw=1)
            ax.axhline(where[p]["mean"] * f, color="grey", ls="--", lw=1)
            ax.set_xticks(x)
            ax.set_xticklabels([b["label"] for b in rows], rotation=30, ha="right", fontsize=8)
            ax.tick_params(axis="y", labelsize=8)
            ax.set_title(f"{p}: {REGIMES[r][0]}", fontsize=9)
            if k % columns == 0:
                ax.set_ylabel(f"mean error [{unit}]", fontsize=8)
        row += rows_of[p]
    if panels:
        axes[0, 0].legend(handles=[Patch(color="#1f77b4", alpha=0.8, label="bin (95 % interval)"),
                                   Patch(color="#d62728", alpha=0.8, label="flagged (vs mean or floor)"),
                                   plt.Line2D([], [], color="grey", ls="--", label="phase mean")],
                          loc="upper left", fontsize=7, framealpha=0.8)
    # fixed spacing for any number of rows (tight_layout would draw the whole grid once more to
    # measure it): margins in inches, and half a panel's height between rows for the rotated bin
    # labels and the next row's titles
    height = fig.get_figheight()
    fig.subplots_adjust(left=0.05, right=0.99, wspace=0.3, top=1.0 - 0.35 / height, bottom=0.75 / height, hspace=0.5)
    return save_figure(fig, path, tight=False)


def plot_effects(candidates: list, path) -> Path:
    """Held-out RMS reduction [%] of each candidate and phase with its 95 % interval."""
    from ttsim_jax.plots import pyplot, save_figure

    plt = pyplot()
    rows = [(c["name"], p, c["heldout"][p]) for c in candidates for p in c["phases"]]
    fig, ax = plt.subplots(figsize=(7, 0.35 * max(len(rows), 3) + 1))
    colours = {"flight": "#1f77b4", "table": "#2ca02c", "racket": "#ff7f0e"}
    y = np.arange(len(rows))[::-1]
    for k, (name, p, h) in enumerate(rows):
        lo, hi = h["ci95"]
        ax.barh(y[k], h["pct"], color=colours.get(p, "grey"), alpha=0.8)
        if math.isfinite(lo) and math.isfinite(hi):
            ax.errorbar(h["pct"], y[k], xerr=[[max(h["pct"] - lo, 0)], [max(hi - h["pct"], 0)]], fmt="none", ecolor="k")
    ax.set_yticks(y)
    ax.set_yticklabels([f"{n} ({p})" for n, p, _ in rows], fontsize=8)
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xlabel("held-out RMS error reduction [%] (95 % interval)")
    ax.set_title("candidate effects, ranked")
    from matplotlib.patches import Patch

    shown = dict.fromkeys(p for _, p, _ in rows)  # the phases the bars are of, in their order
    ax.legend(handles=[Patch(color=colours.get(p, "grey"), alpha=0.8, label=f"{p} error") for p in shown],
              title="phase", fontsize=8, title_fontsize=8, loc="lower right")
    return save_figure(fig, path)


def plot_before_after(arrays: dict, path) -> Path:
    """Histograms of the held-out errors per phase, before and after."""
    from ttsim_jax.plots import pyplot, save_figure

    plt = pyplot()
    phases = [k[len("before_"):] for k in arrays if k.startswith("before_")]
    fig, axes = plt.subplots(1, max(1, len(phases)), figsize=(3.4 * max(1, len(phases)), 3), squeeze=False)
    for ax, p in zip(axes[0], phases):
        unit, f = _show(p)
        b = np.asarray(arrays[f"before_{p}"]) * f
        a = arrays.get(f"after_{p}")
        top = np.percentile(b, 99) if len(b) else 1.0
        edges = np.linspace(0, top if top > 0 else 1.0, 40)
        ax.hist(np.clip(b, 0, edges[-1]), edges, alpha=0.5, label="model")
        if a is not None:
            ax.hist(np.clip(np.asarray(a) * f, 0, edges[-1]), edges, alpha=0.5, label="with the effects")
        ax.set_xlabel(f"{p} error [{unit}]")
        ax.legend(fontsize=7)
    return save_figure(fig, path)


def _pm(v, ci, f=1.0, fmt="{:.3g}") -> str:
    if not math.isfinite(v):
        return "-"
    return f"{fmt.format(v * f)} [{fmt.format(ci[0] * f)}, {fmt.format(ci[1] * f)}]"


def _significance(c: dict) -> str:
    """'yes', 'no', or for a candidate tried on top of accepted ones what it adds there."""
    if not c["significant"]:
        return "no"
    adds = c.get("adds")
    if not adds:
        return "yes"
    p = max(adds["heldout"], key=lambda k: adds["heldout"][k]["pct"])
    h = adds["heldout"][p]
    word = "yes" if adds["accepted"] else "alone only"
    return f"{word}; on top of {'+'.join(adds['on_top_of'])}: {p} {_pm(h['pct'], h['ci95'], 1.0, '{:.1f}')} %"


def floor_lines(floor: dict) -> list:
    """Markdown lines of the noise floor per phase (:mod:`ttsim_jax.diagnose.floor`): the model's RMS
    error on all items, the floor a perfect model would reach on this record, and the removable gap
    sqrt(error^2 - floor^2), each with its 95 % interval; a phase without a floor gets its reason.

    Arguments:
        floor: the diagnosis' ``floor`` ({phase: dict or reason}).

    Returns:
        list of lines (empty without a floor).
    """
    if not floor:
        return []
    lines = ["", "Noise floor: the RMS error a perfect model would reach on this record (from the position noise "
             "of the record itself), and the removable gap sqrt(error^2 - floor^2) above it (95 % intervals).", "",
             "| phase | items | RMS error | floor | removable | position noise x/y/z |", "|---|---|---|---|---|---|"]
    notes = []
    for p, f in floor.items():
        if isinstance(f, str):
            lines.append(f"| {p} | - | - | - | - | - |")
            notes.append(f"- {p}: no floor: {f}")
            continue
        unit, k = _show(p)
        s = " / ".join(f"{v * 1e3:.2f}" for v in f["sigma_m"])
        lines.append(f"| {p} | {f['n']} | {_pm(f['error'], f['error_ci95'], k)} {unit} | "
                     f"{_pm(f['floor'], f['floor_ci95'], k)} {unit} | {_pm(f['removable'], f['removable_ci95'], k)} "
                     f"{unit} | {s} mm |")
        if isinstance(f.get("spin_noise"), str) and not any(n.startswith("- spin noise") for n in notes):
            notes.append(f"- spin noise not in the contacts' floor: {f['spin_noise']}")
    return lines + ([""] + notes if notes else [])


def bound_lines(bound: dict) -> list:
    """Markdown lines of the model-free correction per phase (:mod:`ttsim_jax.diagnose.bound`): how
    far a flexible map of the named variables lowers the held-out error, and its strongest terms."""
    if not bound:
        return []
    lines = ["", "How far any correction gets: a model-free map from named physical variables to the errors, fitted "
             "and scored as the candidates are:", ""]
    for p, b in bound.items():
        lines.append(f"- {b['text']}" if "text" in b else f"- {p}: no bound: {b.get('reason', 'no data')}")
    return lines


def limit_lines(limits: dict) -> list:
    """Markdown lines of the detection limits (:mod:`ttsim_jax.diagnose.limits`): per candidate and
    phase, the smallest effect these data would have shown as significant."""
    if not limits.get("candidates"):
        return []
    from ttsim_jax.diagnose.limits import MAX_SIZE, describe

    lines = ["", "Detection limits: the smallest effect of each candidate that these data would have shown as "
             "significant (injected into the model's predictions with the record's own residuals as its noise, "
             "either sign), in the candidate's parameters, as the RMS change of the phase's errors over their RMS, "
             "and as the held-out reduction it would make.", "",
             "| effect | phase | smallest effect shown | share of the error [%] | held-out reduction [%] |",
             "|---|---|---|---|---|"]
    for name, per in limits["candidates"].items():
        for p, e in per.items():
            if e["size"] is None:
                lines.append(f"| {name} | {p} | not within {MAX_SIZE:g} x its typical size | - | - |")
                continue
            lines.append(f"| {name} | {p} | {describe(name, e).split(': ', 1)[1]} | {e['share_pct']:.1f} | "
                         f"{e['reduction_pct']:.1f} |")
    return lines


def markdown(out: Diagnosis | dict, data: str = "", model: str = "") -> str:
    """The report's Markdown, from a :class:`~ttsim_jax.diagnose.result.Diagnosis` or its JSON (a
    stored ``diagnosis.json``)."""
    out = out.to_json() if isinstance(out, Diagnosis) else out
    v = out["verdict"]
    lines = [f"# Sim-to-real gap diagnosis{f' of {model}' if model else ''}{f' on {data}' if data else ''}", "",
             f"**Verdict.** {v['text']}", ""]
    lines += ["## Where", "", "Mean error per phase, 95 % group-bootstrap interval "
              f"(flagged: the interval's lower end above {FLAG_RATIO} x the phase's mean).", "",
              "| phase | items | groups | mean error | flagged regimes |", "|---|---|---|---|---|"]
    for p, w in out["where"].items():
        unit, f = _show(p)
        flagged = ", ".join(f"{r} {label}" for r, label in w["flagged"]) or "none"
        lines.append(f"| {p} | {w['n']} | {w['groups']} | {_pm(w['mean'], w['ci95'], f)} {unit} | {flagged} |")
    no_data = out.get("no_data", {})
    for p in no_data:
        lines.append(f"| {p} | 0 | 0 | no data | - |")
    lines.append("")
    lines += [f"- {p}: no data: {why}" for p, why in no_data.items()]
    lines += [f"- {p}: {why}" for p, why in out["skipped"].items() if p not in no_data]
    lines += [f"- {p}: {n} left out: {why}" for p, reasons in out.get("left_out", {}).items() for why, n in reasons.items()]
    src = out.get("spin_sources") or {}
    if src.get("latent") or src.get("zero"):
        lines.append("- flight segments' spin: " + ", ".join(f"{k} {n}" for k, n in src.items() if n)
                     + " (latent: fitted from the segment's own samples under the diagnosed model, where the record "
                     "has no confident spin; it takes up any force across the flight, so an unmodelled lift or "
                     "side force on those segments is read as spin, not as a gap)")
    if out.get("pooled_sessions"):
        lines.append("- per-session effects (air_flow, ball_variation, worn_ball) fitted with one parameter set for "
                     "all sessions: the median session holds too few segments and contacts to fit its own")
    lines += floor_lines(out.get("floor", {}))
    lines += ["", f"![gap by phase and regime]({FIGURES['where']})", "", "Residual dependences (Spearman, over segments / "
              "contacts; |rho| >= 0.3, p < 0.001):", ""]
    deps = [(p, d) for p, ds in out["dependence"].items() for d in ds]
    lines += [f"- {p}: {d['error']} on {d['quantity']}: rho {d['rho']:+.2f}" for p, d in deps[:12]] or ["- none"]
    lines += ["", "## Which effect", "", "Each candidate fitted on the training split, scored on the held-out split "
              "(reduction of the RMS error: flight, of the 3-D position error; contacts, of the norm of (velocity error, "
              "radius x spin error); 95 % paired bootstrap interval).", "",
              "| rank | effect | phase | held-out reduction [%] | significant | fitted parameters |", "|---|---|---|---|---|---|"]
    for c in out["candidates"]:
        params = params_text(c["params"], c["name"])
        for p in c["phases"]:
            h = c["heldout"][p]
            lines.append(f"| {c['rank']} | {c['name']} | {p} | {_pm(h['pct'], h['ci95'], 1.0, '{:.1f}')} | "
                         f"{_significance(c)} | `{params}` |")
    lines += limit_lines(out.get("limits", {}))
    lines += ["", f"![ranked effects]({FIGURES['effects']})", "", "Effects on the record (sizes, not physics):", ""]
    rec = out["record"]
    if "position_noise" in rec:
        s = rec["position_noise"]["sigma"]
        lines.append(f"- position_noise: sigma x/y/z = {s[0] * 1e3:.2f} / {s[1] * 1e3:.2f} / {s[2] * 1e3:.2f} mm")
    if "missing_frames" in rec:
        lines.append(f"- missing_frames: {100 * rec['missing_frames']['fraction']:.1f} % of frames inside segments")
    sn = rec.get("spin_noise", {})
    if sn:
        lines.append(f"- spin_noise: {100 * sn['low_confidence_fraction']:.0f} % of segments with spin confidence below 0.5 "
                     f"(median {sn['median_confidence']:.2f})")
    sc = rec.get("spin_check", {})
    if sc:
        lines.append(f"- spin_check: {sc['skipped']}" if "skipped" in sc else f"- spin_check: {sc['summary']}")
    corr = out.get("spin_correction", {})
    if corr and "skipped" not in corr:
        lines.append("- spin correction:" + correction_text(corr))
    rs = rec.get("racket_state_error", {})
    if rs.get("n"):
        b = rs["vel_bias"]
        lines.append(f"- racket_state_error: a racket velocity bias of ({b[0]:+.2f}, {b[1]:+.2f}, {b[2]:+.2f}) m/s "
                     f"(spread {np.linalg.norm(rs['vel_spread']):.2f} m/s) would explain the racket-contact velocity "
                     f"residuals: RMS {rs['rms_before']:.3f} -> {rs['rms_after']:.3f} m/s over {rs['n']} contacts")
    lines += ["", "## How far it shrinks", ""]
    if out.get("combined"):
        c = out["combined"]
        lines.append(f"With {c['name']} (held-out):")
        lines.append("")
        lines += ["| phase | RMS before | RMS after | reduction [%] |", "|---|---|---|---|"]
        for p, h in c["heldout"].items():
            unit, f = _show(p)
            lines.append(f"| {p} | {h['before_rms'] * f:.3g} {unit} | {h['after_rms'] * f:.3g} {unit} | "
                         f"{_pm(h['pct'], h['ci95'], 1.0, '{:.1f}')} |")
        for p, ba in out["before_after"].items():
            unit, f = _show(p)
            lines += ["", f"{p}, mean error by regime before -> after [{unit}]:", ""]
            for r, rows in ba["regimes"].items():
                cells = ", ".join(f"{b['label']}: {b['before'] * f:.3g} -> {b['after'] * f:.3g}" for b in rows)
                lines.append(f"- {r}: {cells}")
    else:
        lines.append("No candidate is significant: nothing to add to the model.")
    shares = out["verdict"].get("shares", {})
    if shares:
        lines += ["", "Share of each phase's removable gap (error above the noise floor, in the mean square) that the "
                  "accepted effects close on held-out data (explained: 70 % or more in every phase they act in):", ""]
        for p, g in shares.items():
            lines.append(f"- {p}: " + ("no gap above the floor beyond the phase's resolution" if g["share"] is None else
                                       f"{100 * g['share']:.0f} % (95 % interval {100 * g['ci95'][0]:.0f} to "
                                       f"{100 * g['ci95'][1]:.0f} %)"))
    lines += bound_lines(out.get("bound", {}))
    for g in out.get("indistinguishable", []):
        lines.append(f"- indistinguishable on these data (cosine {g['cosine']:.2f}): {', '.join(g['names'])}; "
                     f"{g['separate']} would tell them apart")
    for name, found in out.get("reads_as", {}).items():
        for r in found:
            lines.append(f"- {name} reads on these data as {r['text']} (cosine {r['cosine']:.2f}); {r['separate']} "
                         "would tell them apart")
    lines += ["", f"![held-out errors before and after]({FIGURES['before_after']})"]
    if out.get("landing"):
        g = out["landing"]
        lines += ["", f"Landing error (rollouts, {g['n']} contacts): median {g['before_median']:.3f} m"
                  + (f" -> {g['after_median']:.3f} m with the effects (median {g['reduction_median_pct']:+.0f} % lower)"
                     if "after_median" in g else "")]
    spent = sorted((out.get("timings") or {}).items(), key=lambda kv: -kv[1])[:4]
    where_time = " (" + ", ".join(f"{k} {v:.0f} s" for k, v in spent) + ")" if spent else ""
    lines += ["", f"Run time {out['seconds']:.0f} s{where_time}. Every number is in diagnosis.json.", ""]
    return "\n".join(lines)


def write_report(out: Diagnosis, out_dir, data: str = "", model: str = "") -> dict:
    """Writes ``report.md``, ``diagnosis.json`` (``out.to_json()``) and the figures to ``out_dir``;
    returns {name: path}."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    paths = {"where": plot_where(out.where, d / FIGURES["where"]),
             "effects": plot_effects(out.candidates, d / FIGURES["effects"]),
             "before_after": plot_before_after(out.arrays, d / FIGURES["before_after"])}
    body = out.to_json()
    js = d / "diagnosis.json"
    atomic_write(js, json.dumps(body, indent=1).encode(), "the diagnosis")
    md = d / "report.md"
    atomic_write(md, markdown(body, data, model).encode(), "the report")
    return dict(paths, json=js, report=md)
