"""Column definitions of the measured-data format (tables, dtypes, units) and its version.

A dataset is six tables (see ``docs/data_format.md``):

* ``sessions``: one row per recording session (a continuous stream of observations).
* ``observations``: ball positions over time, optional spin with a confidence, and the flight
  segment each sample belongs to.
* ``events``: labelled contacts (table, racket, net, out, other) that split a session into segments.
* ``rackets``: the racket state at each racket contact event.
* ``segments``: flight segments, the spans between consecutive events, with their spin.
* ``contact_states``: the ball's state just before and just after a contact where it was measured
  directly (a racket-bounce rig, a tracker that writes states), instead of estimated from the
  observations (optional: datasets written before schema 1.2 read it as empty).

Everything is SI and in the canonical world frame: origin at the centre of the table's playing
surface, x along the table's length, y across, z up; a ball resting on the table has z = 0.02.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ttsim_jax.physics.dimensions import FLOOR_Z, NET_HEIGHT, TABLE_LENGTH, TABLE_WIDTH  # noqa: F401 (public here too)

#: Version of the on-disk layout, "MAJOR.MINOR". A reader accepts files with the same major version;
#: a newer minor version may only add optional columns or tables (which older readers ignore, and which
#: a newer reader fills with their defaults, or reads as empty, in older files) or metadata keys.
#: 1.1 added the dataset id and page checksums (docs/data_format.md, "Integrity"); 1.2 the
#: ``contact_states`` table and the rackets' ``config`` column; 1.3 the metadata's ``left_out``
#: counts (what the import mended or left out); 1.4 the SHA-256 of every file and of the metadata itself.
SCHEMA_VERSION = "1.4"

#: Name written into every dataset's metadata; data in any other frame must be converted first.
CANONICAL_FRAME = "ttsim-table-centre-v1"
FRAME_DESCRIPTION = (
    f"origin at the centre of the table's playing surface; x along the table's length ({TABLE_LENGTH} m), "
    f"y across ({TABLE_WIDTH} m), z up; table surface at z = 0, floor at z = {FLOOR_Z}; net at x = 0, "
    f"{NET_HEIGHT} m high; right-handed"
)

BALL_RADIUS = 0.02

#: Event kinds, in the order of their integer codes in JAX batches.
EVENT_KINDS = ("table", "racket", "net", "out", "other")
EVENT_CODES = {kind: code for code, kind in enumerate(EVENT_KINDS)}

UNITS = {
    "length": "m",
    "time": "s",
    "velocity": "m/s",
    "angular_velocity": "rad/s",
    "orientation": "unit quaternion (w, x, y, z), racket frame -> world frame",
}


@dataclasses.dataclass(frozen=True)
class Column:
    """One column of a table.

    Attributes:
        name: column name as in the Parquet file and the in-memory table.
        dtype: ``"int64"``, ``"float64"`` or ``"string"``.
        unit: physical unit ("" when dimensionless).
        doc: meaning, one line.
        default: value used when a builder is not given the column; ``None`` for required columns.
    """

    name: str
    dtype: str
    unit: str
    doc: str
    default: object = None

    @property
    def required(self) -> bool:
        return self.default is None

    @property
    def numpy_dtype(self):
        return {"int64": np.int64, "float64": np.float64, "string": object}[self.dtype]


def _xyz(prefix: str, unit: str, doc: str, default=None) -> tuple[Column, ...]:
    return tuple(Column(f"{prefix}{a}", "float64", unit, f"{doc}, {a} component", default) for a in "xyz")


SESSIONS = (
    Column("session_id", "int64", "", "unique id of the session"),
    Column("name", "string", "", "human-readable label, e.g. the original file", ""),
    Column("notes", "string", "", "free text, e.g. launcher settings as JSON", ""),
)

OBSERVATIONS = (
    Column("session_id", "int64", "", "session the sample belongs to"),
    Column("t", "float64", "s", "time; strictly increasing within a session"),
    Column("x", "float64", "m", "ball centre, x"),
    Column("y", "float64", "m", "ball centre, y"),
    Column("z", "float64", "m", "ball centre, z (0.02 when resting on the table)"),
    *_xyz("spin_", "rad/s", "ball angular velocity (0 when unknown)", 0.0),
    Column("spin_conf", "float64", "", "confidence of the spin in [0, 1]; 0 = no spin measured", 0.0),
    Column("segment_id", "int64", "", "flight segment of the sample; -1 = in no segment", -1),
)

EVENTS = (
    Column("event_id", "int64", "", "unique id of the event"),
    Column("session_id", "int64", "", "session of the event"),
    Column("t", "float64", "s", "contact time"),
    Column("kind", "string", "", "one of " + ", ".join(EVENT_KINDS)),
    Column("x", "float64", "m", "ball centre at the contact, x"),
    Column("y", "float64", "m", "ball centre at the contact, y"),
    Column("z", "float64", "m", "ball centre at the contact, z"),
)

RACKETS = (
    Column("event_id", "int64", "", "the racket contact event this state belongs to"),
    *_xyz("", "m", "centre of the racket face (blade mid-plane)"),
    Column("qw", "float64", "", "orientation racket -> world, unit quaternion w"),
    Column("qx", "float64", "", "orientation quaternion x"),
    Column("qy", "float64", "", "orientation quaternion y"),
    Column("qz", "float64", "", "orientation quaternion z"),
    *_xyz("v", "m/s", "linear velocity of the face centre"),
    *_xyz("w", "rad/s", "angular velocity of the racket, world frame"),
    Column("d_y", "float64", "m", "contact point on the face along racket y (x-axis = face normal)"),
    Column("d_z", "float64", "m", "contact point on the face along racket z (handle -> tip)"),
    Column("config", "string", "", "racket configuration (blade, sponge, rubber) as named in the metadata's "
           "equipment['rackets']; '' = not given", ""),
)

SEGMENTS = (
    Column("segment_id", "int64", "", "unique id of the segment"),
    Column("session_id", "int64", "", "session of the segment"),
    Column("t_start", "float64", "s", "start: time of the opening event, or of the first sample"),
    Column("t_end", "float64", "s", "end: time of the closing event, or of the last sample"),
    Column("start_event_id", "int64", "", "event opening the segment; -1 = session start", -1),
    Column("end_event_id", "int64", "", "event closing the segment; -1 = session end", -1),
    *_xyz("spin_", "rad/s", "spin of the ball in this segment (0 when unknown)", 0.0),
    Column("spin_conf", "float64", "", "confidence of the segment's spin in [0, 1]", 0.0),
)

CONTACT_STATES = (
    Column("event_id", "int64", "", "the table or racket contact event these states belong to"),
    *_xyz("v_in_", "m/s", "ball velocity just before the contact"),
    *_xyz("w_in_", "rad/s", "ball spin just before the contact"),
    *_xyz("v_out_", "m/s", "ball velocity just after the contact"),
    *_xyz("w_out_", "rad/s", "ball spin just after the contact"),
    Column("spin_conf_in", "float64", "", "confidence of the incoming spin in [0, 1]; 0 = not measured", 1.0),
    Column("spin_conf_out", "float64", "", "confidence of the outgoing spin in [0, 1]; 0 = not measured", 1.0),
)

#: Table name -> its columns, in file order.
TABLES: dict[str, tuple[Column, ...]] = {
    "sessions": SESSIONS,
    "observations": OBSERVATIONS,
    "events": EVENTS,
    "rackets": RACKETS,
    "segments": SEGMENTS,
    "contact_states": CONTACT_STATES,
}
#: Tables a dataset of an older minor version may lack (read as empty), with the version that added them.
OPTIONAL_TABLES = {"contact_states": "1.2"}

#: Columns holding positions (checked for millimetres given as metres).
POSITION_COLUMNS = {
    "observations": ("x", "y", "z"),
    "events": ("x", "y", "z"),
    "rackets": ("x", "y", "z"),
}

#: Columns that identify a row and must be unique.
ID_COLUMNS = {"sessions": "session_id", "events": "event_id", "segments": "segment_id", "rackets": "event_id",
              "contact_states": "event_id"}


def column(table: str, name: str) -> Column:
    """Returns the definition of ``table.name``; KeyError for unknown names."""
    for col in TABLES[table]:
        if col.name == name:
            return col
    raise KeyError(f"table {table!r} has no column {name!r}")


def empty_table(table: str) -> dict[str, np.ndarray]:
    """A table with zero rows and every column of ``table``."""
    return {c.name: np.zeros(0, c.numpy_dtype) for c in TABLES[table]}


def parse_version(version: str) -> tuple[int, int]:
    """``"1.0"`` -> ``(1, 0)``; ValueError for anything else."""
    major, minor = str(version).split(".")
    return int(major), int(minor)
