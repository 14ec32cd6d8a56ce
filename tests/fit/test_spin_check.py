"""The spin check (``ttsim_jax.fit.spin_check``) on generated flights whose record's spin was left
as it was, turned by 10 degrees, sign-flipped on every segment or on a quarter of them, or scaled
by 0.8 or 1.2."""

from __future__ import annotations

import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.fit.latent_spin import fit_latent_spin
from ttsim_jax.fit.spin_check import check_record_spin, check_spin, corrected_spins, findings, spin_scale
from test_latent_spin import NOISE, flights


def rotation(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def across(model, n, low, high, seed):
    """n flights with spins of ``low``-``high`` rad/s about random axes across the launch
    direction (top, back and side spin): (spins, times, positions)."""
    rng = np.random.default_rng(seed)
    axis = np.cross([1.0, 0.0, 0.0], rng.normal(size=(n, 3)))
    spins = rng.uniform(low, high, n)[:, None] * axis / np.linalg.norm(axis, axis=1, keepdims=True)
    times, positions, _ = flights(model, spins, seed=2 * seed)
    return spins, times, positions


@pytest.fixture(scope="module")
def record():
    """True spins of 150-400 rad/s (sizes the flight shows) and the latent spin of their flights."""
    model = load_model("conti2026")
    spins, times, positions = across(model, 64, 150, 400, 3)
    return spins, fit_latent_spin(times, positions, model, noise=NOISE)


@pytest.fixture(scope="module")
def scaled():
    """Flights with spins of 30-400 rad/s across the flight and their (times, positions)."""
    model = load_model("conti2026")
    return (model, *across(model, 96, 30, 400, 4))


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
    assert c.rotation_axis[0] < -0.95  # the correction: back about the axis it was turned about
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
    assert c.opposite_above is None  # flipped whatever their size: they gather nowhere


def test_signs_flipped_on_the_largest_spins_are_placed_at_their_size(record):
    """An estimator that reads large spins backwards: the check says above which size."""
    spins, ls = record
    size = np.linalg.norm(spins, axis=1)
    flip = size > 340.0
    c = check_spin(np.where(flip[:, None], -spins, spins), ls)
    g = c.opposite_above
    assert g is not None and g["p"] < 0.01
    assert 330.0 < g["size"] < 350.0, g
    assert g["opposite"] >= g["n"] - 1 and g["rest_share"] <= 0.05
    assert f"gather at measured spins of {g['size']:.0f} rad/s and more" in c.summary()
    assert c.to_json()["opposite_above"] == g


def test_nothing_to_compare_says_so(record):
    spins, ls = record
    c = check_spin(np.zeros_like(spins), ls)
    assert c.n == 0 and "no segment" in c.summary()
    with pytest.raises(ValueError, match=r"shape \(63, 3\); the latent spins are of 64 segments"):
        check_spin(spins[1:], ls)


@pytest.mark.parametrize("k", [0.8, 1.0, 1.2])
def test_a_scaled_spin_reads_its_scale(scaled, k):
    model, spins, times, positions = scaled
    out = spin_scale(model, times, positions, k * spins)
    assert out["n"] == len(spins)
    assert abs(1.0 / out["scale"] - k) < 0.03, out["scale"]
    lo, hi = out["interval"]
    assert lo <= out["scale"] <= hi and hi - lo < 0.15
    # the cost is least near the truth, not at the grid's ends
    assert 0 < int(np.argmin(out["cost"])) < len(out["scales"]) - 1


#: The turn of :func:`checks`' turned record, about the direction of flight (across stays across).
TURN_DEG = 12.0


@pytest.fixture(scope="module")
def checks(scaled):
    """The record check of the ``scaled`` flights with their spins as they are ("ok"), 20 % high,
    sign-flipped on every segment or on every fourth, and turned by :data:`TURN_DEG` about x: each
    record's (spins, check), the flights' latent fit made once for all."""
    from ttsim_jax.fit.latent_spin import fit_latent_spin

    model, spins, times, positions = scaled
    latent = fit_latent_spin(times, positions, model)
    some = spins.copy()
    some[::4] *= -1.0
    records = {"ok": spins, "high": 1.2 * spins, "flipped": -spins, "some": some,
               "turned": spins @ rotation([1.0, 0.0, 0.0], TURN_DEG).T}
    return {k: (r, check_record_spin(model, times, positions, r, latent=latent)) for k, r in records.items()}


def test_the_record_check_names_what_is_off_and_passes_a_consistent_record(checks):
    ok, high, flipped = (checks[k][1] for k in ("ok", "high", "flipped"))
    assert ok["findings"] == [] and ok["summary"].endswith("consistent")
    assert [f for f in high["findings"] if f.startswith("spin reads")] == [f"spin reads {100 * (high['reads'] - 1):.0f} % high"]
    assert abs(high["reads"] - 1.2) < 0.03
    assert flipped["findings"][0] == "sign flipped on every segment"
    # by hand: a rotation interval clear of the threshold is named; a scale interval holding 1 is not
    assert findings(dict(n=10, opposite=0.0, opposite_interval=[0.0, 0.1], rotation_deg=10.0,
                         rotation_interval_deg=[7.0, 13.0], rotation_axis=[0.0, 0.0, 1.0], reads=1.02,
                         reads_interval=[0.97, 1.07])) == ["axis turned by 10 deg (turned back right-handed about [0.0, 0.0, 1.0])"]
    # a scale interval clear of 1 is named only where the size is resolved (not at the grid's end)
    scaled_off = dict(n=10, opposite=0.0, opposite_interval=[0.0, 0.1], rotation_deg=1.0,
                      rotation_interval_deg=[0.0, 3.0], rotation_axis=[0.0, 0.0, 1.0], reads=2.0,
                      reads_interval=[1.3, 2.0])
    assert findings(dict(scaled_off, scale_resolved=True)) == ["spin reads 100 % high"]
    assert findings(dict(scaled_off, scale_resolved=False)) == []
    assert "None" not in str(ok["summary"]) and "nan" not in ok["summary"]


def test_the_correction_undoes_what_the_check_found(scaled, checks):
    """corrected_spins on the checks of records scaled, sign-flipped and turned: the true spins back
    (the scale within 3 %, the direction within 2 degrees); a consistent record left as it is."""
    spins = scaled[1]
    same, done = corrected_spins(*checks["ok"])
    assert done == [] and np.array_equal(same, spins)
    high = checks["high"][1]
    back, done = corrected_spins(*checks["high"])
    assert done == [f"size multiplied by {high['scale']:.2f}"]
    np.testing.assert_allclose(back, spins, rtol=0.03, atol=1e-9)
    back, done = corrected_spins(*checks["flipped"])
    assert done[0] == "sign flipped back on every segment" and np.allclose(back, spins)
    # some signs flipped: those segments (and only those) flipped back
    back, done = corrected_spins(*checks["some"])
    assert done[0].startswith("sign flipped back on the")
    assert np.median(np.linalg.norm(back - spins, axis=1) / np.linalg.norm(spins, axis=1)) < 1e-9
    # an axis turned about x, turned back
    back, done = corrected_spins(*checks["turned"])
    assert any(d.startswith("axis turned back by") for d in done), checks["turned"][1]["findings"]
    cos = np.sum(back * spins, 1) / (np.linalg.norm(back, axis=1) * np.linalg.norm(spins, axis=1))
    assert np.degrees(np.arccos(np.clip(np.median(cos), -1, 1))) < 2.0
