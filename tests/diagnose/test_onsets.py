"""The onset grid of the ``buckling`` candidate (:mod:`ttsim_jax.diagnose.onsets`).

* the closed-form depth and fall of :func:`best_onset` on errors linear in the depth;
* on the small generated buckling dataset (tests/diagnose/data; no noise, exact racket states), the
  grid's start lies at the true table onset, width and depth (onset and width on the grid).
"""

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.data import load
from ttsim_jax.diagnose import candidates as C
from ttsim_jax.diagnose import onsets as O
from ttsim_jax.diagnose.phases import collect

DATA = Path(__file__).parent / "data" / "buckling"


def test_best_onset_closed_form():
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(5, 200, 6))  # error change per unit depth at 5 grid points
    e0 = -0.2 * jac[3] + rng.normal(0.0, 0.01, (200, 6))  # a model that lacks a depth of 0.2 at point 3
    probe = e0[None] + O.PROBE * jac
    weight = np.ones(200)
    k, depth, fall = O.best_onset(e0, probe, weight)
    assert k == 3 and abs(depth - 0.2) < 0.01
    np.testing.assert_allclose(fall, np.sum(e0**2) - np.sum((e0 + depth * jac[3]) ** 2), rtol=1e-9)
    # a loss beyond DEPTH_MAX is clipped to it (the fall is that of the clipped depth)
    e_big = -0.5 * jac[3]
    k, depth, fall = O.best_onset(e_big, e_big[None] + O.PROBE * jac, weight)
    assert k == 3 and depth == O.DEPTH_MAX
    np.testing.assert_allclose(fall, np.sum(e_big**2) - np.sum((e_big + depth * jac[3]) ** 2), rtol=1e-9)
    # a loss that would have to be negative (a gain) is not taken: depth 0, no fall
    k, depth, fall = O.best_onset(-e0, -e0[None] + O.PROBE * jac[3:4], weight)
    assert depth == 0.0 and fall == 0.0


@pytest.fixture(scope="module")
def problem():
    model = load_model("conti2026", dtype=jnp.float32)
    ph = collect(load(DATA), model, phases=("table", "racket"))
    return model, C.problem(ph, model)


def test_grid_start_is_near_the_true_onsets(problem):
    model, pb = problem
    sp, const = C.spec("buckling")
    second = O.onset_stage(pb, model, (sp,), (const,), None, None, 0)
    assert second is not None
    spec2, const2 = second
    assert set(spec2.free) == set(O.SCALES)
    start = {k: float(np.asarray(v)) for k, v in const2["start"].items()}
    # truth: table onset 3, width 2, depth 0.15; racket onset 10, width 5, depth 0.15
    assert start["table_onset"] == 3.0 and start["table_width"] == 2.0, start
    assert abs(start["table_depth"] - 0.15) < 0.03, start
    # the racket's onset is not pinned by the dataset's 35 racket contacts (a handful above 10 m/s
    # normal to the face: onsets 9 and 14 fit about as well); a loss is found there all the same
    assert start["racket_onset"] >= 8.0 and start["racket_depth"] > 0.05, start
