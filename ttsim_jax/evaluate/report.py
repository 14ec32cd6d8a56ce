"""The summary, report and files of an evaluation (``ttsim evaluate``).

:func:`summarise` turns what :func:`ttsim_jax.evaluate.stages.evaluate_models` computed into the
report's numbers (medians, 75th percentiles, biases, reductions against the reference model with
paired bootstrap intervals); :func:`write_report` writes them (``metrics.json``), every per-item
value (``samples.npz``), the figures (PNG) and ``report.md``.
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np

from ttsim_jax.evaluate import racket_groups
from ttsim_jax.evaluate.result import STAGES, Evaluation
from ttsim_jax.evaluate.stages import LANDING_SKIP_REASONS, TABLE_SKIP_REASONS, counts_text
from ttsim_jax.data.contact_states import SKIP_REASONS
from ttsim_jax.fit.flight import spin_source_counts
from ttsim_jax.files.atomic import atomic_write
from ttsim_jax.fit.network_evaluation import COMPONENTS, DISTANCE_BANDS, ERROR_NAMES, distance_bands
from ttsim_jax.results import Skipped, jsonable


def reduction(ref: float, value: float) -> float:
    """Reduction of ``value`` against ``ref`` in % (positive: smaller than the reference)."""
    return float(100.0 * (ref - value) / ref) if ref and math.isfinite(ref) and math.isfinite(value) else math.nan


BOOTSTRAP = 1000


def reduction_ci(ref_values, values, q: float, n_boot: int = BOOTSTRAP, seed: int = 0) -> list:
    """95 % interval of the reduction [%] of the ``q``-th percentile of ``values`` against that of
    ``ref_values``: a paired bootstrap over the items (those finite in both), ``n_boot`` draws.

    Returns:
        [low, high] (NaN with fewer than two items).
    """
    x, y = np.asarray(ref_values, np.float64), np.asarray(values, np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 2:
        return [math.nan, math.nan]
    rng = np.random.default_rng(seed)
    draws = []
    for lo in range(0, n_boot, 100):  # 100 resamples at a time bounds the memory
        idx = rng.integers(0, len(x), (min(100, n_boot - lo), len(x)))
        a, b = np.percentile(x[idx], q, axis=1), np.percentile(y[idx], q, axis=1)
        draws.append(100.0 * (a - b) / np.where(a > 0, a, np.nan))
    r = np.concatenate(draws)
    r = r[np.isfinite(r)]
    return [float(np.percentile(r, 2.5)), float(np.percentile(r, 97.5))] if len(r) else [math.nan, math.nan]


def _headline(values: dict, names: list, ref: str) -> dict:
    """Per model: :func:`_stats` of its values and the reductions of the median and the 75th
    percentile against the reference, with their bootstrap intervals."""
    per = {n: _stats(values[n]) for n in names}
    for n in names:
        for key, q in (("median", 50), ("p75", 75)):
            per[n][f"reduction_{key}_pct"] = reduction(per[ref][key], per[n][key])
            per[n][f"reduction_{key}_ci95"] = reduction_ci(values[ref], values[n], q)
    return per


def _stats(x) -> dict:
    """n, median, 75th percentile, mean of the finite values of ``x``."""
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    if not len(x):
        return dict(n=0, median=math.nan, p75=math.nan, mean=math.nan)
    return dict(n=int(len(x)), median=float(np.median(x)), p75=float(np.percentile(x, 75)), mean=float(np.mean(x)))


def _not_finite(values: dict, spin=None) -> dict:
    """{model: why} for each model with items that have no finite value (so that its n is smaller
    than the number of items): how many, and the largest spin among them.

    Arguments:
        values: {model: (S,) per-item values}, NaN where the model's simulation failed.
        spin: optional (S, 3) the spins the items were flown with [rad/s].
    """
    out = {}
    for name, v in values.items():
        bad = ~np.isfinite(np.asarray(v, np.float64))
        if not bad.any():
            continue
        text = (f"{int(bad.sum())} of {len(bad)} segments without a finite RMSE: the model's flight gave non-finite "
                "positions (as with spins or speeds far beyond the range its drag and Magnus coefficients cover")
        if spin is not None and len(spin):
            text += f"; the largest spin among them is {float(np.linalg.norm(np.asarray(spin)[bad], axis=-1).max()):.4g} rad/s"
        out[name] = text + ")"
    return out


def _abs_stats(e) -> dict:
    """:func:`_stats` of the signed errors' magnitudes ``|e|``, with their median ``bias``."""
    return dict(_stats(np.abs(e)), bias=_stats(e)["median"])


