"""The whole diagnosis of a model on a dataset: where, which effect, how far the gap shrinks.

:func:`diagnose` runs, in order:

1. the phases' items (:mod:`ttsim_jax.diagnose.phases`) and the model's own errors on them, with a
   seeded split of segments and contacts into training and held-out parts;
2. *where* (:mod:`ttsim_jax.diagnose.where`): the model's errors by phase and regime on all items,
   with the landing error of ``ttsim evaluate``'s rollouts unless ``landing`` is off;
3. the model-free residual dependences and the record effects' sizes
   (:mod:`ttsim_jax.diagnose.residuals`);
4. *which effect* (:mod:`ttsim_jax.diagnose.candidates`): every candidate fitted on the training
   part, scored on the held-out part, ranked; and each one's detection limit
   (:mod:`ttsim_jax.diagnose.limits`): the smallest effect these data would have shown;
5. *how far*: forward selection among the significant candidates (:func:`select`: each fitted
   jointly with those accepted before it and kept when it adds significantly, at most :data:`TOP`),
   the accepted ones' held-out errors against the model's per phase and regime, and the landing
   error of the model with them (per-session parameters averaged over the sessions);
6. the verdict (:mod:`ttsim_jax.diagnose.verdict`): the accepted effects by rank (and those significant alone that add nothing on top
   of them), or "unexplained" with where the gap is (flagged regimes and significant dependences)
   when no candidate reduces a held-out error significantly.

Nothing here reads a generator's truth files.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable

import numpy as np

from ttsim_jax.data.contact_states import ContactFit
from ttsim_jax.diagnose import ambiguity, candidates, residuals, spin_record, where
from ttsim_jax.diagnose.defaults import LEARNING_RATE, MAX_SEGMENTS, QUICK, STEPS, TEST_FRACTION
from ttsim_jax.diagnose.floor import floors
from ttsim_jax.diagnose.limits import limits
from ttsim_jax.diagnose.phases import collect
from ttsim_jax.diagnose.result import Diagnosis
from ttsim_jax.diagnose.verdict import (EXPLAINED_SHARE, IMPLAUSIBLE_SESSIONS,  # noqa: F401 (public here too)
                                        gap_shares, implausible, interchangeable, open_gaps, verdict)
from ttsim_jax.errors import UserError
from ttsim_jax.results import Skipped


class NoData(UserError, ValueError):
    """The dataset has no usable item in any phase; the message gives each phase's reason."""


#: Most effects accepted by the forward selection (fitted jointly for the before/after).
TOP = 3
#: Phases of the "where" analysis.
PHASES = candidates.PHASES + ("landing",)


@dataclasses.dataclass(frozen=True)
class Settings:
    """What the diagnosis does.

    Attributes:
        effects: candidate names (None: every simulator effect of the catalogue).
        test_fraction: share of segments / contacts held out.
        seed: seed of the split and the bootstraps.
        steps: Adam steps per candidate; lr: initial step size (units of each parameter's scale).
        landing: run the landing rollouts (where, and before/after).
        combine: forward selection among the significant candidates (:func:`select`): each fitted
            jointly with those accepted before it, kept when it adds significantly; the accepted
            ones' joint fit is the before/after (else every significant candidate is reported and
            the before/after is the first with those after it that act in other phases).
        max_segments: flight segments used at most (a seeded random subset of more; None: every one).
        fit: contact state estimation.
        spin: where a flight segment's spin comes from (:func:`ttsim_jax.diagnose.phases.flights`):
            ``"auto"`` (default) the measured spin where the record has one of confidence >=
            ``fit.min_spin_conf``, the latent spin fitted under the diagnosed model elsewhere;
            ``"measured"``, ``"latent"``, ``"zero"``.
        spin_check: check the measured spins against the flights in the record section
            (:func:`ttsim_jax.diagnose.residuals.spin_check`).
        spin_correct: where the check finds the record's spin off, try its correction on the
            flight phase and, where it lowers the held-out flight error significantly, let every
            later stage work on the corrected spin (:mod:`ttsim_jax.diagnose.spin_record`).
    """

    effects: tuple | None = None
    test_fraction: float = TEST_FRACTION
    seed: int = 0
    steps: int = STEPS
    lr: float = LEARNING_RATE
    landing: bool = True
    combine: bool = True
    max_segments: int | None = MAX_SEGMENTS
    fit: ContactFit = ContactFit()
    spin: str = "auto"
    spin_check: bool = True
    spin_correct: bool = True

    @classmethod
    def quick(cls, **kw) -> "Settings":
        """Fewer steps and segments, no landing rollouts, no joint fit, no spin check."""
        return cls(**{**QUICK, **kw})


