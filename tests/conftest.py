"""Shared fixtures. Float64 is enabled so finite-difference checks are meaningful; tests that
exercise the float32 path ask for it explicitly (``dtype`` fixture).

The suite's time is XLA compilation, and the xdist workers (and the command-line tests' child
processes) compile many of the same programs. They share one persistent compilation cache, a
temporary folder made for the run and removed after it; set ``TTSIM_TEST_JAX_CACHE`` to a folder
of your own to keep the compiled programs between runs (safe: JAX keys every entry on the program,
the compile options and its own version).
"""

import os
import shutil
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

# The suite is compilation-bound, so it compiles for compile speed: XLA's legacy CPU emitters and
# LLVM without optimisation (-O0) cut the suite's CPU time by about a fifth (1,146 -> 892 s summed
# over the tests) and make the few tests with large batches run slower; the benchmarks keep XLA's
# defaults. Read when the backend starts, so set before any test touches a device; subprocesses
# inherit it. TTSIM_TEST_XLA_DEFAULT=1 runs the suite with XLA's defaults instead.
_FAST_COMPILE = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=0")
if not os.environ.get("TTSIM_TEST_XLA_DEFAULT"):
    _flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = " ".join([_flags] + [f for f in _FAST_COMPILE if f.split("=")[0] not in _flags]).strip()

if "TTSIM_TEST_JAX_CACHE" not in os.environ:  # the controller makes it; workers inherit the variable
    os.environ["TTSIM_TEST_JAX_CACHE"] = tempfile.mkdtemp(prefix="ttsim-jax-cache-")
    os.environ["TTSIM_TEST_JAX_CACHE_OWNED"] = os.environ["TTSIM_TEST_JAX_CACHE"]
# environment variables as well as the config, so subprocesses started by tests use the cache too
for _name, _value in (("jax_compilation_cache_dir", os.environ["TTSIM_TEST_JAX_CACHE"]),
                      ("jax_persistent_cache_min_compile_time_secs", 0.0),
                      ("jax_persistent_cache_min_entry_size_bytes", 0)):
    os.environ[_name.upper()] = str(_value)
    jax.config.update(_name, _value)


# The heaviest test files, heaviest first (worker seconds of one run at 2 workers, 2026-12-03:
# 166, 123, 116, 96, 82, 67, 64 s of 1,329 s in all). xdist hands out whole files (--dist
# loadfile, so that a file's compiled programs and fixtures are reused); a heavy file handed out
# last leaves the other worker idle until it ends, so they go first.
HEAVY_FIRST = ("kernel/test_fused.py", "kernel/test_rollout.py", "kernel/test_models_on_every_path.py",
               "test_docs_snippets.py", "residual/test_residual_rally.py", "env/test_intercept.py",
               "diagnose/test_diagnose_spin.py", "diagnose/test_diagnose.py", "kernel/test_rally.py",
               "fit/test_spin_check.py", "fit/test_fit_pipeline.py", "reality/test_generator.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    tests = Path(__file__).resolve().parent

    def key(item):
        try:
            name = Path(str(item.fspath)).resolve().relative_to(tests).as_posix()
        except ValueError:
            name = ""
        return rank.get(name, len(rank))

    items.sort(key=key)  # stable: the order within a file and among the rest is kept


def pytest_unconfigure(config):
    owned = os.environ.get("TTSIM_TEST_JAX_CACHE_OWNED")
    if owned and not os.environ.get("PYTEST_XDIST_WORKER"):
        shutil.rmtree(owned, ignore_errors=True)

REPO = Path(__file__).resolve().parents[1]


def real_data_dir() -> Path:
    env = os.environ.get("TTSIM_REAL_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data" / "real"


@pytest.fixture
def real_data() -> Path:
    """The folder of the public measured data: $TTSIM_REAL_DATA, else ../shared/data/real."""
    return real_data_dir()


@pytest.fixture(params=[jnp.float32, jnp.float64], ids=["f32", "f64"])
def dtype(request):
    return request.param


# A ball of radius 0.02 m over the ITTF table, for the tests of segmentation and of the flight fit.
RADIUS = 0.02


def simulate(p0, v0, *, duration, rate=180.0, kd=0.11, e=0.9, hit_at=None, hit_vel=None, seed=None, noise=0.0, t0=0.0):
    """Ball flight with drag and table bounces at z = radius, sampled at ``rate``.

    Returns:
        t (T,), pos (T, 3), bounce_times list, bounce_positions list.
    """
    h = 1e-4
    p = np.array(p0, float)
    v = np.array(v0, float)
    g = np.array([0.0, 0.0, -9.81])
    t_out, p_out, bt, bp = [], [], [], []
    n_steps = int(round(duration / h))
    every = int(round(1.0 / (rate * h)))
    hit_done = False
    for k in range(n_steps + 1):
        t = k * h
        if k % every == 0:
            t_out.append(t0 + t)
            p_out.append(p.copy())
        if hit_at is not None and not hit_done and t >= hit_at:
            v = np.array(hit_vel, float)
            hit_done = True
        v = v + h * (g - kd * np.linalg.norm(v) * v)
        p_new = p + h * v
        if p_new[2] < RADIUS and v[2] < 0 and abs(p_new[0]) < 1.37 and abs(p_new[1]) < 0.7625:
            frac = (p[2] - RADIUS) / (p[2] - p_new[2])
            bt.append(t0 + t + frac * h)
            bp.append(p + frac * (p_new - p))
            p_new = p + frac * h * v
            p_new[2] = RADIUS
            v = np.array([v[0] * 0.85, v[1] * 0.85, -e * v[2]])
        p = p_new
    pos = np.array(p_out)
    if noise:
        pos = pos + np.random.default_rng(seed).normal(0.0, noise, pos.shape)
    return np.array(t_out), pos, bt, [np.asarray(b) for b in bp]


@pytest.fixture
def simulate_flight():
    """The :func:`simulate` function (fixtures avoid importing conftest by name)."""
    return simulate
