"""A candidate that fits only with parameters no lab meets is reported as such, never accepted."""

import math
from types import SimpleNamespace

from ttsim_jax.diagnose.verdict import implausible, verdict


def cand(name, pct, params):
    return SimpleNamespace(spec=SimpleNamespace(name=name), params=params,
                           heldout={"table": {"pct": pct, "ci95": [pct - 2.0, pct + 2.0]}})


def test_implausible_names_parameter_value_and_range():
    lines = implausible({"table_tilt": {"slope": [0.0164, 0.001], "offset": 0.0}, "spin_decay": {"rate": 0.2, "quadratic": 0.0}})
    assert lines == ["table_tilt.slope[0] = 0.0164 (plausible -0.0131 to 0.0131)"]
    assert implausible({"air_flow": {"wind": [0.0, 0.0, 0.08]}}) == ["air_flow.wind[2] = 0.08 m/s (plausible -0.05 to 0.05)"]


def test_a_per_session_effect_is_implausible_only_in_more_than_half_of_its_sessions():
    ok = {"d_radius": 1e-4, "d_mass": 1e-5}
    wild = {"d_radius": 1e-4, "d_mass": 9e-5}
    assert implausible({"ball_variation": {s: (wild if s < 5 else ok) for s in range(10)}}) == []
    (line,) = implausible({"ball_variation": {s: (wild if s < 6 else ok) for s in range(10)}})
    assert line.startswith("ball_variation.d_mass = 9e-05 kg in 6 of 10 sessions")


def test_verdict_rejects_an_implausible_fit_and_says_why():
    tilt = cand("table_tilt", 8.2, {"table_tilt": {"slope": [0.0164, 0.0], "offset": 0.0}})
    out = {"where": {}, "dependence": {}, "candidates": []}
    v = verdict(out, [], [], [tilt])
    assert not v.explained and v.implausible == ["table_tilt"]
    assert v.text.startswith("Unexplained: no candidate effect with plausible parameters")
    assert "table_tilt (table: held-out RMS error 8.2 % lower" in v.text and "slope[0] = 0.0164" in v.text
    decay = cand("spin_decay", 5.0, {"spin_decay": {"rate": 0.2, "quadratic": 0.0}})
    v = verdict(out, [decay], [], [tilt])
    assert v.explained and v.effects == ["spin_decay"] and "Not accepted as causes" in v.text


def test_the_selfcheck_withholds_only_plausible_effects():
    import numpy as np

    from ttsim_jax import effects as fx
    from ttsim_jax.diagnose.selfcheck import DRAWS

    rng = np.random.default_rng(1)
    for name, draw in DRAWS.items():
        bad = [f for f in (fx.effect_class(name).implausible(draw(rng)) for _ in range(200)) if f]
        assert not bad, (name, bad[:2])


def floor(error, fl, lo=None, hi=None):
    """A floor entry as :func:`ttsim_jax.diagnose.floor.floors` writes it."""
    removable = max(error**2 - fl**2, 0.0) ** 0.5
    return dict(error=error, error_ci95=[lo or 0.95 * error, hi or 1.05 * error], floor=fl,
                floor_ci95=[0.97 * fl, 1.03 * fl], removable=removable, removable_ci95=[0.9 * removable, 1.1 * removable])


def diagnosed(before, after, pct, ci, floors):
    """The parts of a diagnosis's dict that the verdict reads: the accepted effects' held-out
    errors in the table phase, and the floors."""
    return {"where": {}, "dependence": {}, "candidates": [], "floor": floors,
            "before_after": {"table": {"heldout": dict(pct=pct, ci95=ci, before_rms=before, after_rms=after)}}}


def test_explained_only_when_most_of_the_removable_gap_is_closed():
    from ttsim_jax.diagnose.verdict import gap_shares

    worn = cand("worn_ball", 40.0, {"worn_ball": {"loss": 0.02}})
    # error 0.5 m/s over a floor of 0.3: removable^2 = 0.16; after 0.32: closes (0.25 - 0.1024) / 0.16 = 92 %
    out = diagnosed(0.5, 0.32, 36.0, [30.0, 40.0], {"table": floor(0.5, 0.3), "flight": floor(0.002, 0.0019)})
    g = gap_shares(out)["table"]
    assert abs(g["share"] - (0.25 - 0.32**2) / 0.16) < 1e-9 and g["ci95"][0] < g["share"] < g["ci95"][1]
    v = verdict(out, [worn])
    assert v.level == "explained" and v.explained and v.text.startswith("Explained by: worn_ball")
    assert "closes 92 % (95 % interval" in v.text and "is left" not in v.text
    # the same fall over a floor of 0.1: removable^2 = 0.24: closes 61.5 %, the rest is left
    out = diagnosed(0.5, 0.32, 36.0, [30.0, 40.0], {"table": floor(0.5, 0.1)})
    v = verdict(out, [worn])
    assert v.level == "partly explained" and not v.explained
    assert v.text.startswith("Partly explained by: worn_ball") and "closes 62 %" in v.text and "38 % is left" in v.text


