"""Contact detection and segmentation into flight segments.

A raw observation stream (a session) is split at contacts:

* table bounces: a local minimum of z where the vertical velocity reverses (falling faster than
  ``min_speed`` before, rising faster than ``min_speed`` after), whose contact height is within
  ``height_tol`` of the ball radius and which lies over the table;
* other contacts: an abrupt change of the (gravity-compensated) velocity between the samples
  before and after, away from any bounce. Near the net line and below its top they are labelled
  ``net``, near the floor ``out``, else ``other`` (a racket, a hand, the launcher, a wall: without a
  measured racket state it cannot be called a racket contact).

Contact times and positions come from intersecting the flight curves fitted just before and just
after the contact, so they fall between samples. The sessions are then split into flight segments
at the events (:func:`segments_from_events`, from :mod:`ttsim_jax.data.event_segments`).

Dropping the segments a flight model cannot fit is the flight fit's business:
:func:`ttsim_jax.fit.segment_filter.filter_segments`, which ends in :func:`drop_segments` here.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import schema
from .dataset import Dataset
from .event_segments import segments_from_events
from .tables import concat_tables, fill_defaults, select_rows
from .tracks import closest_approach, find_breaks, robust_lines, session_slices, track_slices

GRAVITY = 9.81


@dataclasses.dataclass(frozen=True)
class Contact:
    """A contact found in a stream of samples.

    Attributes:
        kind: event kind (``table``, ``net``, ``out``, ``other``).
        t: contact time [s] (between samples).
        pos: (3,) ball centre at the contact [m].
        index: index of the last sample before the contact.
        dv: size of the velocity change [m/s].
        clean: True when the samples around the contact are evenly spaced (no dropped frames), so
            the contact height is trustworthy to a few millimetres.
    """

    kind: str
    t: float
    pos: np.ndarray
    index: int
    dv: float
    clean: bool


def _line_fit(tau, values):
    """Least-squares lines through (tau, values) along the last-but-one axis; returns (a, b)."""
    tm = tau.mean(axis=-1, keepdims=True)
    vm = values.mean(axis=-2, keepdims=True)
    dt = tau - tm
    b = np.sum(dt[..., None] * (values - vm), axis=-2) / np.sum(dt**2, axis=-1)[..., None]
    a = vm[..., 0, :] - b * tm
    return a, b


def _sampling_clean(t: np.ndarray, lo: int, hi: int) -> bool:
    dt = np.diff(t)
    if len(dt) == 0:
        return False
    return bool(np.max(dt[max(lo, 0) : min(hi, len(dt))]) <= 2.5 * np.median(dt))


def find_bounces(
    t,
    pos,
    *,
    window: int = 4,
    min_window: int = 2,
    min_speed: float = 0.5,
    height: tuple[float, float] | None = (schema.BALL_RADIUS - 0.03, schema.BALL_RADIUS + 0.03),
    on_table: bool = True,
) -> list[Contact]:
    """Finds ball bounces (z-velocity reversals) in one session.

    Arguments:
        t: (T,) strictly increasing times [s].
        pos: (T, 3) ball centre positions [m].
        window: samples fitted on each side of a candidate (fewer next to the ends of the
            session, down to ``min_window``).
        min_window: fewest samples on a side.
        min_speed: least vertical speed [m/s] before and after for a reversal to count.
        height: accepted range of contact heights [m] (default: ball radius +- 3 cm), or None to
            accept any height (to measure where the bounces of an unknown frame sit).
        on_table: also require the contact to lie over the table (canonical frame).

    Returns:
        Contacts of kind ``table``, in time order.
    """
    t = np.asarray(t, np.float64)
    pos = np.asarray(pos, np.float64)
    z = pos[:, 2]
    n = len(t)
    out: list[Contact] = []
    for i in range(min_window, n - min_window):
        if not (z[i] <= z[i - 1] and z[i] < z[i + 1]):
            continue
        w = min(window, i, n - 1 - i)
        tau = t - t[i]
        # With the gravity term moved to the left, free flight is a straight line in tau.
        zg = z + 0.5 * GRAVITY * tau**2
        _, vin = _line_fit(tau[i - w : i + 1], z[i - w : i + 1, None])
        _, vout = _line_fit(tau[i : i + w + 1], z[i : i + w + 1, None])
        if vin[0] > -min_speed or vout[0] < min_speed:
            continue
        best = None
        for split in (i, i + 1):
            pre = slice(max(split - w, 0), split)
            post = slice(split, min(split + w, n))
            if split - pre.start < min_window or post.stop - split < min_window:
                continue
            a1, b1 = _line_fit(tau[pre], zg[pre, None])
            a2, b2 = _line_fit(tau[post], zg[post, None])
            if b1[0] == b2[0]:
                continue
            tc = (a2[0] - a1[0]) / (b1[0] - b2[0])
            if not (tau[split - 1] - 1e-9 <= tc <= tau[split] + 1e-9):
                continue
            resid = np.concatenate([zg[pre] - (a1[0] + b1[0] * tau[pre]), zg[post] - (a2[0] + b2[0] * tau[post])])
            cost = float(np.mean(resid**2))
            if best is None or cost < best[0]:
                best = (cost, tc, a1[0] + b1[0] * tc - 0.5 * GRAVITY * tc**2)
        if best is None:
            best = (0.0, 0.0, z[i])
        _, tc, zc = best
        if height is not None and not (height[0] <= zc <= height[1]):
            continue
        tabs = t[i] + tc
        xc = float(np.interp(tabs, t, pos[:, 0]))
        yc = float(np.interp(tabs, t, pos[:, 1]))
        if on_table and not (
            abs(xc) <= schema.TABLE_LENGTH / 2 + schema.BALL_RADIUS and abs(yc) <= schema.TABLE_WIDTH / 2 + schema.BALL_RADIUS
        ):
            continue
        index = i if tc >= 0 else i - 1
        clean = w >= 3 and _sampling_clean(t, i - 2, i + 2)
        out.append(Contact("table", float(tabs), np.array([xc, yc, zc]), index, float(vout[0] - vin[0]), clean))
    return out


#: How near [m] a contact point must lie to the table top's outline (horizontally and in height) to
#: count as a hit on the table's edge (:func:`find_kinks`'s ``edge_rel_dv``).
EDGE_BAND = schema.BALL_RADIUS + 0.02


def at_table_edge(pc) -> bool:
    """Whether a ball centre ``pc`` touches the table top's edge: within :data:`EDGE_BAND` of the
    surface's height and of its outline, not over the playing surface's inside."""
    x, y, z = (abs(float(v)) for v in pc)
    hx, hy = schema.TABLE_LENGTH / 2, schema.TABLE_WIDTH / 2
    near_outline = max(x - hx, y - hy) > -EDGE_BAND and x < hx + EDGE_BAND and y < hy + EDGE_BAND
    return near_outline and z < EDGE_BAND


def find_kinks(
    t, pos, *, window: int = 5, min_dv: float = 2.0, min_rel_dv: float = 0.5, edge_rel_dv: float = 0.2,
    max_gap: float = 0.03, exclude=()
) -> list[Contact]:
    """Finds abrupt velocity changes (contacts other than table bounces) in one session.

    The velocity just before and just after each sample boundary is estimated from robust
    straight-line fits to ``window`` samples on each side, after removing gravity, so free flight
    shows only the small changes due to drag and lift.

    Arguments:
        t: (T,) strictly increasing times [s].
        pos: (T, 3) positions [m].
        window: samples per side.
        min_dv: least velocity change [m/s] to call a contact.
        min_rel_dv: least velocity change relative to the speed at the contact. Camera timestamps
            jitter by milliseconds, which at 10 m/s fakes changes of a few m/s; real contacts
            (rackets, edges, the net) change the velocity by a good fraction of the speed.
        edge_rel_dv: the same at the table's edge (:func:`at_table_edge`): a ball that clips the
            edge glances off it, and jitter fakes a contact at the edge only where the ball passes it.
        max_gap: largest distance [m] between the two fitted paths where they meet; a larger gap
            means a jump in the measurements, not a contact.
        exclude: sample indices of known contacts (bounces); kinks within ``window`` samples of
            them are ignored.

    Returns:
        Contacts of kind ``net``, ``out`` or ``other``, in time order.
    """
    t = np.asarray(t, np.float64)
    pos = np.asarray(pos, np.float64)
    n = len(t)
    if n < 2 * window:
        return []
    t0 = t[0]
    tau = t - t0
    p = pos.copy()
    p[:, 2] += 0.5 * GRAVITY * tau**2
    idx = np.arange(n - window + 1)[:, None] + np.arange(window)[None, :]
    a, b = robust_lines(tau[idx], p[idx])  # fit k covers samples k .. k+window-1
    # Split s separates samples < s from samples >= s: pre fit starts at s-window, post at s.
    s = np.arange(window, n - window + 1)
    a1, b1, a2, b2 = a[s - window], b[s - window], a[s], b[s]
    dv = np.linalg.norm(b2 - b1, axis=-1)
    taken: list[Contact] = []
    excluded = np.asarray(list(exclude), int)
    order = np.argsort(-dv)
    used = np.zeros(len(s), bool)
    for k in order:
        if dv[k] < min_dv:
            break
        if used[max(0, k - window) : k + window + 1].any():
            continue
        split = s[k]
        if excluded.size and np.min(np.abs(excluded - (split - 1))) <= window:
            continue
        tc, gap = closest_approach(a1[k], b1[k], a2[k], b2[k], tau[split - 1], tau[split])
        tc, gap = float(tc), float(gap)
        if gap > max_gap:
            continue
        g_tc = np.array([0.0, 0.0, GRAVITY * tc])
        speed = max(np.linalg.norm(b1[k] - g_tc), np.linalg.norm(b2[k] - g_tc))
        pc = a1[k] + b1[k] * tc
        pc[2] -= 0.5 * GRAVITY * tc**2
        if dv[k] < (edge_rel_dv if at_table_edge(pc) else min_rel_dv) * speed:
            continue
        used[k] = True
        taken.append(Contact(_kind_of(pc), float(t0 + tc), pc, int(split - 1), float(dv[k]), _sampling_clean(t, split - 3, split + 2)))
    return sorted(taken, key=lambda c: c.t)


def _kind_of(pc) -> str:
    x, y, z = pc
    if z < schema.FLOOR_Z + 0.1:
        return "out"
    if abs(x) < 0.05 + schema.BALL_RADIUS and z < schema.NET_HEIGHT + schema.BALL_RADIUS + 0.03 and abs(y) < 0.92:
        return "net"
    return "other"


def detect_contacts(t, pos, *, bounce_kw: dict | None = None, kink_kw: dict | None = None) -> list[Contact]:
    """Table bounces and other contacts of one session, in time order.

    Arguments:
        t: (T,) times [s]; pos: (T, 3) positions [m], canonical frame.
        bounce_kw: keyword arguments for :func:`find_bounces`.
        kink_kw: keyword arguments for :func:`find_kinks`.

    Returns:
        List of :class:`Contact`.
    """
    bounces = find_bounces(t, pos, **(bounce_kw or {}))
    # Floor bounces end play ("out"); a floor is no table, so look for them separately.
    floor = find_bounces(
        t, pos, height=(schema.FLOOR_Z + schema.BALL_RADIUS - 0.05, schema.FLOOR_Z + schema.BALL_RADIUS + 0.05), on_table=False
    )
    floor = [dataclasses.replace(c, kind="out") for c in floor]
    kinks = find_kinks(t, pos, exclude=[c.index for c in bounces + floor] + [c.index + 1 for c in bounces + floor], **(kink_kw or {}))
    kinks = kinks_beside_bounces(t, pos, bounces + floor, kinks, kink_kw)
    return sorted(bounces + floor + kinks, key=lambda c: c.t)


#: Samples per side of the velocity fits that look for a contact right beside a bounce.
NEAR_WINDOW = 3


#: Standard errors by which a velocity change beside a bounce must stand out (short fits are noisy,
#: and time stamps that jitter by milliseconds fake changes of metres per second).
KINK_SIGMAS = 5.0


def velocity_change_sigmas(t, pos, lo: int, split: int, hi: int) -> float:
    """How many standard errors apart the velocities of least-squares lines through samples
    ``lo:split`` and ``split:hi`` are (gravity removed), the errors from the two fits' pooled
    residuals: jitter and noise scatter the samples about their lines, a contact does not."""
    if split - lo < 3 or hi - split < 3:
        return 0.0
    tau = t[lo:hi] - t[split]
    p = np.array(pos[lo:hi], np.float64)
    p[:, 2] += 0.5 * GRAVITY * tau**2
    slopes, rss, spread, dof = [], 0.0, [], 0
    for part in (slice(0, split - lo), slice(split - lo, hi - lo)):
        a, b = _line_fit(tau[part], p[part])
        rss += float(np.sum((p[part] - (a + b * tau[part, None])) ** 2))
        spread.append(float(np.sum((tau[part] - tau[part].mean()) ** 2)))
        slopes.append(b)
        dof += 3 * (len(tau[part]) - 2)
    se = np.sqrt(rss / dof * (1.0 / spread[0] + 1.0 / spread[1]))  # per axis
    return float(np.linalg.norm(slopes[1] - slopes[0]) / max(se * np.sqrt(3.0), 1e-12))


def kinks_beside_bounces(t, pos, bounces, kinks, kink_kw: dict | None = None) -> list[Contact]:
    """The contacts of :func:`find_kinks` with those within a few samples of a bounce added, which
    it cannot see there: its velocity fits of ``window`` samples per side would straddle the
    bounce, so it ignores the samples beside one. A ball blocked or half-volleyed 15-30 ms after
    it bounced (3-6 frames at 200 Hz) is common play; left undetected, the bounce's flight segment
    holds a racket contact.

    Each stretch between bounces is searched on its own, with :data:`NEAR_WINDOW` samples per side
    (none of them across a bounce). A contact there within ``window`` samples of a bounce is added;
    one of ``kinks`` within ``window`` samples of an added one, that the short fits do not find
    too, is its echo (its wide fits straddled the contact) and is dropped.

    Arguments:
        t: (T,) times [s]; pos: (T, 3) positions [m].
        bounces: the session's table and floor bounces (:class:`Contact`); kinks: the contacts
            :func:`find_kinks` found, bounces excluded.
        kink_kw: :func:`find_kinks`'s keyword arguments (its ``window`` is the blind distance).

    Returns:
        The contacts other than bounces (kind ``net``, ``out`` or ``other``).
    """
    kw = dict(kink_kw or {})
    blind = int(kw.pop("window", 5))
    kw.pop("exclude", None)
    n = len(t)
    edges = [0, *sorted({c.index + 1 for c in bounces if 0 < c.index + 1 < n}), n]
    if len(edges) == 2:
        return list(kinks)
    added, short = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        if hi - lo < 2 * NEAR_WINDOW:
            continue
        for c in find_kinks(t[lo:hi], pos[lo:hi], window=NEAR_WINDOW, **kw):
            c = dataclasses.replace(c, index=c.index + lo)
            short.append(c.index)
            # within the samples find_kinks excludes beside a bounce (its exclude rule)
            beside = (lo > 0 and c.index - lo <= blind) or (hi < n and hi - 1 - c.index <= blind)
            split = c.index + 1
            if beside and velocity_change_sigmas(t, pos, max(lo, split - blind - 1), split, min(hi, split + blind + 1)) > KINK_SIGMAS:
                added.append(c)
    near = lambda i, others, d: any(abs(i - j) <= d for j in others)  # noqa: E731
    mine = [a.index for a in added]
    others = [i for i in short if i not in mine]
    kept = [c for c in kinks if not near(c.index, mine, blind) or near(c.index, others, 1)]
    return kept + [a for a in added if not near(a.index, [c.index for c in kept], blind)]


def detect_events(ds: Dataset, *, bounce_kw: dict | None = None, kink_kw: dict | None = None) -> Dataset:
    """Detects contacts in every session that has no labelled events, then re-derives segments.

    Contacts are looked for in each track of a session (:mod:`ttsim_jax.data.tracks`): the samples
    either side of a pause or a jump belong to different flights, and a fit across them would fake
    a contact.

    Arguments:
        ds: dataset in the canonical frame (observations grouped by session, in time order).
        bounce_kw, kink_kw: passed to :func:`find_bounces` / :func:`find_kinks`.

    Returns:
        The dataset with detected events added (ids after the existing ones) and segments split at
        all events and breaks (existing segment spins are recomputed from the observations).
    """
    obs = ds.observations
    labelled = set(np.unique(ds.events["session_id"]).tolist())
    next_id = int(ds.events["event_id"].max()) + 1 if len(ds.events["event_id"]) else 0
    rows = {"event_id": [], "session_id": [], "t": [], "kind": [], "x": [], "y": [], "z": []}
    pos = ds.positions
    for sid, a, b in session_slices(obs["session_id"]):
        if sid in labelled:
            continue
        t, p = obs["t"][a:b], pos[a:b]
        for lo, hi in track_slices(b - a, find_breaks(t, p)):
            for c in detect_contacts(t[lo:hi], p[lo:hi], bounce_kw=bounce_kw, kink_kw=kink_kw):
                rows["event_id"].append(next_id)
                next_id += 1
                rows["session_id"].append(sid)
                rows["t"].append(c.t)
                rows["kind"].append(c.kind)
                rows["x"].append(c.pos[0])
                rows["y"].append(c.pos[1])
                rows["z"].append(c.pos[2])
    new = fill_defaults("events", {k: np.asarray(v, object if k == "kind" else None) for k, v in rows.items()})
    events = concat_tables([ds.events, new], "events")
    order = np.lexsort((events["t"], events["session_id"]))
    return segments_from_events(ds.replace(events=select_rows(events, order)))


def drop_segments(ds: Dataset, keep: np.ndarray) -> Dataset:
    """``ds`` without the segments whose row of ``keep`` (bool, one per segment row) is False: their
    rows leave the segments table, their observations stay with ``segment_id = -1``; events stay."""
    seg, obs = ds.segments, ds.observations
    kept_ids = seg["segment_id"][keep]
    observations = dict(obs)
    observations["segment_id"] = np.where(np.isin(obs["segment_id"], kept_ids), obs["segment_id"], -1)
    return ds.replace(segments=select_rows(seg, keep), observations=observations)
