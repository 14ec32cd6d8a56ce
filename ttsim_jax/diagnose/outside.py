"""The selfcheck's suite outside the catalogue (``ttsim diagnose selfcheck --outside``): its cases,
how their games reach the diagnosis (labelled, or as a tracker's raw log), and how far the
model-free bound (:mod:`ttsim_jax.diagnose.bound`) gets on them. Scoring and running the cases is
:mod:`ttsim_jax.diagnose.selfcheck`'s.
"""

from __future__ import annotations

import math

import numpy as np

from ttsim_jax import effects as fx
from ttsim_jax.diagnose import candidates as candidate_fit

#: Kinds of the cases outside the catalogue: how the generated games reach the diagnosis.
OUTSIDE_KINDS = ("outside", "outside_log", "outside_oneway")
#: The outside suite: each effect generated and withheld from the candidates, in every phase, as
#: labelled games and as a tracker's raw logs, in both directions and in one; the effects on the
#: record (a tracker's clock running fast, a camera's scale, a spin estimator's scale and axis) have
#: no candidate at all (the last only the record section's spin check). The last cases are controls:
#: the model's own physics and the record's noise, once recorded without any spin (the flights then
#: fly their latent spin), right when nothing is found and no phase stands above its noise floor.
OUTSIDE_PLAN = (
    ("outside", ("racket_edge",)),
    ("outside", ("table_tilt",)),
    ("outside", ("spin_decay",)),
    ("outside", ("worn_ball",)),
    ("outside_log", ("buckling",)),
    ("outside_log", ("table_unevenness",)),
    ("outside_log", ("air_flow",)),
    ("outside_oneway", ("air_flow",)),
    ("outside_oneway", ("spin_decay",)),
    ("outside_log", ("table_friction",)),
    ("outside", ("clock_rate",)),
    ("outside_oneway", ("air_density",)),
    ("outside", ("camera_scale",)),
    ("outside", ("spin_calibration",)),
    ("control", ("spin_unmeasured",)),
    ("control", ()),
)

def effect_phases(names) -> tuple:
    """The phases the effects ``names`` act in; an effect on the record (a clock, a camera's scale)
    distorts every measured position or time, hence every phase."""
    out = set()
    for n in names:
        cls = fx.effect_class(n)
        out.update(candidate_fit.phases_of(cls) if cls.WHERE == "simulator" else candidate_fit.PHASES)
    return tuple(p for p in candidate_fit.PHASES if p in out)


#: Per effect, words of the model-free correction's terms (:mod:`ttsim_jax.diagnose.bound`) that name
#: the variables it acts through: a case's bound *names the right variables* when its strongest
#: term in the effect's phase holds one of them.
TERMS = {
    "spin_decay": ("lift", "ω", "spin"),
    "air_flow": ("wind", "fixed direction", "horizontal", "per session"),
    "air_density": ("drag", "lift"),
    "table_tilt": ("normal", "contact position"),
    "table_unevenness": ("normal", "contact position"),
    "table_friction": ("slip", "tangential", "r·ω"),
    "ball_variation": ("drag", "normal"),
    "worn_ball": ("normal",),
    "buckling": ("normal", "speed"),
    "racket_logo": ("contact point", "|d|"),
    "racket_edge": ("contact point", "|d|"),
    "rubber_anisotropy": ("tangential",),
    "clock_rate": ("gravity or clock", "drag"),
    "camera_scale": ("gravity or clock", "drag"),
    "spin_calibration": ("lift", "ω", "spin", "r·ω"),
}


def bound_score(names, bound: dict, oracle: dict) -> dict:
    """How far the model-free correction (the diagnosis's ``bound``) gets in the effects' phase: its
    held-out reduction there against the oracle's (``bound_share``; NaN without an oracle; 0 where
    the reduction is not significant, ``bound_pct_raw`` and ``bound_share_raw`` keep it), its
    strongest terms, and whether the first names a variable of :data:`TERMS` (``bound_named``).

    The phase is the oracle's best one; without an oracle (an effect on the record), the phase of the
    bound's largest significant reduction."""
    phases = effect_phases(names)
    ok = {p: b for p, b in (bound or {}).items() if isinstance(b, dict) and "heldout" in b and p in phases}
    if not ok:
        return dict(bound_phase=None, bound_pct=math.nan, bound_share=math.nan, bound_pct_raw=math.nan,
                    bound_share_raw=math.nan, bound_terms=[], bound_named=False)
    ranked = {p: h for p, h in oracle.items() if p in ok}
    if ranked:
        p = max(ranked, key=lambda q: ranked[q]["pct"])
    else:
        p = max(ok, key=lambda q: ok[q]["heldout"]["pct"] if ok[q]["heldout"].get("significant") else -math.inf)
    b = ok[p]
    pct = float(b["heldout"]["pct"]) if b["heldout"].get("significant") else 0.0
    terms = [t["name"] for t in b.get("terms", [])]
    words = [w for n in names for w in TERMS.get(n, ())]
    raw = float(b["heldout"]["pct"])
    ref = oracle[p]["pct"] if p in oracle and oracle[p]["pct"] > 0 else math.nan
    return dict(bound_phase=p, bound_pct=pct, bound_share=float(pct / ref), bound_pct_raw=raw,
                bound_share_raw=float(raw / ref),
                bound_terms=terms, bound_named=bool(terms and any(w in terms[0] for w in words)))


def outside_cases(plan=OUTSIDE_PLAN, candidates=None) -> list:
    """[(kind, names)] of the outside suite (:data:`OUTSIDE_PLAN`), without the cases of effects
    the catalogue does not hold (an older plan run with a newer catalogue)."""
    return [(k, tuple(n)) for k, n in plan if all(x in fx.CATALOGUE for x in n)]


def as_tracker_log(ds, *, one_way: bool = False):
    """``ds`` as a tracker without labels would hand it over: its observations written as a
    multi-throw CSV log (:func:`ttsim_jax.data.write_csv`, no events, no racket states) and imported
    through :func:`ttsim_jax.data.read_csv` (contacts detected, sessions split at pauses and jumps).

    Arguments:
        ds: a labelled dataset (generated games).
        one_way: keep only the flight segments that travel towards +x (every throw the same way, as
            from a launcher): the others are not written, as a tracker that did not follow them.

    Returns:
        The imported dataset.
    """
    import tempfile

    from ttsim_jax.data import read_csv, write_csv

    rows = None
    if one_way:
        seg_of = ds.observations["segment_id"]
        x = ds.positions[:, 0]
        towards = {}
        for sid in np.unique(seg_of[seg_of >= 0]):
            k = np.flatnonzero(seg_of == sid)
            towards[int(sid)] = x[k[-1]] > x[k[0]]
        rows = np.array([towards.get(int(s), False) for s in seg_of], bool)
    with tempfile.TemporaryDirectory() as tmp:
        return read_csv(write_csv(ds, tmp, rows=rows))
