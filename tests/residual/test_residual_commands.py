"""`train residual` / `evaluate residual` through the ``ttsim`` command (in-process)."""

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from ttsim_jax.cli import main
from ttsim_jax.cli import residual as commands
from ttsim_jax.data import save
from ttsim_jax.fit.network_config import load_train_config
from ttsim_jax.reality.synthetic_contacts import true_residual
from ttsim_jax.physics.network_checkpoint import checkpoint_metadata, load_residual
from ttsim_jax.reality import synthetic_contact_dataset

TINY_TOML = """
[model]
n_inputs = 8
trunk = [16, 16]
dropout = 0.1
head_width = 8
n_clusters = 10

[attenuation]
a = 7.282
b = 12.899
c = 0.052

[training]
learning_rate = 3e-3
weight_decay = 5e-4
batch_size = 16
max_epochs = 50
patience = 50
kmeans_iters = 5
"""


def parser():
    ap = argparse.ArgumentParser(prog="ttsim")
    sub = ap.add_subparsers(dest="command", required=True)
    commands.register(sub)
    return ap


def run(argv):
    return main(argv)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    ds, _ = synthetic_contact_dataset(100, seed=5, residual_fn=true_residual, noise=0.0005)
    save(ds, root / "data")
    (root / "tiny.toml").write_text(TINY_TOML)
    return root


def test_help_text_for_every_option():
    ap = parser()
    for group in ("train", "evaluate"):
        sub = ap._subparsers._group_actions[0].choices[group]
        res = sub._subparsers._group_actions[0].choices["residual"]
        for action in res._actions:
            assert action.help, (group, action.option_strings)
    with pytest.raises(SystemExit):
        ap.parse_args(["train", "residual", "--data", "d"])  # --out is required


def test_register_extends_an_existing_group(tmp_path):
    ap = argparse.ArgumentParser(prog="ttsim")
    sub = ap.add_subparsers(dest="command", required=True)
    train = sub.add_parser("train").add_subparsers(dest="what", required=True)
    train.add_parser("aero")
    commands.register(sub)
    assert ap.parse_args(["train", "aero"]).what == "aero"
    args = ap.parse_args(["train", "residual", "--data", str(tmp_path), "--out", str(tmp_path / "o")])
    assert args.func is commands.cmd_train_residual and args.model == "conti2026"


def test_train_then_evaluate(workdir, capsys):
    out = workdir / "net.ttres"
    argv = ["train", "residual", "--data", str(workdir / "data"), "--out", str(out), "--config",
            str(workdir / "tiny.toml"), "--epochs", "3", "--seed", "2", "--quiet"]
    assert run(argv) == 0
    text = capsys.readouterr().out
    assert "100 of 100 racket contacts usable" in text
    for label in ("0-5 cm", "5-8 cm", "> 8 cm", "all (n=10)", "|v|", "|w|", "inside 1 sigma", "sigma calibration"):
        assert label in text, label
    model = load_residual(out)
    meta = checkpoint_metadata(out)
    assert meta["model"] == "conti2026" and meta["epochs"] == 3 and meta["train_config"]["seed"] == 2
    assert meta["contacts"]["used"] == 100 and model.config.trunk == (16, 16)
    assert np.all(np.asarray(model.sigma_scale) > 0)

    # the finished run leaves no training state: a second run refuses only to overwrite the checkpoint,
    # there is nothing to resume, and once the checkpoint is moved away the same command runs again
    state = Path(str(out) + ".state")
    assert not state.exists()
    assert run(argv) == 2
    err = capsys.readouterr().err
    assert "--force" in err and "--resume" not in err
    assert run(argv + ["--resume"]) == 2
    assert "finished run" in capsys.readouterr().err
    out.rename(workdir / "kept.ttres")
    assert run(argv) == 0
    assert "all (n=10)" in capsys.readouterr().out and not state.exists()
    again = load_residual(out)  # same data, settings and seed: the same network
    np.testing.assert_array_equal(np.asarray(again.sigma_scale), np.asarray(model.sigma_scale))

    assert run(["evaluate", "residual", "--data", str(workdir / "data"), "--checkpoint", str(out), "--split", "test",
                "--json"]) == 0
    captured = capsys.readouterr()
    rep = json.loads(captured.out)
    assert "100 of 100 racket contacts usable" in captured.err
    assert rep["model"] == "conti2026" and rep["overall"]["n"] == 10
    assert [b["band"] for b in rep["bands"]] == ["0-5 cm", "5-8 cm", "> 8 cm", "all"]
    assert rep["bands"][-1]["n"] == 10
    assert run(["evaluate", "residual", "--data", str(workdir / "data"), "--checkpoint", str(out)]) == 0
    assert "all (n=100)" in capsys.readouterr().out


def test_errors_exit_2_with_a_message(workdir, capsys):
    bad = workdir / "bad.toml"
    bad.write_text(TINY_TOML.replace("n_clusters = 10", "n_clusters = 10\nbogus = 1"))
    argv = ["train", "residual", "--data", str(workdir / "data"), "--out", str(workdir / "x.ttres"), "--quiet"]
    assert run(argv + ["--config", str(bad)]) == 2
    assert "bogus" in capsys.readouterr().err
    assert run(argv + ["--config", str(workdir / "tiny.toml"), "--resume"]) == 2
    assert "no training state" in capsys.readouterr().err
    assert run(["train", "residual", "--data", str(workdir / "missing"), "--out", str(workdir / "y.ttres"),
                "--config", str(workdir / "tiny.toml"), "--quiet"]) == 2
    assert "error:" in capsys.readouterr().err
    assert run(["evaluate", "residual", "--data", str(workdir / "data"), "--checkpoint", str(workdir / "none")]) == 2
    assert "none: no such file" in capsys.readouterr().err


SAMPLE = Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games"


def test_default_config_trains_on_the_bundled_sample(tmp_path, capsys):
    """The bundled config asks for 1000 k-means centres; the sample has a few dozen contacts."""
    out = tmp_path / "sample.ttres"
    assert main(["train", "residual", "--data", str(SAMPLE), "--out", str(out), "--epochs", "2", "--quiet"]) == 0
    text = capsys.readouterr().out
    n_train = checkpoint_metadata(out)["n_train"]
    assert f"lowered from 1000 to {n_train}" in text
    assert load_residual(out).config.n_clusters == n_train < 1000


def test_help_states_the_defaults_of_clusters_epochs_and_seed(capsys):
    assert main(["train", "residual", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    for model in commands.MODELS:
        config, tcfg = load_train_config(commands.bundled_config(model))
        for value in (config.n_clusters, tcfg.max_epochs, tcfg.seed):
            assert f"{value} for {model}" in text
    for option, key in (("--clusters", "n_clusters"), ("--epochs", "max_epochs"), ("--seed", "seed")):
        assert f"{option} " in text and f"(default: the config's {key}," in text
