"""Reports of a sensitivity study: ranked tables, heatmaps, error-budget bars and a JSON of every number.

Sensitivities are made comparable across inputs of different units by scaling each column by a
typical change (:func:`column_scales`): for state inputs a typical measurement error (the budget's
racket deviations, spin noise; :data:`STATE_SCALES` for the others), for model parameters 1 % of the
parameter's value. A group's sensitivity for a shot is then the Frobenius norm of its scaled
Jacobian columns: the change of the target [its unit] that a typical change of every input of the
group, along the gradient, causes; for isotropic state errors it is the standard deviation they
cause.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ttsim_jax.plots import save_figure
from ttsim_jax.sensitivity import budgets
from ttsim_jax.sensitivity.jacobians import STATE_GROUPS, Jacobian

# Typical per-axis errors of the state inputs (the racket's: the budget's defaults per axis).
STATE_SCALES = {
    "ball.pos": 0.002, "ball.vel": 0.05, "ball.spin": budgets.SPIN_ABS_STD,
    "racket.pos": budgets.RACKET_POS_STD / math.sqrt(3), "racket.rot": math.radians(budgets.RACKET_ROT_STD_DEG) / math.sqrt(3),
    "racket.vel": budgets.RACKET_VEL_STD / math.sqrt(3), "racket.ang_vel": 1.0,
}
PARAM_STEP = 0.01  # relative change of a model parameter


def column_scales(jac: Jacobian) -> np.ndarray:
    """(C,) the typical change of each input (see the module docstring); a parameter whose value is
    0 takes 1 % of a tenth of the RMS of its group's nonzero values (1e-6 if they are all 0)."""
    nominal = np.abs(jac.nominal[0])
    scale = np.zeros(len(jac.columns))
    for g in dict.fromkeys(jac.groups):
        mask = jac.groups == g
        if g in STATE_SCALES:
            scale[mask] = STATE_SCALES[g]
            continue
        vals = nominal[mask]
        nonzero = vals[vals > 0]
        floor = 0.1 * float(np.sqrt(np.mean(nonzero**2))) if len(nonzero) else 1e-4
        scale[mask] = PARAM_STEP * np.where(vals > 0, vals, floor)
    return scale


def group_sensitivity(jac: Jacobian, scale: np.ndarray) -> dict:
    """group -> (B,) norm of the scaled Jacobian columns of that group (all target components)."""
    scaled = jac.jac * scale[None, None]
    return {g: np.sqrt(np.sum(scaled[:, :, jac.groups == g] ** 2, (1, 2))) for g in dict.fromkeys(jac.groups)}


def regimes(speed, spin, contact) -> dict:
    """Regime labels of each shot: speed terciles, spin class, contact position on the face."""
    speed = np.asarray(speed)
    lo, hi = np.quantile(speed, [1 / 3, 2 / 3]) if len(speed) else (0.0, 0.0)
    sp = np.where(speed <= lo, f"speed <= {lo:.1f} m/s", np.where(speed <= hi, f"speed {lo:.1f}-{hi:.1f} m/s",
                                                                  f"speed > {hi:.1f} m/s"))
    spin = np.asarray(spin)
    sc = np.where(spin < -100, "backspin (< -100 rad/s)", np.where(spin > 100, "topspin (> 100 rad/s)", "flat"))
    d = np.linalg.norm(np.asarray(contact), axis=-1)
    cp = np.where(d < 0.015, "contact within 15 mm of centre", "contact off centre")
    return {"speed": sp, "spin": sc, "contact": cp}


def usable(jac: Jacobian, flags: dict, groups=None) -> np.ndarray:
    """(B,) the shots whose gradients with respect to ``groups`` (default: every group) hold beyond
    the point: landed, and no probe of those groups flipped the event sequence or found central
    differences at two steps disagreeing.

    A flag is per group because a shot's Jacobian can be exact and smooth in its racket state while
    a table's breakpoints make the landing curve sharply within a 0.1 % change of them: that shot's
    racket-state sensitivities and error budget still hold.
    """
    if groups is None:
        return jac.valid & ~flags["flag"]
    ok = jac.valid.copy()
    for g in groups:
        if g in flags["groups"]:
            ok &= ~flags["groups"][g]
    return ok


