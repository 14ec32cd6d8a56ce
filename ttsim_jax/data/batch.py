"""Padded, masked JAX batches of segments, events and racket contacts.

All batches are ``flax.struct`` dataclasses (pytrees), so they go through ``jax.jit`` / ``vmap``
as they are. Padding repeats the last real value (no NaN reaches a gradient) and is marked by
``mask == False``; padded segments have ``segment_id == -1``. Building a batch validates the
dataset first, so a bad row raises a :class:`~ttsim_jax.data.errors.DataError` instead of ending
up in a batch.
"""

from __future__ import annotations

from typing import Iterator

import jax.numpy as jnp
import numpy as np
from flax import struct

from . import schema
from .dataset import Dataset


@struct.dataclass
class SegmentBatch:
    """S flight segments, each padded to T samples.

    Attributes:
        times: (S, T) sample times relative to ``t0`` [s].
        positions: (S, T, 3) ball centre positions [m].
        spin: (S, 3) segment spin [rad/s] (zeros when unknown).
        spin_conf: (S,) spin confidence in [0, 1].
        mask: (S, T) True for real samples.
        t0: (S,) absolute time of each segment's first sample [s].
        segment_id: (S,) segment ids (-1 for padding).
        session_id: (S,) session ids (-1 for padding).
    """

    times: jnp.ndarray
    positions: jnp.ndarray
    spin: jnp.ndarray
    spin_conf: jnp.ndarray
    mask: jnp.ndarray
    t0: jnp.ndarray
    segment_id: jnp.ndarray
    session_id: jnp.ndarray


@struct.dataclass
class EventBatch:
    """E contact events.

    Attributes:
        t: (E,) contact times [s].
        kind: (E,) integer codes, index into :data:`schema.EVENT_KINDS`.
        position: (E, 3) ball centre at the contact [m].
        event_id: (E,) ids.
        session_id: (E,) session ids.
        mask: (E,) True for real events (False for padding).
    """

    t: jnp.ndarray
    kind: jnp.ndarray
    position: jnp.ndarray
    event_id: jnp.ndarray
    session_id: jnp.ndarray
    mask: jnp.ndarray


@struct.dataclass
class RacketContactBatch:
    """R racket contacts with the racket state and the segments before and after.

    Attributes:
        t: (R,) contact times [s].
        ball_position: (R, 3) ball centre at the contact [m].
        racket_position: (R, 3) face centre [m].
        racket_quat: (R, 4) orientation racket -> world (w, x, y, z).
        racket_velocity: (R, 3) [m/s].
        racket_ang_vel: (R, 3) [rad/s], world frame.
        contact_point: (R, 2) (d_y, d_z) on the face [m].
        in_segment: (R,) row in the dataset's segments table of the incoming segment (-1: none).
        out_segment: (R,) row of the outgoing segment (-1: none).
        event_id: (R,) ids.
        mask: (R,) True for real contacts.
    """

    t: jnp.ndarray
    ball_position: jnp.ndarray
    racket_position: jnp.ndarray
    racket_quat: jnp.ndarray
    racket_velocity: jnp.ndarray
    racket_ang_vel: jnp.ndarray
    contact_point: jnp.ndarray
    in_segment: jnp.ndarray
    out_segment: jnp.ndarray
    event_id: jnp.ndarray
    mask: jnp.ndarray


def _checked(ds: Dataset, validate: bool) -> Dataset:
    if validate:
        from .validate import validate as check

        check(ds)
    return ds


def segment_lengths(ds: Dataset) -> np.ndarray:
    """(S,) number of observations of each row of ``ds.segments``."""
    ids, counts = np.unique(ds.observations["segment_id"], return_counts=True)
    lookup = dict(zip(ids.tolist(), counts.tolist()))
    return np.array([lookup.get(int(s), 0) for s in ds.segments["segment_id"]], np.int64)


