import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Racket, load_model, simulate
from ttsim_jax.cli import main


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
    r = simulate(m64, b32, 20)
    assert r.final.pos.dtype == jnp.float64
