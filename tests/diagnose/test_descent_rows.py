"""The descent flies the training segments only (``candidates.flight_split``); every other segment
gets its initial state fitted at the end with the effects found. So a candidate's errors on every
row are those of the model plus its fitted effects with each segment at its own optimal state, as
``candidates.evaluate`` computes them from scratch (per segment, its RMS error); and the second
descent of a refined candidate runs the first one's compiled program (the same static spec)."""

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.data import load
from ttsim_jax.diagnose import bumps, gusts, onsets, stages
from ttsim_jax.diagnose import candidates as C
from ttsim_jax.diagnose.diagnosis import Settings
from ttsim_jax.diagnose.phases import Phases, collect

CLEAN = Path(__file__).parents[1] / "evaluate" / "data" / "clean"  # durr2026, no effect (as test_diagnose)


def _problem_with_train(train):
    return C.Problem(data={"flight": {"train": jnp.asarray(train, jnp.float32)}}, phases=("flight",), n_sessions=1,
                     sessions=np.zeros(1))


def test_flight_split_pads_each_part_with_rows_of_its_own():
    train = np.array([0, 1, 1, 0, 1, 0, 0, 1, 1, 1, 0, 0], np.float32)
    rows, valid, rest = (np.asarray(a) for a in C.flight_split(_problem_with_train(train), multiple=4))
    assert rows.tolist() == [1, 2, 4, 7, 8, 9, 9, 9] and valid.tolist() == [1] * 6 + [0] * 2
    assert rest.tolist() == [0, 3, 5, 6, 10, 11, 11, 11]
    # no training segment: one row flown with no weight; no other segment: a training row repeated
    rows, valid, rest = (np.asarray(a) for a in C.flight_split(_problem_with_train(np.zeros(3)), multiple=4))
    assert not valid.any() and rest.tolist() == [0, 1, 2, 2]
    rows, valid, rest = (np.asarray(a) for a in C.flight_split(_problem_with_train(np.ones(3)), multiple=4))
    assert valid.tolist() == [1, 1, 1, 0] and set(rest.tolist()) <= set(rows.tolist())


@pytest.mark.parametrize("name, stage", [("air_flow", gusts), ("table_unevenness", bumps), ("buckling", onsets)])
def test_a_second_descent_runs_the_first_descents_program(name, stage):
    sp, const = C.spec(name)
    second, second_const = stages.second_descent(sp, const["start"], stage.SCALES)
    assert second == sp and hash(second) == hash(sp)
    # what the first descent holds (step 0) the second frees
    assert {k for k in sp.free if const["scale"][k] == 0.0} <= set(stage.SCALES)
    assert all(second_const["scale"][k] > 0 for k in stage.SCALES)


def test_every_rows_errors_are_the_fitted_effects_at_the_rows_own_optimal_states():
    st = Settings.quick()
    truth = load_model("durr2026", dtype=jnp.float32)
    # a model whose air is 30 % denser than the data's: errors of centimetres that the fitted air
    # density takes away, so that states fitted before it (the model's) are far from the right ones
    model = truth.replace(aero=truth.aero.replace(rho_air=truth.aero.rho_air * 1.3))
    ph: Phases = collect(load(CLEAN), model, st.fit, max_segments=st.max_segments, seed=st.seed)
    pb = C.problem(ph, model, st.test_fraction, st.seed)
    cand = C.fit(pb, ["air_density"], model, steps=st.steps, lr=st.lr)
    errors, _ = C.evaluate(model, (cand.spec,), cand.consts, cand.u, pb, iterations=stages.GN_START,
                           phases=("flight",))
    n = ph.flights.n
    train = np.asarray(pb.data["flight"]["train"])[:n] > 0
    mask = np.asarray(pb.data["flight"]["mask"])[:n]

    def rms(e):  # per segment [m]: the states' fit is flat along some directions, its objective is not
        return np.sqrt(np.sum(np.asarray(e)[:n] ** 2, axis=(1, 2)) / np.maximum(mask.sum(1), 1))

    got, want = rms(cand.errors["flight"]), rms(errors["flight"])
    before = rms(pb.base["flight"])
    assert train.any() and (~train).any() and np.median(before) > 1e-3  # the denser air's centimetres
    assert np.median(want) < 0.5 * np.median(before)
    for rows in (~train, train):  # held-out rows fitted at the end; training rows along the descent
        np.testing.assert_allclose(got[rows], want[rows], rtol=1e-3, atol=1e-6)
