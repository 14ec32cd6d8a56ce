"""Withheld-effect validation of the diagnosis (``ttsim diagnose selfcheck``).

Each *case* generates a dataset with the reality generator (conti2026 plus the case's effects at
random magnitudes drawn by :func:`draw`, plus paper-like position noise :data:`NOISE`), diagnoses it
with conti2026 (the effects hidden from the model) and scores the result against the truth. Kinds:

* *single*: one catalogue effect;
* *pair*: two catalogue effects at once;
* *control*: no effect at all, only the record's noise (last in every suite): the right answer is
  "no gap": nothing significant and no phase above its noise floor, the model-free bound included;
* *outside*: an effect the diagnosis's catalogue lacks (the candidates are every simulator effect
  but it): the right answer is "unexplained", with the gap located in the phase it acts in. The
  outside suite (:data:`OUTSIDE_PLAN`, ``--outside``) also records some cases as a tracker does
  (*outside_log*: the games written as a multi-throw log of observations only, no labelled events,
  and imported through the CSV path, :func:`as_tracker_log`; *outside_oneway*: that log keeping only
  the flights towards +x, every throw the same way as from a launcher).

Scores (:func:`score`, a pure function of the diagnosis's JSON, the oracle's held-out scores and the
truth, so that it is testable without simulation):

* *oracle*: the model given the true effects with their true parameters, scored on the same
  held-out split (:func:`oracle_scores`). A case is **detectable** when the oracle itself passes the
  diagnosis's significance rule (:func:`ttsim_jax.diagnose.candidates.significant`) in a phase the
  effects act in. An undetectable case (the effect, at its drawn magnitude, changes the held-out
  errors by less than the data resolves) cannot be found by any method; it is reported apart, and
  scored right when nothing is significant ("nothing found") and as a false alarm otherwise;
* *rank 1*: the first candidate is significant and is the true effect, or one the diagnosis reports
  as interchangeable with it on these data (each adds nothing on top of the other; counted, and
  named in the outcome) (pairs: one of the two;
  *both*: the two true effects are the diagnosis's first two accepted effects (significant, and
  the second adding significantly on top of the first, :func:`ttsim_jax.diagnose.diagnosis.select`)
  or reported interchangeable with them, one each);
* *phase*: the located phase, the phase where the first candidate's held-out reduction is largest
  among its significant ones, is one the true effects act in. For an *outside* case the located
  phases are those where the "where" analysis flags a regime; right when the true phase is among
  them;
* *shrink recovered*: in the oracle's best phase, the largest held-out reduction of a significant
  candidate as a fraction of the oracle's (0 when nothing is significant).

The summary's rates are over the detectable single-effect cases. The generator's truth is read
here, and only here: the diagnosis itself never sees it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Callable

import jax.numpy as jnp
import numpy as np

from ttsim_jax import effects as fx
from ttsim_jax.diagnose import candidates as candidate_fit
from ttsim_jax.diagnose import stages
from ttsim_jax.diagnose.spin_record import NAME as SPIN_RECORD
from ttsim_jax.diagnose.outside import (OUTSIDE_KINDS, OUTSIDE_PLAN, TERMS, as_tracker_log,  # noqa: F401 (the selfcheck's names)
                                        bound_score, effect_phases, outside_cases)
from ttsim_jax.diagnose.selfcheck_report import OUTCOME_COLOURS, plot, table, verdict_of  # noqa: F401 (its face)
from ttsim_jax.errors import UserError

#: Paper-like triangulation noise: per-axis standard deviation [m] (the catalogue's typical value).
NOISE = (0.0015, 0.0015, 0.001)
#: Effects of ``--quick`` (one per phase, and one that acts in a narrow regime).
QUICK = ("spin_decay", "air_flow", "table_tilt", "buckling")
#: Pair cases of the full run.
PAIRS = (("spin_decay", "table_tilt"), ("air_flow", "buckling"), ("ball_variation", "racket_edge"),
         ("worn_ball", "table_unevenness"))
#: The outside case's effect: generated, but not a candidate.
OUTSIDE = "racket_edge"
#: Games per generated dataset (about 150 flight segments, 70 table and 30 racket contacts each)
#: and flight segments diagnosed at most, per case: full run (None: every one, the diagnosis's
#: default) and ``--quick``.
GAMES = {"full": 14, "quick": 8}
SEGMENTS = {"full": None, "quick": 384}
#: Parameters of an effect that vary within a session faster than a diagnosis's flight segments
#: sample it (air_flow's gusts, periods of 1-20 s, against a segment every ~10 s of a session at
#: 128 segments, the default before every segment was): no held-out method resolves them, so an outside case also scores
#: the model-free bound against the oracle with them at neutral (``oracle_steady_pct``).
UNRESOLVED = {"air_flow": ("gust_amp",)}
#: Tries of successive seeds when the generator refuses its own data.
TRIES = 4
#: The record effects whose right answer is the spin check's correction of the record's spin.
SPIN_EFFECTS = {"spin_calibration"}


def _direction(rng, n: int = 2) -> np.ndarray:
    u = rng.normal(size=n)
    return u / np.linalg.norm(u)


def _signed(rng, lo: float, hi: float) -> float:
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))


def _warp(rng, bumps: int = 4, apart: float = 0.6) -> dict:
    """``table_unevenness`` of a warped top: ``bumps`` bumps or dips where the balls land, centres at
    least ``apart`` metres apart, the effect's other bumps flat."""
    n = fx.effect_class("table_unevenness").N_BUMPS
    centers = []
    while len(centers) < bumps:
        c = np.array([_signed(rng, 0.5, 1.25), rng.uniform(-0.55, 0.55)])
        if all(np.linalg.norm(c - o) >= apart for o in centers):
            centers.append(c)
    amplitude = [_signed(rng, 0.0045, 0.0065) for _ in range(bumps)] + [0.0] * (n - bumps)
    centers += [np.zeros(2)] * (n - bumps)
    return {"amplitude": amplitude, "center": np.array(centers), "width": np.append(rng.uniform(0.2, 0.35, bumps),
                                                                                   [0.25] * (n - bumps))}


