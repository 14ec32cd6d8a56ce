"""The paper's segment filter: segments too short, with too little spin confidence, or that the
constant-coefficient flight fit (:mod:`ttsim_jax.fit.flightfit`) cannot follow to within
``max_rmse``, are dropped from a dataset, and the report says how many and why.

It sits with the flight fit rather than with the segmentation in :mod:`ttsim_jax.data.segment`
because it runs that fit; what it drops is dropped by :func:`ttsim_jax.data.segment.drop_segments`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ttsim_jax.data.dataset import Dataset
from ttsim_jax.data.segment import drop_segments

from .flightfit import ballistic_rmse_many


@dataclasses.dataclass
class FilterReport:
    """What :func:`filter_segments` kept and dropped.

    Attributes:
        total: segments examined.
        kept: segments kept.
        dropped: reason -> segment ids dropped for it (first failing reason only). Reasons:
            ``too_short``, ``low_spin_conf``, ``rmse``.
        rmse: segment id -> fitted RMSE [m] for every segment that was fitted.
        thresholds: the thresholds used.
    """

    total: int = 0
    kept: int = 0
    dropped: dict = dataclasses.field(default_factory=lambda: {"too_short": [], "low_spin_conf": [], "rmse": []})
    rmse: dict = dataclasses.field(default_factory=dict)
    thresholds: dict = dataclasses.field(default_factory=dict)

    def counts(self) -> dict:
        """reason -> number of segments dropped for it."""
        return {k: len(v) for k, v in self.dropped.items()}

    def __str__(self) -> str:
        parts = ", ".join(f"{n} {reason}" for reason, n in self.counts().items())
        th = ", ".join(f"{k}={v}" for k, v in self.thresholds.items())
        return f"kept {self.kept} of {self.total} segments; dropped: {parts} ({th})"


def filter_segments(
    ds: Dataset,
    *,
    min_spin_conf: float | None = 0.5,
    max_rmse: float | None = 0.02,
    min_samples: int = 5,
    rmse_fn: Callable | None = None,
) -> tuple[Dataset, FilterReport]:
    """Drops segments unfit for model fitting, as in the paper, and reports why.

    Arguments:
        ds: segmented dataset.
        min_spin_conf: drop segments whose spin confidence is below this (None: keep all).
        max_rmse: drop segments whose flight-model fit has a larger RMSE [m] (None: no fit).
        min_samples: drop segments with fewer observations.
        rmse_fn: ``rmse_fn(times (T,), positions (T, 3), spin (3,)) -> rmse_m``; default: the
            constant-coefficient aerodynamic fit of :mod:`ttsim_jax.fit.flightfit` (run batched).

    Returns:
        (dataset, report): the dataset without the dropped segments (their observations stay, with
        ``segment_id = -1``; events stay), and a :class:`FilterReport`.
    """
    seg = ds.segments
    obs = ds.observations
    report = FilterReport(thresholds={"min_spin_conf": min_spin_conf, "max_rmse": max_rmse, "min_samples": min_samples})
    ids = seg["segment_id"]
    report.total = len(ids)
    counts = dict(zip(*np.unique(obs["segment_id"], return_counts=True)))
    alive = np.ones(len(ids), bool)
    for k, sid in enumerate(ids):
        if counts.get(sid, 0) < min_samples:
            report.dropped["too_short"].append(int(sid))
            alive[k] = False
        elif min_spin_conf is not None and seg["spin_conf"][k] < min_spin_conf:
            report.dropped["low_spin_conf"].append(int(sid))
            alive[k] = False
    if max_rmse is not None and alive.any():
        todo = np.flatnonzero(alive)
        times, positions, spins = [], [], []
        pos = ds.positions
        for k, rows in zip(todo, ds.segment_rows(ids[todo])):
            times.append(obs["t"][rows])
            positions.append(pos[rows])
            spins.append([seg["spin_x"][k], seg["spin_y"][k], seg["spin_z"][k]])
        if rmse_fn is None:
            rmse = ballistic_rmse_many(times, positions, np.asarray(spins))
        else:
            rmse = np.array([float(rmse_fn(tt, pp, np.asarray(ss))) for tt, pp, ss in zip(times, positions, spins)])
        for k, r in zip(todo, rmse):
            report.rmse[int(ids[k])] = float(r)
            if not (r <= max_rmse):  # NaN fails too
                report.dropped["rmse"].append(int(ids[k]))
                alive[k] = False
    report.kept = int(alive.sum())
    return drop_segments(ds, alive), report