def _test_rows(pb, phase):
    return np.flatnonzero(np.asarray(pb.data[phase]["test"]) > 0)


def _items(ph, pb, phase, errors, radius, rows=None):
    if phase == "flight":
        return where.flight_items(ph.flights, errors, pb.x0, radius, rows)
    return where.contact_items(getattr(ph, phase), phase, errors, radius, rows)


def _components(ph, phase, errors):
    e = np.asarray(errors, np.float64)
    if phase == "flight":
        return e[: ph.flights.n][ph.flights.mask[: ph.flights.n] > 0]
    return e[: len(getattr(ph, phase)), :3]


def _landing_before_after(ds, model, best, fit, radius):
    """The landing rollouts of the model, and of the model plus the accepted effects ``best`` (a
    fitted candidate, or None): (landing stage of the model, the after-effects landing errors or
    None, the cases or None when the landing stage was skipped).

    The model runs with the accepted effects attached at their neutral values, which reproduce it
    exactly (``tests/effects``): the two rollouts then share one compiled program, where the model
    alone and the model with effects would each trace and load a rally kernel of their own."""
    from ttsim_jax.evaluate.stages import EvaluateSettings, landing_cases, landing_stage

    st = EvaluateSettings(fit=fit)
    models = [("model", model)]
    if best is not None:
        fitted = _with_effects(model, best)
        extra = fitted.effects[len(model.effects):]
        neutral = tuple(type(e).neutral(dtype=model.ball.radius.dtype) for e in extra)
        models = [("model", model.replace(effects=tuple(model.effects) + neutral)), ("after", fitted)]
    res = landing_stage(ds, models, st)
    if isinstance(res, Skipped):
        return res, None, None
    return res, res.error.get("after"), landing_cases(ds, st, radius)


def _with_effects(model, cand) -> object:
    """The model plus a fitted candidate's effects (per-session parameters averaged)."""
    from ttsim_jax import effects as fx

    extra = []
    for name, values in cand.params.items():
        cls = fx.effect_class(name)
        if cls.SCOPE == "session" and values and isinstance(next(iter(values)), int):
            values = {k: np.mean([np.asarray(v[k]) for v in values.values()], axis=0) for k in cls.PARAMS}
        extra.append(cls.from_dict({k: np.asarray(v) for k, v in values.items()}, dtype=model.ball.radius.dtype))
    return model.replace(effects=tuple(model.effects) + tuple(extra))