#: Magnitudes of the selfcheck, per effect: the upper part of each effect's realistic range (its
#: ``sample`` draw, :mod:`ttsim_jax.effects.physical`), where it changes the data by more than
#: paper-like noise resolves on a case's data; parameters not drawn here come from ``sample``. A
#: case whose oracle still fails the significance rule is *undetectable* (module docstring): these
#: ranges are chosen so that every effect is detectable in most cases, measured with the oracle on
#: generated games (the table contacts' RMS error is about 0.31 m/s; a significant table effect must
#: lower it by 0.01 m/s, which takes a velocity change of about 0.08 m/s RMS).
#:
#: * spin_decay: rate 0.15-0.3 1/s, quadratic 1e-4-2e-4 s/rad (measured decay times of 40+ balls are
#:   seconds; the catalogue's range is 0.05-0.3 and 0-2e-4);
#: * air_flow: steady wind 0.2-0.4 m/s, horizontal, any heading (ventilation in a hall; catalogue
#:   0.05-0.4), the same in every game, with the catalogue's gusts;
#: * table_tilt: slope 0.009-0.0125 (0.5-0.7 degrees: a table on an unlevelled floor; the largest
#:   the catalogue draws), any direction, the surface's height at the centre unchanged. A slope of
#:   0.0072 lowers the table errors by 1.8-2.4 %: below the significance rule;
#: * table_unevenness: a warped top (:func:`_warp`): four bumps or dips of 4.5-6.5 mm (the catalogue's
#:   heights have a 1.2 mm spread), 0.2-0.35 m wide, at least 0.6 m apart, centred where the balls
#:   land (0.5-1.25 m from the net, at most 0.55 m from the centre line: 90 % of the games'
#:   bounces); their flanks slope by up to 0.015, as table_tilt's draw. Six bumps of 1-2 mm anywhere
#:   on the table changed the table errors by 0.5 %, six of 3-4 mm where the balls land by 2.2 %;
#: * ball_variation: radius +0.15 to +0.3 mm, mass +-0.025 to 0.033 g (within the ITTF tolerances: 2.67-2.77 g);
#: * worn_ball: restitution loss 2-4 %;
#: * buckling: a ball that buckles early (a soft or cracked shell): table onset 2-3 m/s, width
#:   1-2 m/s, loss 6-10 %; racket onset 5-8 m/s, width 4-8 m/s, loss 10-15 %. The catalogue's
#:   onsets (4-6 and 12-18 m/s, for competition speeds) lie above nearly every impact of the
#:   generator's games (normal impact speed on the table: median 2.5 m/s, 90th percentile 3.4; on
#:   the racket: median 5.5 m/s, 90th percentile 9.8);
#: * racket_logo: grip loss 35-50 %, restitution -0.03 to -0.06 (its games: :data:`SCENES`);
#: * racket_edge: rim restitution loss 12-20 %, grip loss 10-20 %; rubber_anisotropy: 6-12 % either
#:   sign;
#: * outside the catalogue: table_friction 25-35 % lower (a dusty or worn coating); air_density
#:   15-25 % lower (a hall at 1,500-2,000 m, or hot); clock_rate 0.3-0.5 % fast (a tracker's frame
#:   clock); camera_scale 0.5-1 % either way (a calibration error); spin_calibration: the record's
#:   spin 15-25 % high or low and turned by 10-15 degrees (a spin estimator's calibration);
#:   spin_unmeasured: no spin recorded at all (a tracker without spin).
DRAWS = {
    "spin_decay": lambda r: {"rate": r.uniform(0.15, 0.3), "quadratic": r.uniform(1e-4, 2e-4)},
    "air_flow": lambda r: {"wind": np.append(r.uniform(0.2, 0.4) * _direction(r), 0.0)},
    "table_tilt": lambda r: {"slope": r.uniform(0.009, 0.0125) * _direction(r), "offset": 0.0},
    "table_unevenness": lambda r: _warp(r),
    "ball_variation": lambda r: {"d_radius": r.uniform(1.5e-4, 3e-4), "d_mass": _signed(r, 2.5e-5, 3.3e-5)},
    "worn_ball": lambda r: {"loss": r.uniform(0.02, 0.04)},
    "buckling": lambda r: {"table_onset": r.uniform(2.0, 3.0), "table_width": r.uniform(1.0, 2.0),
                           "table_depth": r.uniform(0.06, 0.1), "racket_onset": r.uniform(5.0, 8.0),
                           "racket_width": r.uniform(4.0, 8.0), "racket_depth": r.uniform(0.1, 0.15)},
    "racket_logo": lambda r: {"grip_loss": r.uniform(0.35, 0.5), "d_restitution": r.uniform(-0.06, -0.03)},
    "racket_edge": lambda r: {"dead": r.uniform(0.12, 0.2), "grip_loss": r.uniform(0.1, 0.2)},
    "rubber_anisotropy": lambda r: {"anisotropy": _signed(r, 0.06, 0.12)},
    # outside the catalogue (the outside suite): what labs meet, at magnitudes the data resolve
    "table_friction": lambda r: {"d_mu": -r.uniform(0.25, 0.35)},
    "air_density": lambda r: {"d_rho": -r.uniform(0.15, 0.25)},
    "clock_rate": lambda r: {"rate": r.uniform(0.003, 0.005), "latency": 0.0},
    "camera_scale": lambda r: {"scale": _signed(r, 0.005, 0.01)},
    "spin_calibration": lambda r: {"scale": _signed(r, 0.15, 0.25),
                                   "rotation": list(np.radians(r.uniform(10.0, 15.0)) * _direction(r, 3)),
                                   "flip": 0.0},
    "spin_unmeasured": lambda r: {"fraction": 1.0},
}

