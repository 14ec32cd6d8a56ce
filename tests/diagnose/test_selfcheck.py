"""The selfcheck's scoring rules on hand-made diagnosis results (no simulation): detectable and
undetectable cases, rank 1, the located phase, the shrink recovered, pairs, the outside case, the
summary's rates, and the magnitudes drawn per effect."""

import json
import math
import os

import numpy as np
import pytest

from ttsim_jax import effects as fx
from ttsim_jax.diagnose import selfcheck as SC


def held(pct, before=0.1, lo=None):
    """A held-out score: ``pct`` % lower RMS, its interval's lower end ``lo`` (default pct - 2)."""
    return dict(pct=pct, ci95=[pct - 2.0 if lo is None else lo, pct + 2.0], before_rms=before,
                after_rms=before * (1.0 - pct / 100.0), n=200)


def cand(name, significant=True, **heldout):
    return dict(name=name, significant=significant, heldout=heldout)


NO_WHERE = {"flight": {"flagged": []}, "table": {"flagged": []}, "racket": {"flagged": []}}


def test_true_effect_first_is_found_with_its_phase_and_shrink():
    oracle = {"table": held(40.0)}
    cands = [cand("table_tilt", table=held(30.0)), cand("worn_ball", table=held(5.0), racket=held(1.0, lo=-1.0))]
    r = SC.score("single", ["table_tilt"], cands, NO_WHERE, oracle)
    assert r["detectable"] and r["rank1"] and r["outcome"] == "found"
    assert r["phase"] == "table" and r["phase_right"]
    assert r["shrink"] == pytest.approx(30.0 / 40.0)


def test_wrong_first_candidate_is_a_miss_but_its_shrink_counts():
    oracle = {"flight": held(20.0, before=0.003)}
    cands = [cand("air_flow", flight=held(12.0, before=0.003)), cand("spin_decay", flight=held(10.0, before=0.003))]
    r = SC.score("single", ["spin_decay"], cands, NO_WHERE, oracle)
    assert not r["rank1"] and r["outcome"] == "missed" and r["top"] == "air_flow"
    assert r["phase"] == "flight" and r["phase_right"]
    assert r["shrink"] == pytest.approx(12.0 / 20.0)  # the best significant reduction in the oracle's phase


def test_located_phase_is_the_largest_significant_one():
    # ball_variation acts in all phases: its racket reduction is larger but not significant
    c = cand("ball_variation", flight=held(8.0, before=0.003), racket=held(15.0, lo=-3.0))
    assert SC.located_phase(c) == "flight"
    r = SC.score("single", ["spin_decay"], [c], NO_WHERE, {"flight": held(10.0, before=0.003)})
    assert r["phase"] == "flight" and r["phase_right"] and not r["rank1"]


def test_undetectable_case_nothing_found_is_right_and_kept_out_of_the_rates():
    # the oracle's own reduction is inside the noise: interval's lower end below the rule's 1 %
    weak = SC.score("single", ["spin_decay"], [cand("spin_decay", False, flight=held(0.5, before=0.003))], NO_WHERE,
                    {"flight": held(0.8, before=0.003, lo=-0.5)})
    assert not weak["detectable"] and weak["unexplained"] and weak["outcome"] == "undetectable: nothing found"
    assert math.isnan(weak["shrink"])
    alarm = SC.score("single", ["spin_decay"], [cand("air_flow", flight=held(3.0, before=0.003))], NO_WHERE,
                     {"flight": held(0.8, before=0.003, lo=-0.5)})
    assert alarm["outcome"] == "undetectable: false alarm (air_flow)"
    found = SC.score("single", ["table_tilt"], [cand("table_tilt", table=held(30.0))], NO_WHERE, {"table": held(40.0)})
    missed = SC.score("single", ["buckling"], [cand("buckling", False, table=held(1.0, lo=-1.0))], NO_WHERE,
                      {"table": held(20.0)})
    rows = [dict(r, kind="single") for r in (weak, alarm, found, missed)]
    s = SC.summary(rows)
    assert s["n_single"] == 2 and s["rank1_rate"] == 0.5 and s["phase_rate"] == 0.5
    assert s["median_shrink"] == pytest.approx(0.5 * (30.0 / 40.0 + 0.0))
    assert s["n_undetectable"] == 2 and s["undetectable_nothing_found"] == 1


