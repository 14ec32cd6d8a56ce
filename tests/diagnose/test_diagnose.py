"""``ttsim diagnose`` end to end on small generated datasets (tests/diagnose/data/README.md):

* an effect withheld from the model (buckling, at a clear magnitude) is ranked first, is
  significant, and its parameters come out roughly;
* data with no effect (the truth is the model) gives no significant candidate and the verdict
  "unexplained" (the CLI end to end: files, JSON keys, report).

Each dataset is diagnosed once per module; the candidates are a few effects that compete for the
same phases (table and racket restitution, a table tilt, a racket region, a flight effect).
"""

import dataclasses
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
    return dict(diagnosis=out, problem=keep["problem"], model=model)


def test_withheld_effect_ranks_first_and_is_significant(withheld):
    cands = withheld["diagnosis"].candidates
    assert cands[0]["name"] == "buckling", [(c["name"], c["best_reduction_pct"]) for c in cands]
    assert cands[0]["significant"]
    v = withheld["diagnosis"].verdict
    assert v.level != "unexplained" and v.effects[0] == "buckling"
    # the table's gap (noise-free data: all of its error is removable) is closed; the text says how much
    assert v.shares["table"]["share"] >= 0.7 and "of the table gap" in v.text
    # the table phase is where it acts and where it is found
    h = cands[0]["heldout"]["table"]
    assert h["ci95"][0] > 10.0, h


def test_withheld_effect_parameters_are_recovered_roughly(withheld):
    p = withheld["diagnosis"].candidates[0]["params"]["buckling"]
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
    found = withheld["diagnosis"].candidates[0]["heldout"]["table"]["pct"]
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
    # where the time went: every stage once, the candidates each, adding up to the run time
    t = d["timings"]
    assert {"model errors", "noise floor", "model-free bounds", "verdict"} <= set(t), t
    assert {f"candidate {n}" for n in ("spin_decay", "worn_ball", "table_tilt")} <= set(t), t
    assert all(v >= 0.0 for v in t.values()) and abs(sum(t.values()) - d["seconds"]) < 0.05 * d["seconds"] + 0.1
    assert "Run time" in report and "candidate " in report.split("Run time")[1].splitlines()[0]


def test_forward_selection_keeps_an_effect_only_when_it_adds(withheld):
    """``select``: on data with buckling alone, a worn ball (a lower restitution at every speed) adds
    nothing on top of buckling, while buckling on top of a worn ball lowers the table errors
    significantly (a loss that grows with the impact speed); the accepted ones' joint fit is kept."""
    from ttsim_jax.diagnose import candidates as C
    from ttsim_jax.diagnose.diagnosis import select

    pb, model = withheld["problem"], withheld["model"]
    st = Settings.quick(effects=CANDIDATES)
    group = tuple(c for c in C.candidate_names(CANDIDATES))  # the withheld run's compiled group
    fits = {n: C.fit(pb, [n], model, group=group, steps=st.steps, lr=st.lr) for n in ("buckling", "worn_ball")}
    group_of = {n: group for n in group}
    accepted, best, adds = select(pb, [fits["buckling"], fits["worn_ball"]], model, group_of, st)
    assert [c.spec.name for c in accepted] == ["buckling"] and best is fits["buckling"]
    assert not adds["worn_ball"]["accepted"] and adds["worn_ball"]["on_top_of"] == ["buckling"]
    assert adds["worn_ball"]["interchangeable_with"] == []  # buckling does add on top of a worn ball
    accepted, best, adds = select(pb, [fits["worn_ball"], fits["buckling"]], model, group_of, st)
    assert [c.spec.name for c in accepted] == ["worn_ball", "buckling"], adds
    assert adds["buckling"]["heldout"]["table"]["ci95"][0] > 10.0
    assert best.spec.name == "worn_ball+buckling" and set(best.params) == {"worn_ball", "buckling"}


