"""Metrics and summaries of simulated or measured rallies.

The face: ``evaluate_models(ds, models, EvaluateSettings(...)) -> Evaluation`` (``ttsim evaluate``
from Python: the flight, table, racket and landing stages of :mod:`.stages`, each a typed result
of :mod:`.result` or a ``Skipped`` with the reason) and ``write_report`` (its files).
"""

from ttsim_jax.lazy import exports

_NAMES = {**dict.fromkeys(["evaluate_models", "EvaluateSettings"], "ttsim_jax.evaluate.stages"),
          **dict.fromkeys(["Evaluation", "TableStage", "RacketStage", "LandingStage"], "ttsim_jax.evaluate.result"),
          "FlightStage": "ttsim_jax.fit.flight", "Skipped": "ttsim_jax.results",
          "write_report": "ttsim_jax.evaluate.report"}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = list(_NAMES)
