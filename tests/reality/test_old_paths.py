"""The generator's old import paths still give its names for one release, with a DeprecationWarning."""

import importlib
import sys

import pytest

from ttsim_jax import reality
from ttsim_jax.physics import rotations
from ttsim_jax.reality import config, game, strokes


def test_the_old_generator_module_warns_and_gives_the_same_objects(monkeypatch):
    monkeypatch.delitem(sys.modules, "ttsim_jax.data.generator", raising=False)  # import it afresh
    with pytest.warns(DeprecationWarning, match=r"ttsim_jax\.data\.generator moved to ttsim_jax\.reality"):
        old = importlib.import_module("ttsim_jax.data.generator")
    homes = (reality, config, strokes, game, rotations)
    for name in old.__all__:
        home = next(m for m in homes if hasattr(m, name))
        assert getattr(old, name) is getattr(home, name), name
    assert {"generate", "make_config", "write", "load_truth", "GeneratorError", "matrix_to_quat"} <= set(old.__all__)


def test_the_synthetic_contact_dataset_keeps_its_old_path():
    with pytest.warns(DeprecationWarning, match="synthetic_contact_dataset"):
        from ttsim_jax.fit.contacts import synthetic_contact_dataset
    assert synthetic_contact_dataset is reality.synthetic_contact_dataset
