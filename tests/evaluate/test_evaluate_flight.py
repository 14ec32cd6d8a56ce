"""Flight-segment RMSE of a model (ttsim_jax.fit.flight) on segments flown by a known model."""

import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.reality.synthetic_segments import synthetic_segments
from ttsim_jax.fit.flight import flight_rmse


@pytest.fixture(scope="module")
def nakashima():
    return load_model("nakashima2011")


def _segments(model, noise):
    return synthetic_segments(model.aero, model.ball.radius, model.ball.mass, 16, seed=2, noise=noise)


def test_the_true_model_reproduces_noise_free_flights(nakashima):
    times, pos, spins, _ = _segments(nakashima, 0.0)
    assert np.all(flight_rmse(nakashima, times, pos, spins) < 2e-4)
    assert np.all(flight_rmse(nakashima, times, pos, spins, fit_position=True) < 2e-4)


def test_rmse_is_the_noise_for_the_true_model_and_grows_for_a_wrong_one(nakashima):
    times, pos, spins, _ = _segments(nakashima, 0.002)
    true = flight_rmse(nakashima, times, pos, spins)
    # sqrt(3) sigma, a little more because the first (noisy) observation is the initial position.
    assert np.sqrt(3) * 0.002 < np.median(true) < 1.3 * np.sqrt(3) * 0.002
    heavier = nakashima.replace(aero=nakashima.aero.replace(drag=nakashima.aero.drag.replace(
        value=nakashima.aero.drag.value + 0.1)))
    assert np.all(flight_rmse(heavier, times, pos, spins) > true)
    # Fitting the initial position too frees the first sample's noise: a smaller error.
    assert np.median(flight_rmse(nakashima, times, pos, spins, fit_position=True)) < np.median(true)
