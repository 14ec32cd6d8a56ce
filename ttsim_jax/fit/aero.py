"""Old import path of the per-segment flight fit, kept for one release.

The fit moved to the data layer, where the segment filter uses it too:
:mod:`ttsim_jax.data.flightfit` (the fit), :mod:`ttsim_jax.data.segment_batches` (a dataset's
segments as padded arrays) and :mod:`ttsim_jax.data.synthetic_segments`. Reading a name here
imports it from there, with a :class:`DeprecationWarning`.
"""

from __future__ import annotations

import importlib
import warnings

_MOVED = {
    **dict.fromkeys(["CD_0", "CM_0", "COMPILER_OPTIONS", "ITERATIONS", "PARAMS", "TOL", "Air", "SegmentFits",
                     "default_air", "fit_batch", "fit_one", "fit_segments", "initial_guess", "integrate",
                     "jacobian", "normal_equations", "residual", "summarize", "trajectory"],
                    "ttsim_jax.data.flightfit"),
    **dict.fromkeys(["BATCH", "CAPACITIES", "GROUP", "balanced_rows", "batches", "capacity", "dataset_segments",
                     "grouped_batches", "pack"], "ttsim_jax.data.segment_batches"),
    "synthetic_segments": "ttsim_jax.data.synthetic_segments",
}


def __getattr__(name: str):
    if name not in _MOVED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"ttsim_jax.fit.aero.{name} moved to {_MOVED[name]}.{name}; the old path goes in the next release",
                  DeprecationWarning, stacklevel=2)
    return getattr(importlib.import_module(_MOVED[name]), name)


def __dir__():
    return sorted(set(globals()) | set(_MOVED))