#: Generator settings of the games of a case with the effect (on top of the case's own): an effect
#: confined to a small region of the racket face shows only in the contacts there.
#:
#: * racket_logo: contacts spread wider over the face (a robot hitting off-centre more often:
#:   40 % within 5 cm of the centre, 40 % at 5-8 cm, 20 % beyond; the default is 60/28/12 %), so
#:   that 1 in 15 contacts rather than 1 in 19 falls in the logo (33 of 498 against 52 of 999 in
#:   generated games): fewer cases whose held-out split holds too few of them to be significant.
SCENES = {"racket_logo": {"contact_bands": (0.4, 0.4, 0.2)}}


def draw(name: str, rng: np.random.Generator) -> dict:
    """Fixed parameter values of ``name`` for a case (:data:`DRAWS`; {} for an effect without a
    selfcheck range: the generator's ``sample`` draws it)."""
    f = DRAWS.get(name)
    return {k: np.asarray(v, np.float64).tolist() for k, v in f(rng).items()} if f else {}


# ---------------------------------------------------------------------------------------------- oracle
def oracle_scores(pb, model, names, truth: dict) -> dict:
    """Held-out scores (:func:`ttsim_jax.diagnose.candidates.score`) of the model with the true
    effects ``names`` (one name or several) at their true parameters (``truth``: the generator's
    ``truth.json`` dict), in the phases they act in."""
    names = (names,) if isinstance(names, str) else tuple(names)
    specs, consts, us = [], [], []
    for name in names:
        cls = fx.effect_class(name)
        per_session = cls.SCOPE == "session"
        specs.append(candidate_fit.Spec(name, cls, tuple(cls.PARAMS), per_session))
        consts.append(dict(start={k: np.zeros(p.shape) for k, p in cls.PARAMS.items()},
                           scale={k: np.float64(1.0) for k in cls.PARAMS}))
        if per_session:
            values = [truth["sessions"][int(s)]["effects"][name] for s in pb.sessions]
        else:
            values = [truth["effects"][name]["params"]]
        us.append({k: jnp.asarray(np.stack([np.broadcast_to(np.asarray(v[k], np.float64), p.shape) for v in values]),
                                  jnp.float32) for k, p in cls.PARAMS.items()})
    phases = tuple(p for p in pb.phases if any(p in s.phases for s in specs))
    errors, _ = candidate_fit.evaluate(model, tuple(specs), tuple(consts), tuple(us), pb, stages.GN_START, phases)
    return candidate_fit.score(pb, errors)