def test_an_insignificant_gain_below_the_phase_resolution_is_not_detectable():
    # 20 % of a 1e-5 m/s error is far below the table's 0.01 m/s resolution
    r = SC.score("single", ["table_tilt"], [], NO_WHERE, {"table": held(20.0, before=1e-5)})
    assert not r["detectable"]


def test_a_true_spin_corrected_as_if_wrong_is_scored_as_a_wrong_cause():
    """The games record their spin true: a verdict that puts the gap on the record's spin (thinner
    air read as a spin read high) names a wrong cause beside the right one, and the case says so."""
    oracle = {"flight": held(40.0, before=0.003)}
    cands = [cand("air_density", flight=held(38.0, before=0.003))]
    on_record = dict(level="partly explained", effects=["spin_record", "air_density"], gaps=[])
    r = SC.score("single", ["air_density"], cands, NO_WHERE, oracle, on_record)
    assert r["rank1"] and r["spin_wrong"] and r["outcome"] == "found, the record's spin wrongly corrected"
    clean = SC.score("single", ["air_density"], cands, NO_WHERE, oracle, dict(on_record, effects=["air_density"]))
    assert not clean["spin_wrong"] and clean["outcome"] == "found"
    assert SC.summary([dict(r, kind="single"), dict(clean, kind="single")])["spin_wrong"] == 1
    # outside the catalogue too (thinner air withheld, put on the record), and the figure calls it wrong;
    # a spin estimator's own error put on the record is right
    thin = SC.score("outside", ["air_density"], [], NO_WHERE, oracle, dict(on_record, effects=["spin_record"]))
    assert thin["spin_wrong"] and thin["outcome"].endswith(", the record's spin wrongly corrected")
    assert SC.verdict_of(dict(thin, kind="outside")) == "wrong"
    assert not SC.score("outside", ["spin_calibration"], [], NO_WHERE, {}, dict(on_record, effects=["spin_record"]))["spin_wrong"]


def test_pair_scores_both_effects():
    oracle = {"flight": held(10.0, before=0.003), "table": held(30.0), "racket": held(5.0)}
    both = [cand("buckling", table=held(25.0)), cand("air_flow", flight=held(9.0, before=0.003))]
    r = SC.score("pair", ["air_flow", "buckling"], both, NO_WHERE, oracle)
    assert r["rank1"] and r["both"] and r["outcome"] == "both found"
    assert r["oracle_phase"] == "table" and r["shrink"] == pytest.approx(25.0 / 30.0)
    one = SC.score("pair", ["air_flow", "buckling"], both[:1] + [cand("worn_ball", table=held(3.0))], NO_WHERE, oracle)
    assert one["rank1"] and not one["both"] and one["outcome"] == "one found"


def test_outside_case_is_unexplained_and_located_by_the_flagged_phase():
    where = {"flight": {"flagged": []}, "table": {"flagged": []}, "racket": {"flagged": [("distance", "0.07-0.1 m")]}}
    nothing = [cand("racket_logo", False, racket=held(0.5, lo=-2.0))]
    r = SC.score("outside", ["racket_edge"], nothing, where, {"racket": held(15.0)})
    assert r["unexplained"] and r["located"] == ["racket"] and r["phase_right"]
    assert r["outcome"] == "unexplained, located in racket"
    wrong = SC.score("outside", ["racket_edge"], nothing, dict(where, racket={"flagged": []},
                     table={"flagged": [("speed", "5-9 m/s")]}), {"racket": held(15.0)})
    assert wrong["unexplained"] and not wrong["phase_right"]
    absorbed = SC.score("outside", ["racket_edge"], [cand("worn_ball", racket=held(4.0))], where, {"racket": held(15.0)})
    assert not absorbed["unexplained"] and absorbed["outcome"].startswith("explained by worn_ball")
    s = SC.summary([dict(r, kind="outside"), dict(absorbed, kind="outside")])
    assert s["outside_unexplained"] == [True, False] and s["n_single"] == 0