# ---------------------------------------------------------------------------------------------- summary
def summarise(result: Evaluation) -> dict:
    """The numbers of the report (``metrics.json``, JSON-ready): per stage and model, medians, 75th
    percentiles, means and reductions in % against the reference model; a skipped stage's reason."""
    names, ref = result.models, result.reference
    out = dict(models=names, reference=ref, settings=result.settings)
    for stage, r in result.stages().items():
        out[stage] = r.to_json() if isinstance(r, Skipped) else _SUMMARY[stage](r, names, ref)
    return jsonable(out, finite=True)


def _flight_summary(f, names: list, ref: str) -> dict:
    return dict(n_segments=len(f.segment_id), spin_measured=f.spin_measured, n_without_spin=f.n_without_spin,
                unit="m", models=_headline(f.rmse, names, ref), spin_sources=spin_source_counts(f.spin_source),
                not_finite=_not_finite(f.rmse, f.spin))


def _table_summary(t, names: list, ref: str) -> dict:
    per = {n: {c: _abs_stats(t.error[n][:, k]) for k, c in enumerate(COMPONENTS)} for n in names}
    for n in names:
        for c in COMPONENTS:
            per[n][c]["reduction_median_pct"] = reduction(per[ref][c]["median"], per[n][c]["median"])
    return dict(n_bounces=t.n_bounces, n_used=len(t.event_id), n_with_spin_in=int(np.sum(t.spin_known[:, 0])),
                spin_sources=spin_source_counts(t.spin_source), n_with_spin=int(np.sum(t.spin_known.all(1))),
                skip_counts=t.skip_counts, units=dict(velocity="m/s", spin="rad/s"), models=per)


def _racket_summary(r, names: list, ref: str) -> dict:
    bands = [(label, sel) for label, _, _, sel in distance_bands(r.distance, DISTANCE_BANDS)]
    bands.append(("all", np.ones(len(r.distance), bool)))
    per = {n: {label: dict(n=int(sel.sum()), **{c: _abs_stats(r.error[n][sel, k]) for k, c in enumerate(ERROR_NAMES)})
               for label, sel in bands} for n in names}
    for n in names:
        for label, _ in bands:
            for c in ERROR_NAMES:
                cell = per[n][label][c]
                cell["reduction_median_pct"] = reduction(per[ref][label][c]["median"], cell["median"])
    return dict(n_contacts=r.n_contacts, n_used=len(r.event_id), skip_counts=r.skip_counts,
                frame="racket (x = face normal)", units=dict(velocity="m/s", spin="rad/s"),
                bands=[label for label, _ in bands], models=per, groups=racket_groups.groups(r))


def _landing_summary(g, names: list, ref: str) -> dict:
    per = _headline(g.error, names, ref)
    for n in names:
        per[n].update(not_hit=int(np.sum(~g.hit[n])), no_landing=int(np.sum(g.hit[n] & ~np.isfinite(g.error[n]))))
    return dict(n_contacts=g.n_contacts, n_used=len(g.event_id), skip_counts=g.skip_counts,
                spin_sources=spin_source_counts(g.spin_source), through_bounce=int(np.sum(g.through_bounce)),
                unit="m", models=per)


_SUMMARY = dict(flight=_flight_summary, table=_table_summary, racket=_racket_summary, landing=_landing_summary)


# ---------------------------------------------------------------------------------------------- files
FIGURES = dict(flight="flight_rmse.png", table="table_errors.png", racket="racket_errors.png",
               racket_spin="racket_spin.png",
               landing_hist="landing_hist.png", landing_xy="landing_xy.png")


def _num(v, fmt) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def _cell(stat: dict, velocity: bool) -> str:
    """'median (bias)' of a summary cell, 3 decimals for velocities [m/s], 1 for spins [rad/s]."""
    fmt = ".3f" if velocity else ".1f"
    return f"{_num(stat['median'], fmt)} ({_num(stat['bias'], '+' + fmt)})"


def _reduction(m: dict, key: str) -> str:
    """'26 [18, 33]': a reduction [%] and its bootstrap interval."""
    lo, hi = m[f"reduction_{key}_ci95"]
    return f"{_num(m[f'reduction_{key}_pct'], '.0f')} [{_num(lo, '.0f')}, {_num(hi, '.0f')}]"


def _table_md(head: list, rows: list) -> list:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]


SECTIONS = dict(flight="Flight segments: 3-D position RMSE", table="Table contacts: post-bounce errors",
                racket="Racket contacts: errors by contact distance", landing="Landing position")