# ---------------------------------------------------------------------------------------------- scoring
def located_phase(cand: dict) -> str | None:
    """The phase of a candidate's largest significant held-out reduction (None: not significant)."""
    sig = [p for p, h in cand["heldout"].items() if candidate_fit.significant(p, h)]
    return max(sig, key=lambda p: cand["heldout"][p]["pct"]) if sig else None


def score(kind: str, names, candidates: list, where: dict, oracle: dict, verdict: dict | None = None) -> dict:
    """The scores of one case (module docstring).

    Arguments:
        kind: "single", "pair" or "outside"; names: the true effects.
        candidates: the diagnosis's ranked candidates (its JSON ``candidates``: name, significant,
            heldout {phase: {pct, ci95, before_rms, after_rms}}).
        where: the diagnosis's ``where`` ({phase: {"flagged": [(regime, label)], ...}}).
        oracle: :func:`oracle_scores`.
        verdict: the diagnosis's ``verdict`` (its ``level`` and ``gaps``); without it an outside
            case counts as explained when anything is significant, and is located by the flagged
            regimes alone.

    Returns:
        dict: detectable, top, rank1, both (pairs), phase, phase_right, located (outside: flagged
        phases), unexplained, found_pct, oracle_pct, shrink, spin_wrong, outcome (one word for the
        table).
    """
    out = _scores(kind, tuple(names), candidates, where, oracle, verdict)
    # of every kind: the record's spin corrected where the games recorded it true names a wrong
    # cause (a flight effect read as the spin estimator's error), beside the right one or alone
    out["spin_wrong"] = bool(verdict) and SPIN_RECORD in verdict.get("effects", []) and not set(names) & SPIN_EFFECTS
    if out["spin_wrong"]:
        out["outcome"] += ", the record's spin wrongly corrected"
    return out