def test_outside_case_is_wrong_only_when_explained_and_located_by_a_gap_above_the_floor():
    stand_in = [cand("worn_ball", racket=held(20.0))]
    oracle = {"racket": held(30.0)}
    partly = SC.score("outside_log", ["racket_edge"], stand_in, NO_WHERE, oracle,
                      dict(level="partly explained", gaps=["racket"]))
    assert not partly["wrong_explained"] and partly["located"] == ["racket"] and partly["phase_right"]
    assert partly["outcome"] == "partly explained by worn_ball, located in racket"
    full = SC.score("outside_log", ["racket_edge"], stand_in, NO_WHERE, oracle, dict(level="explained", gaps=[]))
    assert full["wrong_explained"] and not full["phase_right"] and full["outcome"] == "explained by worn_ball, not located"
    quiet = SC.score("outside_log", ["table_unevenness"], [], NO_WHERE, oracle, dict(level="no gap", gaps=[]))
    assert quiet["outcome"] == "no gap, not located" and not quiet["wrong_explained"]
    s = SC.summary([dict(partly, kind="outside_log"), dict(full, kind="outside_oneway")])
    assert (s["n_outside"], s["outside_wrong_explained"], s["outside_located_rate"]) == (2, 1, 0.5)
    assert [SC.verdict_of(dict(r, kind="outside")) for r in (partly, full)] == ["right", "wrong"]


