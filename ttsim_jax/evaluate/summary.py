"""Summaries of a batch of simulated shots (landing spread, bounce statistics)."""

from __future__ import annotations

import numpy as np

from ttsim_jax.physics.events import FLOOR, KIND_NAMES, NET, OUT, REST, TABLE


def shot_outcomes(kinds, pre_pos, labels, direction=None):
    """Per-shot outcome: where its first bounce on the far half landed, or why it did not.

    Arguments:
        kinds: (B, K) event kinds; pre_pos: (B, K, 3) event positions; labels: (B,) shot types.
        direction: (B,) +1 for shots along +x, -1 along -x (default: +1).

    Returns:
        dict of numpy arrays: ``landed`` (B,) bool, ``landing`` (B, 2) first bounce on the far half
        (NaN if none), ``net`` (B,) touched the net, ``n_bounces`` (B,).
    """
    kinds, pre_pos = np.asarray(kinds), np.asarray(pre_pos)
    b = kinds.shape[0]
    direction = np.ones(b) if direction is None else np.asarray(direction)
    far = (kinds == TABLE) & (pre_pos[..., 0] * direction[:, None] > 0)
    first = np.argmax(far, axis=1)
    landed = far.any(1)
    landing = np.where(landed[:, None], pre_pos[np.arange(b), first, :2], np.nan)
    return dict(landed=landed, landing=landing, net=(kinds == NET).any(1), n_bounces=(kinds == TABLE).sum(1))


def summary_table(kinds, pre_pos, post_vel, labels, status) -> str:
    """A plain-text table per shot type: count, landed, net, bounces, landing spread, how they ended."""
    out = shot_outcomes(kinds, pre_pos, labels)
    labels, status, kinds = np.asarray(labels), np.asarray(status), np.asarray(kinds)
    post_speed = np.linalg.norm(np.asarray(post_vel), axis=-1)
    rows = ["shot type        n   landed  net   bounces  landing x mean±sd [m]   landing y sd [m]  "
            "speed after 1st bounce [m/s]  ended: floor / out / rest / in flight"]
    for name in list(dict.fromkeys(sorted(labels.tolist()))) + ["all"]:
        k = np.ones(len(labels), bool) if name == "all" else labels == name
        land = out["landing"][k & out["landed"]]
        first_bounce = kinds[k, 0] == TABLE
        sp = post_speed[k, 0][first_bounce]
        lx = f"{np.mean(land[:, 0]):5.2f} ± {np.std(land[:, 0]):4.2f}" if len(land) else "   -        "
        ly = f"{np.std(land[:, 1]):5.2f}" if len(land) else "  -  "
        spd = f"{np.median(sp):5.2f}" if len(sp) else "  -  "
        rows.append(f"{name:15s} {k.sum():5d}  {out['landed'][k].mean():5.2f}  {out['net'][k].mean():4.2f}  "
                    f"{out['n_bounces'][k].mean():6.2f}   {lx:>22s}   {ly:>14s}   {spd:>26s}   "
                    f"{(status[k] == FLOOR).mean():5.2f} / {(status[k] == OUT).mean():4.2f} / {(status[k] == REST).mean():4.2f} / "
                    f"{(status[k] == 0).mean():4.2f}")
    return "\n".join(rows)


__all__ = ["shot_outcomes", "summary_table", "KIND_NAMES"]
