"""The diagnosis's verdict: how much of each phase's gap the accepted effects close, what is left
and where it lies, in numbers and in one paragraph of text (:func:`verdict`); and which fitted
parameters no lab meets (:func:`implausible`).

:func:`ttsim_jax.diagnose.diagnosis.diagnose` gathers what the verdict reads (``where``,
``dependence``, ``candidates``, ``floor``, ``bound``, ``before_after``) and calls it last.
"""

from __future__ import annotations

import dataclasses
import math

from ttsim_jax.diagnose.candidates import MIN_GAIN
from ttsim_jax.diagnose.spin_record import NAME as NAME_SPIN, contradicted, text as correction_text
from ttsim_jax.diagnose.specs import PHASES
from ttsim_jax.diagnose.where import shown


#: Share of the sessions beyond which a per-session effect's implausible fits reject it (a session
#: of few items can take a wild value while the effect holds elsewhere: on the bundled games, one
#: of three sessions fitted a single gust standing for several).
IMPLAUSIBLE_SESSIONS = 0.5


def implausible(params: dict) -> list[str]:
    """What in a candidate's fitted parameters lies outside the catalogue's plausible ranges
    (:meth:`~ttsim_jax.effects.base.Effect.implausible`), one line each; empty when all is plausible.

    Arguments:
        params: ``{effect: {param: value}}``, per-session effects ``{effect: {session: {param:
            value}}}`` (a candidate's ``params``). A per-session effect counts as implausible when
            more than :data:`IMPLAUSIBLE_SESSIONS` of its sessions are.

    Returns:
        Lines such as ``"table_tilt.slope[0] = 0.0164 (plausible -0.0131 to 0.0131)"``.
    """
    from ttsim_jax import effects as fx

    def line(name, b, where=""):
        idx = "".join(f"[{i}]" for i in b["index"])
        unit = "" if b["unit"] == "1" else f" {b['unit']}"
        return f"{name}.{b['param']}{idx} = {b['value']:.4g}{unit}{where} (plausible {b['low']:.4g} to {b['high']:.4g})"

    out = []
    for name, values in params.items():
        cls = fx.effect_class(name)
        if values and all(isinstance(k, int) for k in values):
            found = [cls.implausible(v) for v in values.values()]
            bad = [f for f in found if f]
            if len(bad) > IMPLAUSIBLE_SESSIONS * len(found):
                worst = max((b for f in bad for b in f), key=lambda b: max(b["low"] - b["value"], b["value"] - b["high"]))
                out.append(line(name, worst, f" in {len(bad)} of {len(found)} sessions (the furthest)"))
        else:
            out += [line(name, b) for b in cls.implausible(values)]
    return out


def _where_text(out: dict) -> list:
    lines = []
    for p in open_gaps(out):
        f = out["floor"][p]
        lines.append(f"{p}: error {shown(p, f['error'])}, {f['error'] / f['floor']:.1f} x its noise floor "
                     f"{shown(p, f['floor'])}")
    for p, w in out["where"].items():
        for name, label in w["flagged"]:
            row = next(r for r in w["regimes"][name] if r["label"] == label)
            lines.append(f"{p}: {name} {label} ({row['ratio']:.2f} x the phase's mean error)")
    for p, deps in out["dependence"].items():
        for d in deps[:2]:
            lines.append(f"{p}: {d['error']} depends on {d['quantity']} (Spearman rho {d['rho']:+.2f})")
    return lines


def interchangeable(candidates: list) -> dict:
    """{accepted effect: [candidates reported interchangeable with it]} from the ranked candidates'
    JSON (their ``adds``, :func:`~ttsim_jax.diagnose.diagnosis.select`)."""
    same = {}
    for c in candidates:
        for n in c.get("adds", {}).get("interchangeable_with", []):
            same.setdefault(n, []).append(c["name"])
    return same


#: Share of a phase's removable gap that the accepted effects must close on held-out data, in every
#: phase they act in, for the verdict "explained" (below it: "partly explained").
EXPLAINED_SHARE = 0.7


