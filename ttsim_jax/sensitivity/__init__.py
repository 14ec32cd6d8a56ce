"""Sensitivity studies: Jacobians of a shot's landing (and other targets) against every model
parameter and input state through the rally kernel, error budgets and their reports.

Modules: ``cases`` (the shots), ``targets`` (what is differentiated), ``jacobians`` (reverse and
forward mode, finite differences, local-gradient flags), ``budgets`` (linear and Monte Carlo error
budgets), ``report`` (tables, figures, JSON), ``study`` (a whole study, as ``ttsim sensitivity``).

The face: ``run_study(StudyConfig(...), out)``.
"""

from ttsim_jax.lazy import exports

_NAMES = dict.fromkeys(["run_study", "StudyConfig"], "ttsim_jax.sensitivity.study")
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = list(_NAMES)
