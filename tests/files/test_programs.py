"""Traced programs kept on disk (``ttsim_jax.files.programs.stored_jit``): a second wrapper of the
same function (as in a new process) loads the stored program instead of tracing, gives jax.jit's
results, and traces anew whenever a static argument, a shape, the package source or the stored file
changes; under a transformation, or with the compilation cache off, it is plain jax.jit."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax.files import programs
from ttsim_jax.files.programs import stored_jit

TRACES = []


def _step(x, pair, *, n):
    TRACES.append(n)  # runs only while the function is traced
    a, b = pair
    out = x
    for _ in range(n):
        out = jnp.sin(out) * a + b
    return {"out": out, "parts": (out.sum(), jnp.cumsum(x))}


@pytest.fixture
def cache(tmp_path):
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    TRACES.clear()
    yield tmp_path
    jax.config.update("jax_compilation_cache_dir", before)


def _args(size=5):
    x = jnp.linspace(0.0, 1.0, size)
    return x, (jnp.asarray(0.5), jnp.asarray(0.25))


def _same(got, want):
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-12, atol=0.0)
    assert jax.tree.structure(got) == jax.tree.structure(want)


def test_a_stored_program_is_loaded_not_traced_and_matches_jit(cache):
    x, pair = _args()
    want = jax.jit(_step, static_argnames=("n",))(x, pair, n=3)
    TRACES.clear()
    first = stored_jit(_step, static_argnames=("n",))
    _same(first(x, pair, n=3), want)
    assert TRACES == [3]
    assert len(list((cache / "programs").rglob("*.stablehlo"))) == 1
    again = stored_jit(_step, static_argnames=("n",))  # a new process's wrapper
    _same(again(x, pair, n=3), want)
    _same(again(x, pair, n=3), want)
    assert TRACES == [3]
    # a new static value, a new shape: traced once each
    again(x, pair, n=4)
    again(*_args(7), n=3)
    assert TRACES == [3, 4, 3]


def test_an_edited_package_or_a_damaged_file_is_traced_again(cache, monkeypatch):
    x, pair = _args()
    want = stored_jit(_step, static_argnames=("n",))(x, pair, n=2)
    for path in (cache / "programs").rglob("*.stablehlo"):
        path.write_bytes(b"not a program")
    _same(stored_jit(_step, static_argnames=("n",))(x, pair, n=2), want)
    assert TRACES == [2, 2]
    monkeypatch.setattr(programs, "source_hash", lambda: "an edited package")
    _same(stored_jit(_step, static_argnames=("n",))(x, pair, n=2), want)
    assert TRACES == [2, 2, 2]


def test_plain_jit_under_a_transformation_and_with_the_cache_off(cache):
    x, pair = _args()
    fn = stored_jit(_step, static_argnames=("n",))

    def loss(f, x):
        return f(x, pair, n=2)["out"].sum()

    np.testing.assert_allclose(jax.grad(lambda x: loss(fn, x))(x),
                               jax.grad(lambda x: loss(jax.jit(_step, static_argnames=("n",)), x))(x), rtol=1e-12)
    assert not (cache / "programs").exists()
    jax.config.update("jax_compilation_cache_dir", None)
    _same(fn(x, pair, n=2), jax.jit(_step, static_argnames=("n",))(x, pair, n=2))
    assert programs.folder() is None and not (cache / "programs").exists()


def test_only_the_latest_source_versions_are_kept(cache, monkeypatch):
    x, pair = _args()
    versions = cache / "programs"
    for i in range(programs.KEEP_VERSIONS + 2):  # older versions' programs, oldest first
        old = versions / f"old{i}"
        old.mkdir(parents=True)
        (old / "k.stablehlo").write_bytes(b"x")
        os.utime(old, (1e9 + i, 1e9 + i))
    monkeypatch.setattr(programs, "source_hash", lambda: "the current version")
    stored_jit(_step, static_argnames=("n",))(x, pair, n=2)
    kept = sorted(p.name for p in versions.iterdir())
    newest = [f"old{i}" for i in range(programs.KEEP_VERSIONS + 2)][-(programs.KEEP_VERSIONS - 1):]
    assert kept == sorted(newest + ["the current version"[:16]]), kept