def gap_shares(out: dict) -> dict:
    """How much of each phase's removable gap the accepted effects close on the held-out items.

    The removable gap is the model's error above the noise floor (``out["floor"]``,
    :mod:`ttsim_jax.diagnose.floor`), counted in the mean square, where independent parts add:
    share = (before^2 - after^2) / (before^2 - floor^2), with before and after the held-out RMS
    errors of the model without and with the accepted effects (``out["before_after"]``). The 95 %
    interval maps that of the held-out reduction (the floor's own uncertainty is not in it).

    Arguments:
        out: the diagnosis's dict with ``before_after`` and ``floor``.

    Returns:
        {phase: {"share", "ci95", "before", "after", "floor", "removable", "floor_known"}}, the shares as
        fractions; a phase with no removable gap on the held-out items (its error at the floor) gets
        ``share`` None, as does one whose removable gap is below the phase's resolution
        (:data:`~ttsim_jax.diagnose.candidates.MIN_GAIN`).
    """
    res = {}
    for p, ba in out.get("before_after", {}).items():
        h = ba.get("heldout", {})
        b, a = h.get("before_rms"), h.get("after_rms")
        if b is None or a is None or not (math.isfinite(b) and math.isfinite(a)) or b <= 0:
            continue
        fl = out.get("floor", {}).get(p)
        f = fl["floor"] if isinstance(fl, dict) else 0.0
        room = b * b - f * f
        entry = dict(before=b, after=a, floor=f, removable=math.sqrt(max(room, 0.0)), share=None, ci95=None,
                     floor_known=isinstance(fl, dict))
        if entry["removable"] >= MIN_GAIN[p]:
            def share(pct):
                return (b * b - (b * (1.0 - pct / 100.0)) ** 2) / room

            entry.update(share=share(h["pct"]), ci95=[share(h["ci95"][0]), share(h["ci95"][1])])
        res[p] = entry
    return res


#: How far the noise floor itself may be off, as a share of it, beyond its bootstrap interval: the
#: floor leaves out the contact position's noise and the contact-state estimator's own bias
#: (:mod:`ttsim_jax.diagnose.floor`). Measured as the error over the floor of the phases that a
#: case's effect does not act in (there the diagnosed model is the true one), over the selfcheck's
#: singles, outside cases and control (``benchmarks/results/selfcheck_full_rerun``,
#: ``selfcheck_outside``): flight 0.994-1.009, table 0.981-1.034, racket 0.976-1.054.
FLOOR_SYSTEMATIC = {"flight": 0.02, "table": 0.06, "racket": 0.06}


def open_gaps(out: dict) -> list:
    """The phases whose error stands significantly above their noise floor (the error's 95 %
    interval wholly above the floor's, widened by the floor's own systematic uncertainty
    :data:`FLOOR_SYSTEMATIC`) by more than the phase's resolution (a removable gap of at least
    :data:`~ttsim_jax.diagnose.candidates.MIN_GAIN`), in :data:`~ttsim_jax.diagnose.specs.PHASES`
    order. A phase at its floor is no gap: it is not "where the gap lies", and the verdict asks
    nothing of it."""
    fl = out.get("floor", {})
    return [p for p in PHASES if isinstance(fl.get(p), dict)
            and fl[p]["error_ci95"][0] > fl[p]["floor_ci95"][1] * (1.0 + FLOOR_SYSTEMATIC[p])
            and fl[p]["removable"] >= MIN_GAIN[p]]


def _bound_text(out: dict) -> tuple[list, str]:
    """The verdict's sentences on the phases where a model-free correction (``out["bound"]``,
    :mod:`ttsim_jax.diagnose.bound`) lowers the held-out error significantly more than the accepted
    effects do (the lower end of its interval above their reduction): there the catalogue misses
    something, and the correction's strongest terms name the variables that carry it. Returns (those
    phases, the text)."""
    lines, phases = [], []
    for p, b in out.get("bound", {}).items():
        h = b.get("heldout") if isinstance(b, dict) else None
        if not h or not h.get("significant"):
            continue
        acc = out.get("before_after", {}).get(p, {}).get("heldout", {}).get("pct", 0.0)
        if h["ci95"][0] > max(acc, 0.0):
            phases.append(p)
            lines.append(f"In the {p} phase the catalogue closes less than a model-free correction does "
                         f"({max(acc, 0.0):.1f} % against {h['pct']:.1f} %, 95 % interval {h['ci95'][0]:.1f} to "
                         f"{h['ci95'][1]:.1f} %): the gap there is carried by " +
                         ", ".join(f"{t['name']} ({100 * t['share']:.0f} %)" for t in b.get("terms", [])) + ".")
    return phases, (" " + " ".join(lines)) if lines else ""


