"""Where-binning, the group bootstrap and the record-effect sizes on hand-made data (no compilation)."""

import math

import numpy as np
import pytest

from ttsim_jax.diagnose import where as W
from ttsim_jax.diagnose.bootstrap import group_weights, ratio_ci, rms_reduction
from ttsim_jax.diagnose.phases import AXES, Flights, spin_axis
from ttsim_jax.diagnose.residuals import dependence, missing_frames, position_noise, spearman


def _items(high_factor=3.0, n_groups=80, per_group=5, seed=0):
    """Hand-made flight-like items: groups of observations; the error is 1 mm, times
    ``high_factor`` for the groups with speed above 15 m/s (a quarter of them)."""
    rng = np.random.default_rng(seed)
    speed = rng.uniform(5.0, 20.0, n_groups)
    base = np.where(speed > 15.0, high_factor, 1.0) * 1e-3
    group = np.repeat(np.arange(n_groups), per_group)
    error = base[group] * rng.uniform(0.8, 1.2, len(group))
    axis = np.zeros(len(group))  # every item topspin
    return dict(error=error, group=group, regimes=dict(speed=speed[group], spin_axis=axis,
                                                      since_contact=rng.uniform(0, 0.5, len(group))))


def test_the_high_speed_bin_is_flagged_and_no_other():
    s = W.summarise(_items())
    rows = s["regimes"]["speed"]
    assert len(rows) == W.N_BINS
    assert [r["flag"] for r in rows] == [False, False, False, True]
    assert s["flagged"] == [("speed", rows[-1]["label"])]
    # the bins' means are the hand-made errors: 1 mm below 15 m/s, 3 mm in the top quartile (mostly above 15)
    assert rows[0]["mean"] == pytest.approx(1e-3, rel=0.05)
    assert rows[-1]["mean"] > 2.5e-3
    # a quantity the error does not depend on is never flagged
    assert not any(r["flag"] for r in s["regimes"]["since_contact"])
    assert [r["label"] for r in s["regimes"]["spin_axis"]] == ["topspin"]


def test_no_flag_without_a_difference():
    s = W.summarise(_items(high_factor=1.0))
    assert s["flagged"] == []


def test_a_bin_above_the_floor_is_flagged_where_the_phase_is_near_it():
    # a 1.2x bin stands out neither from the phase's mean (1.05 mm) by 25 % nor ...
    it = _items(high_factor=1.2)
    assert W.summarise(it)["flagged"] == []
    # ... but above a floor of 0.9 mm it does, since the phase as a whole is not clearly above that
    s = W.summarise(it, floor=0.9e-3)
    assert s["flagged"] == [("speed", s["regimes"]["speed"][-1]["label"])]
    # a phase far above its floor flags no more than its own outliers: every bin would stand out
    assert W.summarise(_items(high_factor=1.2), floor=0.5e-3)["flagged"] == []


def test_overall_mean_and_interval_are_the_group_bootstrap():
    it = _items()
    s = W.summarise(it, seed=3)
    assert s["mean"] == pytest.approx(it["error"].mean())
    lo, hi = s["ci95"]
    assert lo < s["mean"] < hi
    # resampling whole groups: an interval from 80 groups of 5 correlated items is wider than the
    # naive one from 400 independent items
    naive = 1.96 * it["error"].std() / math.sqrt(len(it["error"]))
    assert (hi - lo) / 2 > 1.5 * naive


def test_bins_edges_and_small_samples():
    v = np.arange(40.0)
    bins = W.bins(v, "speed")
    assert len(bins) == 4 and sum(int(m.sum()) for _, m in bins) == 40
    assert W.bins(np.arange(10.0), "speed") == []  # fewer than 2 bins of MIN_BIN items
    assert W.bins(np.full(50, 2.0), "speed") == []  # one value: nothing to cut


def test_spin_axis_categories():
    vel = np.array([[5.0, 0, 0], [5.0, 0, 0], [5.0, 0, 0], [5.0, 0, 0], [-5.0, 0, 0]])
    spin = np.array([[0, 100.0, 0], [0, -100.0, 0], [0, 0, 100.0], [100.0, 0, 0], [0, -100.0, 0]])
    # ball along +x: +y spin is topspin (Magnus force w x v points down); along -x it is -y
    got = [AXES[int(k)] for k in spin_axis(vel, spin)]
    assert got == ["topspin", "backspin", "sidespin", "gyro", "topspin"]