def _table(rows: dict, columns: dict, ok: dict, unit: str, factor: float) -> str:
    """Markdown table: one row per group (ranked by the first column), median of each column over
    the column's shots whose gradient for that group holds (``ok[group]``)."""
    names = list(columns)
    head = "| group | " + " | ".join(f"{n} (n={int(columns[n].sum())})" for n in names) + " |"
    lines = [head, "|" + "---|" * (len(names) + 1)]
    anywhere = np.any(list(columns.values()), 0)
    overall = {g: np.median(v[anywhere & ok[g]]) if (anywhere & ok[g]).any() else 0.0 for g, v in rows.items()}
    for g in sorted(rows, key=lambda g: -np.nan_to_num(overall[g])):
        cells = [f"{factor * np.median(rows[g][m & ok[g]]):.3g}" if (m & ok[g]).any() else "-" for m in columns.values()]
        lines.append(f"| {g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + (f"\n\n(median over the landed shots whose gradient for the group holds beyond "
                                f"the point, {unit})\n")


def summarise(jac: Jacobian, shots, flags: dict, budget: budgets.Budget | None, scale: np.ndarray) -> dict:
    """Everything a report shows, as plain numbers (JSON-ready) and markdown tables."""
    sens = group_sensitivity(jac, scale)
    ok = usable(jac, flags)
    ok_group = {g: usable(jac, flags, [g]) for g in sens}
    unit, factor = ("mm", 1e3) if jac.target in ("landing", "net_clearance") else (
        ("ms", 1e3) if jac.target == "landing_time" else ("m/s", 1.0))
    landed = jac.valid
    types = {t: landed & (shots.label == t) for t in dict.fromkeys(shots.label)}
    types["all"] = landed
    reg = regimes(shots.speed, shots.spin, shots.contact)
    local = {g: int((landed & ~m).sum()) for g, m in ok_group.items() if (landed & ~m).any()}
    checked = flags.get("checked", True)
    holds = "hold beyond the point" if checked else "were not checked to hold beyond the point (--no-check)"
    md = [f"# Sensitivity of {jac.target} ({', '.join(jac.components)})\n",
          (f"{int(landed.sum())} of {len(landed)} shots landed after the racket; {int(ok.sum())} have gradients that "
           "hold beyond the point for every input group. Gradients flagged as local (an event flip, or central "
           "differences at two steps disagree), by group: "
           + (", ".join(f"{g} {n}" for g, n in sorted(local.items(), key=lambda x: -x[1])) or "none")
           + "; a shot flagged for one group still counts for the others.\n") if checked else
          (f"{int(landed.sum())} of {len(landed)} shots landed after the racket. The local-gradient check was not "
           "run (--no-check): every landed shot counts, including any whose gradient holds only at its point "
           "(an event that flips under a small change).\n"),
          "## By shot type\n", _table(sens, types, ok_group, unit, factor)]

    def medians(cols):
        return {c: {g: float(factor * np.median(v[m & ok_group[g]])) if (m & ok_group[g]).any() else None
                    for g, v in sens.items()} for c, m in cols.items()}

    by_regime = {}
    for name, lab in reg.items():
        cols = {r: landed & (lab == r) for r in dict.fromkeys(lab)}
        md += [f"## By {name}\n", _table(sens, cols, ok_group, unit, factor)]
        by_regime[name] = medians(cols)
    out = dict(unit=unit, by_type=medians(types), by_regime=by_regime, sensitivity=sens, ok=ok, ok_group=ok_group,
               local_by_group=local)
    if budget is not None:
        ok_budget = usable(jac, flags, budget.groups)
        out["ok_budget"] = ok_budget
        md.append("## Landing error budget (linear), mean share of variance by shot type\n")
        md.append("| shot type | std [mm] | " + " | ".join(budget.sources) + " |")
        md.append("|" + "---|" * (len(budget.sources) + 2))
        shares = {}
        for t, m in types.items():
            m = m & ok_budget
            if not m.any():
                continue
            share = np.nanmean(budget.share[:, m], 1)
            std = 1e3 * float(np.median(np.sqrt(np.einsum("bkk->b", budget.cov[m]))))
            shares[t] = dict(std_mm=std, share={s: float(v) for s, v in zip(budget.sources, share)})
            md.append(f"| {t} | {std:.1f} | " + " | ".join(f"{100 * v:.0f} %" for v in share) + " |")
        md.append(f"\n(over the {int(ok_budget.sum())} landed shots whose gradients for the budget's inputs "
                  f"{holds}; std: median over shots of sqrt(trace of the landing covariance))\n")
        out["budget_by_type"] = shares
    out["markdown"] = "\n".join(md)
    return out


def heatmaps(jac: Jacobian, shots, sens: dict, ok_group: dict, path, groups=None, bins: int = 6) -> Path:
    """|d target / d group| (scaled, :func:`group_sensitivity`) averaged over (speed, spin) bins, one
    panel per group (default: the four largest), each over the shots whose gradient for that group
    holds (``ok_group[group]`` (B,), :func:`usable`); PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    factor = 1e3
    groups = groups or sorted(sens, key=lambda g: -np.median(sens[g][ok_group[g]]) if ok_group[g].any() else 0)[:4]
    any_ok = np.any([ok_group[g] for g in groups], 0)
    speed_all, spin_all = np.asarray(shots.speed), np.asarray(shots.spin)
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.6), squeeze=False)
    if any_ok.any():
        es = np.linspace(speed_all[any_ok].min(), speed_all[any_ok].max() + 1e-9, bins + 1)
        ew = np.linspace(spin_all[any_ok].min(), spin_all[any_ok].max() + 1e-9, bins + 1)
    for ax, g in zip(axes[0], groups):
        ok = ok_group[g]
        speed, spin = speed_all[ok], spin_all[ok]
        if len(speed):
            tot, _, _ = np.histogram2d(speed, spin, [es, ew], weights=factor * sens[g][ok])
            cnt, _, _ = np.histogram2d(speed, spin, [es, ew])
            mean = np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)
            im = ax.imshow(mean.T, origin="lower", aspect="auto", extent=[es[0], es[-1], ew[0], ew[-1]], cmap="viridis")
            fig.colorbar(im, ax=ax, label="mm" if jac.target != "bounce_speed" else "")
        ax.set_title(f"{g} ({int(ok.sum())} shots)")
        ax.set_xlabel("speed leaving the racket [m/s]")
        ax.set_ylabel("topspin [rad/s]")
    fig.suptitle(f"|d {jac.target} / d input group| x typical change")
    return save_figure(fig, path)


def budget_bars(summary: dict, sources: list, path) -> Path:
    """Stacked bars of each source's share of the landing variance per shot type, labelled with the
    median landing std; PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = summary.get("budget_by_type", {})
    types = list(data)
    fig, ax = plt.subplots(figsize=(8, 0.5 * len(types) + 1.5))
    left = np.zeros(len(types))
    for s in sources:
        v = np.array([100 * data[t]["share"][s] for t in types])
        ax.barh(types, v, left=left, label=s)
        left += v
    for i, t in enumerate(types):
        ax.text(101, i, f"{data[t]['std_mm']:.1f} mm", va="center")
    ax.set_xlim(0, 115)
    ax.set_xlabel("share of landing variance [%] (label: median landing std)")
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=min(4, len(sources)), fontsize=8)
    return save_figure(fig, path)


