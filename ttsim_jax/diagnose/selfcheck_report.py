"""The selfcheck's figure and table (:mod:`ttsim_jax.diagnose.selfcheck`): per case, what the
diagnosis found against the oracle, coloured and tabulated by the outcome."""

from __future__ import annotations

import math

import numpy as np

from ttsim_jax.diagnose.outside import OUTSIDE_KINDS


#: Colours of the figure's outcomes (found / right: green; missed or a false alarm: red).
OUTCOME_COLOURS = {"right": "#2ca02c", "wrong": "#d62728", "undetectable": "#7f7f7f"}


def verdict_of(r: dict) -> str:
    """A case's outcome class for the figure: "right", "wrong" or "undetectable"."""
    if r.get("spin_wrong"):  # a wrong cause named, whatever else is right
        return "wrong"
    if r["kind"] == "control":
        return "wrong" if r["false_alarm"] else "right"
    if r["kind"] in OUTSIDE_KINDS:
        return "right" if not r.get("wrong_explained", not r["unexplained"]) and r["phase_right"] else "wrong"
    if not r["detectable"]:
        return "undetectable" if r["unexplained"] else "wrong"
    return "right" if r["rank1"] and r["phase_right"] else "wrong"


def plot(result: dict, path):
    """Per case, the held-out reduction the diagnosis found against the oracle's, in the oracle's
    best phase (bars), coloured by the outcome; written to ``path`` (PNG)."""
    from ttsim_jax.plots import pyplot, save_figure

    plt = pyplot()
    rows = [r for r in result["cases"] if "error" not in r]
    height = 0.38 * max(len(rows), 3) + 1.6
    fig, ax = plt.subplots(figsize=(8.5, height))
    y = np.arange(len(rows))[::-1]
    for k, r in enumerate(rows):
        ax.barh(y[k] + 0.18, r["oracle_pct"], height=0.34, color="#c7c7c7", edgecolor="k", lw=0.5)
        ax.barh(y[k] - 0.18, r["found_pct"], height=0.34, color=OUTCOME_COLOURS[verdict_of(r)])
        label = f"{r['oracle_phase'] or '-'}"
        if r["kind"] in OUTSIDE_KINDS + ("control",):
            label = r["outcome"]
        elif math.isfinite(r["shrink"]):
            label += f", {r['shrink']:.2f} of the oracle"
        elif not r["detectable"]:
            label += ", " + r["outcome"]
        ax.text(max(r["oracle_pct"], r["found_pct"], 0.0) + 0.5, y[k], label, va="center", fontsize=7,
                color=OUTCOME_COLOURS["wrong"] if verdict_of(r) == "wrong" else "k")
    ax.set_yticks(y)
    ax.set_yticklabels([f"{r['kind']}: {' + '.join(r['effects'])}" for r in rows], fontsize=8)
    ax.set_xlabel("held-out RMS error reduction [%]: oracle (grey) and diagnosis (coloured)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in OUTCOME_COLOURS.values()]
    ax.legend(handles, ["found, phase right / unexplained and located", "missed or false alarm",
                        "undetectable, nothing found"], fontsize=7, loc="upper center", ncol=3,
              bbox_to_anchor=(0.4, -0.75 / (height - 1.4)), frameon=False)
    ax.set_xlim(0, 1.6 * float(np.nanmax([r["oracle_pct"] for r in rows] + [r["found_pct"] for r in rows] + [1.0])))
    ax.set_title("withheld-effect selfcheck: what the diagnosis recovers of the oracle's shrink", fontsize=9)
    return save_figure(fig, path)


def limit_cell(r: dict) -> str:
    """The table's cell of a case's detection limit: the smallest held-out reduction these data
    would have shown of its (first) true effect, in the oracle's phase (``-`` where not known)."""
    for name in r.get("effects", []):
        e = r.get("limits", {}).get(name, {}).get(r.get("oracle_phase") or "")
        if e:
            return f"{e['reduction_pct']:.1f}" if e.get("size") is not None else "beyond reach"
    return "-"


def table(result: dict) -> str:
    """The per-case Markdown table of a selfcheck and its summary."""
    lines = ["| case | effects | outcome | top candidate | phase | found [%] | oracle [%] | limit [%] | shrink recovered | "
             "model-free bound [%] (of the oracle's; its strongest term) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["cases"]:
        effects = " + ".join(r["effects"])
        if "error" in r:
            lines.append(f"| {r['kind']} | {effects} | {r['error'][:60]} | | | | | | | |")
            continue
        phase = f"{r['phase']} ({'right' if r['phase_right'] else 'wrong'})" if r["phase"] else "-"
        shrink = f"{r['shrink']:.2f}" if math.isfinite(r["shrink"]) else "-"
        bound = "-"
        if r.get("bound_phase"):
            share = f", {r['bound_share']:.2f}" if math.isfinite(r.get("bound_share", math.nan)) else ""
            term = (r["bound_terms"][0] if r.get("bound_terms") else "no term").replace("|", "\\|")  # |v| in a table cell
            raw = r.get("bound_pct_raw", math.nan)
            below = f" ({raw:.1f} not significant)" if r["bound_pct"] == 0.0 and math.isfinite(raw) and raw >= 0.05 else ""
            if math.isfinite(r.get("bound_share_steady", math.nan)):
                share += f" (of the oracle without its unresolved parts: {r['bound_share_steady']:.2f})"
            bound = (f"{r['bound_phase']} {r['bound_pct']:.1f}{below}{share}; {term} "
                     f"({'right' if r['bound_named'] else 'other'})")
        if r["kind"] == "control":
            effects = "none (the record's noise only)"
            sig = r.get("bound_significant", [])
            bound = "significant in " + ", ".join(sig) if sig else "not significant in any phase"
        oracle = f"{r['oracle_pct']:.1f} ({r['oracle_phase']})" if r.get("oracle_phase") else "-"
        lines.append(f"| {r['kind']} | {effects} | {r['outcome']} | {r['top']} | {phase} | {r['found_pct']:.1f} | "
                     f"{oracle} | {limit_cell(r)} | {shrink} | {bound} |")
    s = result["summary"]
    lines.append(f"\nDetectable single effects: {s['n_single']}, true effect first {s['rank1_rate']:.2f} "
                 f"(of them {s.get('n_interchangeable', 0)} as interchangeable with the first), phase right "
                 f"{s['phase_rate']:.2f}, median shrink recovered {s['median_shrink']:.2f}; undetectable cases "
                 f"{s['n_undetectable']} (nothing found in {s['undetectable_nothing_found']}); pairs {s['n_pairs']}, "
                 f"one true effect first {s['pair_rank1_rate']:.2f}, both {s['pair_both_rate']:.2f}; outside the "
                 f"catalogue: {s.get('n_outside', 0)} cases, 'explained' naming a wrong cause in "
                 f"{s.get('outside_wrong_explained', 0)}; of the {s.get('n_outside_resolved', 0)} the data resolve "
                 f"(oracle significant, or an effect on the record), gap located in a phase the effect acts in "
                 f"{s.get('outside_located_rate', math.nan):.2f}, model-free bound reaching 70 % of the oracle's "
                 f"shrink in {s.get('outside_bound_reaching', 0)} of {s.get('n_outside_bounded', 0)} ("
                 f"{s.get('outside_bound_reaching_resolved', 0)} against the oracle without its unresolved parts; median share "
                 f"{s.get('outside_bound_share_median', math.nan):.2f}), its strongest term naming the effect's "
                 f"variables {s.get('outside_bound_named_rate', math.nan):.2f}; effect-free control: "
                 f"{s.get('n_control', 0)} cases, a false alarm in {s.get('control_false_alarms', 0)}, the model-free "
                 f"bound significant in {', '.join(s.get('control_bound_significant', [])) or 'no phase'}; "
                 f"the record's true spin corrected as if wrong in {s.get('spin_wrong', 0)} cases; "
                 f"{result['seconds']:.0f} s wall, {result['cpu_seconds']:.0f} s CPU"
                 + (f" ({result['resumed']} cases taken from an earlier, interrupted run)" if result.get("resumed") else ""))
    return "\n".join(lines)
