"""Training across processes: ``ttsim train ppo`` started once per process with JAX's multi-process
runtime (two processes on this machine's CPU, collectives through gloo) trains what one process
trains with the same total environments and seed: the same checkpoint up to the order of float
sums, written once; and the options that start it are checked.

The task has no domain randomisation: with ``table.e0`` drawn per environment, one update's
rollout flips a discrete event on float rounding, and one process alone differs as much between
XLA's optimisation levels (-O0 against the default: the network's parameters 7e-3 apart after one
update) as between one and two devices."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from ttsim_jax.cli import main
from ttsim_jax.rl.checkpoint import read_checkpoint

from test_ppo import PPO, TASK

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def ttsim(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), JAX_PLATFORMS="cpu")
    return subprocess.Popen([sys.executable, "-m", "ttsim_jax.cli", *args], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@pytest.mark.slow
def test_two_processes_train_what_one_trains(tmp_path):
    (tmp_path / "task.toml").write_text(TASK[:TASK.index("[randomisation]")])
    (tmp_path / "ppo.toml").write_text(PPO.replace("total_env_steps = 10240", "total_env_steps = 2560")
                                       .replace("updates_per_chunk = 10", "updates_per_chunk = 5"))
    common = ["train", "ppo", "--config", "ppo.toml", "--quiet"]
    one = ttsim(*common, "--out", "one", cwd=tmp_path)
    port = free_port()
    two = [ttsim(*common, "--out", "two", "--coordinator", f"localhost:{port}", "--num-processes", "2",
                 "--process-id", str(i), cwd=tmp_path) for i in (0, 1)]
    for proc in [one, *two]:
        out, _ = proc.communicate(timeout=900)
        assert proc.returncode == 0, out[-3000:]
    a = read_checkpoint(tmp_path / "one" / "checkpoint.msgpack")
    b = read_checkpoint(tmp_path / "two" / "checkpoint.msgpack")
    assert [h["env_steps"] for h in a["history"]] == [h["env_steps"] for h in b["history"]] == [1280, 2560]
    leaves_a, leaves_b = jax.tree.leaves(a["runner"]), jax.tree.leaves(b["runner"])
    assert len(leaves_a) == len(leaves_b)
    for x, y in zip(leaves_a, leaves_b):
        x, y = np.asarray(x), np.asarray(y)
        if x.dtype.kind == "f":  # float32 sums in another order: 2e-5 of the largest value after 10 updates
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-4 * max(1.0, float(np.abs(x).max(initial=0.0))))
        else:
            np.testing.assert_array_equal(x, y)
    # the policy learned something (it is not two copies of an untrained network)
    first = jax.tree.leaves(a["runner"]["params"])[0]
    assert np.abs(np.asarray(first)).max() > 0


@pytest.mark.parametrize("argv, match", [
    (["--coordinator", "localhost:1"], "go together"),
    (["--coordinator", "localhost:1", "--num-processes", "2", "--process-id", "2"], r"--process-id 2: must be within 0\.\.1"),
])
def test_the_process_options_are_checked(argv, match, capsys, tmp_path):
    assert main(["train", "ppo", "--out", str(tmp_path / "run"), *argv]) == 2
    err = capsys.readouterr().err
    assert re.search(match, err), err
