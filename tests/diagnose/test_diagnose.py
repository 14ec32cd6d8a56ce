"""``ttsim diagnose`` end to end on small generated datasets (tests/diagnose/data/README.md):

* an effect withheld from the model (buckling, at a clear magnitude) is ranked first, is
  significant, and its parameters come out roughly;
* data with no effect (the truth is the model) gives no significant candidate and the verdict
  "unexplained" (the CLI end to end: files, JSON keys, report).

Each dataset is diagnosed once per module; the candidates are a few effects that compete for the
same phases (table and racket restitution, a table tilt, a racket region, a flight effect).
"""

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.cli import main
from ttsim_jax.data import load
from ttsim_jax.diagnose.diagnosis import Settings, diagnose
from ttsim_jax.diagnose.report import FIGURES

HERE = Path(__file__).parent
BUCKLING = HERE / "data" / "buckling"  # conti2026 + buckling (see buckling.toml)
CLEAN = HERE.parent / "evaluate" / "data" / "clean"  # durr2026, no effect
TRUE_BUCKLING = dict(table_onset=3.0, table_width=2.0, table_depth=0.15)
CANDIDATES = ("worn_ball", "buckling", "table_tilt", "racket_logo")


@pytest.fixture(scope="module")
def withheld():
    ds = load(BUCKLING)
    model = load_model("conti2026", dtype=jnp.float32)
    keep = {}
    out = diagnose(ds, model, Settings.quick(effects=CANDIDATES), keep=keep)
    return dict(out, problem=keep["problem"], model=model)


def test_withheld_effect_ranks_first_and_is_significant(withheld):
    cands = withheld["candidates"]
    assert cands[0]["name"] == "buckling", [(c["name"], c["best_reduction_pct"]) for c in cands]
    assert cands[0]["significant"]
    assert withheld["verdict"]["explained"] and withheld["verdict"]["effects"][0] == "buckling"
    # the table phase is where it acts and where it is found
    h = cands[0]["heldout"]["table"]
    assert h["ci95"][0] > 10.0, h


def test_withheld_effect_parameters_are_recovered_roughly(withheld):
    p = withheld["candidates"][0]["params"]["buckling"]
    # the restitution loss at a 6 m/s impact, from the fitted and the true parameters
    def loss(q):
        r = max(6.0 - q["table_onset"], 0.0) / q["table_width"]
        return q["table_depth"] * (1.0 - np.exp(-r * r))

    fitted = {k: p[k] for k in ("table_onset", "table_width", "table_depth")}
    assert 0.5 * loss(TRUE_BUCKLING) < loss(fitted) < 1.5 * loss(TRUE_BUCKLING), fitted


def test_oracle_shrink_of_the_selfcheck(withheld):
    """The selfcheck's oracle (the model given the true effect) removes the table gap of noise-free
    data, and the diagnosis recovers most of that shrink."""
    from ttsim_jax.diagnose.selfcheck import oracle_scores

    truth = json.loads((BUCKLING / "truth.json").read_text())
    oracle = oracle_scores(withheld["problem"], withheld["model"], "buckling", truth)
    assert oracle["table"]["pct"] > 80.0, oracle
    found = withheld["candidates"][0]["heldout"]["table"]["pct"]
    assert found > 0.8 * oracle["table"]["pct"]


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("diagnose") / "out"
    status = main(["diagnose", "--data", str(CLEAN), "--model", "durr2026", "--out", str(out), "--quick", "--effects",
                   "spin_decay,worn_ball,table_tilt,table_unevenness,racket_logo", "--quiet"])
    return status, out


def test_no_effect_no_significant_candidate(clean_run):
    status, out = clean_run
    assert status == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert [c["name"] for c in d["candidates"]] and not any(c["significant"] for c in d["candidates"]), d["candidates"]
    assert not d["verdict"]["explained"] and d["verdict"]["text"].startswith("Unexplained")
    # the model is the truth: its held-out errors are tiny (noise-free data; state estimation only)
    assert d["where"]["flight"]["mean"] < 1e-3


def test_cli_writes_every_file(clean_run):
    status, out = clean_run
    for name in list(FIGURES.values()) + ["report.md", "diagnosis.json"]:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    d = json.loads((out / "diagnosis.json").read_text())
    assert set(d["phases"]) == {"flight", "table", "racket"}
    assert {"where", "dependence", "record", "candidates", "verdict", "settings", "loss_history"} <= set(d)
    assert set(d["record"]) >= {"position_noise", "missing_frames", "spin_noise", "racket_state_error"}
    # noise-free data: the estimated position noise is far below a real tracker's millimetres
    assert max(d["record"]["position_noise"]["sigma"]) < 2e-4
    report = (out / "report.md").read_text()
    for fig in FIGURES.values():
        assert f"]({fig})" in report
    assert "## Where" in report and "## Which effect" in report