def _num(a):
    a = np.asarray(a)
    if a.dtype == bool:
        return a.tolist()
    return np.where(np.isfinite(a), a, np.nan).astype(np.float64).tolist()


def _finite(x):
    """NaN and infinities -> None (JSON has no such numbers)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def write_json(path, *, meta: dict, jac: Jacobian, shots, flags: dict, summary: dict, scale: np.ndarray,
               budget: budgets.Budget | None = None, mc: dict | None = None) -> Path:
    """Every number of the study, one object per shot (with its full Jacobian row), atomically."""
    from ttsim_jax.files.atomic import atomic_write

    shot_rows = []
    for b in range(len(jac.values)):
        row = dict(label=str(shots.label[b]), speed=float(shots.speed[b]), spin=float(shots.spin[b]),
                   contact=_num(shots.contact[b]), valid=bool(jac.valid[b]), flagged=bool(flags["flag"][b]),
                   event_flip=bool(flags["flip"][b]), sequence=jac.sequence[b].tolist(),
                   values=_num(jac.values[b]),
                   flagged_by=[g for g, f in flags["groups"].items() if f[b]],
                   sensitivity={g: float(v[b]) for g, v in summary["sensitivity"].items()},
                   jacobian=_num(jac.jac[b]))
        if budget is not None:
            row["budget"] = dict(cov=_num(budget.cov[b]), share={s: float(budget.share[i, b])
                                                                   for i, s in enumerate(budget.sources)})
        if mc is not None:
            row["monte_carlo"] = dict(cov=_num(mc["cov"][b]), kept=float(mc["kept"][b]))
        shot_rows.append(row)
    doc = dict(meta, target=jac.target, components=list(jac.components), columns=list(jac.columns),
               groups=[str(g) for g in jac.groups], scales=_num(scale), state_groups=list(STATE_GROUPS),
               by_type=summary["by_type"], by_regime=summary["by_regime"],
               budget_by_type=summary.get("budget_by_type"), shots=shot_rows)
    atomic_write(path, json.dumps(_finite(doc)).encode())
    return Path(path)
