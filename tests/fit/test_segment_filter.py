"""The paper's segment filter and the flight fit it runs, on synthetic trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from ttsim_jax.data import Dataset, validate
from ttsim_jax.fit.flightfit import ballistic_rmse
from ttsim_jax.fit.segment_filter import filter_segments


def _three_segment_dataset(simulate_flight, spin_conf):
    t, pos, bt, bp = simulate_flight([-1.5, 0.1, 0.30], [3.5, -0.1, 0.2], duration=0.9, noise=0.001, seed=1)
    pos = pos.copy()
    after = t > bt[1]
    pos[after, 1] += 0.05 * np.sin(60 * t[after])  # the last segment is no ballistic flight
    conf = np.where(t < bt[0], spin_conf, 0.9)
    return Dataset.from_arrays(
        np.zeros(len(t), int), t, pos, spin=np.zeros((len(t), 3)), spin_conf=conf,
        events=dict(session_id=0, t=bt, kind=["table"] * 2, pos=np.array(bp)),
    )


def test_filter_drops_low_confidence_and_bad_fits(simulate_flight):
    ds = _three_segment_dataset(simulate_flight, spin_conf=0.3)
    kept, report = filter_segments(ds)
    assert report.total == 3 and report.kept == 1
    assert report.counts() == {"too_short": 0, "low_spin_conf": 1, "rmse": 1}
    assert report.rmse[int(ds.segments["segment_id"][1])] < 0.005
    assert report.rmse[int(ds.segments["segment_id"][2])] > 0.02
    assert list(kept.segments["segment_id"]) == [ds.segments["segment_id"][1]]
    assert "kept 1 of 3" in str(report)
    validate(kept)


def test_filter_with_a_custom_rmse_fn(simulate_flight):
    ds = _three_segment_dataset(simulate_flight, spin_conf=0.9)
    seen = []

    def rmse_fn(times, positions, spin):
        seen.append((len(times), positions.shape, spin.shape))
        return 0.05 if len(times) > 60 else 0.0

    _, report = filter_segments(ds, rmse_fn=rmse_fn, min_samples=5)
    assert len(seen) == 3 and all(s[1][1] == 3 and s[2] == (3,) for s in seen)
    n = [int((ds.observations["segment_id"] == s).sum()) for s in ds.segments["segment_id"]]
    assert report.counts()["rmse"] == sum(k > 60 for k in n)


def test_default_flight_fit_is_accurate(simulate_flight):
    t, pos, _, _ = simulate_flight([-1.2, 0.0, 0.4], [5.0, 0.2, 1.0], duration=0.25, noise=0.001, seed=2)
    assert len(t) > 30
    r = ballistic_rmse(t, pos, np.zeros(3))
    # Isotropic 1 mm noise gives a 3-D RMSE of sqrt(3) mm once the model fits.
    assert r == pytest.approx(np.sqrt(3) * 1e-3, rel=0.25)