def _flight_md(f: dict, names: list, figures: dict) -> list:
    mm = lambda v: _num(None if v is None else 1e3 * v, ".1f")  # noqa: E731
    rows = [[n, str(m["n"]), mm(m["median"]), mm(m["p75"]), _reduction(m, "median"), _reduction(m, "p75")]
            for n, m in f["models"].items()]
    src = f.get("spin_sources") or {}
    if src.get("latent"):
        spin = (f"segments: {src.get('measured', 0)} with their measured spin, {src['latent']} with the latent spin "
                "(fitted per model from the segment's own samples: their errors are in-sample, with three more "
                f"parameters), {src.get('zero', 0)} with spin 0 (too short to fit one)")
    elif f["spin_measured"]:
        spin = f"segments with a measured spin ({f['n_without_spin']} without one left out)"
    else:
        spin = "segments, none with a measured spin: every model flies with spin 0"
    why = [f"n of {n}: {text}." for n, text in (f.get("not_finite") or {}).items()]
    return ([f"{f['n_segments']} {spin}; initial position the first observation, initial velocity fitted per "
             "segment.", ""]
            + _table_md(["model", "n", "median [mm]", "75th pct [mm]", "median reduction [%] [95 % CI]",
                         "75th pct reduction [%] [95 % CI]"], rows)
            + (["", *why] if why else [])
            + ["", f"![flight RMSE]({figures['flight']})", ""])


def _table_contacts_md(t: dict, names: list, figures: dict) -> list:
    head = ["model"] + list(COMPONENTS)
    rows = [[n] + [_cell(per[c], c[0] == "v") for c in COMPONENTS] for n, per in t["models"].items()]
    reductions = [[n] + [_num(per[c]["reduction_median_pct"], ".0f") for c in COMPONENTS]
                  for n, per in t["models"].items()]
    return ([f"{t['n_used']} of {t['n_bounces']} bounces used; pre-bounce spin: {_sources_text(t['spin_sources'])}; "
             "spin errors for the "
             f"{t['n_with_spin']} with measured spins on both sides. Skipped: "
             f"{counts_text(t['skip_counts'], TABLE_SKIP_REASONS)}.",
             "Median |error| (bias: median signed error), velocity in m/s, spin in rad/s; world frame.", ""]
            + _table_md(head, rows) + ["", "Reduction of the median |error| [%]:", ""] + _table_md(head, reductions)
            + ["", f"![table contact errors]({figures['table']})", ""])


def _racket_md(r: dict, names: list, figures: dict) -> list:
    count = {b: r["models"][names[0]][b]["n"] for b in r["bands"]}
    head = ["model"] + [f"{b} (n={count[b]}{'' if count[b] else ': no contact at this distance'})" for b in r["bands"]]
    rows = [[f"{n} {q}"] + [_cell(per[b][q], q == "|v|") for b in r["bands"]]
            for q in ("|v|", "|w|") for n, per in r["models"].items()]
    components = [[n] + [_num(per["all"][c]["median"], ".3f" if c[0] == "v" else ".1f") for c in COMPONENTS]
                  for n, per in r["models"].items()]
    return ([f"{r['n_used']} of {r['n_contacts']} racket contacts used (usable for every model). Skipped: "
             f"{counts_text(r['skip_counts'], SKIP_REASONS)}.",
             "Median |error| of the speed |v| [m/s] and spin magnitude |w| [rad/s] after the contact (bias in "
             "brackets), per band of contact distance from the face centre; racket frame.", ""]
            + _table_md(head, rows) + ["", "All bands, median |error| per component (racket frame):", ""]
            + _table_md(["model"] + list(COMPONENTS), components)
            + ["", f"![racket contact errors]({figures['racket']})", ""]
            + racket_groups.markdown(r.get("groups", {}), names)
            + [f"![predicted against measured outgoing spin]({figures['racket_spin']})", ""])


def _sources_text(counts: dict) -> str:
    """'12 measured, 30 latent (the incoming segment's, fitted under each model), 1 spin 0'."""
    words = dict(measured="measured", latent="latent (the incoming segment's, fitted under each model)", zero="spin 0")
    return ", ".join(f"{counts.get(k, 0)} {w}" for k, w in words.items() if counts.get(k, 0)) or "none"


def _landing_md(g: dict, names: list, figures: dict) -> list:
    rows = [[n, str(m["n"]), _num(m["median"], ".3f"), _num(m["p75"], ".3f"), _reduction(m, "median"),
             _reduction(m, "p75"), str(m["not_hit"]), str(m["no_landing"])] for n, m in g["models"].items()]
    bounce = (f" ({g['through_bounce']} of the latent spins fitted across the bounce before the contact, both "
              "segments as one flight)") if g.get("through_bounce") else ""
    return ([f"{g['n_used']} of {g['n_contacts']} racket contacts used; incoming spin: "
             f"{_sources_text(g['spin_sources'])}{bounce}. Skipped: "
             f"{counts_text(g['skip_counts'], LANDING_SKIP_REASONS)}. Simulated from the last observation before the "
             "contact with the measured racket state until the table plane.", ""]
            + _table_md(["model", "n", "median [m]", "75th pct [m]", "median reduction [%] [95 % CI]",
                         "75th pct reduction [%] [95 % CI]", "racket missed", "no landing"], rows)
            + ["", f"![landing error histogram]({figures['landing_hist']})",
               f"![landing points]({figures['landing_xy']})", ""])


