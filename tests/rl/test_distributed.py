"""Training across processes: ``ttsim train ppo`` started once per process with JAX's multi-process
runtime (two processes on this machine's CPU, collectives through gloo) trains what one process
trains on as many devices (two host devices) with the same total environments and seed: the same
checkpoint, written once; and the options that start it are checked.

Each device steps its own environments with its own random draws
(:func:`ttsim_jax.rl.distributed.per_shard`), so the runs compare on the same number of devices,
domain randomisation included."""

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


def ttsim(*args, cwd, devices=1):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), JAX_PLATFORMS="cpu")
    if devices > 1:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}").strip()
    return subprocess.Popen([sys.executable, "-m", "ttsim_jax.cli", *args], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@pytest.mark.slow
def test_two_processes_train_what_one_trains_on_two_devices(tmp_path):
    (tmp_path / "task.toml").write_text(TASK)  # table.e0 drawn per environment
    (tmp_path / "ppo.toml").write_text(PPO.replace("total_env_steps = 10240", "total_env_steps = 2560")
                                       .replace("updates_per_chunk = 10", "updates_per_chunk = 5"))
    common = ["train", "ppo", "--config", "ppo.toml", "--quiet"]
    one = ttsim(*common, "--out", "one", cwd=tmp_path, devices=2)
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
        np.testing.assert_array_equal(x, y)  # each device ran the same program on the same rows
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
