"""Identification of each physics stage's parameters from data (one module per stage).

The face: ``fit_dataset`` (``ttsim fit`` from Python: :mod:`.pipeline`, with ``FitSettings``,
``FitResult`` and ``write_fit``), the per-segment flight fit (``fit_segments``, :mod:`.flightfit`;
the paper's segment filter ``filter_segments``), the latent spin of a segment and across a bounce
(``fit_latent_spin``, ``fit_bounce_spin`` and their dataset forms) and the spin check of a record
(``check_spin``, ``check_record_spin``).
"""

from ttsim_jax.lazy import exports

_NAMES = {**dict.fromkeys(["fit_dataset", "FitSettings", "FitResult", "write_fit"], "ttsim_jax.fit.pipeline"),
          **dict.fromkeys(["fit_segments", "SegmentFits"], "ttsim_jax.fit.flightfit"),
          "filter_segments": "ttsim_jax.fit.segment_filter",
          **dict.fromkeys(["fit_latent_spin", "dataset_latent_spin", "LatentSpin"], "ttsim_jax.fit.latent_spin"),
          **dict.fromkeys(["fit_bounce_spin", "dataset_bounce_spin", "BounceSpin"], "ttsim_jax.fit.bounce_spin"),
          **dict.fromkeys(["check_spin", "check_record_spin", "SpinCheck"], "ttsim_jax.fit.spin_check")}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = list(_NAMES)
