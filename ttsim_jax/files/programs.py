"""Traced programs kept on disk, so that a command run again skips Python tracing.

JAX's compilation cache (:func:`~ttsim_jax.files.cache.enable_compilation_cache`) saves the XLA
compilation, but every process still traces and lowers each program to find it there: for a
diagnosis of the bundled sample that was about 15 s of a 45 s run, the descents' programs alone
1-2.5 s each. :func:`stored_jit` wraps a function like ``jax.jit`` and keeps each traced program
(``jax.export``'s serialized StableHLO) in ``<compilation cache>/programs/<source hash>`` (the
:data:`KEEP_VERSIONS` latest source versions are kept); a later process with the same package
source, library versions, static arguments, argument structure, shapes and dtypes loads it
instead of tracing, and the compilation cache then supplies the executable.

What a program depends on is in its key: a hash of every source file of the package (so an edited
package never runs a stale program) and of the versions of :data:`TRACED_LIBRARIES`, the backend,
the numeric configuration (x64, precision, promotion), the function's name, the static
arguments' ``repr`` and the arguments' tree structure and abstract values. The
stored files are written atomically; one that cannot be read is traced again. Called under a JAX
transformation (a tracer among the arguments) or with the compilation cache off, the wrapper is
plain ``jax.jit``. The folder must be trusted, as the compilation cache's: JAX runs what it loads.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import pickle
from pathlib import Path

from ttsim_jax.files.atomic import atomic_write

_PACKAGE = Path(__file__).resolve().parents[1]


#: Source versions (package and libraries) whose programs are kept; older ones are removed.
KEEP_VERSIONS = 4
#: Libraries whose code runs while a program is traced: their versions are part of its key.
TRACED_LIBRARIES = ("jax", "jaxlib", "flax", "optax", "numpy")


@functools.lru_cache(maxsize=1)
def source_hash() -> str:
    """Hash of every ``.py`` file of the package (names and contents) and of the versions of
    :data:`TRACED_LIBRARIES`."""
    from importlib.metadata import PackageNotFoundError, version

    def known(name):
        try:
            return version(name)
        except PackageNotFoundError:
            return "-"

    h = hashlib.sha256(repr([(n, known(n)) for n in TRACED_LIBRARIES]).encode())
    for path in sorted(_PACKAGE.rglob("*.py")):
        h.update(str(path.relative_to(_PACKAGE)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def folder() -> Path | None:
    """Where this package source's traced programs are kept: ``programs/<source hash>`` in the
    compilation cache's folder (JAX's own entries there are files ``*-cache``; deleting the folder
    deletes both), or None while the compilation cache is off."""
    import jax

    cache = jax.config.jax_compilation_cache_dir
    return Path(cache) / "programs" / source_hash()[:16] if cache else None


def _prune(where: Path) -> None:
    """Removes the programs of all but the :data:`KEEP_VERSIONS` most recently made source versions
    (an edited package's programs are never loaded again; this bounds the folder)."""
    import shutil

    try:
        versions = sorted((p for p in where.parent.iterdir() if p.is_dir() and p != where),
                          key=lambda p: p.stat().st_mtime, reverse=True)
    except OSError:
        return
    for old in versions[KEEP_VERSIONS - 1:]:
        shutil.rmtree(old, ignore_errors=True)


def stored_jit(fn=None, *, static_argnames=()):
    """``jax.jit(fn, static_argnames=...)`` whose traced programs are kept on disk (see the module
    docstring). Usable as a decorator, with or without arguments.

    Arguments:
        fn: the function; its outputs must be arrays in tuples, lists and dicts (their structure
            is stored beside the program).
        static_argnames: keyword arguments that are static, as for ``jax.jit``.

    Returns:
        A callable with ``fn``'s signature; ``.jitted`` is the plain ``jax.jit`` of ``fn``.
    """
    if fn is None:
        return functools.partial(stored_jit, static_argnames=static_argnames)
    import jax

    jitted = jax.jit(fn, static_argnames=static_argnames)
    loaded = {}  # (folder, key) -> (callable over the leaves, output structure)
    name = f"{fn.__module__}.{fn.__qualname__}"
    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        where = folder()
        named = signature.bind(*args, **kwargs).arguments  # every argument by name, in order
        static = {k: v for k, v in named.items() if k in static_argnames}
        dynamic = {k: v for k, v in named.items() if k not in static_argnames}
        leaves, tree = jax.tree_util.tree_flatten(dynamic)
        if where is None or any(isinstance(x, jax.core.Tracer) for x in leaves):
            return jitted(*args, **kwargs)
        leaves = [jax.numpy.asarray(x) for x in leaves]
        avals = [(x.shape, str(x.dtype), bool(getattr(x, "weak_type", False))) for x in leaves]
        flags = (jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision,
                 jax.config.jax_numpy_dtype_promotion, jax.config.jax_numpy_rank_promotion)
        # the source version is the folder's name (folder()), not part of the key
        key = hashlib.sha256(repr((jax.default_backend(), flags, name, str(tree), avals,
                                   sorted((k, repr(v)) for k, v in static.items()))).encode()).hexdigest()[:40]
        if (where, key) not in loaded:
            loaded[where, key] = _load(where, key) or _export(where, key, fn, tree, leaves, static)
        run, out_tree = loaded[where, key]
        return jax.tree_util.tree_unflatten(out_tree, run(*leaves))

    call.jitted = jitted
    return call


def _load(where: Path, key: str):
    import jax

    try:
        exported = jax.export.deserialize(bytearray((where / f"{key}.stablehlo").read_bytes()))
        skeleton = pickle.loads((where / f"{key}.tree").read_bytes())
    except Exception:  # missing, cut short or from an incompatible writer: trace again
        return None
    return jax.jit(exported.call), jax.tree_util.tree_structure(skeleton)


def _export(where: Path, key: str, fn, tree, leaves, static):
    import jax

    out_tree = []

    def flat(*xs):
        out = fn(**jax.tree_util.tree_unflatten(tree, xs), **static)
        leaves_out, structure = jax.tree_util.tree_flatten(out)
        out_tree.append(structure)
        return leaves_out

    exported = jax.export.export(jax.jit(flat))(*leaves)
    structure = out_tree[0]
    try:
        skeleton = pickle.dumps(jax.tree_util.tree_unflatten(structure, [0] * structure.num_leaves))
        if not where.is_dir():
            where.mkdir(parents=True, exist_ok=True)
            _prune(where)
        atomic_write(where / f"{key}.tree", skeleton)
        atomic_write(where / f"{key}.stablehlo", bytes(exported.serialize()))
    except (OSError, pickle.PicklingError, TypeError, AttributeError):
        pass  # a read-only cache or an output that cannot be described: traced again next time
    return jax.jit(exported.call), structure
