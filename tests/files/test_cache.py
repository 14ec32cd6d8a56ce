"""The ``ttsim`` commands' persistent compilation cache: where it goes, how to move it or turn it
off, and that a cache JAX was already given is kept. One child process (the cache is a process
setting) tries every case in turn."""

import json
import os
import platform
import subprocess
import sys
import textwrap
from pathlib import Path

CASES = textwrap.dedent("""
    import json, os, sys
    import jax
    from ttsim_jax.files.cache import enable_compilation_cache
    root = sys.argv[1]
    out = {}
    for name, env, given in [("default", {}, None), ("off", {"TTSIM_COMPILE_CACHE": "off"}, None),
                             ("moved", {"TTSIM_COMPILE_CACHE": root + "/mine"}, None),
                             ("given", {}, root + "/jax")]:
        os.environ.pop("TTSIM_COMPILE_CACHE", None)
        os.environ.update(env)
        jax.config.update("jax_compilation_cache_dir", given)
        out[name] = [enable_compilation_cache(), jax.config.jax_compilation_cache_dir]
    print(json.dumps(out))
""")


def test_cache_folder_setting_and_a_given_cache(tmp_path):
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COMPILATION_CACHE_DIR", "TTSIM_COMPILE_CACHE", "XDG_CACHE_HOME")}
    run = subprocess.run([sys.executable, "-c", CASES, str(tmp_path)], env=dict(env, XDG_CACHE_HOME=str(tmp_path)),
                         capture_output=True, text=True, check=True)
    out = json.loads(run.stdout.strip().splitlines()[-1])
    default = tmp_path / "ttsim_jax" / "xla" / (platform.node() or "local")
    assert out["default"] == [str(default)] * 2 and default.is_dir()
    assert out["off"] == [None, None]
    assert out["moved"] == [str(tmp_path / "mine")] * 2 and (tmp_path / "mine").is_dir()
    assert out["given"] == [str(tmp_path / "jax")] * 2 and not (tmp_path / "jax").exists()


def test_compile_notice_prints_one_line_only_for_a_slow_call(capsys):
    """The line comes while a slow first call is still running, and a quick call prints nothing."""
    import time

    from ttsim_jax.files.cache import compile_notice

    with compile_notice("the quick program", 5.0, after_s=0.5):
        pass
    with compile_notice("the slow program", 120.0, after_s=0.05):
        time.sleep(0.5)
    time.sleep(0.6)  # past the quick block's timer: cancelled, it says nothing
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("ttsim_jax: preparing the slow program: compiling takes about 120 s the first time")