def test_outside_plan_and_the_tracker_log_of_one_direction():
    from pathlib import Path

    from ttsim_jax.data import load

    plan = SC.outside_cases()
    assert len(plan) >= 9 and {k for k, _ in plan} == set(SC.OUTSIDE_KINDS) | {"control"}
    assert plan[-1] == ("control", ())  # last: the stored cases of a run without it keep their numbers
    assert SC.outside_cases((("outside", ("no_such_effect",)),)) == []
    ds = load(Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games")
    log = SC.as_tracker_log(ds, one_way=True)
    assert len(log.events["t"]) and "racket" not in set(log.events["kind"])
    x = log.positions[:, 0]
    for sid in log.segments["segment_id"]:
        k = np.flatnonzero(log.observations["segment_id"] == sid)
        assert x[k[-1]] > x[k[0]], sid  # every flight kept goes towards +x
    both = SC.as_tracker_log(ds)
    assert len(log.segments["segment_id"]) < 0.7 * len(both.segments["segment_id"])


@pytest.mark.parametrize("name", sorted(SC.DRAWS))
def test_drawn_magnitudes_are_valid_parameters_in_the_upper_realistic_range(name):
    cls = fx.effect_class(name)
    rng = np.random.default_rng(3)
    draws = [SC.draw(name, rng) for _ in range(50)]
    for d in draws:
        cls.from_dict(d)  # raises naming the parameter when a draw has the wrong shape
    if name == "table_tilt":
        slope = np.linalg.norm([d["slope"] for d in draws], axis=1)
        assert slope.min() >= 0.009 and slope.max() <= 0.0125
    if name == "table_unevenness":
        for d in draws:
            h, c = np.abs(d["amplitude"]), np.array(d["center"])
            bumps = c[h > 0]
            assert len(bumps) == 4 and h[h > 0].min() >= 0.0045 and h.max() <= 0.0065
            # where the balls land, apart from each other
            assert np.all((np.abs(bumps[:, 0]) >= 0.5) & (np.abs(bumps[:, 0]) <= 1.25) & (np.abs(bumps[:, 1]) <= 0.55))
            gaps = np.linalg.norm(bumps[:, None] - bumps[None], axis=-1) + np.eye(len(bumps))
            assert gaps.min() >= 0.6
    if name == "buckling":
        onsets = np.array([[d["table_onset"], d["racket_onset"]] for d in draws])
        assert onsets[:, 0].max() <= 3.0 and onsets[:, 1].max() <= 8.0
    if name == "air_flow":
        wind = np.array([d["wind"] for d in draws])
        assert np.all(wind[:, 2] == 0.0) and 0.2 <= np.linalg.norm(wind, axis=1).min() <= 0.4


def test_cases_plan():
    plan = SC.cases(("spin_decay",), (("air_flow", "buckling"),), "racket_edge")
    assert plan == [("single", ("spin_decay",)), ("pair", ("air_flow", "buckling")), ("outside", ("racket_edge",)),
                    ("control", ())]
    assert SC.cases(("spin_decay",), (), None, control=False) == [("single", ("spin_decay",))]
    assert SC.case_path("run", 5, ()).name == "05_control.json"


def test_the_control_case_is_right_only_when_nothing_is_found_and_no_phase_is_located():
    quiet = SC.score("control", [], [cand("worn_ball", False, table=held(0.3, lo=-1.0))], NO_WHERE, {},
                     dict(level="unexplained", gaps=[]))
    assert not quiet["false_alarm"] and quiet["outcome"] == "nothing found" and quiet["located"] == []
    above = SC.score("control", [], [], NO_WHERE, {}, dict(level="unexplained", gaps=["flight"]))
    assert above["false_alarm"] and above["outcome"] == "false alarm: nothing significant, located in flight"
    named = SC.score("control", [], [cand("worn_ball", table=held(5.0))], NO_WHERE, {},
                     dict(level="explained", gaps=[]))
    assert named["false_alarm"] and named["outcome"] == "false alarm: worn_ball"
    rows = [dict(r, kind="control", effects=[], bound_significant=b)
            for r, b in ((quiet, []), (above, ["flight"]), (named, []))]
    assert [SC.verdict_of(r) for r in rows] == ["right", "wrong", "wrong"]
    s = SC.summary(rows)
    assert (s["n_control"], s["control_false_alarms"], s["control_bound_significant"]) == (3, 2, ["flight"])
    assert s["n_undetectable"] == 0 and s["n_single"] == 0
    text = SC.table(dict(cases=rows, summary=s, seconds=1.0, cpu_seconds=1.0))
    assert "| control | none (the record's noise only) | nothing found |" in text
    assert "a false alarm in 2, the model-free bound significant in flight" in text


def test_a_candidate_that_worsens_another_phase_is_not_significant():
    """A gain in one phase bought with a material loss in another (the signature of a fit to a bias
    of the racket contact estimates) does not explain the data; a loss that is insignificant, or
    consistent but below the phase's resolution (a side of the effect left near neutral), does not
    matter."""
    from ttsim_jax.diagnose.candidates import MIN_GAIN, explains

    gain = held(10.0, before=0.3)
    material = dict(held(-12.0, before=0.3), ci95=[-15.0, -9.0])
    assert material["after_rms"] - material["before_rms"] > MIN_GAIN["table"]
    assert not explains({"racket": gain, "table": material, "flight": held(0.0, before=0.003, lo=-0.3)})
    assert explains({"racket": gain, "table": held(0.2, lo=-0.5)})
    # consistent (interval below -1 %) but 0.5 mm/s: under the table's resolution
    assert explains({"racket": gain, "table": dict(held(-0.5, before=0.1), ci95=[-0.6, -0.4])})
    assert explains({"racket": gain, "table": dict(held(-5.0, before=0.05), ci95=[-6.0, -4.0])})
    # above the resolution, but the interval reaches above -1 %
    assert explains({"racket": gain, "table": dict(held(-12.0, before=0.3), ci95=[-15.0, -0.5])})


def test_figure_colours_each_case_by_its_outcome(tmp_path):
    oracle = {"table": held(40.0)}
    found = SC.score("single", ["table_tilt"], [cand("table_tilt", table=held(30.0))], NO_WHERE, oracle)
    missed = SC.score("single", ["table_tilt"], [cand("worn_ball", table=held(30.0))], NO_WHERE, oracle)
    quiet = SC.score("single", ["buckling"], [], NO_WHERE, {"table": held(0.1, lo=-1.0)})
    alarm = SC.score("single", ["buckling"], [cand("worn_ball", table=held(5.0))], NO_WHERE, {"table": held(0.1, lo=-1.0)})
    where = dict(NO_WHERE, racket={"flagged": [("speed", "above 9 m/s")]})
    outside = SC.score("outside", ["racket_edge"], [], where, {"racket": held(30.0)})
    verdicts = [SC.verdict_of(dict(r, kind=k)) for r, k in ((found, "single"), (missed, "single"), (quiet, "single"),
                                                          (alarm, "single"), (outside, "outside"))]
    assert verdicts == ["right", "wrong", "undetectable", "wrong", "right"]
    rows = [dict(r, kind="single", effects=["table_tilt"]) for r in (found, missed)]
    path = SC.plot(dict(cases=rows + [dict(outside, kind="outside", effects=["racket_edge"])]), tmp_path / "s.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000


# ---------------------------------------------------------------------------------------------- resume
class _Interrupted(Exception):
    pass


def _fake_cases(monkeypatch, calls, stop_at=None):
    """run_case replaced by a scorer of hand-made results (no simulation), raising at ``stop_at``."""
    def run_case(kind, names, seed, settings, games, present):
        if len(calls) == stop_at:
            raise _Interrupted
        calls.append((kind, tuple(names), seed))
        found = SC.score(kind, list(names), [cand(names[0], table=held(20.0 + seed / 100))], NO_WHERE,
                         {"table": held(40.0)})
        return dict(found, kind=kind, effects=list(names), seed=seed)

    monkeypatch.setattr(SC, "run_case", run_case)


def test_an_interrupted_selfcheck_resumes_from_its_stored_cases(tmp_path, monkeypatch):
    from ttsim_jax.diagnose.diagnosis import Settings

    plan = SC.cases(("spin_decay", "air_flow", "table_tilt"), (), None, control=False)
    settings = Settings.quick()
    calls = []
    _fake_cases(monkeypatch, calls, stop_at=2)
    with pytest.raises(_Interrupted):
        SC.selfcheck(plan, settings, seed=5, store=tmp_path)
    assert [p.name for p in SC.stored_cases(tmp_path)] == ["00_spin_decay.json", "01_air_flow.json"]
    calls.clear()
    _fake_cases(monkeypatch, calls)
    resumed = SC.selfcheck(plan, settings, seed=5, store=tmp_path, resume=True)
    assert calls == [("single", ("table_tilt",), 205)] and resumed["resumed"] == 2
    calls.clear()
    fresh = SC.selfcheck(plan, settings, seed=5)
    assert len(calls) == 3
    # the same rows and summary (as JSON: NaN, the score of an undetectable case, equals itself there)
    same = lambda r: json.dumps([{k: v for k, v in c.items() if k != "wall_seconds"} for c in r["cases"]] +  # noqa: E731
                                [r["summary"]])
    assert same(resumed) == same(fresh)
    # stored cases of other options are refused, naming the file and the option
    with pytest.raises(SC.ResumeError, match=r"00_spin_decay\.json: stored with seed = 5"):
        SC.selfcheck(plan, settings, seed=6, store=tmp_path, resume=True)


def test_a_stored_case_of_other_draws_is_not_resumed(tmp_path, monkeypatch):
    """The key holds the drawn parameters: cases stored before a change of DRAWS are refused."""
    from ttsim_jax.diagnose.diagnosis import Settings

    plan = SC.cases(("spin_decay",), (), None, control=False)
    _fake_cases(monkeypatch, [])
    SC.selfcheck(plan, Settings.quick(), seed=5, store=tmp_path)
    monkeypatch.setitem(SC.DRAWS, "spin_decay", lambda r: {"rate": r.uniform(0.05, 0.1), "quadratic": 0.0})
    with pytest.raises(SC.ResumeError, match=r"00_spin_decay\.json: stored with params = "):
        SC.selfcheck(plan, Settings.quick(), seed=5, store=tmp_path, resume=True)


def test_selfcheck_command_refuses_to_overwrite_stored_cases(tmp_path, capsys):
    from ttsim_jax.cli import main

    (tmp_path / "cases").mkdir()
    (tmp_path / "cases" / "00_spin_decay.json").write_text("{}")
    assert main(["diagnose", "selfcheck", "--quick", "--out", str(tmp_path), "--quiet"]) == 2
    assert "pass --resume to continue that run, or --force" in capsys.readouterr().err
    assert main(["diagnose", "selfcheck", "--quick", "--resume", "--out", str(tmp_path), "--quiet"]) == 2
    assert "00_spin_decay.json: no 'row' in the case file" in capsys.readouterr().err
    assert main(["diagnose", "selfcheck", "--quick", "--resume", "--quiet"]) == 2


def test_an_effect_reported_interchangeable_with_the_first_counts_as_found():
    """A worn ball's lower restitution and a buckling loss starting below every impact explain the
    same errors: when the diagnosis reports them interchangeable, the case counts as found, says
    so, and is counted apart in the summary; a merely redundant second candidate does not count."""
    first = cand("buckling", racket=held(14.0))
    same = dict(cand("worn_ball", racket=held(13.5)), adds=dict(accepted=False, on_top_of=["buckling"],
                                                                heldout={}, interchangeable_with=["buckling"]))
    oracle = {"racket": held(14.0)}
    r = SC.score("single", ["worn_ball"], [first, same], NO_WHERE, oracle)
    assert r["rank1"] and r["interchangeable"] and r["outcome"] == "found as interchangeable with buckling"
    redundant = dict(same, adds=dict(same["adds"], interchangeable_with=[]))
    r2 = SC.score("single", ["worn_ball"], [first, redundant], NO_WHERE, oracle)
    assert not r2["rank1"] and r2["outcome"] == "missed"
    s = SC.summary([dict(r, kind="single"), dict(r2, kind="single")])
    assert s["n_interchangeable"] == 1 and s["rank1_rate"] == 0.5


def test_a_pair_counts_an_effect_reported_interchangeable_with_the_second_accepted_one():
    """spin_decay + table_tilt where a warped top, accepted second, absorbs the tilt: with the tilt
    reported interchangeable with it both are found; merely redundant, one."""
    first = cand("spin_decay", table=held(52.0))
    warped = dict(cand("table_unevenness", table=held(2.7)),
                  adds=dict(accepted=True, on_top_of=["spin_decay"], heldout={"table": held(6.6)},
                            interchangeable_with=[]))
    tilt = dict(cand("table_tilt", table=held(2.3)),
                adds=dict(accepted=False, on_top_of=["spin_decay", "table_unevenness"],
                          heldout={"table": held(0.7, lo=-0.6)}, interchangeable_with=["table_unevenness"]))
    oracle = {"table": held(56.8)}
    r = SC.score("pair", ["spin_decay", "table_tilt"], [first, warped, tilt], NO_WHERE, oracle)
    assert r["both"] and r["outcome"] == "both found"
    redundant = dict(tilt, adds=dict(tilt["adds"], interchangeable_with=[]))
    r = SC.score("pair", ["spin_decay", "table_tilt"], [first, warped, redundant], NO_WHERE, oracle)
    assert not r["both"] and r["outcome"] == "one found"


def test_a_case_keeps_each_candidate_and_what_it_added_on_top():
    """A case's row keeps the ranked candidates, so a pair's missing effect can be examined
    afterwards: whether it was significant alone and what it added on top of the accepted ones."""
    first = dict(cand("spin_decay", table=held(52.0)), best_reduction_pct=52.0, params={"rate": [0.2]})
    tilt = dict(cand("table_tilt", table=held(6.0)),
                adds=dict(accepted=False, on_top_of=["spin_decay"], heldout={"table": held(0.4, lo=-0.3)},
                          interchangeable_with=[]))
    digest = SC.candidate_digest([first, tilt, cand("worn_ball", significant=False, racket=held(0.1, lo=-1.0))])
    assert [c["name"] for c in digest] == ["spin_decay", "table_tilt", "worn_ball"]
    assert digest[0] == dict(name="spin_decay", significant=True, heldout={"table": dict(pct=52.0, ci95=[50.0, 54.0])},
                             implausible=[])
    assert digest[1]["adds"] == dict(accepted=False, on_top_of=["spin_decay"],
                                     heldout={"table": dict(pct=0.4, ci95=[-0.3, 2.4])}, interchangeable_with=[])
    assert not digest[2]["significant"] and "adds" not in digest[2]
    json.dumps(digest)  # stored in the case file as is


def test_a_subset_runs_each_case_at_its_full_run_seed():
    """``benchmarks/selfcheck_subset.py`` reruns cases of the full selfcheck on the same datasets: every
    case of each part it plans gets the seed that case has in the full run (case i: seed 100 i)."""
    import importlib.util
    from pathlib import Path

    from ttsim_jax.diagnose import candidates as C

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "selfcheck_subset.py"
    spec = importlib.util.spec_from_file_location("selfcheck_subset", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    full = SC.cases(C.candidate_names(), SC.PAIRS, SC.OUTSIDE)
    assert full[-1] == ("control", ())
    for pairs in (None, [SC.PAIRS[1]], SC.PAIRS[::-1]):
        parts = mod.plan_parts(["worn_ball", "buckling"], pairs)
        assert len(parts) == (1 if pairs is None else len(pairs)) + 2
        for _, plan, first in parts:
            for i, case in enumerate(plan):
                assert first + 100 * i == 100 * full.index(case), case
    assert [p[2] for p in mod.plan_parts([], [SC.PAIRS[1]])] == [100 * (len(C.candidate_names()) + 1)]  # after the singles


def test_the_bound_is_scored_against_the_oracle_and_its_terms():
    bound = {"table": {"heldout": dict(pct=30.0, ci95=[25.0, 35.0], significant=True),
                       "terms": [{"name": "post-bounce r·ω y, in proportion to the normal speed × slip x", "share": 0.6}]},
             "flight": {"reason": "too few"}}
    b = SC.bound_score(["table_friction"], bound, {"table": held(40.0)})
    assert (b["bound_phase"], b["bound_pct"], b["bound_share"], b["bound_named"]) == ("table", 30.0, 0.75, True)
    assert not SC.bound_score(["worn_ball"], dict(bound, table=dict(bound["table"], terms=[{"name": "impact angle", "share": 1}])),
                              {"table": held(40.0)})["bound_named"]
    # a reduction below the significance rule counts as none, and is kept apart
    weak = SC.bound_score(["table_tilt"], dict(bound, table=dict(bound["table"], heldout=dict(
        pct=3.0, ci95=[2.0, 4.0], significant=False))), {"table": held(4.0)})
    assert (weak["bound_pct"], weak["bound_share"], weak["bound_pct_raw"], weak["bound_share_raw"]) == (0.0, 0.0, 3.0, 0.75)
    record = SC.bound_score(["clock_rate"], bound, {})  # no oracle for an effect on the record
    assert record["bound_phase"] == "table" and math.isnan(record["bound_share"])
    assert SC.bound_score(["air_density"], bound, {})["bound_phase"] is None  # no bound in its phase
    rows = [dict(kind="outside", effects=["table_friction"], detectable=True, unexplained=True, phase="table", phase_right=True,
                 top="none significant", outcome="unexplained", found_pct=0.0, oracle_pct=40.0, oracle_phase="table",
                 shrink=0.0, wrong_explained=False, **b)]
    # an effect the oracle cannot resolve is not counted against locating or bounding
    rows.append(dict(rows[0], detectable=False, phase_right=False, bound_share=0.0, bound_named=False))
    result = dict(cases=rows, summary=SC.summary(rows), seconds=1.0, cpu_seconds=1.0)
    assert result["summary"]["outside_bound_reaching"] == 1 and result["summary"]["outside_bound_named_rate"] == 1.0
    assert result["summary"]["outside_located_rate"] == 1.0 and result["summary"]["n_outside_resolved"] == 1
    assert "table 30.0, 0.75; post-bounce r·ω y" in SC.table(result)


def test_the_unresolved_parts_of_an_effect_are_set_to_neutral_in_a_copy_of_the_truth():
    truth = {"sessions": [{"effects": {"air_flow": {"wind": [0.3, 0.0, 0.0], "gust_amp": [[0.1, 0, 0]] * 3}}}],
             "effects": {"air_flow": {"params": {"wind": [0.3, 0.0, 0.0], "gust_amp": [[0.2, 0, 0]] * 3}}}}
    steady = SC.neutral_parts(truth, SC.UNRESOLVED)
    assert steady["sessions"][0]["effects"]["air_flow"]["gust_amp"] == [[0.0, 0.0, 0.0]] * 3
    assert steady["effects"]["air_flow"]["params"]["gust_amp"] == [[0.0, 0.0, 0.0]] * 3
    assert steady["sessions"][0]["effects"]["air_flow"]["wind"] == [0.3, 0.0, 0.0]
    assert truth["sessions"][0]["effects"]["air_flow"]["gust_amp"][0] == [0.1, 0, 0]  # the truth itself unchanged
    row = dict(kind="outside_log", effects=["air_flow"], detectable=True, phase_right=True, bound_share=0.36,
               bound_share_steady=0.8, bound_named=True, unexplained=True)
    s = SC.summary([row, dict(row, bound_share=0.75, bound_share_steady=math.nan), dict(row, bound_share=0.2,
                                                                                          bound_share_steady=0.5)])
    assert (s["outside_bound_reaching"], s["outside_bound_reaching_resolved"]) == (1, 2)


@pytest.mark.skipif(not os.path.exists("/proc/self/maps"), reason="memory maps are counted from Linux's /proc")
def test_compiled_programs_are_dropped_only_when_the_memory_maps_crowd():
    import jax
    import jax.numpy as jnp

    assert not SC.release_compiled_if_crowded(share=1e9)
    f = jax.jit(lambda x: jnp.sin(x) + 3.0)
    f(jnp.ones(7)).block_until_ready()
    assert f._cache_size() == 1
    # a share below what is in use: dropped (the next call compiles again)
    assert SC.release_compiled_if_crowded(share=1e-9)
    assert f._cache_size() == 0


def test_a_significant_fit_beyond_the_plausible_ranges_is_not_the_top_candidate():
    """The diagnosis does not accept a fit that needs parameters no lab meets (a buckling loss
    over a 0.03 m/s width): the case is scored on what it accepts, as its verdict reads."""
    oracle = {"racket": held(11.3)}
    stand_in = dict(cand("buckling", racket=held(11.2)), implausible=["buckling.racket_width = 0.03323 m/s"])
    r = SC.score("single", ["worn_ball"], [stand_in, cand("worn_ball", racket=held(11.1))], NO_WHERE, oracle)
    assert r["rank1"] and r["top"] == "worn_ball" and r["outcome"] == "found"
    assert SC.candidate_digest([stand_in])[0]["implausible"] == ["buckling.racket_width = 0.03323 m/s"]
    plausible = SC.score("single", ["worn_ball"], [cand("buckling", racket=held(11.2)),
                                                  cand("worn_ball", racket=held(11.1))], NO_WHERE, oracle)
    assert not plausible["rank1"] and plausible["top"] == "buckling"