def test_ratio_and_reduction_intervals():
    w = group_weights(50, seed=1)
    value, (lo, hi) = ratio_ci(np.ones(50) * 2.0, np.ones(50), w)
    assert value == lo == hi == 2.0
    before = np.full(50, 4.0)
    pct, ci = rms_reduction(before, before / 4.0, np.ones(50), w)  # RMS halves
    assert pct == pytest.approx(50.0) and ci[0] == pytest.approx(50.0)


def test_position_noise_and_missing_frames_sizes():
    rng = np.random.default_rng(0)
    s, t_len = 64, 128
    dt = 0.005
    tau = np.tile(np.arange(t_len) * dt, (s, 1))
    mask = np.ones((s, t_len))
    tau[:, 60:] += dt  # one frame missing in every segment
    sigma = np.array([0.001, 0.002, 0.0005])
    true = np.stack([3.0 * tau, 0.5 * tau, 0.3 + 2.0 * tau - 4.905 * tau**2], -1)
    pos = true + rng.normal(size=true.shape) * sigma
    fl = Flights(t0=np.zeros(s), tau=tau, pos=pos, mask=mask, spin=np.zeros((s, 3)), session=np.zeros(s, np.int64),
                 segment_id=np.arange(s), n=s)
    got = position_noise(fl)
    assert np.allclose(got["sigma"], sigma, rtol=0.08)
    mf = missing_frames(fl)
    assert mf["interval"] == pytest.approx(dt)
    assert mf["fraction"] == pytest.approx(1.0 / t_len, rel=1e-6)


def test_dependence_finds_the_driving_quantity_only():
    it = _items()
    deps = dependence(it)
    assert deps and deps[0]["quantity"] == "speed" and deps[0]["rho"] > 0.5
    assert all(d["quantity"] != "since_contact" for d in deps)
    rho, p = spearman(np.arange(20.0), np.arange(20.0) ** 3)
    assert rho == pytest.approx(1.0) and p < 1e-6


def test_spearman_ties_and_constants():
    # a constant quantity (e.g. spin 0 where none is measured) carries no dependence, whatever the rows' order
    assert math.isnan(spearman(np.zeros(30), np.arange(30.0))[0])
    # tied values share their mean rank: a two-valued quantity against the row order
    x = np.repeat([0.0, 1.0], 10)
    rho, _ = spearman(x, np.tile(np.arange(10.0), 2))
    assert rho == pytest.approx(0.0, abs=1e-12)


def test_segment_lengths_alone_make_no_dependence():
    """A perfect model's flight residuals: the noise less its projection on each segment's fit
    (here a quadratic per axis: 3 parameters, as a segment flown with a latent spin), over
    segments of 12-80 samples. The short segments' residuals are smaller, which without
    :func:`~ttsim_jax.diagnose.where.null_scale` reads as a dependence on the time since the
    contact (the segment's length)."""
    rng = np.random.default_rng(4)
    s, t_len, dt, sigma = 1500, 80, 1.0 / 150.0, 0.0015
    n = rng.integers(12, t_len + 1, s)
    tau = np.tile(np.arange(t_len) * dt, (s, 1))
    mask = (np.arange(t_len)[None] < n[:, None]).astype(np.float64)
    res = np.zeros((s, t_len, 3))
    for i in range(s):
        a = np.vander(tau[i, :n[i]], 3)
        e = rng.normal(0.0, sigma, (n[i], 3))
        res[i, :n[i]] = e - a @ np.linalg.lstsq(a, e, rcond=None)[0]
    pos = np.stack([3.0 * tau, 0.5 * tau, 0.3 + 2.0 * tau - 4.905 * tau**2], -1)
    fl = Flights(t0=np.zeros(s), tau=tau, pos=pos, mask=mask, spin=np.zeros((s, 3)), session=np.zeros(s, np.int64),
                 segment_id=np.arange(s), n=s, spin_source=np.full(s, "latent"))
    states = np.tile([0.0, 0.0, 0.3, 3.0, 0.5, 2.0], (s, 1)) + rng.normal(0.0, 0.5, (s, 6))
    it = W.flight_items(fl, res, states, 0.02)
    assert not any(d["quantity"] == "since_contact" for d in dependence(it))
    raw = {k: v for k, v in it.items() if k != "null_scale"}
    assert any(d["quantity"] == "since_contact" and d["error"] == "|error|" for d in dependence(raw))
