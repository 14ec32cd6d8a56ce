"""Measured-data layer: format, validation, segmentation, importers and JAX batches.

Main entry points::

    from ttsim_jax.data import Dataset, load, save, validate, import_source
    from ttsim_jax.data import detect_events, segment_batch, iter_segment_batches

The flight fit and the paper's segment filter that runs it are in :mod:`ttsim_jax.fit`
(``ttsim_jax.fit.segment_filter.filter_segments``).

See ``docs/data_format.md`` for the format.
"""

from ttsim_jax.lazy import exports

_NAMES = {
    **dict.fromkeys(["EventBatch", "RacketContactBatch", "SegmentBatch", "event_batch", "iter_segment_batches",
                     "racket_contact_batch", "segment_batch"], "ttsim_jax.data.batch"),
    **dict.fromkeys(["read_csv", "write_csv"], "ttsim_jax.data.csvlog"),
    **dict.fromkeys(["Dataset", "Metadata"], "ttsim_jax.data.dataset"),
    **dict.fromkeys(["DataError", "DataWarning"], "ttsim_jax.data.errors"),
    **dict.fromkeys(["import_source"], "ttsim_jax.data.importers"),
    **dict.fromkeys(["load", "save"], "ttsim_jax.data.io"),
    **dict.fromkeys(["BALL_RADIUS", "CANONICAL_FRAME", "EVENT_KINDS", "SCHEMA_VERSION"], "ttsim_jax.data.schema"),
    **dict.fromkeys(["detect_events", "find_bounces", "segments_from_events"], "ttsim_jax.data.segment"),
    **dict.fromkeys(["problems", "validate"], "ttsim_jax.data.validate"),
}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = sorted(_NAMES)

# ``validate`` is also the name of a submodule: once that is imported, the import system sets the
# package's attribute to the module and ``__getattr__`` is never asked again, so ``from
# ttsim_jax.data import validate`` would give the module. Bound here, the function stays (cheap:
# numpy only).
from .validate import validate  # noqa: E402
