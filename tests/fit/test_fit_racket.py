"""Racket contact identification recovers the updated base model's five parameters."""

import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.fit import racket as R
from ttsim_jax.reality import synthetic_stages as S

N = 3000


@pytest.fixture(scope="module")
def model():
    return load_model("conti2026")


def _fit(model, noise_vel, noise_spin):
    x, y = S.synthetic_arrays(model.racket, float(model.ball.radius), float(model.ball.mass), N, seed=4,
                              noise_vel=noise_vel, noise_spin=noise_spin)
    # Started from durr2026 (a "nakashima" racket: a neutral start, not the truth).
    return R.fit_racket(x, y, load_model("durr2026").replace(ball=model.ball))


def test_five_parameters_within_2_percent(model):
    fit = _fit(model, 0.05, 5.0)
    print("\nracket fit (3000 contacts, noise 0.05 m/s, 5 rad/s):")
    for k in R.PARAMETERS:
        true = float(getattr(model.racket, k))
        print(f"  {k}: {fit.values[k]:.5f} +- {fit.stderr[k]:.5f} (true {true:.5f}, "
              f"{100 * (fit.values[k] / true - 1):+.2f} %)")
        assert fit.values[k] == pytest.approx(true, rel=0.02)
        assert abs(fit.values[k] - true) < 4 * fit.stderr[k]
    assert fit.errors["fitted"]["velocity"] < fit.errors["base"]["velocity"]


def test_noiseless_contacts_give_the_exact_parameters(model):
    fit = _fit(model, 0.0, 0.0)
    for k in R.PARAMETERS:
        assert fit.values[k] == pytest.approx(float(getattr(model.racket, k)), rel=1e-4, abs=1e-6)


def test_bad_input_is_refused(model):
    with pytest.raises(ValueError, match=r"\(N, 8\)"):
        R.fit_racket(np.zeros((20, 6)), np.zeros((20, 6)), model)
    y = np.zeros((20, 6))
    y[7, 2] = np.nan
    with pytest.raises(ValueError, match=r"rows \[7\]"):
        R.fit_racket(np.zeros((20, 8)), y, model)


def test_a_parameter_beyond_its_physical_range_is_held_at_the_bound(model):
    """Contacts whose normal spin grows (e_s = 1.1, beyond the [0, 1] a model file allows): the free
    fit finds e_s > 1; the fit holds it at 1, refits the others, and the written model loads."""
    truth = model.racket.replace(e_s=model.racket.e_s * 0 + 1.1)
    x, y = S.synthetic_arrays(truth, float(model.ball.radius), float(model.ball.mass), N, seed=4)
    fit = R.fit_racket(x, y, load_model("durr2026").replace(ball=model.ball))
    assert fit.values["e_s"] == 1.0 and fit.stderr["e_s"] == 0.0
    assert len(fit.bounds) == 1 and fit.bounds[0].startswith("e_s = 1 (the free fit: 1.1")
    lo, hi = R.bounds()
    assert all(lo[i] <= fit.values[k] <= hi[i] for i, k in enumerate(R.PARAMETERS))
    for k in ("e0", "e1", "et0", "et1"):  # e_s acts on the normal spin alone: the others are unaffected
        assert fit.values[k] == pytest.approx(float(getattr(model.racket, k)), rel=1e-3, abs=1e-5)
        assert fit.stderr[k] >= 0.0
