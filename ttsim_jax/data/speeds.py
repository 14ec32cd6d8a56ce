"""Sample-to-sample speeds of a record, each step measured over at least a frame, and the flight
segments faster than any ball: what the plausibility checks (:mod:`ttsim_jax.data.validate`), the
import's glitch rules (:mod:`ttsim_jax.data.glitches`) and ``ttsim data info`` read."""

from __future__ import annotations

import numpy as np

from .dataset import Dataset
from .tracks import MAX_SPEED


def group_medians(keys: np.ndarray, values: np.ndarray):
    """Medians of ``values`` per run of equal ``keys`` (runs contiguous): (keys, first index, medians)."""
    start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    stop = np.r_[start[1:], len(keys)]
    group = np.repeat(np.arange(len(start)), stop - start)
    v = values[np.lexsort((values, group))]
    return keys[start], start, 0.5 * (v[start + (stop - start - 1) // 2] + v[start + (stop - start) // 2])


def step_speeds(ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Speeds between consecutive samples of one session [m/s], each step measured against at
    least the session's frame (its median sampling interval), as the breaks are
    (:func:`ttsim_jax.data.tracks.find_breaks`): timestamps that jitter by a millisecond bring two
    samples 10 us apart now and then, and 1 cm over 10 us reads as a 1,000 m/s ball.

    Returns:
        (rows (K,) the first sample of each step, speeds (K,)).
    """
    obs = ds.observations
    sid = np.asarray(obs["session_id"])
    inner = np.flatnonzero(sid[1:] == sid[:-1])
    if not inner.size:
        return inner, np.zeros(0)
    t = np.asarray(obs["t"], np.float64)
    dt = t[inner + 1] - t[inner]
    runs = np.flatnonzero(np.r_[True, sid[inner][1:] != sid[inner][:-1]])
    _, _, frames = group_medians(sid[inner], dt)
    frame = np.repeat(frames, np.diff(np.r_[runs, len(inner)]))
    pos = ds.positions
    return inner, np.linalg.norm(pos[inner + 1] - pos[inner], axis=-1) / np.maximum(dt, frame)


def run_speeds(ds: Dataset):
    """Contiguous runs of samples of one segment (or, outside segments, of one session) and their
    speeds: (start (G,) first row of each run, count (G,), group (N,) each sample's run, speed (G,)
    the run's median sample-to-sample speed [m/s], :func:`step_speeds`)."""
    obs = ds.observations
    seg, sid = np.asarray(obs["segment_id"]), np.asarray(obs["session_id"])
    n = len(seg)
    start = np.flatnonzero(np.r_[True, (seg[1:] != seg[:-1]) | (sid[1:] != sid[:-1])])  # contiguous (validated)
    count = np.diff(np.r_[start, n])
    group = np.repeat(np.arange(len(start)), count)
    rows, step = step_speeds(ds)
    within = group[rows + 1] == group[rows]
    speed = np.zeros(len(start))  # median sample-to-sample speed: a tracking jump does not move it
    if within.any():
        g, _, med = group_medians(group[rows[within] + 1], step[within])
        speed[g] = med
    return start, count, group, speed


def implausible_segments(ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The flight segments that fly faster than any ball in the game (:data:`MAX_SPEED`, by the
    median of their sample-to-sample speeds, each step measured against at least a frame).

    Returns:
        (segment ids (K,), their speeds (K,) [m/s]).
    """
    if len(ds.observations["t"]) < 2:
        return np.zeros(0, np.int64), np.zeros(0)
    start, _, _, speed = run_speeds(ds)
    seg = np.asarray(ds.observations["segment_id"])[start]
    bad = (speed > MAX_SPEED) & (seg >= 0)
    return seg[bad].astype(np.int64), speed[bad]
