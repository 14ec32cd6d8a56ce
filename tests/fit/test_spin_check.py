"""The spin check (``ttsim_jax.fit.spin_check``) on generated flights whose record's spin was left
as it was, turned by 10 degrees, or sign-flipped on every segment or on a quarter of them."""

from __future__ import annotations

import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.fit.latent_spin import fit_latent_spin
from ttsim_jax.fit.spin_check import check_spin
from test_latent_spin import NOISE, flights


def rotation(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


@pytest.fixture(scope="module")
def record():
    """True spins (top, back and side spin of 150-400 rad/s, sizes the flight shows) and the
    latent spin of their flights."""
    model = load_model("conti2026")
    rng = np.random.default_rng(3)
    s = 64
    axis = np.cross([1.0, 0.0, 0.0], rng.normal(size=(s, 3)))
    spins = rng.uniform(150, 400, s)[:, None] * axis / np.linalg.norm(axis, axis=1, keepdims=True)
    times, positions, _ = flights(model, spins, seed=6)
    return spins, fit_latent_spin(times, positions, model, noise=NOISE)


def test_an_unchanged_record_is_consistent(record):
    spins, ls = record
    c = check_spin(spins, ls)
    assert c.n >= 48
    assert c.opposite[0] <= 0.05 and c.opposite[1][0] == 0.0
    assert c.rotation_deg[0] < 5.0 and c.angle_deg < 5.0
    assert "0 % " in c.summary()


def test_an_axis_turned_by_ten_degrees_is_named(record):
    spins, ls = record
    turned = spins @ rotation([1.0, 0.0, 0.0], 10.0).T  # about the direction of flight: across stays across
    c = check_spin(turned, ls)
    assert abs(c.rotation_deg[0] - 10.0) < 3.0
    lo, hi = c.rotation_deg[1]
    assert lo > 5.0 and hi < 15.0
    assert abs(abs(c.rotation_axis[0]) - 1.0) < 0.05  # the axis it was turned about
    assert c.angle_after_deg < c.angle_deg - 4.0


def test_a_flipped_sign_is_named_on_every_segment_or_on_some(record):
    spins, ls = record
    assert check_spin(-spins, ls).opposite[0] >= 0.95
    flip = np.zeros(len(spins), bool)
    flip[::4] = True
    c = check_spin(np.where(flip[:, None], -spins, spins), ls)
    share, (lo, hi) = c.opposite
    assert lo <= 0.25 <= hi and abs(share - 0.25) < 0.1
    assert set(c.opposite_rows.tolist()) <= set(np.flatnonzero(flip).tolist()) | set(np.flatnonzero(~ls.ok).tolist())
    assert c.rotation_deg[0] < 5.0  # the others are as they were


def test_nothing_to_compare_says_so(record):
    spins, ls = record
    c = check_spin(np.zeros_like(spins), ls)
    assert c.n == 0 and "no segment" in c.summary()
    with pytest.raises(ValueError, match=r"shape \(63, 3\); the latent spins are of 64 segments"):
        check_spin(spins[1:], ls)