def _scores(kind: str, names: tuple, candidates: list, where: dict, oracle: dict, verdict: dict | None) -> dict:
    true_phases = effect_phases(names)
    # the diagnosis's accepted effects: significant, and not redundant on top of those before them
    # (a significant fit beyond the plausible ranges stands in for something else and is not accepted)
    sig = [c for c in candidates if c["significant"] and not c.get("implausible")
           and c.get("adds", {}).get("accepted", True)]
    oracle = {p: h for p, h in oracle.items() if p in true_phases}
    detectable = any(candidate_fit.significant(p, h) for p, h in oracle.items())
    best = max(oracle, key=lambda p: oracle[p]["pct"]) if oracle else None
    ref = oracle[best]["pct"] if best else math.nan
    found = max([c["heldout"][best]["pct"] for c in sig if best in c["heldout"]], default=0.0)
    top = sig[0]["name"] if sig else None
    phase = located_phase(sig[0]) if sig else None
    from ttsim_jax.diagnose.verdict import interchangeable

    same = interchangeable(candidates)

    def true_among(c):  # the true effects among an accepted one and those reported interchangeable with it
        return ({c["name"]} | set(same.get(c["name"], ()))) & set(names)

    hit = bool(sig and true_among(sig[0]))
    out = dict(detectable=bool(detectable), top=top or "none significant", rank1=hit,
               interchangeable=hit and top not in names,
               phase=phase, phase_right=bool(phase in true_phases), unexplained=not sig,
               found_pct=float(found), oracle_pct=float(ref), oracle_phase=best,
               shrink=float(found / ref) if detectable and ref > 0 else math.nan)
    if kind == "pair":
        first, second = (true_among(c) for c in sig[:2]) if len(sig) >= 2 else (set(), set())
        out["both"] = bool(first and second and first | second == set(names))
    # located: the phases above their noise floor, or with a regime flagged
    gaps = (verdict or {}).get("gaps", [])
    located = [p for p in candidate_fit.PHASES if p in gaps or where.get(p, {}).get("flagged")]
    if kind == "control":
        # Right: nothing accepted and nothing located.
        out.update(located=located, phase=located[0] if located else None, phase_right=not located,
                   level=verdict["level"] if verdict else ("explained" if sig else "unexplained"),
                   false_alarm=bool(sig or located))
        out["outcome"] = "nothing found" if not out["false_alarm"] else \
            f"false alarm: {top or 'nothing significant'}" + (", located in " + "+".join(located) if located else "")
        return out
    if kind in OUTSIDE_KINDS:
        # Right: never "explained" (the cause is not among the candidates; "partly explained" says
        # how much is left), and the gap located in a phase the effect acts in: above its noise
        # floor, or a regime flagged in it.
        level = verdict["level"] if verdict else ("explained" if sig else "unexplained")
        # a record's spin estimator off (spin_calibration) has no candidate but the spin check's
        # correction: naming the record's spin (spin_record.NAME first among the verdict's effects) is right
        by_spin = bool(verdict) and verdict.get("effects", [None])[:1] == [SPIN_RECORD] and set(names) <= SPIN_EFFECTS
        out.update(located=located, phase=located[0] if located else None, level=level,
                   phase_right=bool(set(located) & set(true_phases)) or by_spin, rank1=by_spin,
                   wrong_explained=level == "explained" and not by_spin)
        who = SPIN_RECORD if by_spin else top
        out["outcome"] = (f"{level} by {who}" if who and level.endswith("explained") and level != "unexplained"
                          else level) + \
            (", located in " + "+".join(located) if located else ", not located")
        return out
    if not detectable:
        out["outcome"] = "undetectable: nothing found" if not sig else f"undetectable: false alarm ({top})"
    elif kind == "pair":
        out["outcome"] = "both found" if out["both"] else "one found" if out["rank1"] else "missed"
    else:
        out["outcome"] = ("found" if top in names else f"found as interchangeable with {top}") if out["rank1"] else "missed"
    return out


