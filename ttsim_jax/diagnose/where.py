"""Where the gap lies: a model's errors per phase, binned by regime, with bootstrap intervals.

Items and their error (:func:`items`):

* flight: every observation of a flight segment, the 3-D distance [m] between the flight flown
  from the segment's fitted initial state and the observation; grouped by segment;
* table / racket: every contact, the magnitude [m/s] of the post-contact error as the candidates
  score it (:func:`ttsim_jax.diagnose.candidates.item_sums`): the velocity error and the radius x
  spin error, where measured (world frame for the table, racket frame for the racket; for a bounce
  whose incoming spin is not measured, of the normal velocity error only); a spin gap shows here as
  it does in the candidates' scores; one group each;
* landing: every racket contact with a measured landing point, the landing distance error [m]
  (from ``ttsim evaluate``'s landing rollouts); one group each.

Regimes (:data:`ttsim_jax.diagnose.phases.REGIMES`): numeric quantities are cut at their quartiles
(fewer bins for few items: at least :data:`MIN_BIN` items per bin), the spin axis by category.

Statistic: the mean error of the bin's items, with a 95 % interval from a group bootstrap
(:mod:`ttsim_jax.diagnose.bootstrap`; whole segments are resampled, since the observations of one
segment share its error).

**Flag rule**: a bin *stands out* when the lower end of its 95 % interval lies above
:data:`FLAG_RATIO` (1.25) times the phase's overall mean error, i.e. its error is confidently at
least 25 % above the phase's, or, in a phase that as a whole is not clearly above its noise floor,
above 1.25 times the floor (:func:`summarise`); bins with fewer than :data:`MIN_BIN` items or from
fewer than :data:`MIN_GROUPS` groups are never flagged.
"""

from __future__ import annotations

import math

import numpy as np

from ttsim_jax.diagnose.bootstrap import group_weights, ratio_ci
from ttsim_jax.diagnose.defaults import FLAG_RATIO
from ttsim_jax.diagnose.floor import flight_params_per_axis
from ttsim_jax.diagnose.phases import AXES, REGIMES, contact_regimes, kinematic_regimes

#: Fewest items of a bin (smaller bins are merged by using fewer quantiles).
MIN_BIN = 8
#: Fewest groups (segments, contacts) of a flagged bin.
MIN_GROUPS = 3
#: Quantile bins of a numeric regime quantity.
N_BINS = 4
#: Units of each phase's error.
UNITS = {"flight": "m", "table": "m/s", "racket": "m/s", "landing": "m"}
#: The unit a report shows each SI unit of :data:`UNITS` in, and the factor to it: positions in mm
#: (a flight's error is millimetres), velocities in m/s; one per quantity in the verdict and tables.
SHOWN = {"m": ("mm", 1e3), "m/s": ("m/s", 1.0)}


def shown(phase: str, value: float, digits: int = 3) -> str:
    """``value`` (in the phase's unit of :data:`UNITS`) as the reports show it: "4.39 mm"."""
    unit, factor = SHOWN[UNITS[phase]]
    return f"{value * factor:.{digits}g} {unit}"


def flight_items(fl, residuals, states, radius: float, rows=None) -> dict:
    """Flight items (observations) from position residuals (S, T, 3) and fitted states (S, 6).

    ``rows``: the segment rows to use (default: the real ones).
    """
    res = np.asarray(residuals, np.float64)
    x = np.asarray(states, np.float64)
    rows = np.arange(fl.n) if rows is None else np.asarray(rows)
    seg = kinematic_regimes(x[rows, 3:6], fl.spin[rows], radius)
    m = fl.mask[rows] > 0
    seg_of = np.broadcast_to(np.arange(len(rows))[:, None], m.shape)[m]
    out = dict(error=np.linalg.norm(res[rows], axis=-1)[m], group=seg_of,
               regimes={k: v[seg_of] for k, v in seg.items()})
    out["regimes"]["x"] = fl.pos[rows][..., 0][m]
    out["regimes"]["y"] = fl.pos[rows][..., 1][m]
    out["regimes"]["since_contact"] = fl.tau[rows][m]
    out["null_scale"] = null_scale(fl, rows)[seg_of]
    return out


def null_scale(fl, rows) -> np.ndarray:
    """(len(rows),) per flight segment, the RMS residual a perfect model leaves of unit noise: a
    segment's fit takes k parameters per axis out of its n samples
    (:func:`~ttsim_jax.diagnose.floor.flight_params_per_axis`), so sqrt((n - k) / n). Short
    segments' residuals are smaller for it, so an error compared across segments of different
    lengths (:func:`ttsim_jax.diagnose.residuals.dependence`: the time since the contact is a
    segment's length) is divided by it first."""
    n = np.sum(fl.mask[rows] > 0, axis=1).astype(np.float64)
    source = fl.spin_source[rows] if fl.spin_source is not None else np.full(len(rows), "")
    k = flight_params_per_axis(source)
    return np.sqrt(np.clip((n - k) / np.maximum(n, 1.0), 0.05, 1.0))


