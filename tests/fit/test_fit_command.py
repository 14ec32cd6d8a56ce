"""`ttsim fit` through the command line (in-process), on the bundled sample dataset (a small
generated one: 238 segments, 115 table bounces, 51 racket contacts)."""

import json
from pathlib import Path

import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.cli import main

SAMPLE = Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "fitted"
    status = main(["fit", "--data", str(SAMPLE), "--out", str(out), "--test-fraction", "0.3", "--quiet"])
    return status, out.with_suffix(".toml"), out.with_suffix(".fit.json")


def test_fit_writes_a_loadable_model_and_a_summary(fitted, capsys):
    status, toml, summary = fitted
    assert status == 0
    model, base = load_model(toml), load_model("conti2026")
    assert model.name == "fitted"
    # Aerodynamics fitted, the breakpoints and what no stage fits from the base model.
    assert not np.allclose(np.asarray(model.aero.drag.cd), np.asarray(base.aero.drag.cd))
    np.testing.assert_array_equal(np.asarray(model.aero.drag.sp), np.asarray(base.aero.drag.sp))
    np.testing.assert_array_equal(np.asarray(model.table.mu), np.asarray(base.table.mu))
    info = json.loads(summary.read_text())
    assert info["stages"] == ["aero", "table", "racket"]
    c = info["aero"]["counts"]
    assert c["segments"] == c["too_short"] + c["low_spin_conf"] + c["held_out"] + c["fitted"]
    assert c["used"] == sum(info["aero"]["segments"]["used"]) > 20
    assert info["test_sessions"] and c["held_out"] > 0
    # Segments that entered the fit are in no held-out session.
    assert len(info["aero"]["segments"]["segment_id"]) == c["fitted"]
    used_rmse = [r for r, u in zip(info["aero"]["segments"]["rmse"], info["aero"]["segments"]["used"]) if u]
    assert max(used_rmse) <= 0.02
    for stage in info["stages"]:
        assert info["seconds"][stage]["wall"] > 0 and info["seconds"][stage]["cpu"] > 0


def test_fit_contact_stages_write_their_values_and_counts(fitted):
    _, toml, summary = fitted
    model, info = load_model(toml), json.loads(summary.read_text())
    table, racket = info["table"], info["racket"]
    for stage, n_events in ((table, 115), (racket, 51)):
        c = stage["counts"]
        assert c["total"] == n_events
        assert c["used"] + c["held_out"] + sum(c["skipped"].values()) == n_events
        assert c["used"] >= 10 and c["held_out"] > 0
    # The config holds the fitted values the summary reports; no bounce gains energy (the free fit's
    # e0 is above 1 on this sample).
    assert float(model.table.e0) == pytest.approx(table["fit"]["e0"], rel=1e-5)
    assert table["fit"]["e0"] <= float(model.table.e_max) and table["fit"]["unconstrained"]["e0"] > 1.0
    assert float(model.table.e1) == pytest.approx(table["fit"]["e1"], rel=1e-5)
    np.testing.assert_allclose(np.asarray(model.table.residual[1]), table["fit"]["residual"]["dA_vw"], rtol=1e-5)
    pattern = np.array([table["fit"]["pattern"][k] for k in ("dA_vv", "dA_vw", "dA_wv", "dA_ww")], bool)
    np.testing.assert_array_equal(np.asarray(model.table.residual) != 0, pattern)
    assert table["fit"]["cv_lambda"] >= table["fit"]["cv_lambda_min"] > 0
    assert model.racket.kind == "updated"
    for k in ("e0", "e1", "et0", "et1", "e_s"):
        assert float(getattr(model.racket, k)) == pytest.approx(racket["fit"]["values"][k], rel=1e-5)
        assert racket["fit"]["stderr"][k] > 0


