"""Detection limits: the bisection, the linear injection against its closed form, invariance to an
effect the record already holds, and the limits in a diagnosis's report."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from ttsim_jax.diagnose import candidates as C
from ttsim_jax.diagnose import limits as L


def test_limit_size_bisects_to_the_threshold():
    for t in (0.0031, 0.3, 7.0, 55.0):
        s = L.limit_size(lambda x: x >= t)
        assert t <= s < t * 1.02, (t, s)
    assert L.limit_size(lambda x: False) == math.inf
    assert L.limit_size(lambda x: True) == L.MIN_SIZE


def table_problem(n=600, sigma=0.3, seed=0):
    """A table phase of ``n`` contacts whose model errors are Gaussian noise of ``sigma`` per
    component, split 60/40."""
    rng = np.random.default_rng(seed)
    r = rng.normal(0.0, sigma, (n, 6))
    test = (rng.random(n) < 0.4).astype(np.float32)
    data = {"table": {"train": 1.0 - test, "test": test}}
    return SimpleNamespace(base={"table": r}, data=data, norm={"table": float(np.mean(np.sum(r**2, 1)))},
                           phases=("table",)), rng


def test_injected_effect_is_found_above_its_limit_and_not_below():
    pb, rng = table_problem()
    delta = {"table": np.tile([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], (600, 1)) * rng.uniform(0.5, 1.5, (600, 1))}
    size = L.limit_size(lambda s: all(C.significant("table", L.heldout_at(pb, delta, sg * s)["table"])
                                      for sg in (1.0, -1.0)))
    assert math.isfinite(size)
    for sg in (1.0, -1.0):  # either sign shows above the limit
        assert C.significant("table", L.heldout_at(pb, delta, sg * 1.05 * size)["table"])
    assert not all(C.significant("table", L.heldout_at(pb, delta, sg * 0.9 * size)["table"]) for sg in (1.0, -1.0))
    # closed form: at the limit the effect's mean square lifts the held-out mean square by about
    # 2 x the 1 % reduction the rule asks for plus the interval's half-width: some per cent of it
    h = L.heldout_at(pb, delta, size)["table"]
    assert 1.0 < h["pct"] < 10.0


def test_an_effect_the_record_holds_does_not_count_as_detected():
    pb, rng = table_problem(seed=1)
    d = np.tile([0.04, 0.01, 0.0, 0.0, 0.0, 0.0], (600, 1))
    clean = L.candidate_limits(pb, {"table": d}, *C.spec("worn_ball"))["table"]
    held = SimpleNamespace(**{**vars(pb), "base": {"table": pb.base["table"] - 8.0 * d}})  # the record holds 8 x it
    found = L.candidate_limits(held, {"table": d}, *C.spec("worn_ball"))["table"]
    assert found["size"] == pytest.approx(clean["size"], rel=0.03)
    assert found["params"]["loss"] == pytest.approx(clean["size"] * 0.02, rel=0.03)  # loss typical 0.02
    # the held-out rows see as little of it as the training rows: the two signs alike
    for sg in (1.0, -1.0):
        h = L.heldout_at(held, {"table": d}, sg * found["size"])["table"]
        assert h["pct"] > C.MIN_REDUCTION


def test_the_limit_shrinks_with_more_data_and_grows_with_noise():
    d = lambda n: {"table": np.tile([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], (n, 1))}  # noqa: E731
    sp = C.spec("worn_ball")
    few = L.candidate_limits(table_problem(200)[0], d(200), *sp)["table"]
    many = L.candidate_limits(table_problem(3200)[0], d(3200), *sp)["table"]
    noisy = L.candidate_limits(table_problem(3200, sigma=0.6)[0], d(3200), *sp)["table"]["size"]
    # the interval narrows with more data, down to the rule's own floor: a 1 % reduction at least
    assert many["size"] < 0.9 * few["size"] and few["reduction_pct"] > many["reduction_pct"] > C.MIN_REDUCTION
    assert noisy > 1.5 * many["size"]  # the same relative reduction of twice the noise takes twice the effect


def test_describe_names_the_parameters_and_their_units():
    entry = dict(size=0.2, params={"wind": [0.04, 0.0, 0.0]}, share_pct=3.0, reduction_pct=1.5)
    assert L.describe("air_flow", entry) == "air_flow: wind 0.04 m/s"
    assert "not within" in L.describe("buckling", dict(size=None, params={}))
