"""The record's measured spin, corrected by the spin check before the candidates see it.

The spin check (:func:`ttsim_jax.diagnose.residuals.spin_check`) compares the flight segments'
measured spins with the spins their flights show. Where it finds the record's spin off (a sign
flipped on all or some segments, an axis turned, a size read high or low), every candidate fitted
with that spin would be fitted to a wrong one, and a table, air or ball effect would stand in for
the spin estimator's error. So the check is the first candidate, one on the record: its
correction (:func:`ttsim_jax.fit.spin_check.corrected_spins`) is applied to every measured spin
of the record (segments and observations), the phases are collected again (the contacts' states
read the corrected spins too), and the correction is accepted when it lowers the held-out flight
error significantly and makes no contact phase materially worse (the candidates' own tests,
:func:`~ttsim_jax.diagnose.candidates.significant` and :func:`~ttsim_jax.diagnose.candidates.worse`,
on the split of the uncorrected problem). Once
accepted, every later stage (the noise floor, the bounds, the candidates, the limits, the landing)
works on the corrected record.

The contacts are the check on the check: the flights alone cannot tell a spin read 25 % high from
air 20 % thinner than modelled (both bend the flight less than the model with that spin expects),
but a bounce reads the incoming spin through the table's and the racket's laws, not through the
air. Where the record's spin is right and the air or the ball is off, its "correction" moves the
bounces away from the measured ones; that contradiction is reported, and the spin check's
finding is then read as a flight effect, not as the record's.
"""

from __future__ import annotations

import numpy as np

from ttsim_jax.diagnose import candidates

#: The name the verdict gives the correction when it is accepted.
NAME = "spin_record"


def corrected_record(ds, flights, check: dict) -> tuple:
    """(``ds`` with its measured spins corrected as ``check`` reads them, what was undone): the
    spin columns of its segments and observations (:func:`ttsim_jax.fit.spin_check.corrected_spins`;
    a sign flipped on some segments flipped back on the flight segments the check found bent
    opposite, by their segment ids). ``flights``: the :class:`~ttsim_jax.diagnose.phases.Flights`
    the check was run on (its measured rows, in order)."""
    from ttsim_jax.fit.spin_check import corrected_spins

    rows = np.flatnonzero(flights.spin_source[: flights.n] == "measured")
    flipped = np.asarray(flights.segment_id)[rows][np.asarray(check.get("opposite_rows", []), int)]
    tables, applied = {}, {}
    for name in ("segments", "observations"):
        t = dict(getattr(ds, name))
        w = np.stack([np.asarray(t[f"spin_{a}"], np.float64) for a in "xyz"], 1)
        opposite = np.flatnonzero(np.isin(np.asarray(t["segment_id"]), flipped))
        fixed, applied[name] = corrected_spins(w, dict(check, opposite_rows=opposite.tolist()))
        for k, a in enumerate("xyz"):
            t[f"spin_{a}"] = fixed[:, k].astype(np.asarray(t[f"spin_{a}"]).dtype)
        tables[name] = t
    return ds.replace(**tables), applied["segments"]  # counted in segments, not observation rows


def correct(ds, ph, pb, check: dict, collect, seed: int = 0) -> tuple:
    """The spin check's correction, tried on the record.

    Arguments:
        ds: the dataset; ph: its :class:`~ttsim_jax.diagnose.phases.Phases`; pb: their
            :class:`~ttsim_jax.diagnose.candidates.Problem`; check: the spin check's dict (run on
            the flight segments with a measured spin, in row order); collect: ``collect(ds) ->
            (phases, problem)`` as the diagnosis makes them; seed: of the bootstrap.

    Returns:
        (dataset, phases, problem, entry): the corrected ones where the correction is accepted,
        else those given; ``entry`` (JSON-able): ``applied`` (what was undone), ``segments`` (the
        flight segments with a measured spin), ``heldout`` (:func:`~ttsim_jax.diagnose.candidates.score`
        of the corrected model errors in flight against the uncorrected ones, on the uncorrected
        split), ``accepted``; or ``skipped`` (why nothing was tried).
    """
    fl = ph.flights
    if fl is None or "skipped" in check:
        return ds, ph, pb, dict(skipped=check.get("skipped", "no flight phase"))
    if not check.get("findings"):
        return ds, ph, pb, dict(skipped="the spin check found nothing off")
    ds2, applied = corrected_record(ds, fl, check)
    ph2, pb2 = collect(ds2)
    if ph2.flights is None or not np.array_equal(ph2.flights.segment_id, fl.segment_id):
        return ds, ph, pb, dict(skipped="the corrected record gives other flight segments: not compared")
    # the contacts are compared where the corrected record gives the same contacts (their split is
    # the uncorrected problem's, as the flights': the split is stratified by the errors, so it moves)
    same = [p for p in pb.phases if p != "flight" and p in pb2.base
            and np.shape(pb2.base[p]) == np.shape(pb.base[p])
            and np.array_equal(np.asarray(pb2.data[p]["t"]), np.asarray(pb.data[p]["t"]))]
    scores = candidates.score(pb, {"flight": pb2.base["flight"], **{p: pb2.base[p] for p in same}}, seed)
    h = scores.pop("flight")
    finite = all(np.isfinite(np.asarray(pb2.base[p])).all() for p in ["flight", *same])
    contradicted = [p for p, c in scores.items() if candidates.worse(p, c)]
    # the flights are where the check read it: they must gain; no contact may lose
    accepted = bool(finite and candidates.significant("flight", h) and not contradicted)
    entry = dict(applied=applied, segments=int(np.sum(fl.spin_source[: fl.n] == "measured")), heldout=h,
                 contacts=scores, contradicted=contradicted, accepted=accepted)
    return (ds2, ph2, pb2, entry) if accepted else (ds, ph, pb, entry)


def contradicted(entry: dict) -> list:
    """The contact phases that the spin check's correction made materially worse (``entry``: of
    :func:`correct`), [] when none or when nothing was tried: there the bounces agree with the
    record's spin, and what the check read in the flights lies in the flight's physics."""
    return list((entry or {}).get("contradicted", []))


def text(entry: dict) -> str:
    """One sentence on the correction (the verdict's and the report's), "" when none was tried."""
    if not entry or "skipped" in entry:
        return ""
    h = entry["heldout"]
    what = ", ".join(entry["applied"])
    change = (f"the held-out flight error {h['before_rms'] * 1e3:.2f} -> {h['after_rms'] * 1e3:.2f} mm RMS, "
              f"{h['pct']:.1f} % lower (95 % interval {h['ci95'][0]:.1f} to {h['ci95'][1]:.1f} %)")
    if entry["accepted"]:
        return (f" The record's measured spin, corrected as the spin check reads it ({what}, on {entry['segments']} "
                f"flight segments), brings {change}: every later stage and candidate works on the corrected spin.")
    against = contradicted(entry)
    if against:
        worse = "; ".join(f"the {p} error {c['before_rms']:.3g} -> {c['after_rms']:.3g} m/s RMS, "
                          f"{-c['pct']:.1f} % higher (95 % interval {-c['ci95'][1]:.1f} to {-c['ci95'][0]:.1f} %)"
                          for p, c in entry["contacts"].items() if p in against)
        return (f" The spin check's correction ({what}) was tried and not accepted: it brings {change}, but {worse}. "
                "The bounces agree with the measured spin, so the flights bend otherwise for a reason in the flight "
                "(the air or the ball), not in the record.")
    return f" The spin check's correction ({what}) was tried and not accepted: {change}."