def diagnose(ds, model, settings: Settings = Settings(), progress: Callable[[str, int], None] | None = None,
             keep: dict | None = None) -> Diagnosis:
    """The diagnosis of ``model`` on ``ds`` (see the module docstring).

    Arguments:
        ds: a validated dataset; model: a loaded :class:`~ttsim_jax.params.Model` (float32).
        settings: :class:`Settings`.
        progress: optional ``progress(what, units)``: ``units`` of :func:`work_units` are done
            and ``what`` runs next (what a progress bar shows while it runs).
        keep: optional dict that receives the :class:`~ttsim_jax.diagnose.candidates.Problem`
            (``"problem"``), for scoring other models on the same split.

    Returns:
        A :class:`~ttsim_jax.diagnose.result.Diagnosis` (its ``to_json()`` is the report's
        ``diagnosis.json``).
    """
    from ttsim_jax.kernel.ball_step import ball_properties

    tick = progress or (lambda what, n=1: None)
    t_start = time.perf_counter()
    timings, last = {}, [t_start]

    def lap(what):
        """Seconds since the previous lap, under ``what`` (summed), for ``timings``."""
        now = time.perf_counter()
        timings[what] = timings.get(what, 0.0) + now - last[0]
        last[0] = now
    radius = float(ball_properties(model)[0])
    names = candidates.candidate_names(settings.effects)
    def phases_of(data):
        ph_ = collect(data, model, settings.fit, max_segments=settings.max_segments, seed=settings.seed,
                      spin=settings.spin)
        if ph_.flights is None and ph_.table is None and ph_.racket is None:
            raise NoData("no phase has usable data (" + "; ".join(f"{k}: {v}" for k, v in ph_.skipped.items()) + ")")
        pb_ = candidates.problem(ph_, model, settings.test_fraction, settings.seed)
        refuse_non_finite(pb_, ph_)
        return ph_, pb_

    ph, pb = phases_of(ds)
    tick("model errors", 1)
    lap("model errors")
    checked, correction = None, {}
    if settings.spin_check and ph.flights is not None:  # on the record's own spins, before any correction
        checked = residuals.spin_check(ph.flights, model, settings.seed)
        if settings.spin_correct:
            ds, ph, pb, correction = spin_record.correct(ds, ph, pb, checked, phases_of, settings.seed)
        lap("spin check")
    if keep is not None:
        keep["problem"] = pb
    tick("noise floor and bounds", 1)
    out = dict(phases=list(pb.phases), skipped=dict(ph.skipped), left_out=dict(ph.left_out), settings=dict(
        dataclasses.asdict(settings), effects=names, fit=dataclasses.asdict(settings.fit)))
    out["counts"] = {p: (ph.flights.n if p == "flight" else len(getattr(ph, p))) for p in pb.phases}
    if ph.flights is not None:
        from ttsim_jax.fit.flight import spin_source_counts

        out["spin_sources"] = spin_source_counts(ph.flights.spin_source[: ph.flights.n])

    # where, on every item (the landing's after the candidates: see _landing_before_after)
    items = {p: _items(ph, pb, p, pb.base[p], radius) for p in pb.phases}
    out["floor"] = floors(ds, ph, pb, model, settings.fit, settings.seed)
    lap("noise floor")
    floor_of = {p: f["floor"] for p, f in out["floor"].items() if isinstance(f, dict)}
    out["where"] = {p: where.summarise(it, settings.seed, floor_of.get(p)) for p, it in items.items()}
    out["dependence"] = {p: residuals.dependence(it, _components(ph, p, pb.base[p]) if p in pb.base else None)
                         for p, it in items.items()}
    out["record"] = residuals.record_sizes(ds, ph, model, settings.seed, settings.spin_check, checked)
    if correction:
        out["spin_correction"] = correction
    lap("where and the record")
    from ttsim_jax.diagnose.bound import bounds

    out["bound"] = bounds(pb, radius, settings.seed, ph.skipped)  # how far any correction gets, per phase
    lap("model-free bounds")

    # which effect
    cands = []
    available = [n for n in names if any(p in pb.phases for p in candidates.spec(n)[0].phases)]
    group_of = {n: g for g in candidates.groups(available, pb.phases) for n in g}
    tick(f"fitting {names[0]}" if names else "ranking", 0)
    for i, name in enumerate(names):
        following = f"fitting {names[i + 1]}" if i + 1 < len(names) else "forward selection"
        spec, _ = candidates.spec(name)
        if not any(p in pb.phases for p in spec.phases):
            out["skipped"][f"effect {name}"] = f"acts in {', '.join(spec.phases)}: no data there"
            tick(following, 1)
            continue
        cands.append(candidates.fit(pb, [name], model, group=group_of[name], steps=settings.steps, lr=settings.lr))
        lap(f"candidate {name}")
        tick(following, 1)
    ranked = candidates.rank(cands)
    out["candidates"] = [_candidate_json(c, i + 1) for i, c in enumerate(ranked)]
    tick("detection limits", 0)
    out["limits"] = limits(pb, model, names, settings.seed)
    lap("detection limits")
    beyond = {c.spec.name: implausible(c.params) for c in ranked}
    for entry in out["candidates"]:
        entry["implausible"] = beyond[entry["name"]]
    # A fit that needs a 1-degree table tilt or an 8 cm/s indoor updraft is not the cause, however
    # well it fits: it stands in for something the catalogue lacks.
    out["implausible"] = [c.spec.name for c in ranked if c.significant and beyond[c.spec.name]]
    significant = [c for c in ranked if c.significant and not beyond[c.spec.name]]
    out["indistinguishable"] = ambiguity.indistinguishable(pb, [c for c in ranked if c.significant])
    # an accepted fit that moves the errors only as a simpler reading does names no cause
    out["reads_as"] = {c.spec.name: r for c in significant if (r := ambiguity.reads_as(pb, c))}

    # how far
    accepted, best = significant, None
    if len(significant) > 1 and settings.combine:
        accepted, best, adds = select(pb, significant, model, group_of, settings)
        for entry in out["candidates"]:
            if entry["name"] in adds:
                entry["adds"] = adds[entry["name"]]
        out["combined"] = _candidate_json(best, 0 if len(accepted) > 1 else 1)
    elif significant:
        # no joint fit: the first, with those after it that act in phases of their own (fits in
        # disjoint phases are their joint fit), so each phase's share is of a fit made for it
        blocks = []
        for c in significant:
            if not any(_share_a_phase(b, c) for b in blocks):
                blocks.append(c)
        best = _merged(blocks, blocks)
        out["combined"] = _candidate_json(best, 0 if len(blocks) > 1 else 1)
    lap("ranking and forward selection")
    tick("landing rollouts" if settings.landing else "verdict", 1)
    arrays = {f"before_{p}": _items(ph, pb, p, pb.base[p], radius, _test_rows(pb, p))["error"] for p in pb.phases}
    out["before_after"] = {}
    if best is not None:
        for p, e in best.errors.items():
            rows = _test_rows(pb, p)
            before, after = _items(ph, pb, p, pb.base[p], radius, rows), _items(ph, pb, p, e, radius, rows)
            out["before_after"][p] = dict(where.compare(before, after, settings.seed), heldout=best.heldout[p])
            arrays[f"after_{p}"] = after["error"]
    if settings.landing:
        landing, after, cases = _landing_before_after(ds, model, best, settings.fit, radius)
        if cases is None:
            out["skipped"]["landing"] = landing.reason
        else:
            it = where.landing_items(cases, landing.error["model"], radius)
            out["where"]["landing"] = where.summarise(it, settings.seed, floor_of.get("landing"))
            out["dependence"]["landing"] = residuals.dependence(it, None)
            before = landing.error["model"]
            arrays["before_landing"] = before[np.isfinite(before)]
            entry = dict(before_median=float(np.nanmedian(before)), n=int(np.isfinite(before).sum()))
            if after is not None:
                ok = np.isfinite(before) & np.isfinite(after)
                fall = 100.0 * (1.0 - np.median(after[ok]) / np.median(before[ok])) if ok.any() else math.nan
                entry.update(after_median=float(np.nanmedian(after)), reduction_median_pct=fall)
                arrays["after_landing"] = after[np.isfinite(after)]
            out["landing"] = entry
        lap("landing rollouts")
    out["no_data"] = no_data(out["skipped"], settings.landing)
    tick("verdict", 1)
    judged = verdict(out, accepted, [c for c in significant if c not in accepted],
                     [c for c in ranked if c.spec.name in out["implausible"]])
    lap("verdict")
    return Diagnosis(verdict=judged, pooled_sessions=pb.pooled, seconds=time.perf_counter() - t_start, timings=timings,
                     arrays=arrays, histories={c.spec.name: c.history for c in ranked}, **out)