def contact_items(c, kind: str, errors, radius: float, rows=None) -> dict:
    """Contact items from (N, 6) errors (velocity and radius x spin, both used: what the candidates
    are scored on)."""
    e = np.asarray(errors, np.float64)
    rows = np.arange(len(c)) if rows is None else np.asarray(rows)
    reg = contact_regimes(c, kind, radius)
    return dict(error=np.linalg.norm(e[rows, :6], axis=1), group=np.arange(len(rows)),
                regimes={k: np.asarray(v)[rows] for k, v in reg.items()})


def landing_items(cases: dict, error, radius: float) -> dict:
    """Landing items: per racket contact, the landing error [m] and the incoming ball's regimes."""
    err = np.asarray(error, np.float64)
    ok = np.isfinite(err)
    ball = cases["ball"][ok]
    reg = kinematic_regimes(ball[:, 3:6], ball[:, 6:9], radius)
    reg["x"], reg["y"] = cases["measured"][ok, 0], cases["measured"][ok, 1]
    return dict(error=err[ok], group=np.arange(int(ok.sum())), regimes=reg)


def bins(values, name: str) -> list:
    """[(label, mask)] of a regime quantity's bins (see the module docstring)."""
    v = np.asarray(values, np.float64)
    ok = np.isfinite(v)
    if name == "spin_axis":
        return [(AXES[k], ok & (v == k)) for k in range(len(AXES)) if np.sum(ok & (v == k)) >= MIN_BIN]
    n = int(ok.sum())
    k = min(N_BINS, n // MIN_BIN)
    if k < 2:
        return []
    edges = np.unique(np.percentile(v[ok], np.linspace(0, 100, k + 1)))
    if len(edges) < 3:
        return []
    unit = REGIMES[name][1]
    out = []
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        last = i == len(edges) - 2
        mask = ok & (v >= lo) & ((v <= hi) if last else (v < hi))
        out.append((f"{_fmt(lo)}-{_fmt(hi)}{' ' + unit if unit and unit != '1' else ''}", mask))
    return out


def _fmt(x: float) -> str:
    a = abs(x)
    return f"{x:.0f}" if a >= 100 else f"{x:.1f}" if a >= 10 else f"{x:.2f}" if a >= 0.1 else f"{x:.3g}"


def summarise(item: dict, seed: int = 0, floor: float | None = None) -> dict:
    """Overall mean error and the binned means by regime of one phase's items (module docstring).

    Arguments:
        item: the phase's items (:func:`flight_items`, :func:`contact_items`, ...).
        seed: of the bootstrap.
        floor: the phase's noise floor (RMS error of a perfect model, :mod:`ttsim_jax.diagnose.floor`),
            if known. Where the phase as a whole does not stand clearly above it (its interval's lower
            end below :data:`FLAG_RATIO` x the floor), a bin is flagged also when its own interval lies
            above that: a gap confined to a few items (a racket's rim) hides in a phase mean near the
            floor. A bin's mean distance cannot exceed its RMS, so such a bin's RMS error stands above
            the floor too.

    Returns:
        dict: ``n``, ``groups``, ``mean``, ``ci95``, ``regimes`` {name: [{label, n, groups, mean,
        ci95, ratio, flag}]}, ``flagged`` [(regime, label)].
    """
    err, grp = np.asarray(item["error"], np.float64), np.asarray(item["group"])
    n_groups = int(grp.max()) + 1 if len(grp) else 0
    w = group_weights(n_groups, seed=seed)

    def sums(mask):
        return (np.bincount(grp[mask], err[mask], minlength=n_groups), np.bincount(grp[mask], minlength=n_groups).astype(float))

    mean, ci = ratio_ci(*sums(np.ones(len(err), bool)), w)
    out = dict(n=int(len(err)), groups=n_groups, mean=mean, ci95=ci, regimes={}, flagged=[])
    # against the floor only where the phase itself is near it: above it everywhere, every bin would be
    local = floor if floor is not None and math.isfinite(floor) and not ci[0] > FLAG_RATIO * floor else None
    for name, values in item["regimes"].items():
        rows = []
        for label, mask in bins(values, name):
            num, den = sums(mask)
            m, c = ratio_ci(num, den, w)
            g = int(np.sum(den > 0))
            high = c[0] > FLAG_RATIO * mean or (local is not None and c[0] > FLAG_RATIO * local)
            flag = bool(mask.sum() >= MIN_BIN and g >= MIN_GROUPS and math.isfinite(c[0]) and high)
            rows.append(dict(label=label, n=int(mask.sum()), groups=g, mean=m, ci95=c,
                             ratio=m / mean if mean else math.nan, flag=flag))
            if flag:
                out["flagged"].append((name, label))
        if rows:
            out["regimes"][name] = rows
    return out


def compare(before: dict, after: dict, seed: int = 0) -> dict:
    """Per regime bin, the mean error before and after (same items): {regime: [{label, before,
    after, reduction_pct}]} plus the overall ones."""
    b, a = summarise(before, seed), summarise(after, seed)
    out = dict(before=b["mean"], after=a["mean"], regimes={})
    for name, rows in b["regimes"].items():
        out["regimes"][name] = [dict(label=rb["label"], n=rb["n"], before=rb["mean"], after=ra["mean"],
                                     reduction_pct=100.0 * (1.0 - ra["mean"] / rb["mean"]) if rb["mean"] else math.nan)
                                for rb, ra in zip(rows, a["regimes"].get(name, []))]
    return out
