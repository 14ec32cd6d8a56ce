"""Every name a benchmark script or an example imports from the package exists: the benchmarks
import inside their ``main`` (so ``--help`` stays fast), where a name moved or renamed in the
package would only fail when the benchmark is next run, minutes in."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted(REPO.glob("benchmarks/*.py")) + sorted(REPO.glob("examples/*.py"))


def package_imports(path: Path) -> list[tuple[int, str, str]]:
    """(line, module, name) of every ``from ttsim_jax... import name`` in a script, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and \
                node.module.split(".")[0] == "ttsim_jax":
            out += [(node.lineno, node.module, alias.name) for alias in node.names]
    return out


def test_the_benchmarks_import_from_the_package():
    assert len(BENCHMARKS) >= 20 and sum(len(package_imports(p)) for p in BENCHMARKS) >= 50


@pytest.mark.parametrize("path", BENCHMARKS, ids=[str(p.relative_to(REPO)) for p in BENCHMARKS])
def test_every_name_a_benchmark_imports_exists(path):
    missing = []
    for line, module, name in package_imports(path):
        mod = importlib.import_module(module)
        if not hasattr(mod, name):
            try:  # a submodule imported by name
                importlib.import_module(f"{module}.{name}")
            except ImportError:
                missing.append(f"{path.relative_to(REPO)}:{line}: {module} has no {name}")
    assert not missing, "\n".join(missing)
