"""The latent spin across a bounce (:mod:`ttsim_jax.fit.bounce_spin`) on bounces flown by the rally
kernel (its own time of impact and table contact, not the fit's), sampled at 200 Hz with 1 mm of
noise: spins of sizes that one flight cannot tell apart are told apart by the bounce."""

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Record, load_model, simulate
from ttsim_jax.fit.bounce_spin import fit_bounce_spin
from ttsim_jax.physics.events import TABLE

RATE = 200.0


@pytest.fixture(scope="module")
def bounces():
    """Drives over the net with top- and backspin of 60-600 rad/s, bouncing on the far half
    (conti2026, float64): per ball whose first event is a bounce, the samples before it and in the
    0.25 s after it (up to the next event), its time, and the true spins on both sides."""
    model = load_model("conti2026", dtype=jnp.float64)
    rng = np.random.default_rng(5)
    n = 24
    size = rng.uniform(60.0, 600.0, n) * rng.choice([-1.0, 1.0], n)  # top (+y) and back spin
    pos = np.stack([np.full(n, -1.4), rng.uniform(-0.3, 0.3, n), rng.uniform(0.3, 0.45, n)], 1)
    vel = np.stack([rng.uniform(5.0, 8.0, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.3, 1.5, n)], 1)
    spin = np.stack([rng.uniform(-50, 50, n), size, rng.uniform(-80, 80, n)], 1)
    out = simulate(model, Ball.create(pos=pos, vel=vel, spin=spin), n_steps=900, dt=1e-3, record=Record(every=1))
    kind, t_ev = np.asarray(out.events.kind), np.asarray(out.events.time)
    traj, times = np.asarray(out.trajectory.pos), np.asarray(out.times)
    post_spin = np.asarray(out.events.post.spin)
    noise = np.random.default_rng(6)
    cases = []
    for b in range(n):
        first = np.flatnonzero(kind[b] > 0)
        if not len(first) or kind[b, first[0]] != TABLE:
            continue
        t_c = float(t_ev[b, first[0]])
        end = t_ev[b, first[1]] if len(first) > 1 else times[-1]
        grid = np.arange(0.0, min(end, times[-1]) - 0.01, 1.0 / RATE) + 0.0023
        before, after = grid[grid < t_c - 1e-3], grid[(grid > t_c + 1e-3) & (grid < t_c + 0.25)]
        if min(len(before), len(after)) < 12:
            continue
        sample = lambda ts: np.stack([np.interp(ts, times, traj[b, :, k]) for k in range(3)], 1) \
            + noise.normal(0.0, 1e-3, (len(ts), 3))  # noqa: E731
        cases.append(dict(t_in=before, p_in=sample(before), t_out=after, p_out=sample(after), t_c=t_c,
                          w_in=spin[b], w_out=post_spin[b, first[0]]))
    assert len(cases) >= 16
    return model, cases


def test_the_bounce_tells_the_spins_size_where_the_flight_cannot(bounces):
    model, cases = bounces
    fit = fit_bounce_spin([c["t_in"] for c in cases], [c["p_in"] for c in cases], [c["t_out"] for c in cases],
                          [c["p_out"] for c in cases], np.array([c["t_c"] for c in cases]), model, noise=1e-3)
    assert fit.ok.all()
    true_in = np.array([c["w_in"] for c in cases])
    true_out = np.array([c["w_out"] for c in cases])
    size = lambda w: np.abs(w[:, 1])  # noqa: E731 (the top/backspin axis, across the flight)
    joint = np.abs(size(fit.spin_in) / size(true_in) - 1)
    single = np.abs(size(fit.single) / size(true_in) - 1)
    assert np.median(joint) < 0.02 and np.max(joint) < 0.05, np.round(joint, 3)
    assert np.median(joint) < 0.5 * np.median(single)
    np.testing.assert_array_equal(np.sign(fit.spin_in[:, 1]), np.sign(true_in[:, 1]))
    # the spin leaving the bounce, through the table law, is the kernel's
    assert np.median(np.linalg.norm(fit.spin_out - true_out, axis=1) / np.linalg.norm(true_out, axis=1)) < 0.05
    assert np.nanmedian(fit.rmse) < 2e-3  # the 1 mm noise, in 3-D: sqrt(3) mm
    lo = np.sqrt(np.einsum("nii->ni", fit.cov))[:, 1]
    assert np.median(np.abs(fit.spin_in[:, 1] - true_in[:, 1]) / lo) < 3.0  # intervals of the right width


def test_pairs_with_too_few_samples_are_not_fitted_and_inputs_must_match(bounces):
    model, cases = bounces
    c = cases[0]
    fit = fit_bounce_spin([c["t_in"][:5]], [c["p_in"][:5]], [c["t_out"]], [c["p_out"]], np.array([c["t_c"]]), model)
    assert not fit.ok.any() and np.isnan(fit.spin_in).all()
    with pytest.raises(ValueError, match="one of each per bounce"):
        fit_bounce_spin([c["t_in"]], [c["p_in"]], [], [], np.array([c["t_c"]]), model)