def refuse_non_finite(pb, ph) -> None:
    """Raises :class:`NoData` when the model's error on any item of a phase is not finite: a NaN
    would make every score of that phase NaN and the verdict meaningless. The message names the
    items, the likely cause and the remedy.

    Arguments:
        pb: the :class:`~ttsim_jax.diagnose.candidates.Problem` with the model's errors;
        ph: its :class:`~ttsim_jax.diagnose.phases.Phases`.
    """
    bad = []
    for p in pb.phases:
        sse, _ = candidates.item_sums(pb, p, pb.base[p])
        n = ph.flights.n if p == "flight" else len(getattr(ph, p))
        rows = np.flatnonzero(~np.isfinite(sse[:n]))
        if not len(rows):
            continue
        ids = ph.flights.segment_id[rows] if p == "flight" else getattr(ph, p).event_id[rows]
        what = "segments" if p == "flight" else f"{p} contacts"
        listed = ", ".join(str(int(i)) for i in ids[:8]) + (" ..." if len(ids) > 8 else "")
        bad.append(f"{p}: the model's error is not finite on {len(rows)} of {n} {what} "
                   f"({'segment' if p == 'flight' else 'event'} ids {listed})")
    if bad:
        raise NoData(
            "; ".join(bad) + ". Such items usually hold more than one flight (a session whose pauses or "
            "tracking jumps were not split, a missed contact) or samples of something other than the ball. "
            "Import the log with `ttsim data import` (it splits sessions where the tracker lost the ball and "
            "warns about segments that no flight fits) and add --filter to leave those segments out.")