def summary(rows: list) -> dict:
    """Rates of a selfcheck's cases: over detectable single-effect cases rank 1, phase and median
    shrink recovered; counts of undetectable ones (and of them, nothing found); pairs; outside."""
    ok = [r for r in rows if "error" not in r]
    single = [r for r in ok if r["kind"] == "single" and r["detectable"]]
    undet = [r for r in ok if r["kind"] not in OUTSIDE_KINDS + ("control",) and not r["detectable"]]
    pairs = [r for r in ok if r["kind"] == "pair" and r["detectable"]]
    outside = [r for r in ok if r["kind"] in OUTSIDE_KINDS]
    control = [r for r in ok if r["kind"] == "control"]
    shrink = [r["shrink"] for r in single if math.isfinite(r["shrink"])]
    resolved = [r for r in outside if r.get("detectable") or not r.get("oracle_phase")]
    shares = [r["bound_share"] for r in resolved if math.isfinite(r.get("bound_share", math.nan))]

    def rate(rs, key):
        return float(np.mean([r[key] for r in rs])) if rs else math.nan

    return dict(n_single=len(single), rank1_rate=rate(single, "rank1"), phase_rate=rate(single, "phase_right"),
                n_interchangeable=sum(bool(r.get("interchangeable")) for r in single),
                median_shrink=float(np.median(shrink)) if shrink else math.nan,
                n_undetectable=len(undet), undetectable_nothing_found=sum(r["unexplained"] for r in undet),
                n_pairs=len(pairs), pair_rank1_rate=rate(pairs, "rank1"), pair_both_rate=rate(pairs, "both"),
                outside_unexplained=[bool(r["unexplained"]) for r in outside],
                outside_located=[bool(r["phase_right"]) for r in outside],
                n_outside=len(outside), outside_wrong_explained=sum(bool(r.get("wrong_explained")) for r in outside),
                # located and bounded only where the oracle resolves the effect (or, for an effect on
                # the record, which has none, always): an effect the data cannot resolve leaves no gap
                n_outside_resolved=len(resolved), outside_located_rate=rate(resolved, "phase_right"),
                outside_bound_share_median=float(np.median(shares)) if shares else math.nan,
                outside_bound_reaching=sum(v >= 0.7 for v in shares), n_outside_bounded=len(shares),
                # against the oracle without the parts no held-out method resolves (UNRESOLVED)
                outside_bound_reaching_resolved=sum(
                    max(r["bound_share"], r.get("bound_share_steady", math.nan)) >= 0.7 for r in resolved
                    if math.isfinite(r.get("bound_share", math.nan))),
                outside_bound_named_rate=rate(resolved, "bound_named") if all("bound_named" in r for r in resolved) else math.nan,
                n_control=len(control), control_false_alarms=sum(bool(r["false_alarm"]) for r in control),
                spin_wrong=sum(bool(r.get("spin_wrong")) for r in ok),
                control_bound_significant=sorted({p for r in control for p in r.get("bound_significant", ())}),
                errors=len(rows) - len(ok))


# ---------------------------------------------------------------------------------------------- cases
def cases(names=QUICK, pairs=(), outside: str | None = OUTSIDE, control: bool = True) -> list:
    """[(kind, names)] of a selfcheck: every single effect, then the pairs, the outside one and the
    effect-free control."""
    return ([("single", (n,)) for n in names] + [("pair", tuple(p)) for p in pairs] +
            ([("outside", (outside,))] if outside else []) + ([("control", ())] if control else []))


def case_inputs(names, seed: int, present=()) -> tuple[dict, dict]:
    """The generator's inputs of a case: ({effect: parameter values} of the drawn effects (:func:`draw`,
    seeded by ``seed``), of the ``present`` ones at neutral and of the position noise; the
    :data:`SCENES` settings of its effects)."""
    rng = np.random.default_rng(seed)
    params = {n: draw(n, rng) for n in names}
    for n in present:
        params.setdefault(n, {k: np.broadcast_to(p.neutral, p.shape).tolist()
                              for k, p in fx.effect_class(n).PARAMS.items()})
    params["position_noise"] = {"std": list(NOISE)}
    scene = {k: v for n in names for k, v in SCENES.get(n, {}).items()}
    return params, scene


