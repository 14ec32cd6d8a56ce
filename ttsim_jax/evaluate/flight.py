"""Old import path of :mod:`ttsim_jax.fit.flight` (kept for one release; import from there)."""

import warnings

from ttsim_jax.fit.flight import ITERATIONS, flight_rmse, segment_rmse  # noqa: F401 (the names of this path)

warnings.warn("ttsim_jax.evaluate.flight moved to ttsim_jax.fit.flight", DeprecationWarning, stacklevel=2)
