"""The fitted model against the base, stage by stage: what ``ttsim fit`` reports and warns about
(:mod:`ttsim_jax.fit.pipeline`)."""

from __future__ import annotations

import numpy as np


def comparison(on: str, n: int, base: dict, fitted: dict, units: dict) -> dict:
    """One stage's comparison: ``on`` (``"held_out"`` or ``"training"``), ``n`` items, the base's and
    the fitted model's errors by component (``base``, ``fitted``, ``units``) and the components
    where the fitted one is ``worse``."""
    worse = [k for k in base if np.isfinite(base[k]) and np.isfinite(fitted[k]) and fitted[k] > base[k]]
    return dict(on=on, n=int(n), base=base, fitted=fitted, units=units, worse=worse)


def comparison_text(stage: str, c: dict) -> str:
    """One line: where the fitted model of ``stage`` is worse than the base (or that it is not)."""
    where = f"{'held-out' if c['on'] == 'held_out' else 'training'} data, n = {c['n']}"
    if c.get("spin_sources"):
        where += " (spin " + ", ".join(f"{k} {v}" for k, v in c["spin_sources"].items() if v) + ")"
    values = ", ".join(f"{k} {c['base'][k]:.4g} -> {c['fitted'][k]:.4g} {c['units'][k]}" for k in c["base"])
    if not c["worse"]:
        return f"{stage}: the fitted model is no worse than the base on any component ({where}; base -> fitted: " \
               f"{values})"
    return f"warning: {stage}: the fitted model is worse than the base on {', '.join(c['worse'])} " \
           f"({len(c['worse'])} of {len(c['base'])} components; {where}; base -> fitted: {values})"


def flight_comparisons(ds, base_model, fitted_model, sessions, held: bool, settings,
                       parts: dict | None = None) -> dict:
    """{"aero": the base against the fitted model's flight RMSE over the segments of ``sessions``
    (None: every session), and "aero on LABEL" for each of ``parts`` ({label: its sessions}) of
    more than one: the same segments, split by dataset} (empty without segments); ``held``:
    whether those are held out; ``settings``: the :class:`~ttsim_jax.fit.pipeline.FitSettings`
    (its ``min_spin_conf`` and ``spin``)."""
    from ttsim_jax.data.tables import id_index, rows_of
    from ttsim_jax.fit.flight import segment_rmse, spin_source_counts
    from ttsim_jax.results import Skipped

    out = segment_rmse(ds, [("base", base_model), ("fitted", fitted_model)], min_spin_conf=settings.min_spin_conf,
                       sessions=None if sessions is None else tuple(int(s) for s in sessions), spin=settings.spin)
    if isinstance(out, Skipped):
        return {}
    rows = rows_of(id_index(ds.segments["segment_id"]), out.segment_id)
    session = np.asarray(ds.segments["session_id"])[rows]
    groups = {"aero": np.ones(len(session), bool)}
    if parts and len(parts) > 1:  # a pooled fit can serve one dataset at another's cost: each is compared
        groups.update({f"aero on {label}": np.isin(session, list(p)) for label, p in parts.items()})
    source = np.asarray(out.spin_source).astype(str)
    comparisons = {}
    for key, rows in groups.items():
        if not rows.any():
            continue
        stats = {}
        for name in ("base", "fitted"):
            e = np.asarray(out.rmse[name])[rows] * 1e3
            stats[name] = dict(median=float(np.nanmedian(e)), p75=float(np.nanpercentile(e, 75)))
        c = comparison("held_out" if held else "training", int(rows.sum()), stats["base"], stats["fitted"],
                        dict(median="mm", p75="mm"))
        c["spin_sources"] = spin_source_counts(source[rows])
        comparisons[key] = c
    return comparisons
