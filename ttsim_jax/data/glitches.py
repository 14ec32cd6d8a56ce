"""What a tracker's log holds that no followed ball does, mended or left out at import instead of
refusing the log: frames out of time order, duplicated frames, segments faster than any ball.

Loggers that stamp each frame when it arrives and sort by that stamp write frames whose times
jitter by a millisecond, now and then two of them out of order or with the same stamp; a glitch
(another object picked up, a mislabelled frame) leaves a short segment flying at hundreds of m/s.
A unit error (millimetres given as metres, seconds as milliseconds) makes *every* segment
implausible, a glitch a few: so a log is refused only when most of its segments fail
(:data:`MAX_LEFT_OUT`), and otherwise the failing ones are left out with a warning each (session,
time, rule) and counted in the dataset's metadata (``Metadata.left_out``, shown by ``ttsim data
info``).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from .dataset import Dataset
from .errors import DataWarning
from .segment import drop_segments
from .tracks import MAX_SPEED
from .speeds import implausible_segments
from .validate import MAX_ABS_POSITION, MAX_SPIN

#: Largest share of a log's segments left out as glitches; beyond it the log is refused (the
#: validation's message names the first bad segment and asks about units).
MAX_LEFT_OUT = 0.5
#: Warnings written one by one at most (the rest are counted).
LISTED = 5
#: Keys of ``Metadata.left_out``.
REORDERED = "samples reordered (out of time order by less than a frame)"
DUPLICATES = "samples dropped (a second frame with the same time stamp)"
FAR = f"samples dropped (further than {MAX_ABS_POSITION:g} m from the table)"
SPIN = f"spins dropped (beyond {MAX_SPIN:.0f} rad/s; the samples kept)"
TOO_FAST = f"segments left out (faster than any ball, {MAX_SPEED:g} m/s)"


def time_order(session_id: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, dict]:
    """The rows of a log in time order within each session, where its frames are out of order by
    less than a frame (the session's median sampling interval), without the second of two frames
    with the same time stamp.

    A session with a frame earlier than its predecessor by a frame or more is left in file order
    (the validation then refuses it, naming the line): that is no jitter but a log that went back in
    time, or sessions mixed up. Rows of a session that are not contiguous are left as they are too.

    Arguments:
        session_id: (N,) each row's session; t: (N,) times [s], in file order.

    Returns:
        (rows (M,) indices into the file's rows, in the order to keep, {what: count} of the rows
        reordered and dropped, keys :data:`REORDERED` and :data:`DUPLICATES`, only where nonzero).
    """
    sid = np.asarray(session_id)
    t = np.asarray(t, np.float64)
    n = len(t)
    starts = np.flatnonzero(np.r_[True, sid[1:] != sid[:-1]]) if n else np.zeros(0, int)
    stops = np.r_[starts[1:], n]
    rows, moved, dropped = [], 0, 0
    for a, b in zip(starts, stops):
        idx = np.arange(a, b)
        ts = t[a:b]
        dt = np.diff(ts)
        if len(dt) and (dt < 0).any():
            frame = float(np.median(dt[dt > 0])) if (dt > 0).any() else 0.0
            behind = np.maximum.accumulate(ts)[:-1] - ts[1:]  # how far each frame lags the latest before it
            if behind.max() < frame:
                order = np.argsort(ts, kind="stable")
                moved += int(np.count_nonzero(order != np.arange(len(order))))
                idx, ts = idx[order], ts[order]
        same = np.r_[False, ts[1:] == ts[:-1]]
        dropped += int(same.sum())
        rows.append(idx[~same])
    counts = {k: v for k, v in ((REORDERED, moved), (DUPLICATES, dropped)) if v}
    return (np.concatenate(rows) if rows else np.zeros(0, int)), counts


def far_samples(pos: np.ndarray, spin: np.ndarray | None, where=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Which samples of a log sit where no ball is (further than
    :data:`~ttsim_jax.data.validate.MAX_ABS_POSITION` from the table's centre: left out) or carry a
    spin no ball has (beyond :data:`~ttsim_jax.data.validate.MAX_SPIN`: their position kept, their
    spin dropped), when only a few do: glitches, each named in a warning (the first :data:`LISTED`,
    then a count). Where more than :data:`MAX_LEFT_OUT` of the samples do, nothing is changed, for
    the validation to refuse the log with its message about units ("looks like millimetres", "is
    it in rad/s?").

    Arguments:
        pos: (N, 3) [m]; spin: (N, 3) [rad/s] or None; where: optional ``where(row) -> str``, the
            place of a row in the user's file, for the warnings.

    Returns:
        (keep (N,) bool, unspun (N,) bool: samples whose spin is to be dropped, {what: count} of
        :data:`FAR` and :data:`SPIN`, where nonzero).
    """
    n_rows = len(pos)
    with np.errstate(invalid="ignore"):
        far = np.any(np.abs(pos) > MAX_ABS_POSITION, axis=-1)
        unspun = (np.linalg.norm(spin, axis=-1) > MAX_SPIN) & ~far if spin is not None else np.zeros(n_rows, bool)
    counts, said = {}, 0
    for mask, key in ((far, FAR), (unspun, SPIN)):
        n = int(mask.sum())
        if not n or n > MAX_LEFT_OUT * n_rows:
            mask[:] = False
            continue
        counts[key] = n
        for row in np.flatnonzero(mask)[:max(LISTED - said, 0)]:
            at = f" ({where(int(row))})" if where is not None else ""
            what = (f"left out: at {np.round(pos[row], 3).tolist()} m, where no ball is" if key == FAR else
                    f"spin dropped: {np.linalg.norm(spin[row]):.4g} rad/s, more than any contact gives a ball")
            warnings.warn(DataWarning(f"a sample{at} {what}: a tracking glitch ({n} of {n_rows} samples)"), stacklevel=3)
            said += 1
    if said < sum(counts.values()):
        warnings.warn(DataWarning(f"... and {sum(counts.values()) - said} more such samples"), stacklevel=3)
    return ~far, unspun, counts


def leave_out_too_fast(ds: Dataset, where=None) -> tuple[Dataset, dict]:
    """``ds`` without its segments faster than any ball (:func:`~ttsim_jax.data.speeds.implausible_segments`),
    each named in a :class:`~ttsim_jax.data.errors.DataWarning` (the first :data:`LISTED`, then a
    count), unless more than :data:`MAX_LEFT_OUT` of the segments are (then ``ds`` is returned
    whole, for the validation to refuse with its message about units).

    Arguments:
        ds: a segmented dataset.
        where: optional ``where(row) -> str``, the place of an observation row in the user's file
            (e.g. its line), for the warnings.

    Returns:
        (dataset, {:data:`TOO_FAST`: count} or {}).
    """
    ids, speeds = implausible_segments(ds)
    total = len(ds.segments["segment_id"])
    if not len(ids) or len(ids) > MAX_LEFT_OUT * total:
        return ds, {}
    obs = ds.observations
    seg_of, sid, t = np.asarray(obs["segment_id"]), np.asarray(obs["session_id"]), np.asarray(obs["t"])
    for k, (i, v) in enumerate(zip(ids, speeds)):
        if k == LISTED:
            warnings.warn(DataWarning(f"... and {len(ids) - LISTED} more segments faster than {MAX_SPEED:g} m/s left out"),
                          stacklevel=3)
            break
        row = int(np.flatnonzero(seg_of == i)[0])
        at = f" ({where(row)})" if where is not None else ""
        warnings.warn(DataWarning(
            f"segment {int(i)} (session {int(sid[row])}, t = {float(t[row]):.4f} s{at}) left out: it flies at {v:.4g} m/s "
            f"(median of its sample-to-sample speeds), faster than any ball ({MAX_SPEED:g} m/s): a tracking glitch "
            f"({len(ids)} of {total} segments)"), stacklevel=3)
    keep = ~np.isin(ds.segments["segment_id"], ids)
    return drop_segments(ds, keep), {TOO_FAST: int(len(ids))}


def noted(ds: Dataset, counts: dict) -> Dataset:
    """``ds`` with ``counts`` added to its metadata's ``left_out``."""
    if not counts:
        return ds
    left = dict(ds.metadata.left_out)
    for k, v in counts.items():
        left[k] = int(left.get(k, 0)) + int(v)
    return ds.replace(metadata=dataclasses.replace(ds.metadata, left_out=left))