def _alike(out: dict, names: list) -> str:
    """The verdict's sentences on the groups of indistinguishable candidates
    (:func:`ttsim_jax.diagnose.ambiguity.indistinguishable`) that hold any of ``names``."""
    text = ""
    for g in out.get("indistinguishable", []):
        if set(g["names"]) & set(names):
            text += (f" {', '.join(g['names'][:-1])} and {g['names'][-1]} are indistinguishable on these data (their effects "
                     f"on the errors alike, cosine {g['cosine']:.2f}): the data cannot name one over the other; "
                     f"{g['separate']} would tell them apart.")
    return text


def spin_findings(out: dict) -> list:
    """What the record section's spin check (:func:`ttsim_jax.diagnose.residuals.spin_check`) found
    off with the record's measured spin: [] when nothing, or when it did not run."""
    return list(out.get("record", {}).get("spin_check", {}).get("findings", []))


def spin_corrected(out: dict) -> bool:
    """Whether the spin check's correction of the record's spin was accepted
    (:mod:`ttsim_jax.diagnose.spin_record`): the later stages then worked on the corrected spin."""
    return bool(out.get("spin_correction", {}).get("accepted"))


def spin_doubted(out: dict) -> bool:
    """Whether the spin check found the record's spin off and nothing since cleared it: its
    correction neither accepted nor contradicted by the contacts
    (:func:`~ttsim_jax.diagnose.spin_record.contradicted`). Then every candidate was fitted to a
    spin that may be wrong, and the verdict says "partly" at most."""
    return bool(spin_findings(out)) and not spin_corrected(out) and not contradicted(out.get("spin_correction"))


def _spin_text(out: dict) -> str:
    found = spin_findings(out)
    if not found:
        return ""
    lead = " The record's measured spin disagrees with its flights (spin check: " + "; ".join(found) + ")."
    if spin_corrected(out) or contradicted(out.get("spin_correction")):
        return lead + correction_text(out["spin_correction"])
    return (lead + correction_text(out.get("spin_correction", {})) + " Every candidate was fitted with that spin, so correct the "
            "record's spin (or run with --spin latent) before reading them as physics.")


def limits_text(out: dict, left_out=()) -> str:
    """The verdict's sentence on what these data could have shown (``out["limits"]``,
    :mod:`ttsim_jax.diagnose.limits`): each candidate's smallest significant effect in its phase
    most sensitive to it, in its own parameters and as a share of that phase's error; "" without
    limits. ``left_out``: candidates not to name (those found)."""
    from ttsim_jax.diagnose.limits import MAX_SIZE, describe

    seen, blind = [], []
    for name, per in out.get("limits", {}).get("candidates", {}).items():
        if name in left_out or not per:
            continue
        p, e = min(per.items(), key=lambda kv: math.inf if kv[1]["size"] is None else kv[1]["share_pct"])
        if e["size"] is not None:
            seen.append(f"{describe(name, e)} ({p}: {e['share_pct']:.2g} % of its error)")
        else:
            blind.append(name)
    text = ""
    if seen:
        text += " These data would have shown, at least: " + "; ".join(seen) + "; none of these is there."
    if blind:
        text += (f" They could not have shown {', '.join(blind)} (not within {MAX_SIZE:g} x their typical sizes, "
                 "in the regimes these data cover).")
    return text


@dataclasses.dataclass(frozen=True)
class Verdict:
    """The diagnosis's verdict (:func:`verdict`).

    Attributes:
        level: ``"explained"``, ``"partly explained"``, ``"unexplained"`` or ``"no gap"``.
        text: one paragraph, as the report and ``ttsim diagnose`` print it.
        effects: the accepted effects by rank (the record's spin first where it was corrected);
            redundant: those significant alone that add nothing on top of them; implausible: those
            significant alone whose fit needs implausible parameters.
        shares: per phase, the share of the removable gap the accepted effects close
            (:func:`gap_shares`); gaps: the phases with a gap above the noise floor
            (:func:`open_gaps`); open: those no accepted effect acts in; where: the located
            regimes, one line each.
    """

    level: str
    text: str
    effects: list
    redundant: list
    implausible: list
    shares: dict
    gaps: list
    open: list
    where: list

    @property
    def explained(self) -> bool:
        """Whether the accepted effects explain the gap."""
        return self.level == "explained"

    def to_json(self) -> dict:
        """The verdict as the JSON report holds it."""
        return dict(dataclasses.asdict(self), explained=self.explained)


