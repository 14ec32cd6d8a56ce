from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import ttsim_jax
from ttsim_jax import Ball, Racket, Record, load_model, simulate
from ttsim_jax.cli import main
from ttsim_jax.cli import simulate as simulate_command

from padding import simulate_shared


def test_simulate_rejects_bad_arguments_with_clear_messages():
    m = load_model("nakashima2011")
    b = Ball.create([[0.0, 0.0, 0.5]], [[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"Record\(every=3\) must divide n_steps=10"):
        simulate(m, b, 10, record=Record(every=3))
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


# ------------------------------------------------------------------ user errors: tests/cli/test_bad_inputs.py
SAMPLE = str(Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games")


def test_internal_errors_keep_their_traceback(monkeypatch):
    def broken(args):
        raise ValueError("an internal bug")  # a ValueError that is no user-error type

    monkeypatch.setattr(simulate_command, "cmd_simulate", broken)
    with pytest.raises(ValueError, match="an internal bug"):
        main(["simulate"])


def test_a_user_error_from_any_layer_is_one_error_line(monkeypatch, capsys):
    """Whatever raises it, a :class:`ttsim_jax.errors.UserError` ends in one ``error:`` line and status 2."""
    from ttsim_jax.errors import UserError

    class Refused(UserError, ValueError):
        pass

    def refused(args):
        raise Refused("--shots 3: refused")

    monkeypatch.setattr(simulate_command, "cmd_simulate", refused)
    assert main(["simulate"]) == 2
    assert capsys.readouterr().err.strip() == "error: --shots 3: refused"


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


def test_argument_errors_come_before_jax_is_imported():
    """A mistyped option is answered at once: parsing imports neither JAX nor the kernel."""
    import subprocess
    import sys

    code = ("import sys; from ttsim_jax.cli import main; status = main(['simulate', '--shots', '-1']); "
            "print(status, sorted(m for m in ('jax', 'flax', 'ttsim_jax.kernel', 'ttsim_jax.params') if m in sys.modules))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.stdout.split("\n")[0] == "2 []", (p.stdout, p.stderr)
    assert "--shots" in p.stderr


def test_simulate_times_its_throughput_with_the_program_it_compiled(tmp_path, capsys, monkeypatch):
    """The throughput re-timing call passes the same arguments as the first (its ``Record``
    included), so it runs the compiled program instead of compiling a second one."""
    calls = []
    real = ttsim_jax.simulate

    def spy(*args, **kwargs):
        calls.append((args[2:], kwargs))
        return real(*args, **kwargs)

    monkeypatch.setattr(ttsim_jax, "simulate", spy)
    assert main(["simulate", "--shots", "8", "--no-aim", "--duration", "0.5", "--plot", str(tmp_path / "s.png")]) == 0
    assert len(calls) == 2 and calls[0] == calls[1], calls
    assert calls[0][1]["record"].every > 0
    assert "ball-steps/s" in capsys.readouterr().out
