"""Flight segments from a dataset's events and tracking breaks.

Kept apart from :mod:`ttsim_jax.data.segment` (contact detection and filtering): building a
:class:`~ttsim_jax.data.Dataset` from arrays derives its segments here, so this module needs the
column tables only, never the dataset class.
"""

from __future__ import annotations

import numpy as np

from . import schema
from .tables import fill_defaults
from .tracks import MIN_SAMPLES, find_breaks, session_slices, track_slices


def segments_from_events(ds, *, min_track: int = MIN_SAMPLES):
    """Splits every session at its events and at its breaks into flight segments.

    Observations between consecutive boundaries (events, and the breaks of
    :func:`ttsim_jax.data.tracks.find_breaks`: pauses and jumps where the tracker did not follow one
    ball) form one segment each (empty spans make none). A segment opened (closed) by a break has
    start (end) event -1, as one at the start (end) of the session. A segment's spin is the
    confidence-weighted mean of its observations' spin, and its confidence the largest among them.

    Arguments:
        ds: :class:`~ttsim_jax.data.Dataset` whose observations are grouped by session and in time order.
        min_track: samples of a track (a span between breaks) below which it forms no segment: its
            observations keep ``segment_id = -1`` (:func:`track_report` counts them).

    Returns:
        The dataset with a new ``segments`` table and ``observations.segment_id`` filled in.
    """
    obs = ds.observations
    ev = ds.events
    seg_id = np.full(len(obs["t"]), -1, np.int64)
    cols = {c.name: [] for c in schema.SEGMENTS}
    ev_by_session: dict[int, np.ndarray] = {}
    if len(ev["t"]):
        order = np.lexsort((ev["t"], ev["session_id"]))
        for sid, a, b in session_slices(ev["session_id"][order]):
            ev_by_session[sid] = order[a:b]
    spin = ds.spins
    conf = obs["spin_conf"]
    pos = ds.positions
    next_id = 0
    for sid, a, b in session_slices(obs["session_id"]):
        t = obs["t"][a:b]
        rows = ev_by_session.get(sid, np.zeros(0, int))
        et = ev["t"][rows]
        breaks = find_breaks(t, pos[a:b])
        bt = np.array([br.t for br in breaks])
        short = np.zeros(b - a, bool)
        for lo, hi in track_slices(b - a, breaks):
            short[lo:hi] = hi - lo < min_track
        n_ev = np.searchsorted(et, t, side="right")  # number of events at or before each sample
        n_br = np.searchsorted(bt, t, side="right")
        part = n_ev + n_br  # both only grow along the session: one value per span between boundaries
        for k in np.unique(part[~short]):
            members = np.flatnonzero((part == k) & ~short)
            first, last = members[0], members[-1]
            # The boundary just before (after) the span is an event unless a break lies between.
            prev_ev, next_ev = n_ev[first] - 1, n_ev[last]
            prev_br, next_br = n_br[first] - 1, n_br[last]
            opened = prev_ev >= 0 and (prev_br < 0 or et[prev_ev] > bt[prev_br])
            closed = next_ev < len(rows) and (next_br >= len(bt) or et[next_ev] < bt[next_br])
            seg_id[a + members] = next_id
            cols["segment_id"].append(next_id)
            cols["session_id"].append(sid)
            cols["start_event_id"].append(int(ev["event_id"][rows[prev_ev]]) if opened else -1)
            cols["end_event_id"].append(int(ev["event_id"][rows[next_ev]]) if closed else -1)
            cols["t_start"].append(et[prev_ev] if opened else t[first])
            cols["t_end"].append(et[next_ev] if closed else t[last])
            w = conf[a + members]
            if np.any(w > 0):
                s = np.sum(spin[a + members] * w[:, None], axis=0) / np.sum(w)
                c = float(np.max(w))
            else:
                s, c = np.zeros(3), 0.0
            cols["spin_x"].append(s[0])
            cols["spin_y"].append(s[1])
            cols["spin_z"].append(s[2])
            cols["spin_conf"].append(c)
            next_id += 1
    segments = fill_defaults("segments", {k: np.asarray(v) for k, v in cols.items()}) if next_id else schema.empty_table("segments")
    observations = dict(obs)
    observations["segment_id"] = seg_id
    return ds.replace(observations=observations, segments=segments)
