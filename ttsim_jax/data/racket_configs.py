"""Racket configurations of a dataset: which blade, sponge and rubber each racket contact was on.

A racket state names its configuration in the rackets table's ``config`` column ('' = not given);
the dataset's ``metadata.equipment["rackets"]`` describes each name (``blade``, ``sponge_mm``,
``rubber``, ``rubber_type``: free-form, as the importer knows them). A session's ``notes`` may be a
JSON object with ``tilt_deg``, the racket's tilt in a rig (tt_rackets).
"""

from __future__ import annotations

import json

import numpy as np

#: The rubber type of a configuration the metadata does not describe.
UNKNOWN_TYPE = "unknown"


def descriptions(ds) -> dict:
    """Configuration name -> its description dict (empty when the metadata holds none)."""
    eq = ds.metadata.equipment
    rackets = eq.get("rackets", {}) if isinstance(eq, dict) else {}
    return {str(k): dict(v) for k, v in rackets.items()} if isinstance(rackets, dict) else {}


def of_events(ds, event_ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per racket contact: (config names (n,) str, rubber types (n,) str, tilts (n,) [deg], NaN where
    no session note gives one); '' and :data:`UNKNOWN_TYPE` for a contact without a configuration."""
    ids = np.asarray(event_ids, np.int64).reshape(-1)
    rows = ds.racket_rows(ids)
    cfg = np.asarray(ds.rackets["config"], object)
    names = np.array([str(cfg[r]) if r >= 0 else "" for r in rows], object)
    desc = descriptions(ds)
    types = np.array([str(desc.get(n, {}).get("rubber_type", UNKNOWN_TYPE)) for n in names], object)
    tilt_of = {}
    for sid, note in zip(np.asarray(ds.sessions["session_id"]).tolist(), ds.sessions["notes"]):
        try:
            tilt_of[sid] = float(json.loads(note).get("tilt_deg", np.nan)) if note else np.nan
        except (ValueError, AttributeError, TypeError):
            tilt_of[sid] = np.nan
    ev_rows = ds.event_rows(ids)
    sess = np.asarray(ds.events["session_id"], np.int64)
    tilts = np.array([tilt_of.get(int(sess[r]), np.nan) if r >= 0 else np.nan for r in ev_rows], np.float64)
    return names, types, tilts


def summary(ds) -> dict:
    """Configuration name -> {n: racket states, tilts_deg: {tilt: n}, and its description}, for
    every configuration named in the rackets table (empty when none is)."""
    ids = np.asarray(ds.rackets["event_id"], np.int64)
    names, _, tilts = of_events(ds, ids)
    desc = descriptions(ds)
    out = {}
    for n in sorted(set(names.tolist()) - {""}):
        k = names == n
        t = tilts[k]
        counts = {f"{v:g}": int(np.sum(t == v)) for v in np.unique(t[np.isfinite(t)])}
        out[n] = dict(n=int(k.sum()), tilts_deg=counts, **desc.get(n, {}))
    return out
