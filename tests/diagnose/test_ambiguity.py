"""Candidates the data cannot tell apart are reported together, with what data would separate them;
a model-free correction that does better than the catalogue is named in the verdict."""

from types import SimpleNamespace

import numpy as np

from ttsim_jax.diagnose.ambiguity import COLLINEAR, indistinguishable, similarity
from ttsim_jax.diagnose.verdict import verdict


def problem(n=40, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.normal(0.0, 0.2, (n, 6))
    w = np.ones(n)
    return SimpleNamespace(base={"table": base}, norm={"table": 0.04},
                           data={"table": {"train": w * (np.arange(n) % 2), "test": w * (np.arange(n) % 2 == 0)}})


def fitted(name, errors):
    return SimpleNamespace(spec=SimpleNamespace(name=name), errors={"table": errors})


def test_parallel_signatures_are_grouped_and_others_are_not():
    pb = problem()
    rng = np.random.default_rng(1)
    shape = rng.normal(0.0, 0.05, pb.base["table"].shape)
    a = fitted("worn_ball", pb.base["table"] - shape)
    b = fitted("buckling", pb.base["table"] - 0.7 * shape - rng.normal(0.0, 0.004, shape.shape))
    c = fitted("table_tilt", pb.base["table"] - rng.normal(0.0, 0.05, shape.shape))
    (g,) = indistinguishable(pb, [a, b, c])
    assert g["names"] == ["worn_ball", "buckling"] and g["cosine"] >= COLLINEAR
    assert "impact speeds" in g["separate"]
    assert indistinguishable(pb, [a, c]) == []
    assert similarity({"table": np.ones(3)}, {"flight": np.ones(3)}) == 0.0


def test_the_verdict_names_indistinguishable_candidates_and_a_better_model_free_correction():
    worn = SimpleNamespace(spec=SimpleNamespace(name="worn_ball"), params={"worn_ball": {"loss": 0.02}},
                           heldout={"table": {"pct": 10.0, "ci95": [8.0, 12.0]}})
    out = {"where": {}, "dependence": {}, "candidates": [],
           "indistinguishable": [dict(names=["worn_ball", "buckling"], cosine=0.97, separate="bounces over a wide range")],
           "before_after": {"table": {"heldout": dict(pct=10.0, ci95=[8.0, 12.0], before_rms=0.3, after_rms=0.27)}},
           "bound": {"table": {"heldout": dict(pct=35.0, ci95=[28.0, 41.0], significant=True),
                               "terms": [{"name": "tangential velocity x per slip x", "share": 0.8}]}}}
    v = verdict(out, [worn])
    assert v["level"] == "partly explained"
    assert "worn_ball and buckling are indistinguishable on these data" in v["text"]
    assert "bounces over a wide range would tell them apart" in v["text"]
    assert ("In the table phase the catalogue closes less than a model-free correction does (10.0 % against 35.0 %"
            in v["text"]) and "tangential velocity x per slip x (80 %)" in v["text"]
    out["bound"]["table"]["heldout"]["ci95"] = [5.0, 41.0]  # not clearly better: no word, no downgrade
    assert "model-free" not in verdict(out, [worn])["text"]
