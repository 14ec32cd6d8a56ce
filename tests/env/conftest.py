"""Fixtures of the environment tests: the scripts of ``examples/`` loaded as modules, so a test runs
them in its own process and reuses the programs it compiled."""

import importlib.util
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture
def example():
    """``example(name)``: the module of ``examples/NAME.py``."""
    def load(name: str):
        spec = importlib.util.spec_from_file_location(f"examples_{name}", EXAMPLES / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