def select(pb, significant: list, model, group_of: dict, settings: Settings) -> tuple[list, candidates.Candidate, dict]:
    """Forward selection among the significant candidates (ranked): the first is accepted; each next
    one is fitted jointly with those accepted so far and accepted when, on top of them, it lowers a
    held-out error significantly (:func:`~ttsim_jax.diagnose.candidates.explains`, against the
    accepted ones' joint fit), until :data:`TOP` are accepted.

    A candidate fitted alone against the model can absorb part of another effect that acts in the
    same phase (a lower restitution of a worn ball mimics part of a buckling loss): significant
    alone, it adds nothing once the other is in the model.

    Effects acting in disjoint phases do not interact in the fit (the loss is a sum over phases and
    each effect's parameters move only its own phases' errors), so the accepted ones are kept as
    blocks of effects that share a phase, and a candidate is refitted only with the blocks it shares
    a phase with: alone (its own fit) where it shares none.

    Two effects can explain the same errors (a buckling loss that starts below nearly every impact is
    a worn ball's lower restitution; a warped top where the balls land, a tilt): when an accepted
    neighbour of a redundant candidate adds nothing on top of it either (with the other accepted
    neighbours beside both, refitted without that one), the two are *interchangeable* on these data,
    and the report says so rather than naming the one that happened to rank first. This costs one
    joint fit per neighbour where a redundant candidate has more than one.

    Returns:
        (accepted candidates, the joint fit of the accepted ones (the first alone when it is the
        only one), {name: {"accepted", "on_top_of", "heldout", "interchangeable_with"}} of each
        candidate tried on top).
    """
    accepted, blocks, adds = [significant[0]], [significant[0]], {}
    for c in significant[1:]:
        if len(accepted) >= TOP:
            break
        near = [b for b in blocks if _share_a_phase(b, c)]
        neighbours = [n for b in near for n in b.params]  # the accepted effects it shares a phase with
        block = c
        if near:
            names = neighbours + [c.spec.name]
            block = candidates.fit(pb, names, model, group=_group(group_of, names), steps=settings.steps,
                                   lr=settings.lr, name="+".join(names))
        current = {p: e for b in blocks for p, e in b.errors.items()}
        on_top = candidates.score(pb, block.errors, base=current)
        ok = candidates.explains(on_top)
        same = []
        if near and not ok:
            # redundant; a neighbour that adds nothing on top of it (and the other neighbours) either
            # is one the data cannot tell it apart from
            for n in neighbours:
                names = [m for m in neighbours if m != n] + [c.spec.name]
                swap = c if len(names) == 1 else candidates.fit(pb, names, model, group=_group(group_of, names),
                                                                steps=settings.steps, lr=settings.lr,
                                                                name="+".join(names))
                if not candidates.explains(candidates.score(pb, block.errors, base=swap.errors)):
                    same.append(n)
        adds[c.spec.name] = dict(accepted=ok, on_top_of=[a.spec.name for a in accepted], heldout=on_top,
                                 interchangeable_with=same)
        if ok:
            accepted.append(c)
            blocks = [b for b in blocks if not any(b is n for n in near)] + [block]
    return accepted, _merged(blocks, accepted), adds


def _share_a_phase(a: candidates.Candidate, b: candidates.Candidate) -> bool:
    """Whether two fits act in a phase in common (else each is the other's joint fit's part)."""
    return bool(set(a.heldout) & set(b.heldout))


def _group(group_of: dict, names: list):
    """The compiled group of candidates holding all of ``names`` (None: a group of their own)."""
    return next((g for g in set(group_of.values()) if set(names) <= set(g)), None)


def _merged(blocks: list, accepted: list) -> candidates.Candidate:
    """One candidate of fits in disjoint phases (its loss history left empty)."""
    if len(blocks) == 1:
        return blocks[0]
    first = blocks[0].spec
    return candidates.Candidate(spec=candidates.Spec("+".join(c.spec.name for c in accepted), first.cls, (), False),
                                consts=(), u=(), history=np.zeros(0),
                                errors={p: e for b in blocks for p, e in b.errors.items()},
                                heldout={p: h for b in blocks for p, h in b.heldout.items()},
                                params={n: v for b in blocks for n, v in b.params.items()})


def no_data(skipped: dict, landing: bool = True) -> dict:
    """{phase: why it has no data} for every phase of :data:`PHASES` without items (the landing
    phase only when its rollouts were asked for)."""
    phases = PHASES if landing else PHASES[:-1]
    return {p: skipped[p] for p in phases if p in skipped}


def work_units(settings: Settings) -> int:
    """Progress units of :func:`diagnose` (for a progress bar)."""
    return 5 + len(candidates.candidate_names(settings.effects))


def _candidate_json(c: candidates.Candidate, rank: int) -> dict:
    return dict(rank=rank, name=c.spec.name, phases=sorted(c.heldout), significant=c.significant,
                best_reduction_pct=c.best, heldout=c.heldout, params=c.params,
                loss=dict(start=float(c.history[0]) if len(c.history) else math.nan,
                          end=float(c.history[-1]) if len(c.history) else math.nan))
