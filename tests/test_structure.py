"""The package's layout: the data flow runs one way.

Read from the source (``ast``), every import counted, those inside functions too (a lazy import is
still an arrow): no import cycle among ``ttsim_jax`` modules, no private name imported across
packages, no module over 600 lines, and no package importing one of a higher layer. And
``import ttsim_jax`` stays light: no gymnasium, no environment module.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "ttsim_jax"
MAX_LINES = 600

# Lowest first; a package may import its own layer and those below it. A top-level module is its
# own "package" here.
LAYERS = (
    ("lazy", "registration", "sizes", "errors", "results", "files", "bundled"),
    ("physics", "state"),
    ("effects", "params"),
    ("data",),
    ("kernel", "shots", "policies", "plots"),
    ("reality", "fit"),
    ("evaluate", "sensitivity", "env"),
    ("diagnose", "rl"),
    ("cli",),
)
LAYER = {name: i for i, names in enumerate(LAYERS) for name in names}
# Modules whose arrows may run up: none since the old import paths of 0.1.0 went.
SHIMS: set[str] = set()


def modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def faces(mods: dict[str, Path]) -> dict[str, dict[str, str]]:
    """{package: {public name: module}} of the packages whose ``__init__`` exports names lazily
    (``ttsim_jax.lazy.exports``), read from their ``_NAMES``: an import of such a name is an arrow
    to the module that holds it, not to the package's face."""
    import importlib

    out = {}
    for name, path in mods.items():
        if path.name == "__init__.py" and "exports(__name__" in path.read_text():
            out[name] = dict(importlib.import_module(name)._NAMES)
    return out


def imports(mods: dict[str, Path]):
    """(edges, names): module -> modules it imports, and (importer, module, name) per imported name.

    A name imported from a package's lazy face (the root's included) counts as imported from the
    module that holds it (:func:`faces`)."""
    face = faces(mods)
    edges, names = defaultdict(set), []
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    source = ".".join(base + ([node.module] if node.module else []))
                else:
                    source = node.module or ""
                if not source.startswith("ttsim_jax"):
                    continue
                for alias in node.names:
                    target = f"{source}.{alias.name}"
                    held = face.get(source, {}).get(alias.name)
                    edges[name].add(target if target in mods else held if held in mods else source)
                    names.append((name, source, alias.name))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name in mods:
                        edges[name].add(alias.name)
    return edges, names


def package_of(module: str) -> str:
    """The first-level package (or top-level module) a module belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "<root>"


def cycles(edges) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], [0]
    for root in list(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter[0]
                    counter[0] += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    component.append(top)
                    if top == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


MODS = modules()
EDGES, NAMES = imports(MODS)


def test_no_import_cycle():
    found = cycles(EDGES)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_no_private_name_imported_across_packages():
    crossing = sorted({f"{importer} imports {source}.{name}" for importer, source, name in NAMES
                       if name.startswith("_") and not name.startswith("__")
                       and package_of(importer) != package_of(source)})
    assert not crossing, "\n".join(crossing)


def test_no_module_over_600_lines():
    long = sorted((len(p.read_text().splitlines()), name) for name, p in MODS.items()
                  if len(p.read_text().splitlines()) > MAX_LINES)
    assert not long, ", ".join(f"{name} ({n} lines)" for n, name in long)


def parameter_counts(tree: ast.AST):
    """(name, line, count) of every function in ``tree``; ``*args`` and ``**kwargs`` count one each."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            yield node.name, node.lineno, (len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
                                           + (a.vararg is not None) + (a.kwarg is not None))


def test_no_kernel_function_takes_more_than_10_parameters():
    """The kernel's stages pass named states and option values (``StepState``, ``Record``,
    ``Execution``, the fused path's ``Drive``), not loose arguments; ``rollout`` and ``simulate``
    take at most 10."""
    wide = sorted(f"{name}.{fn} (line {line}: {n})" for name, p in MODS.items() if name.startswith("ttsim_jax.kernel.")
                  for fn, line, n in parameter_counts(ast.parse(p.read_text())) if n > 10)
    assert any(name.startswith("ttsim_jax.kernel.") for name in MODS)
    assert not wide, ", ".join(wide)
    counted = {fn: n for fn, _, n in parameter_counts(ast.parse("def f(a, b=1, *c, d, **e): pass"))}
    assert counted == {"f": 5}


def test_every_package_has_a_layer_and_no_arrow_runs_up():
    unplaced = sorted({package_of(m) for m in MODS} - set(LAYER) - {"<root>"})
    assert not unplaced, f"packages without a layer in LAYERS: {unplaced}"
    upward = sorted({f"{package_of(a)} -> {package_of(b)} ({a} imports {b})" for a, targets in EDGES.items()
                     for b in targets if a not in SHIMS and package_of(a) != "<root>" and package_of(b) != "<root>"
                     and LAYER[package_of(b)] > LAYER[package_of(a)]})
    assert not upward, "\n".join(upward)


def test_every_layer_name_is_a_package_or_module():
    present = {package_of(m) for m in MODS} - {"<root>"}
    stale = sorted(set(LAYER) - present)
    assert not stale, f"names in LAYERS that are no package or module of ttsim_jax: {stale}"


def test_every_name_of_a_face_is_its_modules():
    """Each lazily exported name is defined in the module its face names, and a name that is also a
    submodule's (``ttsim_jax.data.validate``) is still the object once that submodule is imported
    (the import system sets the package's attribute to the module: the face must bind it eagerly)."""
    import importlib
    import inspect

    wrong = []
    for package, names in faces(MODS).items():
        for name, module in names.items():
            if name not in vars(importlib.import_module(module)):
                wrong.append(f"{package}.{name}: not in {module}")
            if f"{package}.{name}" in MODS:
                importlib.import_module(f"{package}.{name}")
                if inspect.ismodule(getattr(importlib.import_module(package), name)):
                    wrong.append(f"{package}.{name}: the submodule replaces the name")
    assert not wrong, wrong


def test_a_name_from_a_lazy_face_is_an_arrow_to_its_module():
    """``from ttsim_jax import load_model`` in a package is an arrow to the module holding it (the
    root's face would hide it from the layer check)."""
    held = faces(MODS)["ttsim_jax"]["load_model"]
    importers = [a for a, _, n in NAMES if n == "load_model"]
    assert importers and all(held in EDGES[a] for a in importers if a != "ttsim_jax")


def test_the_checks_see_a_cycle_and_an_upward_arrow():
    """The checks themselves: a made-up graph with a cycle is caught."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    assert LAYER["cli"] > LAYER["kernel"] > LAYER["physics"]


def test_import_ttsim_jax_is_light_and_gymnasium_still_finds_the_environment():
    code = ("import sys, ttsim_jax\n"
            "heavy = sorted(m for m in sys.modules if m.split('.')[0] == 'gymnasium' or m.startswith('ttsim_jax.env'))\n"
            "assert not heavy, heavy\n"
            "import gymnasium\n"
            "assert 'ttsim/ReturnBall-v0' in gymnasium.registry\n"
            "assert not any(m.startswith('ttsim_jax.env') for m in sys.modules)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
