"""Flight segments as padded arrays for the compiled flight fit (:mod:`ttsim_jax.fit.flightfit`).

Segments have different lengths. They are padded to a *capacity* (the smallest of ``CAPACITIES``
that holds them; padded samples repeat the last time, so their steps have dt = 0, and carry mask
0), and the integration is a ``while_loop`` that stops at the longest segment of its group: the
work follows the actual lengths while the compiled shape stays (rows, capacity). Segments are
sorted by length and split evenly into groups of at most ``GROUP`` (16) of similar length, one
compiled call each (dispatched ``BATCH // rows`` at a time before the results are awaited), each
with its own integration length and its own stopping iteration. On CPU a step costs per segment
(the tangent arithmetic is not vectorised across segments), so small groups waste little on
padding and on waiting for a slow segment. One capacity means one compilation.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

#: Padded lengths (samples). A segment longer than the last is refused.
CAPACITIES = (256, 1024, 4096)
#: Segments per compiled call.
BATCH = 256
#: Segments integrated side by side within a call: a group's loops run until its slowest segment
#: is done, so small groups of similar lengths waste little (each step's cost is per segment on CPU).
GROUP = 16


def dataset_segments(ds, min_samples: int = 5):
    """The flight segments of a dataset as lists for :func:`~ttsim_jax.fit.flightfit.fit_segments`.

    Arguments:
        ds: a :class:`~ttsim_jax.data.Dataset` with segments.
        min_samples: segments with fewer observations are left out.

    Returns:
        (segment_ids (S,), times list, positions list, spins (S, 3), spin_conf (S,)).
    """
    seg, obs = ds.segments, ds.observations
    pos = ds.positions
    ids, times, positions, spins, conf = [], [], [], [], []
    for k, (sid, rows) in enumerate(zip(seg["segment_id"], ds.segment_rows())):
        if len(rows) < min_samples:
            continue
        ids.append(int(sid))
        times.append(obs["t"][rows])
        positions.append(pos[rows])
        spins.append([seg["spin_x"][k], seg["spin_y"][k], seg["spin_z"][k]])
        conf.append(seg["spin_conf"][k])
    return np.asarray(ids, np.int64), times, positions, np.asarray(spins, np.float64).reshape(-1, 3), np.asarray(conf)


def capacity(n: int) -> int:
    """The padded length of a segment of ``n`` samples (the smallest of :data:`CAPACITIES`)."""
    for c in CAPACITIES:
        if n <= c:
            return c
    raise ValueError(f"a segment of {n} samples is longer than the largest capacity {CAPACITIES[-1]}")


def pack(times: Sequence[np.ndarray], positions: Sequence[np.ndarray], spins, rows: Sequence[int], size: int,
         batch: int, dtype=np.float32):
    """Pads segments ``rows`` into arrays (batch, size) for :func:`~ttsim_jax.fit.flightfit.fit_batch`; unused rows are empty."""
    tau = np.zeros((batch, size), dtype)
    pos = np.zeros((batch, size, 3), dtype)
    mask = np.zeros((batch, size), dtype)
    spin = np.zeros((batch, 3), dtype)
    for row, i in enumerate(rows):
        t = np.asarray(times[i], np.float64)
        k = len(t)
        tau[row, :k] = t - t[0]
        tau[row, k:] = tau[row, k - 1]
        pos[row, :k] = positions[i]
        pos[row, k:] = positions[i][-1]
        mask[row, :k] = 1.0
        spin[row] = spins[i]
    return tau, pos, mask, spin


def balanced_rows(count: int, batch: int) -> int:
    """Rows per batch for ``count`` segments of one capacity: as few batches of at most ``batch``
    rows as hold them, all of one size (one compilation), that size rounded up to a multiple of 8.

    Equal batches rather than full ones and a remainder: the last batch holds the longest
    segments, and its work is its row count times its longest segment, padding rows included.
    """
    n_batches = -(-count // batch)
    return -(-(-(-count // n_batches)) // 8) * 8


def batches(times, positions, spins, batch: int = BATCH, dtype=np.float32, min_samples: int = 3,
            pow2_rows: bool = False):
    """Padded batches of segments: sorted by length, grouped by capacity, ``batch`` rows each.

    The segments of one capacity are split into batches of equal size (:func:`balanced_rows`: one
    shape, one compilation, per capacity): a batch's work is its row count times its longest
    segment. ``pow2_rows``: the row count rounded up to a power of two (at most ``batch``), so that
    a caller making many calls of varying counts compiles a few shapes only.

    Yields:
        (idx, (tau, pos, mask, spin), n_max): the segments' indices (rows beyond ``len(idx)`` are
        empty), the arrays of :func:`pack` and the longest segment's length.
    """
    lengths = np.array([len(t) for t in times], int)
    groups: dict[int, list[int]] = {}
    for i in np.argsort(lengths, kind="stable"):
        if lengths[i] >= min_samples:
            groups.setdefault(capacity(int(lengths[i])), []).append(int(i))
    for size, members in sorted(groups.items()):
        rows = balanced_rows(len(members), batch)
        if pow2_rows:
            rows = min(batch, 1 << (rows - 1).bit_length())
        n_batches = -(-len(members) // rows)
        for part in np.array_split(np.asarray(members), n_batches):
            idx = part.tolist()
            yield idx, pack(times, positions, spins, idx, size, rows, dtype), int(lengths[idx].max())


def grouped_batches(times, positions, spins, batch: int = BATCH, group: int = GROUP, dtype=np.float32):
    """The groups of :func:`batches` (at most ``group`` rows each), ``batch // rows`` to a
    :func:`~ttsim_jax.fit.flightfit.fit_batch` call. Every group of one capacity has the same shape: one compilation.

    Yields:
        (idx, rows, (tau, pos, mask, spin), n_max): the segments' indices and their rows in the
        call's flattened G * R rows, the arrays stacked to (G, R, ...) and (G,) longest lengths.
    """
    calls: list = []

    def flush():
        rows_per = calls[0][1][0].shape[0]
        arrays = tuple(np.stack([c[1][k] for c in calls]) for k in range(4))
        n_max = np.array([c[2] for c in calls], np.int32)
        idx = [i for c in calls for i in c[0]]
        rows = [g * rows_per + r for g, c in enumerate(calls) for r in range(len(c[0]))]
        calls.clear()
        return idx, rows, arrays, n_max

    for item in batches(times, positions, spins, group, dtype):
        if calls and (item[1][0].shape != calls[0][1][0].shape or len(calls) >= max(1, batch // len(item[1][0]))):
            yield flush()
        calls.append(item)
    if calls:
        yield flush()

