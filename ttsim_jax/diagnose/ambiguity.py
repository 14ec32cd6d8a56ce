"""Candidates these data cannot tell apart, and what data would.

Two effects are indistinguishable on a dataset when they move its errors the same way: a steady
wind along the only direction every throw takes, thinner air and lower drag all shorten the same
flights by the same amounts. A candidate's *signature* is the change it makes to the model's errors
on every item (the model's per-item errors minus the candidate's, the flight's per sample), and two
candidates whose signatures are nearly parallel (cosine at least :data:`COLLINEAR` over the phases
they share) are reported together: the diagnosis cannot name one of them over the other, whichever
ranked first. :data:`SEPARATED_BY` says, per effect, what data would break the tie.
"""

from __future__ import annotations

import numpy as np

#: Cosine between two candidates' signatures at or above which they are indistinguishable.
COLLINEAR = 0.9

#: Per effect: what kind of data would tell it from the others that it resembles.
SEPARATED_BY = {
    "air_flow": "throws in several directions (a wind pushes along one direction of the hall, the ball's own "
                "drag along each ball's velocity)",
    "air_density": "throws over a wide range of speeds and spins (air density scales drag and lift together)",
    "spin_decay": "long flights with the spin measured at both ends",
    "ball_variation": "balls weighed and measured, or several balls in one session (size and mass act on bounces too)",
    "table_tilt": "bounces spread over the whole table (a tilt is the same slope everywhere, a warp changes from "
                  "place to place)",
    "table_unevenness": "bounces spread over the whole table (a tilt is the same slope everywhere, a warp changes "
                        "from place to place)",
    "table_friction": "bounces over a range of incoming spins (friction acts on the contact point's slip)",
    "worn_ball": "bounces over a wide range of impact speeds (a worn ball loses restitution at every speed, "
                 "buckling only above its onset)",
    "buckling": "bounces over a wide range of impact speeds (a worn ball loses restitution at every speed, "
                "buckling only above its onset)",
    "racket_logo": "racket contacts spread over the face, with the contact point measured",
    "racket_edge": "racket contacts spread over the face, with the contact point measured",
    "rubber_anisotropy": "racket contacts with the face turned at several angles about its normal",
}


def signature(pb, errors: dict) -> dict:
    """{phase: (K,) change of the model's errors} over the real items of each phase in ``errors``.

    Arguments:
        pb: the :class:`~ttsim_jax.diagnose.candidates.Problem` (``base``: the model's errors).
        errors: a candidate's per-row errors by phase.
    """
    out = {}
    for p, e in errors.items():
        d = np.asarray(pb.base[p], np.float64) - np.asarray(e, np.float64)
        w = np.asarray(pb.data[p]["train"], np.float64) + np.asarray(pb.data[p]["test"], np.float64)
        if p == "flight":
            d = d * (np.asarray(pb.data[p]["mask"], np.float64) * (w[:, None] > 0))[..., None]
        else:
            d = d * (w[:, None] > 0)
        # each phase in units of the model's own error there, so that no phase outweighs another
        out[p] = d.ravel() / np.sqrt(max(pb.norm.get(p, 1.0), 1e-30))
    return out


def similarity(a: dict, b: dict) -> float:
    """Cosine between two signatures over the phases they share (0 when they share none)."""
    shared = [p for p in a if p in b]
    if not shared:
        return 0.0
    x = np.concatenate([a[p] for p in shared])
    y = np.concatenate([b[p] for p in shared])
    nx, ny = np.linalg.norm(x), np.linalg.norm(y)
    return float(x @ y / (nx * ny)) if nx > 0 and ny > 0 else 0.0