def segment_batch(
    ds: Dataset,
    rows=None,
    *,
    max_len: int | None = None,
    pad_to: int | None = None,
    dtype=np.float32,
    validate: bool = True,
) -> SegmentBatch:
    """One padded batch of segments.

    Arguments:
        ds: segmented dataset.
        rows: rows of ``ds.segments`` to include (default: all), in that order.
        max_len: T, the padded length (default: the longest segment of ``ds``; longer segments
            are cut to their first ``max_len`` samples).
        pad_to: S, pad the batch with empty segments up to this many rows.
        dtype: float dtype of times and positions.
        validate: validate ``ds`` first.

    Returns:
        :class:`SegmentBatch`.
    """
    ds = _checked(ds, validate)
    seg = ds.segments
    obs = ds.observations
    rows = np.arange(len(seg["segment_id"])) if rows is None else np.asarray(rows, np.int64)
    lengths_all = segment_lengths(ds)
    T = int(max_len if max_len is not None else max(int(lengths_all.max(initial=0)), 1))
    S = len(rows) if pad_to is None else int(pad_to)
    if S < len(rows):
        raise ValueError(f"pad_to={pad_to} is smaller than the {len(rows)} segments requested")
    members_of = ds.segment_rows(seg["segment_id"][rows])
    times = np.zeros((S, T), dtype)
    pos = np.zeros((S, T, 3), dtype)
    mask = np.zeros((S, T), bool)
    t0 = np.zeros(S, np.float64)
    spin = np.zeros((S, 3), dtype)
    conf = np.zeros(S, dtype)
    seg_id = np.full(S, -1, np.int64)
    ses_id = np.full(S, -1, np.int64)
    p_all = ds.positions
    for j, k in enumerate(rows):
        sid = seg["segment_id"][k]
        members = members_of[j][:T]
        n = len(members)
        seg_id[j] = sid
        ses_id[j] = seg["session_id"][k]
        spin[j] = (seg["spin_x"][k], seg["spin_y"][k], seg["spin_z"][k])
        conf[j] = seg["spin_conf"][k]
        if n == 0:
            continue
        t = obs["t"][members]
        t0[j] = t[0]
        times[j, :n] = t - t[0]
        times[j, n:] = t[-1] - t[0]
        pos[j, :n] = p_all[members]
        pos[j, n:] = p_all[members[-1]]
        mask[j, :n] = True
    return SegmentBatch(
        times=jnp.asarray(times),
        positions=jnp.asarray(pos),
        spin=jnp.asarray(spin),
        spin_conf=jnp.asarray(conf),
        mask=jnp.asarray(mask),
        t0=jnp.asarray(t0.astype(dtype)),
        segment_id=jnp.asarray(seg_id.astype(np.int32)),
        session_id=jnp.asarray(ses_id.astype(np.int32)),
    )


def iter_segment_batches(
    ds: Dataset,
    batch_size: int,
    *,
    max_len: int | None = None,
    shuffle: bool = False,
    seed: int = 0,
    drop_remainder: bool = False,
    dtype=np.float32,
) -> Iterator[SegmentBatch]:
    """Yields batches of ``batch_size`` segments, all of the same shape (one compilation).

    Arguments:
        ds: segmented dataset (validated once, up front).
        batch_size: S.
        max_len: T (default: the longest segment of the whole dataset, so every batch has it).
        shuffle: visit segments in a random order drawn from ``seed``.
        seed: random seed for ``shuffle``.
        drop_remainder: skip the last, partly empty batch instead of padding it.
        dtype: float dtype.

    Yields:
        :class:`SegmentBatch` of shape (batch_size, T).
    """
    _checked(ds, True)
    n = len(ds.segments["segment_id"])
    T = max_len if max_len is not None else max(int(segment_lengths(ds).max(initial=0)), 1)
    order = np.random.default_rng(seed).permutation(n) if shuffle else np.arange(n)
    for start in range(0, n, batch_size):
        rows = order[start : start + batch_size]
        if len(rows) < batch_size and drop_remainder:
            return
        yield segment_batch(ds, rows, max_len=T, pad_to=batch_size, dtype=dtype, validate=False)


