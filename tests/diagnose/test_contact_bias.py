"""The contact-state estimates the diagnosis compares against are unbiased on effect-free data.

Racket contacts with known states (:func:`ttsim_jax.reality.synthetic_contact_dataset`:
flights with gravity, drag and Magnus force into known racket states, the post-contact state the
model's own response, no effect), estimated as the diagnosis does (a polynomial per side,
:class:`~ttsim_jax.data.contact_states.ContactFit`'s defaults):

* noise-free: the velocity estimates' bias (the polynomial's neglect of the drag and Magnus jerk)
  stays below :data:`TOLERANCE`, half the racket phase's resolution
  (:data:`ttsim_jax.diagnose.candidates.MIN_GAIN`);
* with paper-like position noise: the mean racket-contact residual (model response to the
  estimated pre-contact state minus the estimated post-contact state) lies within its 95 %
  bootstrap interval of zero in every velocity component.
"""

import numpy as np

from ttsim_jax.data.contact_states import ContactFit
from ttsim_jax.diagnose.candidates import MIN_GAIN
from ttsim_jax.fit.racket_arrays import contact_arrays
from ttsim_jax.reality import synthetic_contact_dataset

N = 400
TOLERANCE = 0.5 * MIN_GAIN["racket"]


def _estimate(noise):
    ds, truth = synthetic_contact_dataset(N, seed=0, noise=noise)
    a = contact_arrays(ds, "conti2026", fit=ContactFit(), validate=False)
    rows = np.searchsorted(truth["event_id"], a.event_id)
    return a, truth, rows


def test_noise_free_velocity_estimates_are_unbiased():
    a, truth, rows = _estimate(0.0)
    assert len(a) > 0.9 * N
    for est, true in ((a.world_in, truth["vel_in"]), (a.world_out, truth["vel_out"])):
        bias = np.mean(est[:, :3] - true[rows], axis=0)
        assert np.all(np.abs(bias) < TOLERANCE), bias


def test_noisy_racket_residuals_have_zero_mean():
    a, _, _ = _estimate(0.0015)
    r = np.asarray(a.y_base, np.float64)[:, :3] - np.asarray(a.y_obs, np.float64)[:, :3]
    rng = np.random.default_rng(0)
    means = np.stack([r[rng.integers(0, len(r), len(r))].mean(0) for _ in range(2000)])
    lo, hi = np.percentile(means, [2.5, 97.5], axis=0)
    assert np.all((lo < 0.0) & (0.0 < hi)), (r.mean(0), lo, hi)
    # the noise is resolved: the residuals' spread is the velocity estimates' noise, not zero
    assert np.all(r.std(0) > 0.05)


def test_a_biased_estimator_is_caught():
    """The check above can fail: a constant-velocity fit ignores gravity over the window."""
    ds, truth = synthetic_contact_dataset(N, seed=0)
    a = contact_arrays(ds, "conti2026", fit=ContactFit(degree=1, min_samples=4), validate=False)
    rows = np.searchsorted(truth["event_id"], a.event_id)
    bias = np.mean(a.world_in[:, :3] - truth["vel_in"][rows], axis=0)
    assert np.abs(bias[2]) > 10 * TOLERANCE, bias