def test_a_gap_no_accepted_effect_acts_in_is_named():
    worn = cand("worn_ball", 40.0, {"worn_ball": {"loss": 0.02}})
    out = diagnosed(0.5, 0.32, 36.0, [30.0, 40.0], {"table": floor(0.5, 0.3), "flight": floor(0.005, 0.002)})
    v = verdict(out, [worn])
    assert v.level == "partly explained" and v.open == ["flight"]
    assert "Not addressed by any accepted effect: the flight gap (error 5 mm, noise floor 2 mm)" in v.text
    # a flight error at its floor (within the intervals) or above it by less than the resolution is no gap
    out["floor"]["flight"] = floor(0.00201, 0.002, lo=0.0019, hi=0.0021)
    assert verdict(out, [worn]).level == "explained"
    out["floor"]["flight"] = floor(0.00203, 0.002, lo=0.00202, hi=0.00204)
    assert verdict(out, [worn]).open == []


def test_unexplained_locates_gaps_above_the_floor_and_calls_the_rest_noise():
    out = {"where": {}, "dependence": {}, "candidates": [], "floor": {"table": floor(0.6, 0.3)}}
    v = verdict(out, [])
    assert v.level == "unexplained" and "The gap lies in: table: error 0.6 m/s, 2.0 x its noise floor 0.3 m/s" in v.text
    out["floor"]["table"] = floor(0.301, 0.3, lo=0.28, hi=0.32)
    assert verdict(out, []).text.endswith("what remains looks like noise.")


def test_a_phase_at_its_floor_asks_no_share():
    buck = cand("buckling", 30.0, {"buckling": {}})
    buck.heldout = {"racket": {"pct": 30.0, "ci95": [10.0, 45.0]}, "table": {"pct": 1.0, "ci95": [-2.0, 4.0]}}
    out = {"where": {}, "dependence": {}, "candidates": [],
           "floor": {"racket": floor(0.6, 0.3), "table": floor(0.304, 0.298, lo=0.29, hi=0.32)},
           "before_after": {"racket": {"heldout": dict(pct=30.0, ci95=[10.0, 45.0], before_rms=0.6, after_rms=0.42)},
                            "table": {"heldout": dict(pct=1.0, ci95=[-2.0, 4.0], before_rms=0.304, after_rms=0.301)}}}
    v = verdict(out, [buck])
    # racket: (0.36 - 0.1764) / 0.27 = 68 % of its gap: short of 70 %; the table's 0.06 m/s above its floor is no gap
    assert v.level == "partly explained" and "of the racket gap" in v.text and "32 % is left" in v.text
    out["before_after"]["racket"]["heldout"].update(pct=35.0, after_rms=0.39)
    assert verdict(out, [buck]).level == "explained"


def test_a_phase_within_the_floors_own_accuracy_is_no_gap():
    """The floor is known to a few per cent beyond its bootstrap interval (verdict.FLOOR_SYSTEMATIC):
    the cross wind's table at 1.04 x its floor, with tight intervals, is no gap; at 1.15 x it is."""
    from ttsim_jax.diagnose.verdict import FLOOR_SYSTEMATIC, open_gaps

    wind = cand("air_flow", 20.0, {"air_flow": {}})
    wind.heldout = {"flight": {"pct": 20.0, "ci95": [15.0, 25.0]}}
    tight = dict(error=0.308, error_ci95=[0.305, 0.311], floor=0.297, floor_ci95=[0.2955, 0.2985],
                 removable=math.sqrt(0.308**2 - 0.297**2), removable_ci95=[0.07, 0.09])
    assert tight["error_ci95"][0] > tight["floor_ci95"][1]  # "significant" by the intervals alone
    out = {"where": {}, "dependence": {}, "candidates": [], "floor": {"table": tight, "flight": floor(0.004, 0.002)},
           "before_after": {"flight": {"heldout": dict(pct=50.0, ci95=[45.0, 55.0], before_rms=0.004, after_rms=0.002)}}}
    assert open_gaps(out) == ["flight"]
    v = verdict(out, [wind])
    assert v.level == "explained" and v.open == [] and "table gap" not in v.text
    control = {"phases": ["table"], "where": {}, "dependence": {}, "candidates": [], "floor": {"table": tight}}
    v = verdict(control, [])
    assert v.level == "no gap" and v.gaps == [] and v.text.startswith("No gap: no phase's error stands above")
    assert v.text.endswith("what remains looks like noise.")
    # a phase whose floor is not known could hold a gap: then it is no more than "unexplained"
    v = verdict(dict(control, phases=["table", "racket"]), [])
    assert v.level == "unexplained" and v.text.endswith("what remains looks like noise.")
    far = dict(tight, error=0.297 * 1.15, error_ci95=[0.297 * 1.13, 0.297 * 1.17])
    assert open_gaps({"floor": {"table": far}}) == ["table"]
    assert 1.13 > 1.0 + FLOOR_SYSTEMATIC["table"] > 1.04


def test_unexplained_says_what_the_data_could_have_shown():
    limits = {"candidates": {
        "air_flow": {"flight": dict(size=0.2, params={"wind": [0.04, 0.0, 0.0]}, share_pct=3.1, reduction_pct=1.6)},
        "buckling": {"table": dict(size=None, params={}, share_pct=None, reduction_pct=None)}}}
    out = {"where": {}, "dependence": {}, "candidates": [], "floor": {}, "limits": limits}
    v = verdict(out, [])
    assert v.level == "unexplained"
    assert "These data would have shown, at least: air_flow: wind 0.04 m/s (flight: 3.1 % of its error); none of these is there." in v.text
    assert "could not have shown buckling" in v.text
