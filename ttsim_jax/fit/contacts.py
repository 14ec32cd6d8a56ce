"""Old import path of the racket contacts' state estimation and training arrays, kept for one release.

Its names moved: the model-free estimation of the states around a contact to
:mod:`ttsim_jax.data.contact_states`, the racket residual's training arrays to
:mod:`ttsim_jax.fit.racket_arrays`, the quaternion helpers to :mod:`ttsim_jax.physics.rotations`
and :func:`synthetic_contact_dataset` to :mod:`ttsim_jax.reality.synthetic`. Reading a name here
imports it from there, with a :class:`DeprecationWarning`.
"""

from __future__ import annotations

import importlib
import warnings

_MOVED = {
    **dict.fromkeys(["SKIP_REASONS", "ContactEstimate", "ContactFit", "ObservationIndex", "contact_states",
                     "estimate_contact", "fit_contact_state"], "ttsim_jax.data.contact_states"),
    **dict.fromkeys(["MODEL_INPUTS", "ContactArrays", "contact_arrays", "default_inputs", "draw_contact_states",
                     "model_and_name"], "ttsim_jax.fit.racket_arrays"),
    **dict.fromkeys(["matrix_to_quat", "quat_to_matrix"], "ttsim_jax.physics.rotations"),
    "synthetic_contact_dataset": "ttsim_jax.reality.synthetic",
}


def __getattr__(name: str):
    # importlib, not import statements: the modules the names moved to do not import this one, and
    # nothing here is loaded before a name is read
    if name not in _MOVED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"ttsim_jax.fit.contacts.{name} moved to {_MOVED[name]}.{name}; the old path goes in the next "
                  "release", DeprecationWarning, stacklevel=2)
    return getattr(importlib.import_module(_MOVED[name]), name)


def __dir__():
    return sorted(set(globals()) | set(_MOVED))
