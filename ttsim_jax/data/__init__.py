"""Measured-data layer: format, validation, segmentation, importers and JAX batches.

Main entry points::

    from ttsim_jax.data import Dataset, load, save, validate, import_source
    from ttsim_jax.data import detect_events, filter_segments, segment_batch, iter_segment_batches

See ``docs/data_format.md`` for the format.
"""

from .batch import (
    EventBatch,
    RacketContactBatch,
    SegmentBatch,
    event_batch,
    iter_segment_batches,
    racket_contact_batch,
    segment_batch,
)
from .csvlog import read_csv, write_csv
from .dataset import Dataset, Metadata
from .errors import DataError
from .importers import import_source
from .io import load, save
from .schema import BALL_RADIUS, CANONICAL_FRAME, EVENT_KINDS, SCHEMA_VERSION
from .segment import FilterReport, detect_events, filter_segments, find_bounces, segments_from_events
from .validate import problems, validate

__all__ = [
    "BALL_RADIUS",
    "CANONICAL_FRAME",
    "DataError",
    "Dataset",
    "EVENT_KINDS",
    "EventBatch",
    "FilterReport",
    "Metadata",
    "RacketContactBatch",
    "SCHEMA_VERSION",
    "SegmentBatch",
    "detect_events",
    "event_batch",
    "filter_segments",
    "find_bounces",
    "import_source",
    "iter_segment_batches",
    "load",
    "problems",
    "racket_contact_batch",
    "read_csv",
    "write_csv",
    "save",
    "segment_batch",
    "segments_from_events",
    "validate",
]