def indistinguishable(pb, candidates: list) -> list:
    """Groups of candidates whose signatures are nearly parallel, linked pairwise.

    Arguments:
        pb: the Problem; candidates: fitted candidates (``spec.name``, ``errors``), e.g. the
            significant ones.

    Returns:
        [{"names": [...] in the candidates' order, "cosine": the least pairwise cosine that links
        them, "separate": what data would tell them apart}], groups of two or more only.
    """
    sigs = [signature(pb, c.errors) for c in candidates]
    n = len(candidates)
    sim = np.array([[similarity(sigs[i], sigs[j]) if i != j else 1.0 for j in range(n)] for i in range(n)])
    group = list(range(n))

    def root(i):
        while group[i] != i:
            i = group[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            if sim[i, j] >= COLLINEAR:
                group[root(j)] = root(i)
    out = []
    for r in sorted({root(i) for i in range(n)}):
        members = [i for i in range(n) if root(i) == r]
        if len(members) < 2:
            continue
        names = [candidates[i].spec.name for i in members]
        links = [sim[i, j] for i in members for j in members if i < j and sim[i, j] >= COLLINEAR]
        hints = list(dict.fromkeys(SEPARATED_BY.get(m, "data over a wider range of speeds, spins and positions")
                                   for m in names))
        out.append(dict(names=names, cosine=float(min(links)), separate="; ".join(hints)))
    return out


#: Readings of a gap that need no candidate: the simplest change that a family of effects shares.
#: Per reading: its text, the phases and the error component it acts on (the 6-vector of
#: :mod:`~ttsim_jax.diagnose.stages`: the table's post-bounce normal velocity is component 2 and its
#: incoming normal velocity input 2; the racket's are 0 and 0, in the racket frame), and what data
#: would tell an effect from it, and the catalogue's effects that are that change (they are not
#: compared with it). A candidate whose signature on these components is nearly parallel
#: to a reading's (:data:`COLLINEAR`) shows no more than the reading does: the data support the
#: change, not what distinguishes the candidate (buckling's onset, a worn ball's loss at every speed).
READINGS = {
    "uniform_restitution": dict(
        text="a restitution change at every impact speed (the post-contact normal velocity off in proportion to "
             "the normal impact speed): any effect that changes the restitution, a worn or softer ball, a harder "
             "table, reads the same",
        components={"table": (2, 2), "racket": (0, 0)},
        effects=("worn_ball",),  # the effects that are this change and nothing more: they name it
        separate="contacts over a wide range of impact speeds, the slow ones included (buckling sets in above an "
                 "onset, a worn ball loses at every speed)"),
}


def _reading_signature(pb, components: dict) -> dict:
    """{phase: (K,) signature} of a reading: the error component in proportion to the incoming
    normal speed, on the phase's real items, in :func:`signature`'s units."""
    out = {}
    for p, (err, inp) in components.items():
        if p not in pb.data:
            continue
        d = pb.data[p]
        w = (np.asarray(d["train"], np.float64) + np.asarray(d["test"], np.float64)) > 0
        out[p] = np.abs(np.asarray(d["x"], np.float64)[:, inp]) * w / np.sqrt(max(pb.norm.get(p, 1.0), 1e-30))
    return out


def reads_as(pb, candidate) -> list:
    """The :data:`READINGS` that ``candidate`` cannot be told from on these data.

    The candidate's signature (:func:`signature`) is compared on the reading's error component
    only (an effect acting through the restitution also moves the tangential velocity and spin, in
    proportion to its normal change), over the contact phases where it changes the errors.

    Returns:
        [{"reading", "text", "cosine", "separate"}] for each reading whose cosine with the
        candidate is at least :data:`COLLINEAR`.
    """
    sig = signature(pb, candidate.errors)
    out = []
    for key, r in READINGS.items():
        if candidate.spec.name in r["effects"]:
            continue
        ref = _reading_signature(pb, r["components"])
        parts = {}
        for p, (err, _) in r["components"].items():
            if p in sig and p in ref:
                own = sig[p].reshape(-1, 6)
                if np.linalg.norm(own) > 0:
                    parts[p] = own[:, err]
        if not parts:
            continue
        # the candidate must act through this component: most of its change there, not elsewhere
        through = sum(np.sum(v**2) for v in parts.values()) / sum(np.sum(sig[p]**2) for p in parts)
        cos = abs(similarity(parts, ref))
        if cos >= COLLINEAR and through >= 0.5:
            out.append(dict(reading=key, text=r["text"], cosine=cos, separate=r["separate"]))
    return out