def run_case(kind: str, names, seed: int, settings, games: int = GAMES["quick"], present=()) -> dict:
    """One case (module docstring): generate, diagnose, oracle, :func:`score`.

    ``present``: further effects switched on in the generator at their neutral values (exactly no
    effect): cases with the same effects present share the generator's compiled programs."""
    from ttsim_jax import load_model
    from ttsim_jax import reality
    from ttsim_jax.data.errors import DataError
    from ttsim_jax.diagnose.diagnosis import diagnose

    names = tuple(names)
    params, scene = case_inputs(names, seed, present)
    on = [n for n in fx.names() if n in params]
    gen, error = None, ""
    for k in range(TRIES):
        cfg = reality.make_config(games=games, seed=seed + k, effects=on, effect_params=params, max_flight_time=1.5,
                                  truth_observations=False, **scene)
        try:
            gen = reality.generate(cfg, progress=False)
            break
        except DataError as e:  # the generator refuses its own data for some seeds
            error = str(e)
    row = dict(kind=kind, effects=list(names), seed=int(seed))
    if gen is None:
        return dict(row, error=f"generator refused {TRIES} seeds: {error}")
    ds = gen.dataset
    if kind in OUTSIDE_KINDS:
        kept = tuple(n for n in candidate_fit.candidate_names() if n not in names)
        settings = dataclasses.replace(settings, effects=kept)
    if kind in ("outside_log", "outside_oneway"):
        ds = as_tracker_log(ds, one_way=kind == "outside_oneway")
        row["segments"] = dict(labelled=len(gen.dataset.segments["segment_id"]), log=len(ds.segments["segment_id"]))
    model = load_model("conti2026", dtype=jnp.float32)
    keep = {}
    out = diagnose(ds, model, settings, keep=keep)
    # an effect on the record (a tracker's clock) has no simulator oracle: its case is scored on the
    # verdict and the located phase alone
    simulated = [n for n in names if fx.effect_class(n).WHERE == "simulator"]
    oracle = oracle_scores(keep["problem"], model, simulated, gen.truth) if simulated else {}
    row.update(bound_score(names, out.bound, oracle))
    unresolved = {n: UNRESOLVED[n] for n in simulated if n in UNRESOLVED}
    if kind in OUTSIDE_KINDS and unresolved and oracle:
        # the oracle without the parts that vary faster than the segments sample them
        steady = oracle_scores(keep["problem"], model, simulated, neutral_parts(gen.truth, unresolved))
        p = row["bound_phase"]
        if p in steady and steady[p]["pct"] > 0:
            row.update(oracle_steady_pct=float(steady[p]["pct"]), bound_share_steady=row["bound_pct"] / steady[p]["pct"])
    row["bound_significant"] = [p for p, b in (out.bound or {}).items()
                                if isinstance(b, dict) and b.get("heldout", {}).get("significant")]
    # the true effects' detection limits on these data (those among the candidates), beside the oracle
    row["limits"] = {n: out.limits["candidates"][n] for n in names if n in out.limits.get("candidates", {})}
    row["spin_findings"] = list(out.record.get("spin_check", {}).get("findings", []))
    row["spin_sources"] = out.spin_sources or {}
    row.update(score(kind, names, out.candidates, out.where, oracle, out.verdict.to_json()), counts=out.counts,
               verdict=out.verdict.text, floor={p: f for p, f in out.floor.items() if isinstance(f, dict)},
               seconds=out.seconds, truth={n: gen.truth["effects"].get(n, {}).get("params", params[n]) for n in names},
               candidates=candidate_digest(out.candidates))
    return row


def candidate_digest(candidates: list) -> list:
    """What a case keeps of the diagnosis's ranked candidates (its JSON ``candidates``): each one's
    name, significance, held-out reduction and interval per phase, and, where the forward selection
    ran, whether it was accepted, on top of which effects and what it added there; enough to see
    why a true effect was not among the accepted ones without rerunning the case."""
    def phases(heldout):
        return {p: dict(pct=h["pct"], ci95=h["ci95"]) for p, h in heldout.items()}

    out = []
    for c in candidates:
        row = dict(name=c["name"], significant=bool(c["significant"]), heldout=phases(c["heldout"]),
                   implausible=list(c.get("implausible") or []))
        if "adds" in c:
            a = c["adds"]
            row["adds"] = dict(accepted=bool(a.get("accepted", True)), on_top_of=list(a.get("on_top_of", [])),
                               heldout=phases(a.get("heldout", {})),
                               interchangeable_with=list(a.get("interchangeable_with", [])))
        out.append(row)
    return out


class ResumeError(UserError, ValueError):
    """A stored case of ``--resume`` that does not belong to the run asked for (message names it)."""


def _case_key(kind: str, names, seed: int, games: int, settings, present) -> dict:
    """What a case's result depends on, besides the code: stored with it, compared on resume."""
    from ttsim_jax.results import jsonable

    params, scene = case_inputs(names, seed, present)
    return jsonable(dict(kind=kind, effects=list(names), seed=int(seed), games=int(games), present=list(present),
                         settings=repr(settings), params=params, scene=scene))


def neutral_parts(truth: dict, parts: dict) -> dict:
    """A copy of the generator's ``truth`` with the parameters ``parts`` ({effect: names}) at their
    neutral values, in every session and in the dataset-wide parameters."""
    import copy

    out = copy.deepcopy(truth)
    blocks = [s.get("effects", {}) for s in out.get("sessions", [])] + \
        [{n: e.get("params", {}) for n, e in out.get("effects", {}).items()}]
    for effects in blocks:
        for name, keys in parts.items():
            if name in effects:
                cls = fx.effect_class(name)
                for k in keys:
                    effects[name][k] = np.broadcast_to(cls.PARAMS[k].neutral, cls.PARAMS[k].shape).tolist()
    return out


