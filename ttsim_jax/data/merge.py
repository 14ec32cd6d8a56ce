"""Several datasets as one: ids renumbered so that nothing collides.

Sessions, events and segments of each dataset keep their ids plus an offset (the ids taken by the
datasets before it), so the rows that referred to each other still do, and a session id of the
merged dataset tells which dataset it came from (:func:`id_offsets`). Session names get the
dataset's label as a prefix (``"spindoe/012"``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from . import schema
from .dataset import Dataset, Metadata, concat_tables
from .errors import DataError

#: id column -> (table, column) pairs that hold it; -1 ("none") is kept as it is.
_REFERENCES = {
    "session_id": (("sessions", "session_id"), ("observations", "session_id"), ("events", "session_id"),
                   ("segments", "session_id")),
    "event_id": (("events", "event_id"), ("rackets", "event_id"), ("segments", "start_event_id"),
                 ("segments", "end_event_id"), ("contact_states", "event_id")),
    "segment_id": (("segments", "segment_id"), ("observations", "segment_id")),
}


def id_offsets(datasets: Sequence[Dataset]) -> list[dict]:
    """Per dataset, the offset added to its session, event and segment ids by :func:`merge_datasets`.

    Arguments:
        datasets: the datasets, in merge order.

    Returns:
        One dict per dataset: ``{"session_id": k, "event_id": k, "segment_id": k}``.
    """
    out, start = [], dict.fromkeys(_REFERENCES, 0)
    for ds in datasets:
        out.append(dict(start))
        for kind, places in _REFERENCES.items():
            ids = [np.asarray(ds.table(t)[c]) for t, c in places]
            top = max((int(a.max()) for a in ids if len(a)), default=-1)
            low = min((int(a[a >= 0].min()) for a in ids if np.any(a >= 0)), default=0)
            if low < 0:  # cannot happen for a validated dataset; a negative id would collide
                raise DataError(f"negative {kind} {low}", table=places[0][0], column=kind)
            start[kind] += top + 1
    return out


def merge_datasets(datasets: Sequence[Dataset], labels: Sequence[str] | None = None) -> Dataset:
    """One dataset holding every row of ``datasets``, ids offset (see the module docstring).

    Arguments:
        datasets: datasets in the canonical frame (at least one).
        labels: a name per dataset, prefixed to its session names and listed in the merged
            metadata's source (default ``"0"``, ``"1"``, ...).

    Returns:
        The merged :class:`Dataset` (a single dataset is returned as it is).
    """
    datasets = list(datasets)
    if not datasets:
        raise ValueError("merge_datasets: no dataset given")
    labels = [str(k) for k in range(len(datasets))] if labels is None else [str(x) for x in labels]
    if len(labels) != len(datasets):
        raise ValueError(f"merge_datasets: {len(labels)} labels for {len(datasets)} datasets")
    if len(datasets) == 1:
        return datasets[0]
    frames = {ds.metadata.frame for ds in datasets}
    if len(frames) > 1:
        raise DataError(f"the datasets are in different frames {sorted(frames)}; import them into "
                        f"{schema.CANONICAL_FRAME!r}")
    shifted = {name: [] for name in schema.TABLES}
    for ds, off, label in zip(datasets, id_offsets(datasets), labels):
        tables = {name: dict(table) for name, table in ds.tables().items()}
        for kind, places in _REFERENCES.items():
            for t, c in places:
                a = np.asarray(tables[t][c], np.int64)
                tables[t][c] = np.where(a >= 0, a + off[kind], a)
        names = np.asarray(tables["sessions"]["name"], object)
        tables["sessions"]["name"] = np.array([f"{label}/{n}" if n else label for n in names], object)
        for name, table in tables.items():
            shifted[name].append(table)
    meta = Metadata(source="; ".join(f"{label}: {ds.metadata.source}" for ds, label in zip(datasets, labels)),
                    equipment={label: ds.metadata.equipment for ds, label in zip(datasets, labels)},
                    frame=datasets[0].metadata.frame, units=dict(datasets[0].metadata.units),
                    schema_version=datasets[0].metadata.schema_version,
                    notes="merged: " + ", ".join(labels))
    return Dataset(**{name: concat_tables(parts, name) for name, parts in shifted.items()}, metadata=meta)
