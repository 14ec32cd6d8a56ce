"""Column tables of the dataset format: built from arrays with the schema's defaults, selected and
concatenated row-wise.

A table is a plain ``dict`` mapping column name -> 1-D numpy array, all of one length, with the
columns and dtypes of :mod:`ttsim_jax.data.schema`.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from . import schema
from .errors import DataError

Table = dict  # column name -> 1-D numpy array


def fill_defaults(table: str, columns: Mapping[str, Any]) -> Table:
    """Makes a full table from the given columns, filling optional ones with their defaults.

    Arguments:
        table: table name in :data:`schema.TABLES`.
        columns: column name -> array-like; every required column must be present.

    Returns:
        Column dict in schema order with numpy arrays of the schema dtypes.
    """
    cols = schema.TABLES[table]
    known = {c.name for c in cols}
    for name in columns:
        if name not in known:
            raise DataError(f"unknown column; known: {sorted(known)}", table=table, column=name)
    n = None
    for name, values in columns.items():
        m = len(np.atleast_1d(values))
        if n is not None and m != n:
            raise DataError(f"column has {m} rows, others have {n}", table=table, column=name)
        n = m
    n = 0 if n is None else n
    out = {}
    for c in cols:
        if c.name in columns:
            values = np.atleast_1d(np.asarray(columns[c.name]))
        elif c.required:
            raise DataError("missing required column", table=table, column=c.name)
        else:
            values = np.full(n, c.default)
        if c.dtype == "string":
            out[c.name] = np.array([str(v) for v in values], dtype=object)
        else:
            out[c.name] = values.astype(c.numpy_dtype)
    return out


def events_table(session_id, t, kind, pos, event_id=None) -> Table:
    """Events column table from (E,) arrays and (E, 3) ``pos``; ids default to ``0..E-1``."""
    pos = np.asarray(pos, np.float64).reshape(-1, 3)
    n = len(pos)
    return fill_defaults(
        "events",
        {
            "event_id": np.arange(n) if event_id is None else event_id,
            "session_id": np.broadcast_to(session_id, (n,)),
            "t": t,
            "kind": np.broadcast_to(np.asarray(kind, object), (n,)),
            "x": pos[:, 0],
            "y": pos[:, 1],
            "z": pos[:, 2],
        },
    )


def rackets_table(event_id, pos, quat, vel, ang_vel, contact, config=None) -> Table:
    """Rackets column table from (R, 3) ``pos``/``vel``/``ang_vel``, (R, 4) ``quat`` (w, x, y, z),
    (R, 2) ``contact`` (d_y, d_z) and optionally (R,) ``config`` names (default '')."""
    pos = np.asarray(pos, np.float64).reshape(-1, 3)
    quat = np.asarray(quat, np.float64).reshape(-1, 4)
    vel = np.asarray(vel, np.float64).reshape(-1, 3)
    ang_vel = np.asarray(ang_vel, np.float64).reshape(-1, 3)
    contact = np.asarray(contact, np.float64).reshape(-1, 2)
    cols = {"event_id": event_id}
    cols.update(x=pos[:, 0], y=pos[:, 1], z=pos[:, 2])
    cols.update(qw=quat[:, 0], qx=quat[:, 1], qy=quat[:, 2], qz=quat[:, 3])
    cols.update(vx=vel[:, 0], vy=vel[:, 1], vz=vel[:, 2])
    cols.update(wx=ang_vel[:, 0], wy=ang_vel[:, 1], wz=ang_vel[:, 2])
    cols.update(d_y=contact[:, 0], d_z=contact[:, 1])
    if config is not None:
        cols["config"] = np.broadcast_to(np.asarray(config, object), (len(pos),))
    return fill_defaults("rackets", cols)


def contact_states_table(event_id, v_in, w_in, v_out, w_out, spin_conf_in=1.0, spin_conf_out=1.0) -> Table:
    """Contact-states column table from (C,) ``event_id`` and (C, 3) world-frame velocities [m/s]
    and spins [rad/s] just before (``_in``) and after (``_out``) each contact."""
    cols = {"event_id": event_id}
    for name, a in (("v_in_", v_in), ("w_in_", w_in), ("v_out_", v_out), ("w_out_", w_out)):
        a = np.asarray(a, np.float64).reshape(-1, 3)
        cols.update({f"{name}{k}": a[:, i] for i, k in enumerate("xyz")})
    n = len(np.atleast_1d(event_id))
    cols["spin_conf_in"] = np.broadcast_to(np.asarray(spin_conf_in, np.float64), (n,))
    cols["spin_conf_out"] = np.broadcast_to(np.asarray(spin_conf_out, np.float64), (n,))
    return fill_defaults("contact_states", cols)


def sessions_table(session_id, name=None, notes=None) -> Table:
    """Sessions column table; ``name`` and ``notes`` default to empty strings."""
    cols = {"session_id": session_id}
    if name is not None:
        cols["name"] = name
    if notes is not None:
        cols["notes"] = notes
    return fill_defaults("sessions", cols)


def select_rows(table: Table, index) -> Table:
    """Rows ``index`` (bool mask or integer indices) of every column."""
    return {k: v[index] for k, v in table.items()}


def concat_tables(tables: list[Table], name: str) -> Table:
    """Row-wise concatenation of tables of kind ``name`` (an empty list gives an empty table)."""
    if not tables:
        return schema.empty_table(name)
    return {c.name: np.concatenate([t[c.name] for t in tables]).astype(c.numpy_dtype) for c in schema.TABLES[name]}


def id_index(ids) -> tuple[np.ndarray, np.ndarray]:
    """(order, sorted ids) of an int id column: the index :func:`rows_of` looks ids up in."""
    ids = np.asarray(ids, np.int64)
    order = np.argsort(ids, kind="stable")
    return order, ids[order]


def rows_of(index: tuple[np.ndarray, np.ndarray], wanted) -> np.ndarray:
    """(n,) int64 rows holding the ids ``wanted`` in the column ``index`` was built on
    (:func:`id_index`), -1 for an id it does not hold; the last row of an id held twice, as a dict
    built over the rows would have it."""
    order, sorted_ids = index
    wanted = np.asarray(wanted, np.int64).reshape(-1)
    if not len(sorted_ids):
        return np.full(len(wanted), -1, np.int64)
    at = np.searchsorted(sorted_ids, wanted, side="right") - 1
    found = (at >= 0) & (sorted_ids[np.maximum(at, 0)] == wanted)
    return np.where(found, order[np.maximum(at, 0)], -1).astype(np.int64)