def release_compiled_if_crowded(share: float = 0.5) -> bool:
    """Drops JAX's compiled programs (:func:`jax.clear_caches`) when this process's memory maps
    exceed ``share`` of the kernel's limit (``vm.max_map_count``); returns whether it did.

    Every compiled CPU program maps its code sections; a selfcheck compiles hundreds per case, and
    a run of a dozen cases in one process reached the default limit of 65,530 maps, where LLVM
    fails with "Unable to allocate section memory" (free memory notwithstanding). Dropping the
    programs unmaps them; the next case compiles what it needs again. Off Linux (no /proc), nothing."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps") as f:
            used = sum(1 for _ in f)
    except (OSError, ValueError):
        return False
    if used <= share * limit:
        return False
    import gc

    import jax

    jax.clear_caches()
    gc.collect()
    return True


def case_path(store, i: int, names) -> Path:
    """The file of case ``i`` in a run folder's ``cases/``."""
    return Path(store) / "cases" / f"{i:02d}_{'+'.join(names) or 'control'}.json"


def stored_cases(store) -> list:
    """The case files a run folder holds (sorted)."""
    return sorted((Path(store) / "cases").glob("*.json"))


def _load_case(path: Path, key: dict) -> dict:
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError) as e:  # unreadable, not UTF-8 text, not JSON
        raise ResumeError(f"{path}: not a readable case file ({e}); remove it to rerun that case") from None
    if not isinstance(stored, dict) or not isinstance(stored.get("row"), dict):
        raise ResumeError(f"{path}: no 'row' in the case file; remove it to rerun that case")
    got = stored.get("key", {})
    for field in key:
        if got.get(field) != key[field]:
            raise ResumeError(f"{path}: stored with {field} = {got.get(field)!r}, this run has {key[field]!r}; "
                              "resume with the same options, or start over with --force")
    return stored["row"]


def selfcheck(plan=None, settings=None, seed: int = 0, progress: Callable | None = None,
              games: int = GAMES["quick"], store=None, resume: bool = False, present=None) -> dict:
    """Every case of ``plan`` (:func:`cases`; default the quick one) and the :func:`summary`.

    Arguments:
        present: the effects switched on in every case's generator (:func:`run_case`; default every
            effect of ``plan``). Those at neutral change the compiled programs, hence the float32
            rounding (two games of a pair differed by up to 51 µm), not the physics: a case
            reproduces another run's dataset bit for bit only with that run's ``present``.
        store: a run folder: each finished case is written at once, atomically, to
            ``store/cases/NN_<effects>.json`` (:func:`case_path`) with what it depends on.
        resume: take the cases already in ``store`` instead of running them again (their options
            must be this run's: :class:`ResumeError` names the file and the option otherwise).

    Returns:
        {"cases": rows, "summary", "seconds" (wall, this call), "cpu_seconds", "resumed" (cases
        taken from ``store``)}; each row's ``wall_seconds`` is its case's own wall time.
    """
    from ttsim_jax.diagnose.diagnosis import Settings
    from ttsim_jax.results import jsonable
    from ttsim_jax.files.atomic import atomic_write

    settings = settings or Settings.quick(max_segments=SEGMENTS["quick"])
    plan = plan if plan is not None else cases()
    t0, c0 = time.perf_counter(), time.process_time()
    present = tuple(sorted(set(present) if present is not None else {n for _, names in plan for n in names}))
    rows, resumed = [], 0
    for i, (kind, names) in enumerate(plan):
        case_seed = seed + 100 * i
        key = _case_key(kind, names, case_seed, games, settings, present)
        path = case_path(store, i, names) if store is not None else None
        if resume and path is not None and path.exists():
            rows.append(_load_case(path, key))
            resumed += 1
        else:
            start = time.perf_counter()
            row = run_case(kind, names, case_seed, settings, games, present)
            row["wall_seconds"] = time.perf_counter() - start
            rows.append(row)
            if path is not None:
                atomic_write(path, json.dumps(jsonable(dict(key=key, row=row)), indent=1).encode())
            release_compiled_if_crowded()
        if progress:
            progress("+".join(names) or "control")
    return dict(cases=rows, summary=summary(rows), seconds=time.perf_counter() - t0,
                cpu_seconds=time.process_time() - c0, resumed=resumed)
