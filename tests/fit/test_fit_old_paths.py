"""The per-segment flight fit and the contact-state estimation moved to the data layer; their old
paths (ttsim_jax.fit.aero, ttsim_jax.fit.contacts) still give every name for one release, with a
DeprecationWarning naming the new home."""

import importlib

import pytest

from ttsim_jax.fit import aero, contacts


@pytest.mark.parametrize("old", [aero, contacts], ids=["aero", "contacts"])
def test_every_old_name_warns_and_is_the_new_object(old):
    for name, home in old._MOVED.items():
        with pytest.warns(DeprecationWarning, match=rf"{old.__name__}\.{name} moved to {home}\.{name}"):
            value = getattr(old, name)
        assert value is getattr(importlib.import_module(home), name), name


def test_from_imports_work_and_unknown_names_fail():
    with pytest.warns(DeprecationWarning):
        from ttsim_jax.fit.contacts import ContactFit, contact_arrays  # noqa: F401
    with pytest.warns(DeprecationWarning):
        from ttsim_jax.fit.aero import dataset_segments, fit_segments  # noqa: F401
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        contacts.nothing  # noqa: B018
    assert {"fit_segments", "synthetic_segments"} <= set(dir(aero))
