from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ttsim_jax
from ttsim_jax import Ball, Racket, cli, load_model, simulate
from ttsim_jax.cli import main

from padding import simulate_shared


def test_simulate_rejects_bad_arguments_with_clear_messages():
    m = load_model("nakashima2011")
    b = Ball.create([[0.0, 0.0, 0.5]], [[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="record_every=3 must divide n_steps=10"):
        simulate(m, b, 10, record_every=3)
    with pytest.raises(ValueError, match="n_steps must be positive"):
        simulate(m, b, 0)
    with pytest.raises(ValueError, match=r"ball fields must be \(B, 3\)"):
        simulate(m, Ball.create(np.zeros((1, 1, 3)), np.zeros((1, 1, 3))), 10)
    short = Racket.create(jnp.zeros((5, 3)))
    with pytest.raises(ValueError, match="covers 5 steps, the simulation needs 10"):
        simulate(m, b, 10, racket=short)


def test_cli_simulate_bad_options_exit_2_with_message(capsys):
    assert main(["simulate", "--shots", "0"]) == 2
    assert "--shots" in capsys.readouterr().err
    assert main(["simulate", "--types", "forehand_flick"]) == 2
    assert "unknown shot types ['forehand_flick']" in capsys.readouterr().err


def test_cli_simulate_runs_and_writes_outputs(tmp_path, capsys):
    out = tmp_path / "shots.npz"
    png = tmp_path / "shots.png"
    assert main(["simulate", "--shots", "8", "--no-aim", "--duration", "0.5", "--save", str(out),
                 "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "ball-steps/s" in text and "all" in text
    data = np.load(out)
    assert data["pos"].shape == (8, 100, 3)
    assert png.stat().st_size > 10_000


def test_balls_are_cast_to_the_models_dtype():
    m64 = load_model("nakashima2011", dtype=jnp.float64)
    b32 = Ball.create([[0.0, 0.0, 0.5]], [[1.0, 0.0, 0.0]], dtype=jnp.float32)
    r = simulate_shared(m64, b32)  # the suite's shared shape
    assert r.final.pos.dtype == jnp.float64


# ------------------------------------------------------------------ user errors: one line, status 2
SAMPLE = str(Path(__file__).resolve().parents[1] / "ttsim_jax" / "data" / "sample" / "games")


@pytest.fixture(scope="module")
def paths(tmp_path_factory):
    """A directory, a binary file, a text file that is not TOML, and a conti2026 checkpoint."""
    from ttsim_jax.params import config_dir
    from ttsim_jax.physics import residual as R

    root = tmp_path_factory.mktemp("bad")
    (root / "dir").mkdir()
    (root / "bin").write_bytes(bytes(range(256)) * 4)
    (root / "text.txt").write_text("hello\n")
    config = R.load_residual_config(config_dir() / "residual" / "conti2026.toml")
    R.save_residual(root / "conti.ttres", R.init_model(config, jax.random.key(0)), metadata={"model": "conti2026"})
    return root


# (argv with {P} for the fixture's folder, fragments the message must hold: the option or file, the value)
BAD = {
    "simulate-unknown-model": (["simulate", "--model", "conti2099"], ["--model", "conti2099"]),
    "simulate-model-missing-file": (["simulate", "--model", "{P}/mine.toml"], ["--model", "{P}/mine.toml"]),
    "simulate-model-dir": (["simulate", "--model", "{P}/dir"], ["--model", "{P}/dir", "directory"]),
    "simulate-model-binary": (["simulate", "--model", "{P}/bin"], ["--model", "{P}/bin", "not a text file"]),
    "simulate-model-not-toml": (["simulate", "--model", "{P}/text.txt"], ["{P}/text.txt", "not valid TOML"]),
    "simulate-dt-nan": (["simulate", "--dt", "nan"], ["--dt", "'nan'"]),
    "simulate-dt-inf": (["simulate", "--dt", "inf"], ["--dt", "'inf'"]),
    "simulate-dt-negative": (["simulate", "--dt", "-0.001"], ["--dt", "'-0.001'"]),
    "simulate-duration-negative": (["simulate", "--duration", "-1"], ["--duration", "'-1'"]),
    "simulate-duration-nan": (["simulate", "--duration", "nan"], ["--duration", "'nan'"]),
    "simulate-duration-below-a-step": (["simulate", "--duration", "0.001"], ["--duration 0.001", "--dt 0.001"]),
    "simulate-shots-negative": (["simulate", "--shots", "-5"], ["--shots", "'-5'"]),
    "simulate-shots-fraction": (["simulate", "--shots", "2.5"], ["--shots", "'2.5'"]),
    "simulate-seed-negative": (["simulate", "--seed", "-1"], ["--seed", "'-1'"]),
    "simulate-save-under-a-file": (["simulate", "--save", "{P}/bin/out.npz"], ["--save", "{P}/bin/out.npz"]),
    "simulate-plot-dir": (["simulate", "--plot", "{P}/dir"], ["--plot", "{P}/dir", "directory"]),
    "data-info-missing": (["data", "info", "{P}/nope"], ["DIR", "{P}/nope"]),
    "data-info-file": (["data", "info", "{P}/bin"], ["DIR", "{P}/bin"]),
    "data-info-not-a-dataset": (["data", "info", "{P}/dir"], ["{P}/dir", "metadata.json"]),
    "data-import-missing": (["data", "import", "{P}/nope", "--source", "tt3d", "--out", "{P}/o"], ["PATH", "{P}/nope"]),
    "data-import-binary": (["data", "import", "{P}/bin", "--source", "tt3d", "--out", "{P}/o"],
                           ["{P}/bin", "binary content"]),
    "data-import-out-under-a-file": (["data", "import", SAMPLE, "--source", "tt3d", "--out", "{P}/bin/o"],
                                     ["--out", "{P}/bin/o"]),
    "data-import-max-rmse-nan": (["data", "import", SAMPLE, "--source", "tt3d", "--out", "{P}/o", "--max-rmse", "nan"],
                                 ["--max-rmse", "'nan'"]),
    "generate-out-under-a-file": (["generate", "--out", "{P}/bin/g"], ["--out", "{P}/bin/g"]),
    "generate-out-not-empty": (["generate", "--out", "{P}"], ["--out", "{P}", "--force"]),
    "generate-games-zero": (["generate", "--out", "{P}/g", "--games", "0"], ["--games", "'0'"]),
    "generate-lanes-nan": (["generate", "--out", "{P}/g", "--lanes", "nan"], ["--lanes", "'nan'"]),
    "generate-seed-negative": (["generate", "--out", "{P}/g", "--seed", "-3"], ["--seed", "'-3'"]),
    "generate-config-binary": (["generate", "--out", "{P}/g", "--config", "{P}/bin"], ["--config", "{P}/bin"]),
    "generate-config-dir": (["generate", "--out", "{P}/g", "--config", "{P}/dir"], ["--config", "{P}/dir"]),
    "generate-unknown-effect": (["generate", "--out", "{P}/g", "--effects", "windy"], ["windy"]),
    "train-data-missing": (["train", "residual", "--data", "{P}/nope", "--out", "{P}/n.ttres"], ["--data", "{P}/nope"]),
    "train-out-under-a-file": (["train", "residual", "--data", SAMPLE, "--out", "{P}/bin/n.ttres"],
                               ["--out", "{P}/bin/n.ttres"]),
    "train-out-dir": (["train", "residual", "--data", SAMPLE, "--out", "{P}/dir"], ["--out", "{P}/dir"]),
    "train-config-binary": (["train", "residual", "--data", SAMPLE, "--out", "{P}/n.ttres", "--config", "{P}/bin"],
                            ["--config", "{P}/bin"]),
    "train-config-not-toml": (["train", "residual", "--data", SAMPLE, "--out", "{P}/n.ttres", "--config",
                               "{P}/text.txt"], ["{P}/text.txt", "not valid TOML"]),
    "train-epochs-zero": (["train", "residual", "--data", SAMPLE, "--out", "{P}/n.ttres", "--epochs", "0"],
                          ["--epochs", "'0'"]),
    "train-clusters-negative": (["train", "residual", "--data", SAMPLE, "--out", "{P}/n.ttres", "--clusters", "-2"],
                                ["--clusters", "'-2'"]),
    "train-seed-nan": (["train", "residual", "--data", SAMPLE, "--out", "{P}/n.ttres", "--seed", "nan"],
                       ["--seed", "'nan'"]),
    "diagnose-data-missing": (["diagnose", "--out", "{P}/d"], ["--data", "required"]),
    "diagnose-unknown-effect": (["diagnose", "--data", SAMPLE, "--out", "{P}/d", "--effects", "windy"], ["--effects", "windy"]),
    "diagnose-record-effect": (["diagnose", "--data", SAMPLE, "--out", "{P}/d", "--effects", "spin_noise"],
                               ["--effects", "spin_noise", "record"]),
    "diagnose-test-fraction-one": (["diagnose", "--data", SAMPLE, "--out", "{P}/d", "--test-fraction", "1"],
                                   ["--test-fraction", "'1'"]),
    "diagnose-out-under-a-file": (["diagnose", "--data", SAMPLE, "--out", "{P}/bin/d"], ["--out", "{P}/bin/d"]),
    "evaluate-checkpoint-dir": (["evaluate", "residual", "--data", SAMPLE, "--checkpoint", "{P}/dir"],
                                ["--checkpoint", "{P}/dir"]),
    "evaluate-checkpoint-binary": (["evaluate", "residual", "--data", SAMPLE, "--checkpoint", "{P}/bin"],
                                   ["{P}/bin", "not a ttsim residual checkpoint"]),
    "evaluate-checkpoint-missing": (["evaluate", "residual", "--data", SAMPLE, "--checkpoint", "{P}/nope.ttres"],
                                    ["--checkpoint", "{P}/nope.ttres"]),
    "evaluate-checkpoint-other-family": (["evaluate", "residual", "--data", SAMPLE, "--checkpoint",
                                          "{P}/conti.ttres", "--model", "durr2026"],
                                         ["--checkpoint", "{P}/conti.ttres", "conti2026", "--model durr2026"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_user_errors_exit_2_naming_option_and_value(case, paths, capsys):
    argv, fragments = BAD[case]
    assert main([a.replace("{P}", str(paths)) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment.replace("{P}", str(paths)) in lines[0], (fragment, lines[0])


def test_internal_errors_keep_their_traceback(monkeypatch):
    def broken(args):
        raise ValueError("an internal bug")  # a ValueError that is no user-error type

    monkeypatch.setattr(cli, "cmd_simulate", broken)
    with pytest.raises(ValueError, match="an internal bug"):
        main(["simulate"])


def test_version_and_help(capsys):
    assert main(["--version"]) == 0
    assert ttsim_jax.__version__ in capsys.readouterr().out
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for command in ("simulate", "data", "generate", "fit", "train", "evaluate", "diagnose"):
        assert command in out


def test_a_closed_output_pipe_ends_quietly():
    """``ttsim data info DIR | head``: the reader closes the pipe before ttsim writes."""
    import subprocess
    import sys

    code = f"import sys; from ttsim_jax.cli import main; sys.exit(main(['data', 'info', {SAMPLE!r}]))"
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait() == 1 and "Traceback" not in err and "BrokenPipeError" not in err, err
