"""The in-memory dataset: six column tables of numpy arrays plus metadata.

A table is a plain ``dict`` mapping column name -> 1-D numpy array, all of one length, with the
columns and dtypes of :mod:`ttsim_jax.data.schema`. That is what Parquet stores, what pandas or
polars hand back, and what is cheapest to build from simulation output.

The simplest way to make one from arrays (what the reality generator does)::

    ds = Dataset.from_arrays(
        session_id=sid, t=t, pos=pos,                 # (N,), (N,), (N, 3)
        spin=spin, spin_conf=conf,                    # optional (N, 3), (N,)
        events=dict(session_id=..., t=..., kind=..., pos=...),
        rackets=dict(event_id=..., pos=..., quat=..., vel=..., ang_vel=..., contact=...),
        metadata=Metadata(source="generator v1", equipment={...}),
    )

Segments are derived from the events unless given.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from . import schema
from .errors import DataError
from .tables import (Table, concat_tables, contact_states_table, events_table, fill_defaults,  # noqa: F401
                     rackets_table, select_rows, sessions_table)
from .tables import id_index, rows_of


@dataclasses.dataclass
class Metadata:
    """Dataset-level facts stored next to the tables.

    Attributes:
        source: where the data came from (lab, public dataset and citation, or generator version).
        equipment: free-form description of ball, table, racket, tracking system (JSON-able dict).
        frame: name of the coordinate frame; must be :data:`schema.CANONICAL_FRAME`.
        units: unit of each kind of quantity (:data:`schema.UNITS`).
        schema_version: layout version (:data:`schema.SCHEMA_VERSION`).
        notes: anything else worth keeping (free text), e.g. how the frame was established.
        left_out: {what: count} of what the import mended or left out of the log (frames reordered
            or dropped, segments faster than any ball: :mod:`ttsim_jax.data.glitches`); from schema 1.3.
    """

    source: str = ""
    equipment: dict = dataclasses.field(default_factory=dict)
    frame: str = schema.CANONICAL_FRAME
    units: dict = dataclasses.field(default_factory=lambda: dict(schema.UNITS))
    schema_version: str = schema.SCHEMA_VERSION
    notes: str = ""
    left_out: dict = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-able dict (inverse of :meth:`from_dict`)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], file=None) -> "Metadata":
        """Builds metadata from a dict, naming the unknown key if there is one."""
        known = {f.name for f in dataclasses.fields(cls)}
        for key in d:
            if key not in known:
                raise DataError(f"unknown metadata key; known keys: {sorted(known)}", file=file, column=key)
        return cls(**dict(d))


@dataclasses.dataclass
class Dataset:
    """Measured (or generated) ball data in the canonical frame; the unit passed around.

    Attributes:
        sessions, observations, events, rackets, segments, contact_states: column tables (see
            :mod:`ttsim_jax.data.schema` for columns, dtypes and units); ``contact_states`` is
            empty unless contact states were measured directly.
        metadata: :class:`Metadata`.
    """

    sessions: Table
    observations: Table
    events: Table
    rackets: Table
    segments: Table
    metadata: Metadata = dataclasses.field(default_factory=Metadata)
    contact_states: Table = dataclasses.field(default_factory=lambda: schema.empty_table("contact_states"))
    # indexes built on first use (:meth:`event_rows`, :meth:`segments_around`, :meth:`segment_rows`,
    # :meth:`observation_index`, :meth:`contacts`); a replaced copy starts without them
    _indexes: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)

    def table(self, name: str) -> Table:
        """The table called ``name``."""
        if name not in schema.TABLES:
            raise KeyError(f"unknown table {name!r}; tables: {tuple(schema.TABLES)}")
        return getattr(self, name)

    def tables(self) -> dict[str, Table]:
        """All tables by name, in schema order."""
        return {name: getattr(self, name) for name in schema.TABLES}

    @staticmethod
    def n_rows(table: Table) -> int:
        return len(next(iter(table.values()))) if table else 0

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) observed ball positions [m]."""
        o = self.observations
        return np.stack([o["x"], o["y"], o["z"]], axis=-1)

    @property
    def spins(self) -> np.ndarray:
        """(N, 3) observed spin [rad/s] (zeros where unknown)."""
        o = self.observations
        return np.stack([o["spin_x"], o["spin_y"], o["spin_z"]], axis=-1)

    def _index(self, name, build):
        if name not in self._indexes:
            self._indexes[name] = build()
        return self._indexes[name]

    def _lookup(self, name, keys, wanted) -> np.ndarray:
        """Rows of ``wanted`` ids among ``keys`` (an int column), -1 where absent; the sorted keys
        are kept under ``name``."""
        return rows_of(self._index(name, lambda: id_index(keys)), wanted)

    def event_rows(self, event_ids) -> np.ndarray:
        """(E,) int64 rows of the events table holding ``event_ids``, -1 for an id it does not hold."""
        return self._lookup("event_rows", self.events["event_id"], event_ids)

    def racket_rows(self, event_ids) -> np.ndarray:
        """(E,) int64 rows of the rackets table holding the racket states of ``event_ids``, -1 for an
        event without one."""
        return self._lookup("racket_rows", self.rackets["event_id"], event_ids)

    def segments_around(self, event_ids) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the segments table that end and that start at each event.

        Arguments:
            event_ids: (E,) event ids.

        Returns:
            (in_rows (E,), out_rows (E,)) int64, -1 where no segment ends (starts) at the event.
        """
        seg = self.segments
        ends, starts = (np.asarray(seg[k], np.int64) for k in ("end_event_id", "start_event_id"))
        # a segment without an event at that end has -1 there, which no event id is
        return (self._lookup("segment_ends", np.where(ends >= 0, ends, -2), event_ids),
                self._lookup("segment_starts", np.where(starts >= 0, starts, -2), event_ids))

    def segment_rows(self, segment_ids=None) -> list[np.ndarray]:
        """The observation rows of each segment, in time order.

        Arguments:
            segment_ids: the segments (default: every row of the segments table, in its order).

        Returns:
            One int array per segment (empty for a segment without observations).
        """
        ids = self.segments["segment_id"] if segment_ids is None else segment_ids
        order, sorted_ids = self.observations_by_segment()
        lo = np.searchsorted(sorted_ids, ids, side="left")
        hi = np.searchsorted(sorted_ids, ids, side="right")
        return [order[a:b] for a, b in zip(lo, hi)]

    def observations_by_segment(self) -> tuple[np.ndarray, np.ndarray]:
        """(order, sorted segment ids): the observation rows sorted by segment, time order kept
        within each, and their segment ids in that order (built once)."""
        def build():
            order = np.argsort(self.observations["segment_id"], kind="stable")  # keeps time order within a segment
            return order, np.asarray(self.observations["segment_id"])[order]
        return self._index("by_segment", build)

    def observation_index(self):
        """The observations grouped by segment, to look up a segment's samples next to a contact
        (:class:`~ttsim_jax.data.contact_states.ObservationIndex`, built once)."""
        from .contact_states import ObservationIndex

        return self._index("observation_index", lambda: ObservationIndex(self))

    def contacts(self, fit=None, progress=None):
        """Every table and racket contact's measured states, estimated from the observations once
        per :class:`~ttsim_jax.data.contact_states.ContactFit` (default ``ContactFit()``): the
        :class:`~ttsim_jax.data.contact_states.Contacts` that evaluate, fit and diagnose read.
        ``progress``: optional ``progress(done, total)`` while they are estimated."""
        from .contact_states import ContactFit, Contacts

        fit = ContactFit() if fit is None else fit
        return self._index(("contacts", fit), lambda: Contacts.estimate(self, fit, progress))

    def replace(self, **changes) -> "Dataset":
        """A copy with some tables (or the metadata) replaced."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_arrays(
        cls,
        session_id,
        t,
        pos,
        *,
        spin=None,
        spin_conf=None,
        events: Mapping[str, Any] | None = None,
        rackets: Mapping[str, Any] | None = None,
        sessions: Mapping[str, Any] | None = None,
        segments: Mapping[str, Any] | str | None = "events",
        metadata: Metadata | None = None,
        contact_states: Mapping[str, Any] | None = None,
    ) -> "Dataset":
        """Builds a dataset from numpy arrays, filling every optional column with its default.

        Arguments:
            session_id: (N,) int session of each observation; rows of one session must be
                contiguous and in time order.
            t: (N,) times [s].
            pos: (N, 3) ball centre positions [m], canonical frame.
            spin: optional (N, 3) spin [rad/s]; zeros when absent.
            spin_conf: optional (N,) confidence in [0, 1]; 1 where ``spin`` is given, else 0.
            events: optional dict with ``session_id`` (E,), ``t`` (E,), ``kind`` (E,) strings from
                :data:`schema.EVENT_KINDS`, ``pos`` (E, 3) ball centre at contact, and optionally
                ``event_id`` (E,) (default ``0..E-1``).
            rackets: optional dict of racket states, one per racket event: ``pos`` (R, 3),
                ``quat`` (R, 4) (w, x, y, z), ``vel`` (R, 3), ``ang_vel`` (R, 3), ``contact`` (R, 2)
                (d_y, d_z), and optionally ``event_id`` (R,) (default: the racket events in order) and
                ``config`` (R,) racket configuration names.
            sessions: optional dict with ``session_id`` and optional ``name``, ``notes`` (default:
                one row per distinct ``session_id``).
            segments: ``"events"`` to split each session at its events (default), ``None`` for no
                segments, or a segments column table.
            metadata: :class:`Metadata` (default: empty source, canonical frame).
            contact_states: optional dict of directly measured contact states
                (:func:`~ttsim_jax.data.tables.contact_states_table`'s arguments).

        Returns:
            The dataset (not yet validated: call :func:`ttsim_jax.data.validate.validate`).
        """
        session_id = np.asarray(session_id, np.int64)
        t = np.asarray(t, np.float64)
        pos = np.asarray(pos, np.float64).reshape(-1, 3)
        n = len(session_id)
        if len(t) != n or len(pos) != n:
            raise ValueError(f"session_id, t and pos must have the same length, got {n}, {len(t)}, {len(pos)}")
        obs = {"session_id": session_id, "t": t, "x": pos[:, 0].copy(), "y": pos[:, 1].copy(), "z": pos[:, 2].copy()}
        if spin is None:
            spin_arr = np.zeros((n, 3))
            conf = np.zeros(n) if spin_conf is None else np.asarray(spin_conf, np.float64)
        else:
            spin_arr = np.asarray(spin, np.float64).reshape(n, 3)
            conf = np.ones(n) if spin_conf is None else np.asarray(spin_conf, np.float64)
        obs.update(spin_x=spin_arr[:, 0].copy(), spin_y=spin_arr[:, 1].copy(), spin_z=spin_arr[:, 2].copy())
        obs["spin_conf"] = np.broadcast_to(conf, (n,)).astype(np.float64)
        obs["segment_id"] = np.full(n, -1, np.int64)

        ev = events_table(**events) if events is not None else schema.empty_table("events")
        if rackets is not None:
            rackets = dict(rackets)
            if "event_id" not in rackets:
                rackets["event_id"] = ev["event_id"][ev["kind"] == "racket"]
            rk = rackets_table(**rackets)
        else:
            rk = schema.empty_table("rackets")

        if sessions is None:
            ids = np.unique(np.concatenate([session_id, ev["session_id"]]))
            ses = {"session_id": ids, "name": np.full(len(ids), "", object), "notes": np.full(len(ids), "", object)}
        else:
            ses = sessions_table(**sessions)

        ds = cls(
            sessions=ses,
            observations=obs,
            events=ev,
            rackets=rk,
            segments=schema.empty_table("segments"),
            metadata=metadata if metadata is not None else Metadata(),
            contact_states=(contact_states_table(**contact_states) if contact_states is not None
                            else schema.empty_table("contact_states")),
        )
        if isinstance(segments, str):
            if segments != "events":
                raise ValueError(f"segments must be 'events', None or a table, got {segments!r}")
            from .event_segments import segments_from_events

            ds = segments_from_events(ds)
        elif segments is not None:
            seg = fill_defaults("segments", segments)
            ds = ds.replace(segments=seg)
        return ds
