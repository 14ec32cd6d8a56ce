"""A candidate that fits only with parameters no lab meets is reported as such, never accepted."""

from types import SimpleNamespace

from ttsim_jax.diagnose.diagnosis import implausible, verdict


def cand(name, pct, params):
    return SimpleNamespace(spec=SimpleNamespace(name=name), params=params,
                           heldout={"table": {"pct": pct, "ci95": [pct - 2.0, pct + 2.0]}})


def test_implausible_names_parameter_value_and_range():
    lines = implausible({"table_tilt": {"slope": [0.0164, 0.001], "offset": 0.0}, "spin_decay": {"rate": 0.2, "quadratic": 0.0}})
    assert lines == ["table_tilt.slope[0] = 0.0164 (plausible -0.0131 to 0.0131)"]
    assert implausible({"air_flow": {"wind": [0.0, 0.0, 0.08]}}) == ["air_flow.wind[2] = 0.08 m/s (plausible -0.05 to 0.05)"]


def test_a_per_session_effect_is_implausible_only_in_more_than_a_quarter_of_its_sessions():
    ok = {"d_radius": 1e-4, "d_mass": 1e-5}
    wild = {"d_radius": 1e-4, "d_mass": 9e-5}
    assert implausible({"ball_variation": {s: (wild if s < 2 else ok) for s in range(10)}}) == []
    (line,) = implausible({"ball_variation": {s: (wild if s < 4 else ok) for s in range(10)}})
    assert line.startswith("ball_variation.d_mass = 9e-05 kg in 4 of 10 sessions")


def test_verdict_rejects_an_implausible_fit_and_says_why():
    tilt = cand("table_tilt", 8.2, {"table_tilt": {"slope": [0.0164, 0.0], "offset": 0.0}})
    out = {"where": {}, "dependence": {}, "candidates": []}
    v = verdict(out, [], [], [tilt])
    assert not v["explained"] and v["implausible"] == ["table_tilt"]
    assert v["text"].startswith("Unexplained: no candidate effect with plausible parameters")
    assert "table_tilt (table: held-out RMS error 8.2 % lower" in v["text"] and "slope[0] = 0.0164" in v["text"]
    decay = cand("spin_decay", 5.0, {"spin_decay": {"rate": 0.2, "quadratic": 0.0}})
    v = verdict(out, [decay], [], [tilt])
    assert v["explained"] and v["effects"] == ["spin_decay"] and "Not accepted as causes" in v["text"]


def test_the_selfcheck_withholds_only_plausible_effects():
    import numpy as np

    from ttsim_jax import effects as fx
    from ttsim_jax.diagnose.selfcheck import DRAWS

    rng = np.random.default_rng(1)
    for name, draw in DRAWS.items():
        bad = [f for f in (fx.effect_class(name).implausible(draw(rng)) for _ in range(200)) if f]
        assert not bad, (name, bad[:2])
