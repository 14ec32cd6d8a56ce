"""What the analysis layers' typed results share: :class:`Skipped`, :class:`ItemArrays` and
:func:`jsonable`.

A stage of ``ttsim evaluate`` (or the flight scoring of ``ttsim fit``) returns either its typed
per-item result, an :class:`ItemArrays` dataclass, or :class:`Skipped` with the reason it could not
run; both have ``to_json()``. Callers ask ``isinstance(stage, Skipped)`` where they once looked for a
``"skipped"`` key.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np


@dataclasses.dataclass(frozen=True)
class Skipped:
    """A stage that did not run.

    Attributes:
        reason: why, in words a reader of the report can act on (the data it lacked, how many
            items were unusable and for which reasons).
    """

    reason: str

    def to_json(self) -> dict:
        """``{"skipped": reason}``: what a report's JSON holds for the stage."""
        return {"skipped": self.reason}


def jsonable(obj, *, finite: bool = False):
    """``obj`` with numpy and JAX values turned into plain Python.

    Arguments:
        obj: dicts, lists, tuples, arrays and scalars, nested.
        finite: replace NaN and infinities by None (JSON without ``NaN``, which strict readers
            refuse); by default they stay floats.
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v, finite=finite) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, finite=finite) for v in obj]
    if isinstance(obj, (np.ndarray, jax.Array)):
        a = np.asarray(obj).tolist()
        return jsonable(a, finite=True) if finite else a
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        obj = obj.item()
    if finite and isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


class ItemArrays:
    """Mixin of a dataclass of per-item arrays: fields that are arrays (one row per item), dicts
    {model name: array}, counts and flags. The dataclass's fields are its documented content."""

    def to_json(self) -> dict:
        """Every field, JSON-ready: arrays as (nested) lists, non-finite values as None."""
        return jsonable({f.name: getattr(self, f.name) for f in dataclasses.fields(self)}, finite=True)

    def arrays(self) -> dict:
        """The per-item arrays, flat: ``{quantity: array}`` and ``{quantity/model: array}`` for the
        dict fields of arrays (what ``samples.npz`` holds under the stage's name); counts and flags
        are left out, and so are dicts of counts (``skip_counts``: {reason: count})."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, dict):
                for name, arr in value.items():
                    if isinstance(arr, (np.ndarray, jax.Array)):
                        out[f"{f.name}/{name}"] = np.asarray(arr)
            elif isinstance(value, np.ndarray):
                out[f.name] = value.astype(str) if value.dtype == object else value
        return out
