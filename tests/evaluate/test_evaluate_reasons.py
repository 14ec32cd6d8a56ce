"""The report never shows a count smaller than its items (n = 0 above all) without the reason."""

import json

import numpy as np

from ttsim_jax.evaluate.report import FIGURES, markdown, summarise
from ttsim_jax.evaluate.result import Evaluation
from ttsim_jax.fit.flight import FlightStage


def result(rmse: dict, spin) -> Evaluation:
    """What evaluate_models returns for the flight stage alone (no simulation needed to judge the report)."""
    names = list(rmse)
    return Evaluation(models=names, reference=names[0], settings={},
                      flight=FlightStage(segment_id=np.arange(len(spin)), spin_measured=True, n_without_spin=0,
                                         rmse={k: np.asarray(v, float) for k, v in rmse.items()},
                                         spin=np.asarray(spin, float), spin_source=np.full(len(spin), "measured"),
                                         latent_spin={}))


def test_a_model_without_finite_flights_is_reported_with_the_reason():
    spin = [[0.0, 1e9, 0.0], [0.0, 3e8, 0.0], [0.0, 200.0, 0.0]]
    s = summarise(result({"nakashima2011": [np.nan, np.nan, np.nan], "conti2026": [0.002, np.nan, 0.003]}, spin))
    f = s["flight"]
    assert f["models"]["nakashima2011"]["n"] == 0 and f["models"]["conti2026"]["n"] == 2
    why = f["not_finite"]
    assert set(why) == {"nakashima2011", "conti2026"}
    assert why["nakashima2011"].startswith("3 of 3 segments without a finite RMSE") and "1e+09 rad/s" in why["nakashima2011"]
    assert why["conti2026"].startswith("1 of 3 segments") and "3e+08 rad/s" in why["conti2026"]
    report = markdown(s, FIGURES)
    assert any(line.startswith("| nakashima2011 | 0 |") for line in report.splitlines())
    assert "n of nakashima2011: 3 of 3 segments without a finite RMSE" in report
    assert "n of conti2026: 1 of 3 segments" in report
    json.dumps(s, allow_nan=False)  # metrics.json stays valid JSON


def test_complete_counts_need_no_reason():
    s = summarise(result({"a": [0.002, 0.003], "b": [0.004, 0.001]}, [[0, 100, 0], [0, 200, 0]]))
    assert s["flight"]["not_finite"] == {}
    assert "n of " not in markdown(s, FIGURES)
