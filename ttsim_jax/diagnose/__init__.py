"""Sim-to-real gap diagnosis (``ttsim diagnose``): where a model's errors lie by phase and regime,
which effect of the catalogue explains them, and how far the gap shrinks with it.

Modules: :mod:`~ttsim_jax.diagnose.phases` (the measured items), :mod:`~ttsim_jax.diagnose.stages`
(differentiable per-phase errors), :mod:`~ttsim_jax.diagnose.where`,
:mod:`~ttsim_jax.diagnose.candidates`, :mod:`~ttsim_jax.diagnose.residuals`,
:mod:`~ttsim_jax.diagnose.diagnosis` (the whole run), :mod:`~ttsim_jax.diagnose.result` (what it
returns), :mod:`~ttsim_jax.diagnose.report`;
``ttsim diagnose`` is :mod:`ttsim_jax.cli.diagnose`.

The face: ``diagnose(ds, model, Settings(...)) -> Diagnosis`` (the whole run; its ``verdict`` a
``Verdict``), ``NoData`` (what it raises on a record it cannot diagnose) and ``write_report`` (its
files).
"""

from ttsim_jax.lazy import exports

_NAMES = {**dict.fromkeys(["diagnose", "Settings", "NoData"], "ttsim_jax.diagnose.diagnosis"),
          "Diagnosis": "ttsim_jax.diagnose.result", "Verdict": "ttsim_jax.diagnose.verdict",
          "write_report": "ttsim_jax.diagnose.report"}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = list(_NAMES)