def event_batch(ds: Dataset, *, kinds=None, pad_to: int | None = None, dtype=np.float32, validate: bool = True) -> EventBatch:
    """All events (or those of ``kinds``) as one padded batch.

    Arguments:
        ds: dataset.
        kinds: optional iterable of kinds to keep (e.g. ``("table",)``).
        pad_to: pad to this many rows.
        dtype: float dtype.
        validate: validate ``ds`` first.

    Returns:
        :class:`EventBatch`.
    """
    ds = _checked(ds, validate)
    ev = ds.events
    keep = np.ones(len(ev["event_id"]), bool) if kinds is None else np.isin(ev["kind"].astype(str), list(kinds))
    rows = np.flatnonzero(keep)
    E = len(rows) if pad_to is None else int(pad_to)
    if E < len(rows):
        raise ValueError(f"pad_to={pad_to} is smaller than the {len(rows)} events")

    def padded(values, fill, dt):
        out = np.full((E,) + values.shape[1:], fill, dt)
        out[: len(values)] = values
        return jnp.asarray(out)

    pos = np.stack([ev["x"], ev["y"], ev["z"]], -1)[rows]
    codes = np.array([schema.EVENT_CODES[k] for k in ev["kind"][rows]], np.int32)
    return EventBatch(
        t=padded(ev["t"][rows], 0.0, dtype),
        kind=padded(codes, -1, np.int32),
        position=padded(pos, 0.0, dtype),
        event_id=padded(ev["event_id"][rows], -1, np.int32),
        session_id=padded(ev["session_id"][rows], -1, np.int32),
        mask=padded(np.ones(len(rows), bool), False, bool),
    )


def racket_contact_batch(ds: Dataset, *, pad_to: int | None = None, dtype=np.float32, validate: bool = True) -> RacketContactBatch:
    """All racket contacts, joined with their events and neighbouring segments.

    Arguments:
        ds: dataset.
        pad_to: pad to this many rows.
        dtype: float dtype.
        validate: validate ``ds`` first (which guarantees every racket event has a state).

    Returns:
        :class:`RacketContactBatch`.
    """
    ds = _checked(ds, validate)
    rk, ev = ds.rackets, ds.events
    n = len(rk["event_id"])
    R = n if pad_to is None else int(pad_to)
    if R < n:
        raise ValueError(f"pad_to={pad_to} is smaller than the {n} racket contacts")
    rows = ds.event_rows(rk["event_id"])
    in_rows, out_rows = ds.segments_around(rk["event_id"])

    def stack(table, names, index=None):
        a = np.stack([np.asarray(table[k], np.float64) for k in names], -1)
        return a if index is None else a[index]

    def padded(values, fill, dt):
        out = np.full((R,) + values.shape[1:], fill, dt)
        out[:n] = values
        return jnp.asarray(out)

    quat_fill = np.zeros((R, 4), dtype)
    quat_fill[:, 0] = 1.0  # padding gets the identity, so rotations built from it stay finite
    quat_fill[:n] = stack(rk, ("qw", "qx", "qy", "qz"))
    return RacketContactBatch(
        t=padded(ev["t"][rows] if n else np.zeros(0), 0.0, dtype),
        ball_position=padded(stack(ev, ("x", "y", "z"), rows) if n else np.zeros((0, 3)), 0.0, dtype),
        racket_position=padded(stack(rk, ("x", "y", "z")) if n else np.zeros((0, 3)), 0.0, dtype),
        racket_quat=jnp.asarray(quat_fill),
        racket_velocity=padded(stack(rk, ("vx", "vy", "vz")) if n else np.zeros((0, 3)), 0.0, dtype),
        racket_ang_vel=padded(stack(rk, ("wx", "wy", "wz")) if n else np.zeros((0, 3)), 0.0, dtype),
        contact_point=padded(stack(rk, ("d_y", "d_z")) if n else np.zeros((0, 2)), 0.0, dtype),
        in_segment=padded(in_rows.astype(np.int32), -1, np.int32),
        out_segment=padded(out_rows.astype(np.int32), -1, np.int32),
        event_id=padded(np.asarray(rk["event_id"]), -1, np.int32),
        mask=padded(np.ones(n, bool), False, bool),
    )
