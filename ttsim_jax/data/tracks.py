"""Where a tracker lost the ball: the breaks in a session's observations, and the tracks between them.

A tracker's session is rarely one flight after another: between throws (or rallies) it records
nothing for seconds, it drops frames behind an occlusion, and it can pick up another object. No
flight segment may straddle such a place: the end of one throw and the start of the next are two
flights, not one. A *break* is where consecutive samples cannot belong to one followed ball:

* a *pause*: no sample for longer than ``max_pause`` (a tracker's pause between throws);
* a *gap*: more than ``max_missing`` frames missing (relative to the session's median sample
  interval) where the flights fitted on either side do not meet (a contact hidden in the gap leaves
  them meeting at the contact, which :mod:`ttsim_jax.data.segment` then finds);
* a *jump*: consecutive samples further apart than any ball flies in the interval (``max_speed``),
  or whose flights either side do not meet while each side is itself a clean flight.

"Meet" uses the test that tells a contact from a measurement jump in
:func:`ttsim_jax.data.segment.find_kinks`: robust straight lines in gravity-compensated coordinates
(free flight is nearly a line there over a few samples) fitted to ``window`` samples on each side,
and their closest approach in the interval between the two samples.

A *track* is the span of a session between two breaks; contacts are detected and segments cut per
track, and a track too short to fit a flight (``min_samples``) is left out of every segment.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

GRAVITY = 9.81
#: Longest time [s] without a sample that a followed ball may spend unobserved: a flight across the
#: table lasts 0.3-1 s, so a longer silence is a pause between throws, not an occlusion.
MAX_PAUSE = 0.25
#: Frames that may be missing without a test (camera hiccups are common and harmless).
MAX_MISSING = 3
#: Closest approach [m] of the flights either side beyond which they are not one ball's.
MAX_JUMP = 0.1
#: Speed [m/s] no table tennis ball reaches (the fastest smashes measured are about 35 m/s).
MAX_SPEED = 50.0
#: Samples per side of the flights compared at a break.
WINDOW = 5
#: Fewest samples of a track that forms segments (a flight fit needs a few).
MIN_SAMPLES = 5


@dataclasses.dataclass(frozen=True)
class Break:
    """A place in a session where the tracker did not follow one ball.

    Attributes:
        index: offset (within the session's samples) of the first sample after the break.
        t: time of the break [s], midway between the samples either side (so a labelled contact
            just after the last sample before a pause stays with the flight before it).
        reason: ``pause``, ``gap`` or ``jump``.
        size: the silence [s] for a pause or a gap, the distance [m] between the flights for a jump.
    """

    index: int
    t: float
    reason: str
    size: float


def session_slices(session_id: np.ndarray) -> list[tuple[int, int, int]]:
    """(session, start, stop) row ranges of contiguous session blocks."""
    if len(session_id) == 0:
        return []
    cuts = np.flatnonzero(np.diff(session_id)) + 1
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts, [len(session_id)]])
    return [(int(session_id[a]), int(a), int(b)) for a, b in zip(starts, stops)]


def robust_lines(tau, values):
    """Theil-Sen lines per window: tau (K, w), values (K, w, 3) -> (a, b) of shape (K, 3).

    A single bad sample (tracking outliers are common) cannot fake a velocity change this way.
    """
    w = tau.shape[-1]
    i, j = np.triu_indices(w, 1)
    slopes = (values[:, j] - values[:, i]) / (tau[:, j] - tau[:, i])[..., None]
    b = np.median(slopes, axis=1)
    a = np.median(values - b[:, None, :] * tau[..., None], axis=1)
    return a, b


def closest_approach(a1, b1, a2, b2, lo, hi):
    """Where and how close two lines p = a + b tau come within lo <= tau <= hi.

    Arguments:
        a1, b1, a2, b2: (K, 3) the lines' offsets and slopes; lo, hi: (K,) the interval.

    Returns:
        ((K,) tau of the closest approach, (K,) the distance there).
    """
    da, db = a2 - a1, b2 - b1
    tc = np.clip(-np.sum(da * db, -1) / np.maximum(np.sum(db * db, -1), 1e-12), lo, hi)
    return tc, np.linalg.norm(da + db * tc[..., None], axis=-1)


def _apart(t, pos, splits, window):
    """For each split s (samples < s against samples >= s, with ``window`` samples on each side):
    the closest approach [m] of the two sides' flights between samples s-1 and s, and the larger of
    the two sides' worst sample deviation from their own flight [m]."""
    tau = t - t[0]
    p = pos.copy()
    p[:, 2] += 0.5 * GRAVITY * tau**2
    pre = splits[:, None] - window + np.arange(window)[None, :]
    post = splits[:, None] + np.arange(window)[None, :]
    a1, b1 = robust_lines(tau[pre], p[pre])
    a2, b2 = robust_lines(tau[post], p[post])
    _, apart = closest_approach(a1, b1, a2, b2, tau[splits - 1], tau[splits])
    dev = lambda idx, a, b: np.max(np.linalg.norm(p[idx] - (a[:, None] + b[:, None] * tau[idx][..., None]), axis=-1), 1)  # noqa: E731
    return apart, np.maximum(dev(pre, a1, b1), dev(post, a2, b2))


def find_breaks(t, pos, *, window: int = WINDOW, max_missing: int = MAX_MISSING, max_pause: float = MAX_PAUSE,
                max_jump: float = MAX_JUMP, max_speed: float = MAX_SPEED) -> list[Break]:
    """The breaks of one session (see the module docstring).

    Arguments:
        t: (T,) strictly increasing times [s]; pos: (T, 3) positions [m].
        window: samples per side of the flights compared.
        max_missing: frames that may be missing without a test.
        max_pause: longest silence [s] within one followed flight.
        max_jump: closest approach [m] of the flights either side beyond which they are two balls'.
        max_speed: fastest plausible ball [m/s].

    Returns:
        Breaks in time order.
    """
    t = np.asarray(t, np.float64)
    pos = np.asarray(pos, np.float64)
    n = len(t)
    if n < 2:
        return []
    dt = np.diff(t)
    step = np.linalg.norm(np.diff(pos, axis=0), axis=-1)
    found: dict[int, Break] = {}
    frame = float(np.median(dt))
    for i in np.flatnonzero(dt > max_pause):
        found[int(i) + 1] = Break(int(i) + 1, float(t[i] + 0.5 * dt[i]), "pause", float(dt[i]))
    # Timestamps jitter by milliseconds around the frame interval: a step is measured against at
    # least one frame, or a jittered pair of samples 1 ms apart reads as a 50 m/s ball.
    for i in np.flatnonzero(step > max_speed * np.maximum(dt, frame)):
        found.setdefault(int(i) + 1, Break(int(i) + 1, float(t[i] + 0.5 * dt[i]), "jump", float(step[i])))
    # Between the hard breaks, test every split for flights that do not meet; a split next to
    # another break has no clean window on that side and is not tested.
    edges = [0] + sorted(found) + [n]
    for lo, hi in zip(edges[:-1], edges[1:]):
        splits = np.arange(lo + window, hi - window + 1)
        if not len(splits):
            continue
        apart, dev = _apart(t[lo:hi], pos[lo:hi], splits - lo, window)
        # A contact inside a window bends its "line" as much as it moves it apart: demand that the
        # sides be clean flights, each within a quarter of the distance between them.
        bad = (apart > max_jump) & (dev < 0.25 * apart)
        for s, d, b in zip(splits, apart, bad):
            if not b:
                continue
            gap = t[s] - t[s - 1]
            reason = "gap" if gap > (max_missing + 1.5) * frame else "jump"
            found[int(s)] = Break(int(s), float(t[s - 1] + 0.5 * gap), reason, float(gap if reason == "gap" else d))
    return [found[k] for k in sorted(found)]


def track_slices(n: int, breaks: list[Break]) -> list[tuple[int, int]]:
    """(start, stop) offsets of the tracks of a session of ``n`` samples with ``breaks``."""
    cuts = [b.index for b in breaks]
    return list(zip([0] + cuts, cuts + [n]))


#: Flight-fit RMSE [m] beyond which a segment is reported as not one ballistic flight (the paper's
#: filtering threshold, as in :func:`ttsim_jax.data.segment.filter_segments`).
MAX_RMSE = 0.02
#: Sessions listed one by one in the report's text at most (the rest are summed up).
LISTED = 12


@dataclasses.dataclass
class TrackingReport:
    """What segmentation found in each session of a dataset, for the person who imported it.

    Attributes:
        sessions: one dict per session: ``session``, ``name``, ``tracks``, ``breaks`` {reason:
            count}, ``bounces`` (table events), ``contacts`` (other events), ``segments``,
            ``left_out`` (samples in no segment, in tracks shorter than ``min_samples``).
        warnings: one line per segment that no flight fits (naming session, time and RMSE).
        unfit: segment ids of the segments that no flight fits.
        min_samples: shortest track that forms segments.
    """

    sessions: list
    warnings: list
    unfit: list
    min_samples: int = MIN_SAMPLES

    def totals(self) -> dict:
        """The per-session counts summed over the sessions."""
        keys = ("tracks", "bounces", "contacts", "segments", "left_out")
        out = {k: int(sum(s[k] for s in self.sessions)) for k in keys}
        out["breaks"] = {r: int(sum(s["breaks"].get(r, 0) for s in self.sessions)) for r in ("pause", "gap", "jump")}
        return out

    @staticmethod
    def _line(d: dict, min_samples: int) -> str:
        br = ", ".join(f"{n} {r}{'s' if n != 1 else ''}" for r, n in d["breaks"].items() if n) or "no breaks"
        text = (f"{d['tracks']} track{'s' if d['tracks'] != 1 else ''} ({br}), {d['bounces']} table bounces, "
                f"{d['contacts']} other contacts, {d['segments']} segments")
        if d["left_out"]:
            text += f"; {d['left_out']} samples left out (in tracks of fewer than {min_samples} samples between breaks)"
        return text

    def __str__(self) -> str:
        lines = [f"segmentation: {len(self.sessions)} sessions: " + self._line(self.totals(), self.min_samples)]
        notable = [s for s in self.sessions if s["tracks"] > 1 or s["left_out"]]
        shown = self.sessions if len(self.sessions) <= LISTED else notable[:LISTED]
        for s in shown:
            lines.append(f"  session {s['session']}" + (f" ({s['name']})" if s["name"] else "") + ": " + self._line(s, self.min_samples))
        if len(self.sessions) > LISTED and len(notable) > LISTED:
            lines.append(f"  ... and {len(notable) - LISTED} more sessions with breaks")
        for w in self.warnings[:LISTED]:
            lines.append(f"warning: {w}")
        if len(self.warnings) > LISTED:
            lines.append(f"warning: ... {len(self.warnings) - LISTED} more like these")
        if self.unfit:
            lines.append(f"{len(self.unfit)} of {self.totals()['segments']} segments fit no ballistic flight within "
                         f"{MAX_RMSE * 1000:.0f} mm: import with --filter to leave them out of fits and diagnoses")
        return "\n".join(lines)


def tracking_report(ds, *, rmse_many: Callable | None = None, max_rmse: float = MAX_RMSE, min_samples: int = MIN_SAMPLES) -> TrackingReport:
    """What segmentation found per session, and the segments that no ballistic flight fits.

    Arguments:
        ds: a segmented dataset (:func:`ttsim_jax.data.segment.segments_from_events`).
        rmse_many: ``rmse_many(times, positions, spins) -> (S,) RMSE [m]`` of a flight fitted to each
            segment, to warn about those beyond ``max_rmse``; the CLI passes the batched
            constant-coefficient fit, :func:`ttsim_jax.fit.flightfit.ballistic_rmse_many` (it
            compiles once). None: no fit.
        max_rmse: RMSE [m] beyond which a segment is not one ballistic flight.
        min_samples: the segmentation's shortest track (for the text).

    Returns:
        :class:`TrackingReport`.
    """
    obs, ev, seg = ds.observations, ds.events, ds.segments
    pos = ds.positions
    names = dict(zip((int(s) for s in ds.sessions["session_id"]), ds.sessions["name"]))
    labelled_kinds = np.asarray(ev["kind"]).astype(str)
    sessions, warnings = [], []
    for sid, a, b in session_slices(obs["session_id"]):
        breaks = find_breaks(obs["t"][a:b], pos[a:b])
        in_session = ev["session_id"] == sid
        counts = {r: sum(br.reason == r for br in breaks) for r in ("pause", "gap", "jump")}
        sessions.append(dict(
            session=sid, name=str(names.get(sid, "")), tracks=len(breaks) + 1, breaks=counts,
            bounces=int(np.sum(in_session & (labelled_kinds == "table"))),
            contacts=int(np.sum(in_session & (labelled_kinds != "table"))),
            segments=int(np.sum(seg["session_id"] == sid)),
            left_out=int(np.sum(obs["segment_id"][a:b] < 0)),
        ))
    unfit = []
    if rmse_many is not None and len(seg["segment_id"]):
        rows = ds.segment_rows()
        usable = [k for k, r in enumerate(rows) if len(r) >= 3]
        if usable:
            spins = np.stack([seg[f"spin_{a}"] for a in "xyz"], -1)[usable]
            rmse = rmse_many([obs["t"][rows[k]] for k in usable], [pos[rows[k]] for k in usable], spins)
            for j, (k, r) in enumerate(zip(usable, rmse)):
                if not (r <= max_rmse):  # NaN too: a fit that failed
                    unfit.append(int(seg["segment_id"][k]))
                    warnings.append(
                        f"session {int(seg['session_id'][k])}, t = {seg['t_start'][k]:.3f} to {seg['t_end'][k]:.3f} s: "
                        f"segment {int(seg['segment_id'][k])} fits no ballistic flight (RMSE "
                        + (f"{r * 1000:.0f} mm" if np.isfinite(r) else "not finite") + f" > {max_rmse * 1000:.0f} mm): "
                        "two flights in one segment (a missed contact or pause), samples of something else, or a "
                        "flight its spin would explain" + ("" if spins[j].any() else " (no spin measured)"))
    return TrackingReport(sessions=sessions, warnings=warnings, unfit=unfit, min_samples=min_samples)
