"""`ttsim fit` through the command line (in-process), on the bundled sample dataset."""

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
    # Aerodynamics fitted, everything else from the base model.
    assert not np.allclose(np.asarray(model.aero.drag.cd), np.asarray(base.aero.drag.cd))
    np.testing.assert_array_equal(np.asarray(model.aero.drag.sp), np.asarray(base.aero.drag.sp))
    np.testing.assert_array_equal(np.asarray(model.table.e0), np.asarray(base.table.e0))
    info = json.loads(summary.read_text())
    c = info["counts"]
    assert c["segments"] == c["too_short"] + c["low_spin_conf"] + c["held_out"] + c["fitted"]
    assert c["used"] == sum(info["segments"]["used"]) > 20
    assert info["test_sessions"] and c["held_out"] > 0
    # Segments that entered the fit are in no held-out session.
    assert len(info["segments"]["segment_id"]) == c["fitted"]
    used_rmse = [r for r, u in zip(info["segments"]["rmse"], info["segments"]["used"]) if u]
    assert max(used_rmse) <= 0.02


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
                 "--quiet"]) == 0
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
