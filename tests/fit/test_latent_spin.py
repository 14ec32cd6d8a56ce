"""The latent spin (``ttsim_jax.fit.latent_spin``) on flights of the model's own physics, integrated
here at 0.1 ms and sampled at 150 Hz with 2 mm of noise: the spin across the direction of flight is
recovered, the component along it is reported as its prior's, and the intervals cover."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.fit.latent_spin import PRIOR_ALONG, fit_latent_spin, initial_guess
from ttsim_jax.physics.aero import flight_step

RATE, DURATION, NOISE, H = 150.0, 0.3, 0.002, 1e-4


@pytest.fixture(scope="module")
def model():
    return load_model("conti2026")


def flights(model, spins, seed=0, noise=NOISE):
    """Sampled positions of flights from the near end at 5-20 m/s with the given spins, with
    ``noise`` [m] (standard deviation per axis)."""
    rng = np.random.default_rng(seed)
    s = len(spins)
    p = np.stack([rng.uniform(-1.4, -1.0, s), rng.uniform(-0.3, 0.3, s), rng.uniform(0.2, 0.4, s)], -1)
    d = np.stack([np.ones(s), rng.uniform(-0.15, 0.15, s), rng.uniform(-0.05, 0.2, s)], -1)
    v = rng.uniform(5, 20, s)[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)
    step = jax.jit(jax.vmap(lambda p, v, w: flight_step(model.aero, model.ball.radius, model.ball.mass, p, v, w, 0.0, H)))
    y, every, samples = (jnp.asarray(p), jnp.asarray(v), jnp.asarray(spins)), int(round(1 / (RATE * H))), []
    for k in range(int(round(DURATION / H)) + 1):
        if k % every == 0:
            samples.append(np.asarray(y[0]))
        y = step(*y)
    pos = np.stack(samples, 1) + rng.normal(0.0, noise, (s, len(samples), 3))
    t = np.arange(len(samples)) / RATE
    return [t] * s, list(pos), v


def across(spin, along):
    return spin - np.sum(spin * along, 1, keepdims=True) * along


@pytest.fixture(scope="module")
def fitted(model):
    """Spins across the launch velocity (top, back and side spin) of 30-600 rad/s, and a spin-free set."""
    rng = np.random.default_rng(1)
    s = 48
    d = np.stack([np.ones(s), np.zeros(s), np.zeros(s)], -1)
    axis = np.cross(d, rng.normal(size=(s, 3)))
    spins = rng.uniform(30, 600, s)[:, None] * axis / np.linalg.norm(axis, axis=1, keepdims=True)
    times, positions, _ = flights(model, spins)
    return spins, fit_latent_spin(times, positions, model, noise=NOISE)


def test_spin_across_the_flight_is_recovered(fitted):
    spins, ls = fitted
    assert ls.ok.all()
    true = across(spins, ls.along)
    est = ls.observed
    cos = np.sum(est * true, 1) / (np.linalg.norm(est, axis=1) * np.linalg.norm(true, axis=1))
    big = np.linalg.norm(true, axis=1) >= 100
    assert np.median(np.degrees(np.arccos(np.clip(cos[big], -1, 1)))) < 3.0
    ratio = np.linalg.norm(est, axis=1) / np.linalg.norm(true, axis=1)
    assert np.median(np.abs(ratio[big] - 1)) < 0.05
    assert np.median(ls.rmse) < 2.0 * NOISE * np.sqrt(3)  # the fit reaches the noise


def test_intervals_cover_the_spin_across_the_flight(fitted):
    """The intervals are about 1.5x too narrow here (median error 1.6 per-axis sigmas where a
    Gaussian's is 1.18), and an eighth of the spins end at another size (the Magnus force barely
    grows with the spin: see the module docstring), unflagged: what the docs say of them."""
    spins, ls = fitted
    err = np.linalg.norm(ls.observed - across(spins, ls.along), axis=1)
    # |err| of a 2-D Gaussian error is below 2.45 of its per-axis sigma 95 % of the time; the
    # stderr here is the root of the 2-D trace (sqrt(2) per-axis sigmas)
    z = err / (ls.stderr_observed / np.sqrt(2))
    assert 0.8 < np.median(z) < 2.5
    assert np.mean(z <= 1.5 * 2.45) >= 0.75


def test_the_component_along_the_flight_is_its_prior(fitted):
    spins, ls = fitted
    along = np.sum(ls.spin * ls.along, 1)
    assert np.median(np.abs(along)) < 0.5 * PRIOR_ALONG  # held near the prior's mean, 0
    sigma_along = np.sqrt(np.einsum("si,sij,sj->s", ls.along, ls.cov, ls.along))
    assert np.median(sigma_along) > 0.5 * PRIOR_ALONG  # and as uncertain as the prior: not measured
    assert np.median(sigma_along) > 5 * np.median(ls.stderr_observed)


def test_no_spin_gives_a_small_spin_and_the_start_is_close(model):
    times, positions, _ = flights(model, np.zeros((8, 3)), seed=4)
    ls = fit_latent_spin(times, positions, model, noise=NOISE)
    assert np.median(np.linalg.norm(ls.observed, axis=1)) < 3 * np.median(ls.stderr_observed)
    # the start's spin (from the mean acceleration) is already of the right sign and size
    spins = np.array([[0.0, 300.0, 0.0]] * 4)
    times, positions, _ = flights(model, spins, seed=5)
    t = jnp.asarray(times[0])
    theta0, _ = initial_guess(model, t, jnp.asarray(positions[0]), jnp.ones_like(t))
    assert 150 < float(theta0[7]) < 450


def test_bad_settings_are_refused(model):
    with pytest.raises(ValueError, match="must be > 0"):
        fit_latent_spin([np.arange(10) / 100.0], [np.zeros((10, 3))], model, noise=0.0)


def test_segment_rmse_flies_the_latent_spin_where_a_record_has_none(model):
    """A dataset of spinning flights recorded without spin: with ``spin="auto"`` every segment is
    flown with its latent spin and fits to the noise; with ``"zero"`` it is not; ``"measured"``
    (nothing measured) flies them with spin 0 too."""
    from ttsim_jax.data import Dataset
    from ttsim_jax.fit.flight import segment_rmse

    spins = np.array([[0.0, 300.0, 0.0], [0.0, -250.0, 80.0], [0.0, 150.0, -200.0], [0.0, 0.0, 0.0]])
    times, positions, _ = flights(model, spins, seed=9)
    sid = np.repeat(np.arange(len(times)), len(times[0]))
    t = np.concatenate([tt + 10.0 * k for k, tt in enumerate(times)])
    ds = Dataset.from_arrays(sid, t, np.concatenate(positions))
    assert len(ds.segments["segment_id"]) == len(times)
    out = {mode: segment_rmse(ds, [("m", model)], spin=mode) for mode in ("auto", "zero", "measured", "latent")}
    assert list(out["auto"].spin_source) == ["latent"] * 4 and list(out["zero"].spin_source) == ["zero"] * 4
    assert list(out["measured"].spin_source) == ["zero"] * 4
    auto, zero = out["auto"].rmse["m"], out["zero"].rmse["m"]
    assert (auto < 2.0 * NOISE * np.sqrt(3)).all()
    assert (zero[:3] > 3 * auto[:3]).all()  # the spinning ones
    np.testing.assert_allclose(out["latent"].rmse["m"], auto)
    with pytest.raises(ValueError, match="spin = 'maybe'"):
        segment_rmse(ds, [("m", model)], spin="maybe")


def test_sidespun_flights_are_fitted_near_the_noise(model):
    """Spins mostly along the flight (300-600 rad/s, either sign, beside 50-200 across): the spin
    along acts through |w| and, as the direction of flight turns, a little across it, so a fit
    started at 0 along the flight stays near there. From the guess and three times it alone these
    flights were fitted to 1.46x the floor (RMS over the segments); with the starts along the
    flight (where the first two leave a segment above the others), 1.15x (the prior on the spin
    along the flight, 50 rad/s wide, holds the rest back: 300 rad/s wide and every start on every
    segment, 1.05x)."""
    rng = np.random.default_rng(7)
    s = 24
    d = np.stack([np.ones(s), np.zeros(s), np.zeros(s)], -1)
    side = np.cross(d, rng.normal(size=(s, 3)))
    side = rng.uniform(50, 200, s)[:, None] * side / np.linalg.norm(side, axis=1, keepdims=True)
    spins = rng.choice([-1.0, 1.0], s)[:, None] * rng.uniform(300, 600, s)[:, None] * d + side
    times, positions, _ = flights(model, spins, seed=3)
    ls = fit_latent_spin(times, positions, model, noise=NOISE)
    n = np.array([len(t) for t in times])
    floor = NOISE * np.sqrt(3.0 * (n - 2) / n)  # what a fit of the initial state leaves of the noise
    assert ls.ok.all()
    assert np.sqrt(np.mean((ls.rmse / floor) ** 2)) < 1.25


def test_a_latent_fit_takes_its_spin_across_the_flight_out_of_the_noise(model):
    """What the noise floor counts (:func:`ttsim_jax.diagnose.floor.flight_params_per_axis`): fitted
    to one short flight (16 samples, where the count shows most) under 192 draws of 2 mm noise, the
    latent fit of (p0, v0, w) leaves a mean square residual of (n - k) / n of the noise's, k
    parameters per axis: 2 2/3 (the two spin components across the flight besides the initial
    state; the one along it is held by its prior), not the 2 of a fit of the initial state alone."""
    from ttsim_jax.diagnose.floor import flight_params_per_axis

    times, clean, _ = flights(model, np.array([[0.0, 300.0, 0.0]]), noise=0.0)
    t, p = times[0][:16], clean[0][:16]
    n = len(t)
    rng = np.random.default_rng(3)
    ratio = []
    for _ in range(3):  # 64 segments a call: their two starts fill one compiled batch
        ls = fit_latent_spin([t] * 64, [p + rng.normal(0.0, NOISE, p.shape) for _ in range(64)], model, noise=NOISE)
        assert ls.ok.all()
        ratio.append(np.mean(ls.rmse**2) / (3.0 * NOISE**2))  # rmse: 3-D, over the three axes' noise
    measured = n * (1.0 - float(np.mean(ratio)))  # parameters per axis the fits took
    k = float(flight_params_per_axis(np.array(["latent"]))[0])
    assert float(flight_params_per_axis(np.array(["measured"]))[0]) == 2.0
    assert abs(measured - k) < 0.2 and measured > 2.4, (measured, k)