def test_forward_selection_does_not_refit_effects_of_disjoint_phases(withheld, monkeypatch):
    """An effect acting in phases that none of the accepted ones acts in is taken with its own fit
    (the joint fit would be the same); the combined result holds both fits' phases."""
    from ttsim_jax.diagnose import candidates as C
    from ttsim_jax.diagnose.diagnosis import select

    pb, model = withheld["problem"], withheld["model"]
    assert "flight" in pb.phases
    st = Settings.quick(effects=CANDIDATES)
    group = tuple(C.candidate_names(CANDIDATES))
    buckling = C.fit(pb, ["buckling"], model, group=group, steps=st.steps, lr=st.lr)
    # the noise-free flights err by less than the flight's resolution: give them a 2 mm error, and a
    # flight effect that halves it (stands in for a fitted air_flow)
    mask = np.asarray(pb.data["flight"]["mask"])[..., None]
    monkeypatch.setitem(pb.base, "flight", np.asarray(pb.base["flight"]) + 0.002 * mask)
    errors = {"flight": pb.base["flight"] * 0.5}
    flight = C.Candidate(spec=C.spec("air_flow")[0], consts=(), u=(), history=np.zeros(1), errors=errors,
                         heldout=C.score(pb, errors), params={"air_flow": {}})
    monkeypatch.setattr(C, "fit", lambda *a, **k: pytest.fail("refitted an effect of disjoint phases"))
    accepted, best, adds = select(pb, [buckling, flight], model, {n: group for n in group}, st)
    assert [c.spec.name for c in accepted] == ["buckling", "air_flow"] and adds["air_flow"]["accepted"]
    assert adds["air_flow"]["heldout"]["flight"]["pct"] == pytest.approx(50.0, abs=0.1)
    assert best.spec.name == "buckling+air_flow" and set(best.heldout) == {"flight", "table", "racket"}
    assert best.errors["table"] is buckling.errors["table"] and set(best.params) == {"buckling", "air_flow"}


def test_forward_selection_reports_interchangeable_effects(withheld, monkeypatch):
    """Two candidates that explain the same errors (their joint fit no better than either alone):
    the second is not accepted, and each adding nothing on top of the other, they are reported as
    interchangeable (in the verdict's text too)."""
    from ttsim_jax.diagnose import candidates as C
    from ttsim_jax.diagnose.diagnosis import _candidate_json, select
    from ttsim_jax.diagnose.verdict import verdict

    pb, model = withheld["problem"], withheld["model"]
    mask = np.asarray(pb.data["flight"]["mask"])[..., None]
    monkeypatch.setitem(pb.base, "flight", np.asarray(pb.base["flight"]) + 0.002 * mask)
    errors = {"flight": pb.base["flight"] * 0.5}

    def fitted(name):
        return C.Candidate(spec=C.spec(name)[0], consts=(), u=(), history=np.zeros(1), errors=errors,
                           heldout=C.score(pb, errors), params={name: {}})

    wind, ball = fitted("air_flow"), fitted("ball_variation")
    monkeypatch.setattr(C, "fit", lambda pb, names, *a, **k: dataclasses.replace(fitted(names[0]), params={
        n: {} for n in names}))
    st = Settings.quick(effects=CANDIDATES)
    accepted, best, adds = select(pb, [wind, ball], model, {}, st)
    assert [c.spec.name for c in accepted] == ["air_flow"] and best is wind
    assert not adds["ball_variation"]["accepted"] and adds["ball_variation"]["interchangeable_with"] == ["air_flow"]
    out = dict(where={}, dependence={}, candidates=[dict(_candidate_json(wind, 1)),
                                                    dict(_candidate_json(ball, 2), adds=adds["ball_variation"])])
    text = verdict(out, accepted, [ball]).text
    assert "air_flow and ball_variation are interchangeable" in text, text


def test_interchangeable_is_asked_of_each_neighbour_with_the_others_beside(withheld, monkeypatch):
    """A redundant candidate with two accepted neighbours in its phase (as a tilt beside spin decay
    and a warped top): it is interchangeable with the neighbour it can stand in for (that one adds
    nothing on top of it and the other neighbour), not with the one that explains other errors."""
    from ttsim_jax.diagnose import candidates as C
    from ttsim_jax.diagnose.diagnosis import select

    pb, model = withheld["problem"], withheld["model"]
    mask = np.asarray(pb.data["flight"]["mask"])[..., None]
    monkeypatch.setitem(pb.base, "flight", np.asarray(pb.base["flight"]) + 0.002 * mask)
    # spin_decay takes half the error; ball_variation and air_flow the same quarter of it
    def errors(names):
        share = 0.5 * ("spin_decay" in names) + 0.25 * bool({"ball_variation", "air_flow"} & set(names))
        return {"flight": pb.base["flight"] * (1.0 - share)}

    fits = []

    def fit(pb, names, *a, **k):
        fits.append(tuple(names))
        e = errors(names)
        return C.Candidate(spec=C.spec(names[-1])[0], consts=(), u=(), history=np.zeros(1), errors=e,
                           heldout=C.score(pb, e), params={n: {} for n in names})

    ranked = [fit(pb, [n]) for n in ("spin_decay", "ball_variation", "air_flow")]
    monkeypatch.setattr(C, "fit", fit)
    accepted, best, adds = select(pb, ranked, model, {}, Settings.quick(effects=CANDIDATES))
    assert [c.spec.name for c in accepted] == ["spin_decay", "ball_variation"], adds
    assert not adds["air_flow"]["accepted"]
    assert adds["air_flow"]["interchangeable_with"] == ["ball_variation"], adds["air_flow"]
    # one joint fit for the redundant one, then one per neighbour, each without it
    assert ("ball_variation", "air_flow") in fits and ("spin_decay", "air_flow") in fits