def verdict(out: dict, significant: list, redundant: list = (), beyond: list = ()) -> Verdict:
    """The verdict: how much of the gap the accepted effects explain, and what is left.

    * *explained*: the accepted effects (:func:`~ttsim_jax.diagnose.diagnosis.select`) close at least :data:`EXPLAINED_SHARE` of
      the removable gap (:func:`gap_shares`) on held-out data in every phase they act in whose error
      stands above its floor (:func:`open_gaps`), and in no phase does a model-free correction
      (``out["bound"]``) do significantly better;
    * *partly explained*: they are significant but close less somewhere: the text says how much
      each phase's gap shrinks and how much is left, and where the rest lies; or they close it, but
      one of them changes the errors only as a reading that needs no candidate does
      (``out["reads_as"]``, :func:`~ttsim_jax.diagnose.ambiguity.reads_as`: buckling fitted with
      its onset below the impacts is a restitution change at every speed), so the data show the
      change and not its cause; or the record's measured spin disagrees with its flights and
      nothing cleared it (:func:`spin_doubted`), so the candidates may have been fitted to a wrong spin;
    * *unexplained*: no candidate with plausible parameters is significant.

    Phases with a gap above their floor that no accepted effect acts in are named in every case.

    Arguments:
        out: the diagnosis's dict so far (``where``, ``dependence``, ``candidates``, ``floor``,
            ``before_after``).
        significant: the accepted effects; ``redundant``: those significant alone that add nothing
            on top of them; ``beyond``: those significant alone whose fit needs implausible
            parameters (never accepted).

    Returns:
        A :class:`Verdict`.
    """
    where = _where_text(out)

    def part(c):
        p = max(c.heldout, key=lambda k: c.heldout[k]["pct"])
        h = c.heldout[p]
        return (f"{c.spec.name} ({p}: held-out RMS error {h['pct']:.1f} % lower, 95 % interval "
                f"{h['ci95'][0]:.1f} to {h['ci95'][1]:.1f} %)")

    def gap(p, g):
        if not g.get("floor_known", True):  # e.g. states measured directly: no positions to read a noise from
            return (f"the {p} gap (error {shown(p, g['before'])} on held-out data; its noise floor is not known, so "
                    "all of it is counted as removable)")
        return (f"the {p} gap (error {shown(p, g['before'])} on held-out data, noise floor {shown(p, g['floor'])}, "
                f"removable {shown(p, g['removable'])})")

    rejected = ""
    if beyond:
        rejected = (" Not accepted as causes, because their fits need parameters that no lab meets (they stand in for "
                    "something the catalogue lacks): " + "; ".join(
                        part(c) + ": " + ", ".join(implausible(c.params)) for c in beyond) + ".")
    shares = gap_shares(out) if significant else {}
    acted = {p for c in significant for p in c.heldout}
    gaps = open_gaps(out)
    untouched = [p for p in gaps if p not in acted]
    rest = ""
    if untouched:
        fl = out["floor"]
        rest = " Not addressed by any accepted effect: " + "; ".join(
            f"the {p} gap (error {shown(p, fl[p]['error'])}, noise floor {shown(p, fl[p]['floor'])})"
            for p in untouched) + "."
    names = dict(effects=[c.spec.name for c in significant], redundant=[c.spec.name for c in redundant],
                 implausible=[c.spec.name for c in beyond], shares=shares, gaps=gaps, open=untouched, where=where)
    if significant:
        # the shares are of the before/after fit (out["combined"]): name the effects it holds
        held = list(out.get("combined", {}).get("params") or [c.spec.name for c in significant])
        who = " + ".join(held)
        # a phase whose error does not stand above its floor has nothing to explain: no share is asked there
        short = [p for p, g in shares.items() if g["share"] is not None and g["share"] < EXPLAINED_SHARE
                 and (p in gaps or not isinstance(out.get("floor", {}).get(p), dict))]
        more, beyond_catalogue = _bound_text(out)
        readings = {c.spec.name: out.get("reads_as", {}).get(c.spec.name) for c in significant}
        readings = {n: r for n, r in readings.items() if r}
        level = ("partly explained" if short or untouched or more or readings or
                 spin_doubted(out) else "explained")
        closes = []
        for p, g in shares.items():
            if g["share"] is None:
                closes.append(f"{gap(p, g)}: no gap above the noise floor beyond the phase's resolution")
                continue
            pct, lo, hi = (100.0 * min(v, 1.0) for v in (g["share"], *g["ci95"]))
            closes.append(f"{who} close{'s' if len(held) == 1 else ''} {pct:.0f} % (95 % interval {lo:.0f} "
                          f"to {hi:.0f} %) of {gap(p, g)}" + (f", {100.0 - pct:.0f} % is left" if p in short else ""))
        text = ("Explained by: " if level == "explained" else "Partly explained by: ") + (
            "the record's measured spin (corrected: below); " if spin_corrected(out) else "") + "; ".join(
            part(c) for c in significant) + "."
        if closes:
            text += " On held-out data " + "; ".join(closes) + "."
        if short:
            located = [w for w in where if w.split(":")[0] in short]
            text += (" What is left lies in: " + "; ".join(located) + "." if located else
                     " What is left is not located in any regime.")
        text += _alike(out, [c.spec.name for c in significant])
        for n, found in readings.items():
            for r in found:
                text += (f" What {n} changes on these data is {r['text']} (cosine {r['cosine']:.2f}): the data show "
                         f"that change, not what names {n}; {r['separate']} would tell them apart.")
        for n, others in interchangeable(out.get("candidates", [])).items():
            text += (f" {n} and {', '.join(others)} are interchangeable on these data: each adds nothing significant "
                     "on top of the other.")
        if redundant:
            text += (" Significant alone but adding nothing significant on top of those: " +
                     "; ".join(part(c) for c in redundant) + ".")
        if spin_corrected(out):
            names["effects"] = [NAME_SPIN] + names["effects"]
        return Verdict(**names, level=level, text=text + rest + rejected + beyond_catalogue + _spin_text(out))
    if spin_corrected(out):
        # the record's spin was the one thing found: explained where nothing is left above a floor
        bound_phases, bound_text = _bound_text(out)
        level = "partly explained" if gaps or bound_phases else "explained"
        text = (("Explained by: " if level == "explained" else "Partly explained by: ") + "the record's measured spin."
                + _spin_text(out) + rest + (" What is left lies in: " + "; ".join(where) + "." if where else "")
                + bound_text + rejected + limits_text(out, [c.spec.name for c in beyond]))
        return Verdict(**dict(names, effects=[NAME_SPIN]), level=level, text=text)
    lead = ("no candidate effect with plausible parameters reduces a held-out error significantly." if beyond else
            "no candidate effect reduces a held-out error significantly.")
    rejected += _alike(out, [c.spec.name for c in beyond])
    if where:
        located = "The gap lies in: " + "; ".join(where) + "."
    elif untouched:
        located = "No regime of those phases stands out and no residual dependence is significant: the gap is spread over them."
    else:
        located = "No regime stands out and no residual dependence is significant: what remains looks like noise."
    bound_phases, bound_text = _bound_text(out)
    floors = out.get("floor", {})
    known = all(isinstance(floors.get(p), dict) and floors[p].get("floor_known", True) for p in out.get("phases", ()))
    if known and out.get("phases") and not (where or gaps or beyond or bound_phases or spin_findings(out)):
        # nothing to explain: every phase at its noise floor, nothing significant, nothing located
        text = ("No gap: no phase's error stands above its noise floor, and " + lead + " " + located +
                limits_text(out, []))
        return Verdict(**names, level="no gap", text=text)
    text = ("Unexplained: " + lead + rejected + rest + " " + located + bound_text + _spin_text(out) +
            limits_text(out, [c.spec.name for c in beyond]))
    return Verdict(**names, level="unexplained", text=text)
