"""The racket stage's errors grouped the way a reader of racket data asks: per racket
configuration, per rubber type, and by the incoming state (speed, spin, incidence angle).

All in the racket frame (x~ the face normal): |dv| and |dw| are the norms of the post-contact
velocity and spin errors, "normal" their x~ component, "tangential" the norm of the other two.
"""

from __future__ import annotations

import math

import numpy as np

from ttsim_jax.fit.racket_configs import error_medians

#: Edges of the incoming-state bands: speed [m/s], spin [rad/s], incidence angle from the normal [deg].
BANDS = {"incoming speed": ((5.0, 8.0), "m/s"), "incoming spin": ((100.0, 300.0), "rad/s"),
         "incidence angle": ((10.0, 20.0), "deg")}


def incoming(x) -> dict:
    """{band name: (N,) value} of the racket-frame pre-contact states ``x`` (N, >= 6)."""
    x = np.asarray(x, np.float64)
    v, w = x[:, :3], x[:, 3:6]
    return {"incoming speed": np.linalg.norm(v, axis=1), "incoming spin": np.linalg.norm(w, axis=1),
            "incidence angle": np.degrees(np.arctan2(np.linalg.norm(v[:, 1:], axis=1), -v[:, 0]))}


def _label(lo, hi, unit) -> str:
    if math.isinf(lo):
        return f"< {hi:g} {unit}"
    return f">= {lo:g} {unit}" if math.isinf(hi) else f"{lo:g}-{hi:g} {unit}"


def groups(r) -> dict:
    """{grouping: {group label: {"n": n, model: {quantity: median}}}} of a racket stage's
    :class:`~ttsim_jax.evaluate.result.RacketStage` ``r``: "config" and "rubber_type" where the
    contacts name configurations, then the bands of :data:`BANDS`."""
    keys = {}
    config = np.asarray(r.config, object)
    if any(config != ""):
        keys["config"] = config
        keys["rubber_type"] = np.asarray(r.rubber_type, object)
    for name, value in incoming(r.x).items():
        edges, unit = BANDS[name]
        cuts = (-math.inf,) + tuple(edges) + (math.inf,)
        labels = np.array([_label(cuts[k], cuts[k + 1], unit) for k in range(len(cuts) - 1)], object)
        keys[name] = labels[np.searchsorted(np.asarray(edges), value, side="right")]
        keys[name + " order"] = labels  # the bands' order, for the report
    out = {}
    for name, key in keys.items():
        if name.endswith(" order"):
            continue
        order = keys.get(name + " order")
        labels = [g for g in (order if order is not None else sorted(set(key.tolist()))) if np.any(key == g)]
        out[name] = {g: dict(n=int(np.sum(key == g)), **{m: error_medians(e[key == g]) for m, e in r.error.items()})
                     for g in labels}
    return out


def spin_component(y_obs) -> int:
    """The racket-frame spin component (0, 1, 2: x~, y~, z~) along which the measured outgoing spin
    varies most: the one a predicted-against-measured figure shows (for a planar rig, the axis of
    topspin and backspin)."""
    y = np.asarray(y_obs, np.float64)
    return int(np.argmax(np.var(y[:, 3:6], axis=0))) if len(y) else 2


def markdown(g: dict, names: list) -> list:
    """Report lines: one table per grouping, median |dv| [m/s] / |dw| [rad/s] per model, and for
    the configurations the normal and tangential parts."""
    lines = []
    for grouping, rows in g.items():
        head = [grouping, "n"] + [f"{n} \\|dv\\| / \\|dw\\|" for n in names]
        body = [[label, str(cell["n"])] + [f"{cell[n]['dv']:.3f} / {cell[n]['dw']:.1f}" for n in names]
                for label, cell in rows.items()]
        lines += [f"By {grouping} (median \\|error\\| of the outgoing velocity [m/s] / spin [rad/s], racket frame):", "",
                  "| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(b) + " |" for b in body]
        lines.append("")
    if "config" in g:
        head = ["config"] + [f"{n} {q}" for n in names for q in ("dv n / t", "dw n / t")]
        body = [[label] + [f"{cell[n]['dv_normal']:.3f} / {cell[n]['dv_tangential']:.3f}" if q == 0 else
                           f"{cell[n]['dw_normal']:.1f} / {cell[n]['dw_tangential']:.1f}" for n in names for q in (0, 1)]
                for label, cell in g["config"].items()]
        lines += ["Per configuration, normal / tangential parts of the median errors:", "",
                  "| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(b) + " |" for b in body]
        lines.append("")
    return lines
