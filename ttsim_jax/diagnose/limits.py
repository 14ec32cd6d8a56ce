"""Detection limits: the smallest effect of each candidate that these data would have shown as
significant, per phase, so that "unexplained" says what the data could not have seen.

For a candidate, the effect at its typical size (each free parameter at its catalogue ``typical``
value, the others where the fit starts them: :mod:`ttsim_jax.diagnose.specs`) changes the
model's errors on every item by Delta (one evaluation of the model with the effect, the flight
segments' initial states refitted as the candidates' fits refit them). The record without the
effect is the model's errors r with their component along Delta taken out, on the training and
the held-out items apart (:func:`without_effect`: an effect the record already holds, or one that
differs between sessions, is neither "detected" nor hidden at any size). An effect of ``s`` times
the typical size *injected* into it (the model's own predictions moved by it, with the record's
own residuals as the noise) leaves the model's errors r - s Delta; the candidate fitted along its
direction on the training items finds ``s`` and leaves r. The held-out test is then the
candidates' own (:func:`~ttsim_jax.diagnose.candidates.score`, the bootstrap interval,
:func:`~ttsim_jax.diagnose.candidates.significant`). The limit is the smallest ``s`` significant
for both signs of the effect (an effect of that size, either way, would show; :func:`limit_size`:
bisection, the held-out reduction grows with ``s``), up to :data:`MAX_SIZE` typical sizes.

Reported per candidate and phase: ``s``, the free parameters' values at ``s`` (e.g. a steady wind
of 0.04 m/s), the change of the phase's errors that the effect makes there as a share of the
phase's RMS error (``share_pct``: RMS of s Delta over RMS of r on the held-out items), and the
held-out reduction of the phase's RMS error it then shows (``reduction_pct``, comparable to the
candidates' and the oracle's).

The linear, one-direction fit is the most favourable the candidates' fits can meet (they fit every
free parameter, per session for a per-session effect, robustly): the limit is a lower bound on
what they detect, and ``benchmarks/detection_limits.py`` measures how close, by generating
effects at 0.5 and 1.5 times the limit.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ttsim_jax.diagnose import candidates, stages

#: Largest size tried, in typical sizes of the effect: beyond it the data could not show it.
MAX_SIZE = 100.0
#: Smallest size tried, in typical sizes.
MIN_SIZE = 1e-3
#: Bisection steps in log size (the limit to within a factor of (MAX_SIZE / MIN_SIZE) ** 2^-steps).
STEPS = 10


def direction(sp, const) -> dict:
    """{param: (shape) the typical effect's step from the fit's start} of a candidate's free
    parameters with a scale (the others, and those started at their typical value, stay)."""
    out = {}
    for k in sp.free:
        p = sp.cls.PARAMS[k]
        if float(const["scale"][k]) <= 0.0 or p.fit_start == "typical":
            continue
        step = np.broadcast_to(np.asarray(p.typical, np.float64) - np.asarray(p.neutral, np.float64), p.shape)
        if np.any(step != 0.0):
            out[k] = step
    return out


def responses(pb, model, names, group) -> dict:
    """{candidate: {phase: (rows, ...) Delta}} of the candidates ``names`` of one compiled group
    ``group`` (:func:`~ttsim_jax.diagnose.candidates.groups`): the change of the model's errors by
    each effect at its typical size, in the phases it acts in (one evaluation each, and one of the
    group at neutral, all one compiled program). A candidate without a typical step is left out."""
    specs, consts = candidates.group_specs(pb, group)
    phases = tuple(p for p in pb.phases if any(p in s.phases for s in specs))
    u0 = candidates.initial_u(specs, pb.n_sessions)
    at_rest, _ = candidates.evaluate(model, specs, consts, u0, pb, stages.GN_START, phases)
    out = {}
    for i, s in enumerate(specs):
        if s.name not in names:
            continue
        step = direction(s, consts[i])
        if not step:
            continue
        u = list(u0)
        u[i] = {k: (jnp.asarray(np.broadcast_to(step[k] / float(consts[i]["scale"][k]), v.shape), v.dtype)
                    if k in step else v) for k, v in u0[i].items()}
        moved, _ = candidates.evaluate(model, specs, consts, tuple(u), pb, stages.GN_START, phases)
        out[s.name] = {p: np.asarray(moved[p], np.float64) - np.asarray(at_rest[p], np.float64)
                       for p in s.phases if p in moved}
    return out


def _dot(a, b, weights):
    """sum over rows of weight x <a_row, b_row>."""
    return float(np.sum(np.asarray(weights, np.float64) * np.sum(a * b, axis=tuple(range(1, a.ndim)))))


def without_effect(pb, p: str, delta) -> np.ndarray:
    """The model's errors in phase ``p`` with their component along ``delta`` taken out, on the
    training and the held-out rows apart: the record as it would be with none of the candidate's
    effect (nor anything alike it), so that an effect the record already holds, or one that varies
    between sessions, does not count as detected or hidden at any size."""
    r = np.asarray(pb.base[p], np.float64)
    rest = r.copy()
    for key in ("train", "test"):
        w = np.asarray(pb.data[p][key], np.float64)
        den = _dot(delta, delta, w)
        if den > 0:
            rows = w > 0
            rest[rows] = r[rows] - (_dot(r, delta, w) / den) * delta[rows]
    return rest


def heldout_at(pb, delta: dict, size: float, seed: int = 0, rest: dict | None = None) -> dict:
    """The held-out scores {phase: score} of the candidate fitted, along its typical direction, to
    an effect of ``size`` typical sizes injected into the record without it (:func:`without_effect`):
    the errors r - size Delta before, the fit finding the size exactly on the training rows
    (the rest is orthogonal to Delta there), so r after. ``rest``: {phase: :func:`without_effect`}
    where already computed (a bisection asks for many sizes)."""
    before, after = {}, {}
    for p, d in delta.items():
        r = rest[p] if rest is not None and p in rest else without_effect(pb, p, d)
        before[p], after[p] = r - size * d, r
    return candidates.score(pb, after, seed=seed, base=before)


def limit_size(shown, lo: float = MIN_SIZE, hi: float = MAX_SIZE, steps: int = STEPS) -> float:
    """The smallest size in [lo, hi] with ``shown(size)`` true, by bisection in log size (``shown``
    false below some size and true above it); inf when not shown at ``hi``, ``lo`` when at ``lo``."""
    if not shown(hi):
        return math.inf
    if shown(lo):
        return lo
    a, b = math.log(lo), math.log(hi)
    for _ in range(steps):
        m = 0.5 * (a + b)
        a, b = (a, m) if shown(math.exp(m)) else (m, b)
    return math.exp(b)


def candidate_limits(pb, delta: dict, sp, const, seed: int = 0) -> dict:
    """One candidate's limits {phase: {"size", "params", "share_pct", "reduction_pct"}} from its
    responses ``delta`` (:func:`responses`): the size in typical sizes, the free parameters' values
    there, the effect's RMS change of the errors over their RMS, and the held-out reduction it then
    shows (the smaller of the two signs); ``size`` and the shares None (no params: JSON holds no inf)
    where even :data:`MAX_SIZE` typical sizes would not show."""
    step = direction(sp, const)
    out = {}
    for p, d in delta.items():
        rest = {p: without_effect(pb, p, d)}

        def scores(s, p=p, d=d, rest=rest):
            return [heldout_at(pb, {p: d}, sign * s, seed, rest)[p] for sign in (1.0, -1.0)]

        # each phase alone: the smallest effect its held-out items show whatever its sign
        size = limit_size(lambda s: all(candidates.significant(p, h) for h in scores(s)))
        entry = dict(size=None, params={}, share_pct=None, reduction_pct=None)  # JSON: no inf or NaN
        if math.isfinite(size):
            entry["size"] = size
            test = np.asarray(pb.data[p]["test"]) > 0
            moved, _ = candidates.item_sums(pb, p, size * d)
            err, _ = candidates.item_sums(pb, p, pb.base[p])
            entry.update(params={k: (size * v).tolist() for k, v in step.items()},
                         share_pct=float(100.0 * math.sqrt(moved[test].sum() / max(err[test].sum(), 1e-30))),
                         reduction_pct=float(min(h["pct"] for h in scores(size))))
        out[p] = entry
    return out


def limits(pb, model, names, seed: int = 0) -> dict:
    """Every candidate's detection limits (module docstring).

    Arguments:
        pb: the diagnosis's :class:`~ttsim_jax.diagnose.candidates.Problem`; model: the diagnosed
            model; names: the candidate names; seed: the bootstraps' seed.

    Returns:
        {"candidates": {name: {phase: {"size", "params", "share_pct"}}}, "phases": {phase:
        {"share_pct", "by"}}: per phase the smallest share of its error any candidate's limit
        makes, and that candidate}.
    """
    available = [n for n in names if any(p in pb.phases for p in candidates.spec(n)[0].phases)]
    found = {}
    for group in candidates.groups(available, pb.phases):
        delta = responses(pb, model, [n for n in group if n in available], group)
        for n, d in delta.items():
            sp, const = candidates.spec(n, pb.pooled)
            found[n] = candidate_limits(pb, d, sp, const, seed)
    phases = {}
    for n, per in found.items():
        for p, e in per.items():
            if e["size"] is not None and e["share_pct"] < phases.get(p, {}).get("share_pct", math.inf):
                phases[p] = dict(share_pct=e["share_pct"], by=n)
    return dict(candidates={n: found[n] for n in names if n in found}, phases=phases)


def describe(name: str, entry: dict) -> str:
    """``"air_flow: wind 0.041 m/s"``: a candidate's limit in its own parameters (the largest
    component of each), or ``"... beyond 100 x its typical size"``."""
    from ttsim_jax import effects as fx

    if entry["size"] is None:
        return f"{name}: not within {MAX_SIZE:g} x its typical size"
    cls = fx.effect_class(name)
    parts = []
    for k, v in entry["params"].items():
        a = np.asarray(v, np.float64).reshape(-1)
        value = float(np.max(np.abs(a))) if a.size > 1 else float(abs(a[0]))
        unit = getattr(cls.PARAMS[k], "unit", "")
        parts.append(f"{k} {value:.2g}" + ("" if unit in ("", "1") else f" {unit}"))
    return f"{name}: {', '.join(parts)}"
