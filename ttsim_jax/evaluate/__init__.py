"""Metrics and summaries of simulated or measured rallies.

The face: ``evaluate_models(ds, models, EvaluateSettings(...))`` (``ttsim evaluate`` from Python:
the flight, table, racket and landing stages of :mod:`.stages`) and ``write_report`` (its files).
"""

from ttsim_jax.lazy import exports

_NAMES = {**dict.fromkeys(["evaluate_models", "EvaluateSettings"], "ttsim_jax.evaluate.stages"),
          "write_report": "ttsim_jax.evaluate.report"}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = list(_NAMES)
