"""Shared fixtures of the data-layer tests: synthetic trajectories and datasets, real-data path."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from ttsim_jax.data import Dataset, Metadata

def real_data_root() -> Path:
    """Where the public measured data lives: $TTSIM_REAL_DATA, else ../shared/data/real."""
    env = os.environ.get("TTSIM_REAL_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"


@pytest.fixture
def rally(simulate_flight):
    """One serve-like flight with two table bounces: (t, pos, bounce_times, bounce_positions)."""
    return simulate_flight([-1.5, 0.1, 0.30], [3.5, -0.1, 0.2], duration=0.9)


@pytest.fixture
def small_dataset(simulate_flight):
    """A valid dataset with observations, all event kinds used by a rally, a racket state."""
    t1, p1, bt1, bp1 = simulate_flight([-1.5, 0.1, 0.30], [3.5, -0.1, 0.2], duration=0.6)
    t2, p2, bt2, bp2 = simulate_flight([1.4, 0.0, 0.35], [-6.0, 0.3, 0.0], duration=0.5, t0=10.0)
    session = np.r_[np.zeros(len(t1), int), np.ones(len(t2), int)]
    t = np.r_[t1, t2]
    pos = np.r_[p1, p2]
    spin = np.tile([0.0, 150.0, 0.0], (len(t), 1))
    conf = np.r_[np.full(len(t1), 0.9), np.zeros(len(t2))]
    ev_t = bt1 + bt2 + [t1[-1] + 0.001]
    ev_pos = bp1 + bp2 + [p1[-1]]
    ev_sid = [0] * len(bt1) + [1] * len(bt2) + [0]
    ev_kind = ["table"] * (len(bt1) + len(bt2)) + ["racket"]
    ds = Dataset.from_arrays(
        session,
        t,
        pos,
        spin=spin,
        spin_conf=conf,
        events=dict(session_id=ev_sid, t=ev_t, kind=ev_kind, pos=np.array(ev_pos)),
        rackets=dict(
            pos=[[p1[-1][0] + 0.03, p1[-1][1], p1[-1][2]]],
            quat=[[np.cos(0.2), 0.0, 0.0, np.sin(0.2)]],
            vel=[[-3.0, 0.1, 0.5]],
            ang_vel=[[0.0, 2.0, 0.0]],
            contact=[[0.01, -0.02]],
        ),
        sessions=dict(session_id=[0, 1], name=["serve", "return"], notes=["", '{"k": 1}']),
        metadata=Metadata(source="unit test", equipment={"ball": "40+", "table": {"length": 2.74}}, notes="synthetic"),
    )
    return ds


def forget_file_sums(path) -> None:
    """Drops the whole-file checksums from dataset ``path``'s metadata.json, as a writer that keeps
    none writes it (before schema 1.4, or another tool rewriting a table on purpose)."""
    import json

    from ttsim_jax.data.io import FILE_SUMS_KEY, METADATA_FILE, METADATA_SUM_KEY

    file = Path(path) / METADATA_FILE
    meta = json.loads(file.read_text())
    meta.pop(FILE_SUMS_KEY, None)
    meta.pop(METADATA_SUM_KEY, None)
    file.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


@pytest.fixture
def forget_sums():
    """The :func:`forget_file_sums` function."""
    return forget_file_sums


@pytest.fixture
def real_root():
    """Root of the public measured data; skips the test when it is absent."""
    root = real_data_root()
    if not root.is_dir():
        pytest.skip(f"public measured data not found at {root} (set TTSIM_REAL_DATA to its folder)")
    return root
