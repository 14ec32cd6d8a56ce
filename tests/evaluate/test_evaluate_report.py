"""``ttsim evaluate`` (ttsim_jax.evaluate.stages and .report) on a small dataset of the reality
generator whose truth is a bundled model with no effects and no noise: the truth scores ~0 in every
stage, a model with lowered restitution coefficients scores the closed-form errors, and the files
are complete.

The dataset (tests/evaluate/data/clean) was made by the command in tests/evaluate/data/README.md;
generating it here would cost minutes of compilation.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.cli import main
from ttsim_jax.data import load
from ttsim_jax.evaluate.report import FIGURES, markdown, summarise
from ttsim_jax.evaluate.stages import STAGES, evaluate_models, reference_name
from ttsim_jax.params import config_dir
from ttsim_jax.results import Skipped

DATA = Path(__file__).parent / "data" / "clean"
TRUTH = "durr2026"  # the generator's truth model for DATA
DE0 = 0.05  # the perturbed model's table and racket e0 are lowered by this


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One ``ttsim evaluate`` of the truth and a perturbed copy (one compilation per stage)."""
    tmp = tmp_path_factory.mktemp("evaluate")
    text = (config_dir() / "models" / f"{TRUTH}.toml").read_text()
    truth = load_model(TRUTH)
    table_e0, racket_e0 = float(truth.table.e0), float(truth.racket.e0)
    lines, section = [], ""
    for line in text.splitlines():
        if line.startswith("["):
            section = line.split("]")[0] + "]"
        if line.replace(" ", "").startswith("e0="):
            value = table_e0 if section == "[table]" else racket_e0 if section == "[racket]" else None
            assert value is not None, f"e0 outside [table] and [racket] in {TRUTH}.toml: {line}"
            line = line.replace(f"{value:g}", f"{value - DE0:g}", 1)
        lines.append(line)
    perturbed = tmp / "perturbed.toml"
    perturbed.write_text("\n".join(lines) + "\n")
    m = load_model(perturbed)
    assert np.isclose(float(m.table.e0), table_e0 - DE0) and np.isclose(float(m.racket.e0), racket_e0 - DE0)
    out = tmp / "out"
    assert main(["evaluate", "--data", str(DATA), "--models", f"{TRUTH},{perturbed}", "--out", str(out), "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    samples = dict(np.load(out / "samples.npz"))
    return dict(out=out, metrics=metrics, samples=samples)


def test_files_and_json_keys_are_complete(run):
    out, m = run["out"], run["metrics"]
    for name in list(FIGURES.values()) + ["report.md", "metrics.json", "samples.npz"]:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    report = (out / "report.md").read_text()
    for fig in FIGURES.values():
        assert f"]({fig})" in report
    assert m["models"] == [TRUTH, "perturbed"] and m["reference"] == TRUTH
    for stage in STAGES:
        assert "skipped" not in m[stage], m[stage]
        assert set(m[stage]["models"]) == {TRUTH, "perturbed"}
    for model in m["flight"]["models"].values():
        assert {"n", "median", "p75", "mean", "reduction_median_pct", "reduction_p75_pct", "reduction_median_ci95",
                "reduction_p75_ci95"} <= set(model)
    for model in m["table"]["models"].values():
        assert set(model) == {"v_x", "v_y", "v_z", "w_x", "w_y", "w_z"}
        assert all({"median", "p75", "bias", "reduction_median_pct"} <= set(c) for c in model.values())
    assert m["racket"]["bands"] == ["0-5 cm", "5-8 cm", "> 8 cm", "all"]
    for model in m["racket"]["models"].values():
        assert set(model) == set(m["racket"]["bands"])
        assert {"|v|", "|w|", "v_x", "w_z"} <= set(model["all"])
    for model in m["landing"]["models"].values():
        assert {"median", "p75", "not_hit", "no_landing", "reduction_median_pct"} <= set(model)
    # the reductions are those of the numbers beside them
    f = m["flight"]["models"]
    assert np.isclose(f["perturbed"]["reduction_median_pct"],
                      100 * (f[TRUTH]["median"] - f["perturbed"]["median"]) / f[TRUTH]["median"])


def test_the_truth_scores_about_zero_in_every_stage(run):
    m, s = run["metrics"], run["samples"]
    assert m["flight"]["n_segments"] >= 20 and m["flight"]["models"][TRUTH]["p75"] < 5e-4
    t = m["table"]["models"][TRUTH]
    assert m["table"]["n_used"] >= 10
    assert max(t[c]["p75"] for c in ("v_x", "v_y", "v_z")) < 0.02  # m/s: the polynomial fits' bias
    assert max(t[c]["p75"] for c in ("w_x", "w_y", "w_z")) < 1.0  # rad/s
    r = m["racket"]["models"][TRUTH]["all"]
    assert m["racket"]["n_used"] >= 5 and r["|v|"]["p75"] < 0.03 and r["|w|"]["p75"] < 2.0
    g = m["landing"]["models"][TRUTH]
    assert g["n"] >= 5 and g["not_hit"] == 0 and g["p75"] < 0.01
    assert np.all(np.isfinite(s[f"landing/error/{TRUTH}"]))


def test_lowered_restitution_gives_the_closed_form_errors(run):
    m, s = run["metrics"], run["samples"]
    # Table: v_z+ = e_n |v_z-|, so lowering e0 lowers v_z+ by DE0 |v_z-| on every bounce.
    d_vz = s["table/error/perturbed"][:, 2] - s[f"table/error/{TRUTH}"][:, 2]
    np.testing.assert_allclose(d_vz, -DE0 * np.abs(s["table/pre"][:, 2]), atol=1e-5)  # float32 simulation
    # Racket (racket frame, x = face normal): v~+_x = -e_n v~_x, so it drops by DE0 |v~_x|; the
    # tangential velocity and the spin do not depend on e_n.
    e_t, e_p = s[f"racket/error/{TRUTH}"], s["racket/error/perturbed"]
    np.testing.assert_allclose(e_p[:, 0] - e_t[:, 0], -DE0 * np.abs(s["racket/x"][:, 0]), atol=1e-5)
    np.testing.assert_allclose(e_p[:, 1:6], e_t[:, 1:6], rtol=1e-5, atol=1e-5)
    # Flight is the same model: the same RMSE, 0 % reduction.
    np.testing.assert_allclose(s["flight/rmse/perturbed"], s[f"flight/rmse/{TRUTH}"])
    assert m["flight"]["models"]["perturbed"]["reduction_median_pct"] == 0.0
    assert m["flight"]["models"]["perturbed"]["reduction_median_ci95"] == [0.0, 0.0]
    # Slower returns land elsewhere: a clearly larger landing error than the truth's, beyond the
    # bootstrap interval.
    g = m["landing"]["models"]
    assert g["perturbed"]["median"] > 5 * g[TRUTH]["median"] + 0.01
    assert g["perturbed"]["reduction_median_ci95"][1] < 0.0


def test_stages_without_data_are_skipped_with_the_reason():
    from ttsim_jax.data.schema import empty_table

    ds = load(DATA)
    ds = ds.replace(rackets=empty_table("rackets"))
    result = evaluate_models(ds, [TRUTH], stages=("racket", "landing"))
    assert isinstance(result.racket, Skipped) and isinstance(result.landing, Skipped)
    assert "racket states" in result.racket.reason and "racket states" in result.landing.reason
    assert result.flight is None and result.table is None and list(result.stages()) == ["racket", "landing"]
    assert result.ran() == {}
    assert result.to_json()["racket"] == {"skipped": result.racket.reason} and "flight" not in result.to_json()
    report = markdown(summarise(result), FIGURES)
    assert report.count("Skipped: no racket states") == 2 and "](racket_errors.png)" not in report
    assert reference_name(["conti2026", "nakashima2011"]) == "nakashima2011"
    assert reference_name(["conti2026", "fitted"]) == "conti2026"


def test_a_missing_dataset_or_an_unknown_model_is_named(tmp_path, capsys):
    assert main(["evaluate", "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "--data" in capsys.readouterr().err
    assert main(["evaluate", "--data", str(DATA), "--models", "durr2026,nakashima2012", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--models" in err and "nakashima2012" in err
    assert main(["evaluate", "--models", "durr2026"]) == 2
    assert "--data and --out required" in capsys.readouterr().err
    assert main(["evaluate", "--data", str(DATA), "--out", str(tmp_path / "o"), "--split", "test"]) == 2
    assert "--split test: give --test-fraction" in capsys.readouterr().err


def test_bootstrap_interval_of_a_reduction():
    from ttsim_jax.evaluate.report import reduction, reduction_ci

    rng = np.random.default_rng(0)
    ref = rng.lognormal(0.0, 0.5, 400)
    assert reduction_ci(ref, 0.5 * ref, 50) == pytest.approx([50.0, 50.0])  # a halving is one in every draw
    other = rng.lognormal(-0.2, 0.5, 400)
    lo, hi = reduction_ci(ref, other, 50)
    assert lo < reduction(np.median(ref), np.median(other)) < hi and 5.0 < hi - lo < 40.0


def _without_spin(ds):
    """``ds`` as a tracker without spin sensing records it: every spin 0 with confidence 0."""
    tables = {}
    for name in ("segments", "observations"):
        t = dict(getattr(ds, name))
        t.update({f"spin_{a}": np.zeros(len(t["spin_conf"])) for a in "xyz"}, spin_conf=np.zeros(len(t["spin_conf"])))
        tables[name] = t
    return ds.replace(**tables)


def test_bounces_and_landings_without_measured_spin_take_the_incoming_latent_spin():
    from ttsim_jax.evaluate.stages import EvaluateSettings

    measured = evaluate_models(load(DATA), [TRUTH], stages=("table", "landing"))
    blind = _without_spin(load(DATA))
    latent = evaluate_models(blind, [TRUTH], EvaluateSettings(spin="auto"), stages=("table", "landing"))
    zero = evaluate_models(blind, [TRUTH], EvaluateSettings(spin="zero"), stages=("table", "landing"))
    t_m, t_l, t_z = measured.table, latent.table, zero.table
    n = len(t_l.event_id)
    assert n == len(t_m.event_id) >= 10 and list(t_l.spin_source) == ["latent"] * n
    assert list(t_z.spin_source) == ["zero"] * n
    # The typed stages' JSON: every field, strict JSON (no NaN), the arrays' values as lists.
    body = json.loads(json.dumps(latent.to_json(), allow_nan=False))
    assert set(body) == {"models", "reference", "settings", "table", "landing"}
    assert body["table"]["event_id"] == t_l.event_id.tolist() and body["table"]["n_bounces"] == t_l.n_bounces
    assert [[None if np.isnan(v) else v for v in row] for row in t_l.error[TRUTH].tolist()] == body["table"]["error"][TRUTH]
    # From the latent spin the truth's bounce meets the measured outgoing velocity far better than
    # from spin 0 (the spin turns into velocity through the table's friction), though not as well
    # as from the true spin: the positions show the spin across the flight well, its size less.
    tangential = lambda t: np.median(np.abs(t.error[TRUTH][:, :2]))  # noqa: E731
    # (measured 0.0006, latent 0.040, spin 0 0.47 m/s when written)
    assert tangential(t_l) < 0.15 * tangential(t_z) and tangential(t_m) < 0.01
    err = np.linalg.norm(t_l.spin_in[TRUTH] - t_m.spin_in[TRUTH], axis=1) / np.linalg.norm(t_m.spin_in[TRUTH], axis=1)
    assert np.median(err) < 0.3  # 0.21 when written
    # A racket contact without a measured spin is flown at its latent spin, not skipped.
    g_l, g_z = latent.landing, zero.landing
    assert len(g_l.event_id) == len(measured.landing.event_id) >= 5 and set(g_l.spin_source) == {"latent"}
    from ttsim_jax.evaluate.stages import landing_cases

    only_measured = landing_cases(blind, EvaluateSettings(spin="measured"), 0.02)
    assert len(only_measured["event_id"]) == 0  # measured only: no spin, no landing
    assert only_measured["skip_counts"]["low_spin_conf_in"] >= len(g_l.event_id)
    # After a bounce the segment into the racket is short, and under durr2026's Magnus law a small
    # and a large spin bend a flight alike (427 rad/s read as 37 from the segment alone); a racket
    # turns spin into velocity, so such a spin lands metres off (a median of 1.1 m, against 1.8 m
    # from spin 0, when fitted from that segment alone). Fitted across the bounce before it, the
    # spin's size is told: 10 of 13 landings come that way, their median error 3 mm and the worst
    # 23 cm when written.
    assert np.all(g_l.hit[TRUTH]) and g_l.through_bounce.sum() >= 0.5 * len(g_l.event_id)
    through = g_l.through_bounce
    assert np.median(g_l.error[TRUTH][through]) < 0.01 and np.max(g_l.error[TRUTH][through]) < 0.3
    assert np.nanmedian(g_l.error[TRUTH]) < 0.1 * np.nanmedian(g_z.error[TRUTH])
    text = markdown(summarise(latent), FIGURES)
    assert f"pre-bounce spin: {n} latent" in text and "incoming spin: " in text
    assert f"({int(through.sum())} of the latent spins fitted across the bounce before the contact" in text
