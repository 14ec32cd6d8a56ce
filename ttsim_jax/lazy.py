"""Lazy package exports: a package's public names are imported on first use.

``import ttsim_jax`` (and so every ``ttsim`` command, before it has checked its arguments) must not
pay for importing JAX, XLA and the kernel; a name such as ``ttsim_jax.rollout`` imports its module
when it is first read (PEP 562).
"""

from __future__ import annotations

import importlib
import importlib.util


def exports(package: str, names: dict[str, str]):
    """``(__getattr__, __dir__)`` for a package whose public ``names`` map to the modules holding them.

    Arguments:
        package: the package's ``__name__``.
        names: ``{public name: absolute module name}``.

    Returns:
        The two module-level functions to assign in the package's ``__init__``.
    """
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str):
        if name not in names:
            # a subpackage read as an attribute (``ttsim_jax.kernel``) is imported as an eager
            # package's would have been
            if not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}") is not None:
                return importlib.import_module(f"{package}.{name}")
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(names[name]), name)
        namespace[name] = value  # later reads skip this function
        return value

    def __dir__():
        return sorted(set(namespace) | set(names))

    return __getattr__, __dir__