def test_fit_table_stage_without_bounces_names_the_option_and_data(tmp_path, capsys):
    from ttsim_jax.data import Dataset, save

    t = np.arange(20) / 200.0  # one flight, no events
    data = tmp_path / "no_bounces"
    save(Dataset.from_arrays(np.zeros(20, int), t, np.stack([5 * t - 1, 0 * t, 0.3 + 2 * t - 4.9 * t * t], 1)), data)
    assert main(["fit", "--data", str(data), "--out", str(tmp_path / "x"), "--stages", "table", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--stages table" in err and str(data) in err and "no table bounces" in err
    assert main(["fit", "--data", str(data), "--out", str(tmp_path / "x"), "--stages", "racket", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--stages racket" in err and str(data) in err and "no racket contacts" in err
    assert not (tmp_path / "x.toml").exists()
    assert main(["fit", "--data", str(data), "--out", str(tmp_path / "x"), "--stages", "aero,wind"]) == 2
    assert "aero, table, racket, residual" in capsys.readouterr().err


def test_fit_refuses_to_overwrite_and_bad_options(fitted, tmp_path, capsys):
    _, toml, _ = fitted
    assert main(["fit", "--data", str(SAMPLE), "--out", str(toml), "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["fit", "--data", str(SAMPLE), "--out", str(tmp_path / "x"), "--test-fraction", "1.5"]) == 2
    assert "fraction" in capsys.readouterr().err
    assert main(["fit", "--data", str(SAMPLE), "--out", str(tmp_path / "x"), "--base", "nakashima2011",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "nakashima2011" in err and "table" in err
    assert not (tmp_path / "x.toml").exists()


def test_fit_drag_only_keeps_the_base_magnus_form(tmp_path):
    out = tmp_path / "drag.toml"
    assert main(["fit", "--data", str(SAMPLE), "--out", str(out), "--test-fraction", "0.3", "--forms", "drag",
                 "--stages", "aero", "--spin", "measured", "--quiet"]) == 0
    model, base = load_model(out), load_model("conti2026")
    for key in ("m1", "s", "w_b", "a", "b", "c"):
        np.testing.assert_allclose(np.asarray(getattr(model.aero.magnus, key)),
                                   np.asarray(getattr(base.aero.magnus, key)), rtol=1e-5)
    assert not np.allclose(np.asarray(model.aero.drag.cd), np.asarray(base.aero.drag.cd))


def test_every_fit_option_has_help():
    from ttsim_jax.cli import build_parser

    fit = build_parser()._subparsers._group_actions[0].choices["fit"]
    assert all(action.help for action in fit._actions)
    assert "--forms" in fit.format_help() and "averaged" in fit.format_help()
    assert "--stages" in fit.format_help() and "residual" in fit.format_help()


@pytest.mark.slow  # trains the network (its compilation is most of a minute of CPU)
def test_fit_residual_stage_trains_a_network_on_what_the_fitted_base_leaves(tmp_path, capsys):
    out = tmp_path / "withnet"
    assert main(["fit", "--data", str(SAMPLE), "--out", str(out), "--stages", "racket,residual", "--epochs", "3",
                 "--test-fraction", "0.3", "--quiet"]) == 0
    network = out.with_suffix(".ttres")
    info = json.loads(out.with_suffix(".fit.json").read_text())
    assert info["stages"] == ["racket", "residual"] and network.is_file()
    res = info["residual"]
    assert 1 <= res["epochs"] <= 3 and np.isfinite(res["best_val_loss"])
    # trained on the training sessions' contacts only, the fitted racket parameters as its base
    assert 3 <= res["contacts"]["used"] < info["racket"]["counts"]["total"]
    from ttsim_jax.physics.network_checkpoint import checkpoint_metadata

    model = load_model(out.with_suffix(".toml"), residual=network)
    assert model.residual is not None and float(model.racket.e0) == pytest.approx(info["racket"]["fit"]["values"]["e0"], rel=1e-5)
    assert checkpoint_metadata(network)["contacts"]["used"] == res["contacts"]["used"]
    # a second run refuses to overwrite the checkpoint
    assert main(["fit", "--data", str(SAMPLE), "--out", str(out), "--stages", "residual", "--quiet"]) != 0
    assert "exists" in capsys.readouterr().err


def test_a_task_randomises_around_the_fit_with_its_standard_errors(fitted, tmp_path):
    """`ttsim fit`'s summary feeds ReturnBall's domain randomisation: {fit = FILE} is a normal law of
    the fitted value and (scale times) its standard error."""
    from ttsim_jax.env.config import FITTED, load_task_config

    _, _, summary = fitted
    info = json.loads(summary.read_text())
    config = load_task_config("return_ball", {"randomisation": {
        "table.e0": {"fit": str(summary)}, "racket.et0": {"fit": str(summary), "scale": 2.0}}})
    laws = {path: (a, b, law) for path, a, b, law in config.randomisation}
    assert laws["table.e0"] == (info["table"]["fit"]["e0"], info["table"]["fit"]["stderr_e0"], "normal")
    assert laws["racket.et0"] == (info["racket"]["fit"]["values"]["et0"],
                                  2.0 * info["racket"]["fit"]["stderr"]["et0"], "normal")
    # every parameter the loader offers is in the summary, finite
    for path in FITTED:
        load_task_config("return_ball", {"randomisation": {path: {"fit": str(summary)}}})
