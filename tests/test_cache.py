"""The ``ttsim`` commands' persistent compilation cache: where it goes, and how to turn it off."""

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

CODE = ("import jax; from ttsim_jax.cache import enable_compilation_cache as e; "
        "print(e()); print(jax.config.jax_compilation_cache_dir)")


def _run(tmp_path, **env):
    base = {k: v for k, v in os.environ.items()
            if k not in ("JAX_COMPILATION_CACHE_DIR", "TTSIM_COMPILE_CACHE", "XDG_CACHE_HOME")}
    out = subprocess.run([sys.executable, "-c", CODE], env=dict(base, XDG_CACHE_HOME=str(tmp_path), **env),
                         capture_output=True, text=True, check=True)
    return out.stdout.split("\n")[:2]


def test_default_folder_is_per_machine_under_the_user_cache(tmp_path):
    chosen, config = _run(tmp_path)
    want = tmp_path / "ttsim_jax" / "xla" / (platform.node() or "local")
    assert Path(chosen) == want and Path(config) == want and want.is_dir()


@pytest.mark.parametrize("setting", ["off", "dir"])
def test_setting_turns_it_off_or_moves_it(tmp_path, setting):
    value = "off" if setting == "off" else str(tmp_path / "mine")
    chosen, config = _run(tmp_path, TTSIM_COMPILE_CACHE=value)
    if setting == "off":
        assert chosen == "None" and config == "None" and not (tmp_path / "ttsim_jax").exists()
    else:
        assert chosen == config == value and Path(value).is_dir()


def test_a_cache_jax_was_given_is_kept(tmp_path):
    chosen, config = _run(tmp_path, JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jax"))
    assert chosen == config == str(tmp_path / "jax") and not (tmp_path / "ttsim_jax").exists()
