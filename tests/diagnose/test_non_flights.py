"""A segment no free flight can give (here: the ball lying still through it, as a ball at rest on
the floor that a generator or a tracker kept as a segment) is left out of the flight
phase and counted, not scored as the model's flight error: one such segment of thousands once
made a whole phase a gap of 3 x its noise floor."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ttsim_jax import load_model
from ttsim_jax.data import load
from ttsim_jax.data.speeds import non_flights
from ttsim_jax.data.validate import borderline
from ttsim_jax.diagnose.phases import collect

from test_diagnose import BUCKLING


def resting(ds, segment_id):
    """``ds`` with the ball of segment ``segment_id`` lying still where it starts."""
    obs = dict(ds.observations)
    rows = np.flatnonzero(np.asarray(obs["segment_id"]) == segment_id)
    for a in "xyz":
        col = np.asarray(obs[a], np.float64).copy()
        col[rows] = col[rows[0]]
        obs[a] = col
    return ds.replace(observations=obs)


def test_a_segment_no_flight_can_give_is_left_out_and_counted():
    ds = load(BUCKLING)
    assert non_flights(ds).size == 0  # the generator's flights are flights
    seg = np.asarray(ds.segments["segment_id"])
    rows = np.bincount(np.asarray(ds.observations["segment_id"])[np.asarray(ds.observations["segment_id"]) >= 0])
    victim = int(seg[np.argmax(rows[seg])])  # the longest
    bad = resting(ds, victim)
    assert non_flights(bad).tolist() == [victim]
    # validation warns of the same segment
    assert any("accelerate more than gravity" in str(w) for w in borderline(bad))
    model = load_model("conti2026", dtype=jnp.float32)
    before = collect(ds, model, phases=("flight",))
    after = collect(bad, model, phases=("flight",))
    assert victim in before.flights.segment_id[: before.flights.n]
    assert victim not in after.flights.segment_id[: after.flights.n]
    assert after.flights.n == before.flights.n - 1
    assert before.left_out == {} and after.left_out == {"flight": {"no free flight (validation's acceleration check)": 1}}
