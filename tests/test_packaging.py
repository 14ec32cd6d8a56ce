"""The wheel: it carries every file of the package and of the top-level configs/ (byte-identical,
so the bundled configs cannot drift from the ones users read), and installed from it the bundled
models and residual configs are found outside the checkout."""

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import ttsim_jax

REPO = Path(__file__).resolve().parents[1]


def _build_isolation_flag() -> list[str]:
    """Build without isolation when this environment has the build backend pyproject.toml asks
    for (fast, offline); otherwise let pip fetch it."""
    try:
        from importlib.metadata import version

        ok = int(version("setuptools").split(".")[0]) >= 77
    except Exception:  # noqa: BLE001 - setuptools absent or an odd version string
        ok = False
    return ["--no-build-isolation"] if ok else []


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel built from a copy of the sources (the checkout gets no build/ or egg-info)."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    for name in ("configs", "ttsim_jax"):
        shutil.copytree(REPO / name, src / name, ignore=ignore)
    out = root / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", *_build_isolation_flag(),
                    "-w", str(out), str(src)], check=True, cwd=root)
    (whl,) = out.glob("ttsim_jax-*.whl")
    return whl


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and "__pycache__" not in p.parts}


def test_wheel_holds_the_configs_and_the_package_byte_identical(wheel):
    with zipfile.ZipFile(wheel) as z:
        held = {n: z.read(n) for n in z.namelist() if not n.endswith("/")}
    configs = _files(REPO / "configs")
    assert any(n.startswith("models/") for n in configs) and any(n.startswith("residual/") for n in configs)
    for name, data in configs.items():
        assert held.get(f"ttsim_jax/configs/{name}") == data, f"configs/{name} missing or different in the wheel"
    for name, data in _files(REPO / "ttsim_jax").items():
        assert held.get(f"ttsim_jax/{name}") == data, f"ttsim_jax/{name} missing or different in the wheel"
    assert f"-{ttsim_jax.__version__}-" in wheel.name


def test_installed_wheel_finds_bundled_configs_outside_the_checkout(wheel, tmp_path):
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    code = ("from ttsim_jax import load_model; from ttsim_jax.params import config_dir; "
            "from ttsim_jax.fit.pipeline import bundled_config; "
            "m = load_model('conti2026'); print(config_dir()); print(bundled_config('durr2026').is_file())")
    env = dict(os.environ, PYTHONPATH=str(site), JAX_PLATFORMS="cpu")
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    where, found = run.stdout.split()
    assert Path(where) == site / "ttsim_jax" / "configs" and found == "True"


def test_source_checkout_reads_the_top_level_configs():
    from ttsim_jax.params import available_models, config_dir

    assert config_dir() == REPO / "configs"
    assert available_models() == sorted(p.stem for p in (REPO / "configs" / "models").glob("*.toml"))


def test_ci_smoke_tests_the_installed_wheel_outside_the_checkout():
    ci = (REPO / ".ci" / "run").read_text()
    wheel_at = ci.index("pip wheel")
    for command in ('cd "$smoke"', "ttsim --version", "ttsim simulate --model conti2026 --shots 100",
                    "load_model('conti2026')"):
        assert ci.find(command, wheel_at) > wheel_at, command
