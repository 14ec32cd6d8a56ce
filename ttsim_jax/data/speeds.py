"""Sample-to-sample speeds of a record, each step measured over at least a frame, and the flight
segments faster than any ball: what the plausibility checks (:mod:`ttsim_jax.data.validate`), the
import's glitch rules (:mod:`ttsim_jax.data.glitches`) and ``ttsim data info`` read."""

from __future__ import annotations

import numpy as np

from .dataset import Dataset
from .tracks import GRAVITY, MAX_SPEED, MIN_SAMPLES

#: Most drag plus Magnus acceleration per squared air speed [1/m]: rho A / (2 m) = 0.28 for a 40 mm,
#: 2.7 g ball in air of 1.2 kg/m^3, times |(C_D, C_M)| <= 1.25 (C_D 0.37-0.55 in the paper's table;
#: lift coefficients of spinning spheres saturate near 0.6, and durr2026 caps its C_M at 1.0).
AERO_PER_SPEED2 = 0.35
#: Air speed [m/s] a ball may have on top of its own (indoor draughts; the generator's wind is
#: within 0.5 m/s).
DRAUGHT = 1.0
#: Standard errors of a segment's fitted acceleration beyond the physical bound that make it borderline.
ACCEL_SIGMAS = 5.0


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


def parabola_accelerations(group, t, pos, speed):
    """Per group (contiguous runs of samples), the acceleration of a least-squares parabola in time
    per axis, the physical bound on it and its standard error.

    Arguments:
        group: (N,) group index of each sample, runs 0, 1, ...; t: (N,) times [s]; pos: (N, 3) [m].
        speed: (G,) each group's median sample-to-sample speed [m/s].

    Returns:
        (G,) |a - g| [m/s^2]; (G,) the bound AERO_PER_SPEED2 (v + DRAUGHT)^2 at the larger of the
        median speed and the fitted speed at either end; (G,) the standard error of the fitted
        acceleration per axis (NaN for fewer than 4 samples).
    """
    n_groups = len(speed)
    count = np.bincount(group, minlength=n_groups)
    start = np.r_[0, np.cumsum(count)[:-1]]
    tau = t - (np.bincount(group, t, n_groups) / count)[group]  # centred: a well-conditioned fit
    powers = np.stack([tau**k for k in range(5)], -1)
    moments = np.stack([np.bincount(group, powers[:, k], n_groups) for k in range(5)], -1)
    normal = np.stack([moments[:, i:i + 3] for i in range(3)], 1)  # (G, 3, 3)
    rhs = np.stack([np.stack([np.bincount(group, powers[:, k] * pos[:, ax], n_groups) for ax in range(3)], -1)
                    for k in range(3)], 1)  # (G, 3 powers, 3 axes)
    with np.errstate(all="ignore"):
        inv = np.linalg.pinv(normal)
        c = inv @ rhs  # offset, velocity, half the acceleration
        rss = np.maximum(np.bincount(group, np.sum(pos**2, -1), n_groups) - np.sum(c * rhs, axis=(1, 2)), 0.0)
        dof = np.where(count > 3, 3 * (count - 3), np.nan)
        sigma = 2.0 * np.sqrt(rss / dof * np.maximum(inv[:, 2, 2], 0.0))
        a = np.linalg.norm(2.0 * c[:, 2] - np.array([0.0, 0.0, -GRAVITY]), axis=-1)
        ends = np.stack([np.minimum.reduceat(tau, start), np.maximum.reduceat(tau, start)], -1)
        v_ends = np.linalg.norm(c[:, None, 1] + 2.0 * c[:, None, 2] * ends[..., None], axis=-1).max(-1)
    bound = AERO_PER_SPEED2 * (np.maximum(speed, v_ends) + DRAUGHT) ** 2
    return a, bound, sigma


def acceleration_excess(group, t, pos, speed, fit):
    """(a, bound, sigma, excess) of :func:`parabola_accelerations` and by how much each group's
    acceleration exceeds the bound beyond :data:`ACCEL_SIGMAS` standard errors (-inf where
    ``fit`` is False or the error is unknown): positive for no free flight (a contact or a tracking
    error inside it)."""
    a, bound, sigma = parabola_accelerations(group, t, pos, speed)
    return a, bound, sigma, np.where(fit & np.isfinite(sigma), a - bound - ACCEL_SIGMAS * sigma, -np.inf)


def non_flights(ds: Dataset) -> np.ndarray:
    """The ids of the segments (of at least :data:`~ttsim_jax.data.tracks.MIN_SAMPLES` samples)
    whose samples no free flight can give: their parabola's acceleration exceeds gravity plus the
    most drag and Magnus force their speed allows, beyond the fit's noise (a ball rolling, resting
    or caught inside the segment, or a tracking error): what validation warns of."""
    if len(ds.observations["t"]) < 2:
        return np.zeros(0, np.int64)
    start, count, group, speed = run_speeds(ds)
    seg = np.asarray(ds.observations["segment_id"])[start]
    fit = (count >= MIN_SAMPLES) & (seg >= 0)
    if not fit.any():
        return np.zeros(0, np.int64)
    *_, excess = acceleration_excess(group, np.asarray(ds.observations["t"], np.float64), ds.positions, speed, fit)
    return np.unique(seg[excess > 0]).astype(np.int64)