def markdown(summary: dict, figures: dict, data: str = "") -> str:
    """The report: one section per stage, tables of the summary's numbers and links to the figures
    (a skipped stage: its reason)."""
    names, ref = summary["models"], summary["reference"]
    lines = [f"# Model evaluation{f' on {data}' if data else ''}", "",
             f"Models: {', '.join(names)}. Reductions are relative to **{ref}** (positive: smaller error); "
             f"95 % intervals from a paired bootstrap over the items ({BOOTSTRAP} draws).", ""]
    body = dict(flight=_flight_md, table=_table_contacts_md, racket=_racket_md, landing=_landing_md)
    for stage in STAGES:
        if stage not in summary:
            continue
        part = summary[stage]
        lines += [f"## {SECTIONS[stage]}", ""]
        lines += [f"Skipped: {part['skipped']}.", ""] if "skipped" in part else body[stage](part, names, figures)
    lines += ["Every number: `metrics.json`; per-item values: `samples.npz`.", ""]
    return "\n".join(lines)


def write_report(result: Evaluation, out_dir, data: str = "") -> dict:
    """Writes ``report.md``, ``metrics.json``, ``samples.npz`` and the figures to ``out_dir``.

    Arguments:
        result: the :class:`~ttsim_jax.evaluate.result.Evaluation` of
            :func:`ttsim_jax.evaluate.stages.evaluate_models`.
        out_dir: output directory (created).
        data: the dataset's name or path, for the report's title.

    Returns:
        {what: path} of the files written.
    """
    from ttsim_jax import plots

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = result.models
    summary = summarise(result)
    ran = result.ran()
    paths = {}
    if "flight" in ran:
        paths["flight"] = plots.plot_violins({"": {n: 1e3 * ran["flight"].rmse[n] for n in names}},
                                             out / FIGURES["flight"], ylabel="3-D position RMSE [mm]",
                                             title="flight segments: position RMSE per model")
    if "table" in ran:
        e = ran["table"].error
        paths["table"] = plots.plot_violins({c: {n: e[n][:, k] for n in names} for k, c in enumerate(COMPONENTS)},
                                            out / FIGURES["table"], ylabel="predicted - measured (m/s | rad/s)",
                                            title="table contact: post-bounce errors per component",
                                            panels=(COMPONENTS[:3], COMPONENTS[3:]))
    if "racket" in ran:
        r = ran["racket"]
        bands = distance_bands(r.distance, DISTANCE_BANDS)
        groups = {}
        for k, q in ((6, "|v| [m/s]"), (7, "|w| [rad/s]")):
            for label, _, _, sel in bands:
                groups[f"{q} {label}"] = {n: r.error[n][sel, k] for n in names}
        keys = list(groups)
        paths["racket"] = plots.plot_violins(groups, out / FIGURES["racket"], ylabel="magnitude error (predicted - measured)",
                                             title="racket contact: speed and spin magnitude errors by contact distance",
                                             panels=(keys[:len(bands)], keys[len(bands):]))
        k = 3 + racket_groups.spin_component(r.y_obs)
        by = np.asarray(r.rubber_type if any(np.asarray(r.config) != "") else np.full(len(r.y_obs), "all"), object)
        panels = {str(g): (r.y_obs[by == g, k], {n: r.predicted[n][by == g, k] for n in names})
                  for g in dict.fromkeys(by.tolist())}
        axis = "xyz"[k - 3]
        paths["racket_spin"] = plots.plot_predicted_vs_measured(
            panels, out / FIGURES["racket_spin"], xlabel=f"measured outgoing spin w~_{axis} [rad/s]",
            ylabel=f"predicted w~_{axis} [rad/s]", title="racket contact: outgoing spin, predicted against measured"
            + (" per rubber type" if len(panels) > 1 or "all" not in panels else ""))
    if "landing" in ran:
        g = ran["landing"]
        paths["landing_hist"], paths["landing_xy"] = plots.plot_landing(
            g.error, g.landing, g.measured, out / FIGURES["landing_hist"], out / FIGURES["landing_xy"])
    atomic_write(out / "metrics.json", (json.dumps(summary, indent=1, allow_nan=False) + "\n").encode(), "the metrics")
    paths["metrics"] = out / "metrics.json"
    buf = io.BytesIO()
    np.savez_compressed(buf, **{f"{stage}/{k}": v for stage, r in ran.items() for k, v in r.arrays().items()})
    atomic_write(out / "samples.npz", buf.getvalue(), "the samples")
    paths["samples"] = out / "samples.npz"
    atomic_write(out / "report.md", markdown(summary, FIGURES, data).encode(), "the report")
    paths["report"] = out / "report.md"
    return paths
