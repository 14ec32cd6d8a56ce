"""Validation of a :class:`~ttsim_jax.data.dataset.Dataset` with errors that point at the bad cell.

Every check yields :class:`~ttsim_jax.data.errors.DataError` s naming the file, table, row, column
and value. :func:`validate` raises the first; :func:`problems` lists them (for ``data info``).
Loading, saving, importing and batching all validate, so a bad row stops the pipeline where it is
read instead of silently corrupting a batch.
"""

from __future__ import annotations

from typing import Iterator, Mapping

import numpy as np

from . import schema
from .dataset import Dataset
from .errors import DataError

#: Largest plausible |coordinate| of a ball or racket in a table-tennis room [m]; a larger value
#: almost always means millimetres were given as metres.
MAX_ABS_POSITION = 10.0
#: A labelled table contact must have the ball centre this close to z = ball radius [m].
TABLE_CONTACT_TOL = 0.03
#: |quaternion| must be 1 within this.
QUAT_TOL = 1e-3


def validate(ds: Dataset, files: Mapping[str, object] | object | None = None) -> None:
    """Raises the first problem of ``ds``, if any.

    Arguments:
        ds: the dataset.
        files: where the tables came from, for messages: a dict table -> path, or one path for all.

    Raises:
        DataError: naming file, table, row, column and value.
    """
    for err in _checks(ds, files):
        raise err


def problems(ds: Dataset, files=None, limit: int | None = 20) -> list[DataError]:
    """All problems of ``ds`` (at most ``limit``); empty when valid.

    Structural problems (missing columns, wrong lengths) stop the search, since later checks need
    the columns.
    """
    out = []
    for err in _checks(ds, files):
        out.append(err)
        if limit is not None and len(out) >= limit:
            break
    return out


def _file_of(files, table):
    if files is None:
        return None
    if isinstance(files, Mapping):
        return files.get(table)
    return files


def _checks(ds: Dataset, files) -> Iterator[DataError]:
    meta = ds.metadata
    meta_file = _file_of(files, "metadata")
    try:
        major, _ = schema.parse_version(meta.schema_version)
    except (ValueError, TypeError):
        yield DataError("schema_version must look like 'MAJOR.MINOR'", file=meta_file, column="schema_version", value=meta.schema_version)
        return
    if major != schema.parse_version(schema.SCHEMA_VERSION)[0]:
        yield DataError(
            f"unsupported schema version; this reader understands {schema.SCHEMA_VERSION.split('.')[0]}.x",
            file=meta_file,
            column="schema_version",
            value=meta.schema_version,
        )
        return
    if meta.frame != schema.CANONICAL_FRAME:
        yield DataError(
            f"data must be in the canonical frame {schema.CANONICAL_FRAME!r} ({schema.FRAME_DESCRIPTION}); convert it first",
            file=meta_file,
            column="frame",
            value=meta.frame,
        )

    structural = list(_check_structure(ds, files))
    yield from structural
    if structural:
        return
    for name, table in ds.tables().items():
        yield from _check_values(name, table, _file_of(files, name))
    yield from _check_ids(ds, files)
    yield from _check_time_order(ds.observations, _file_of(files, "observations"))
    yield from _check_references(ds, files)
    yield from _check_table_level(ds, files)


def _check_structure(ds: Dataset, files) -> Iterator[DataError]:
    for name, cols in schema.TABLES.items():
        table = ds.table(name)
        f = _file_of(files, name)
        if not isinstance(table, Mapping):
            yield DataError(f"table must be a dict of columns, got {type(table).__name__}", file=f, table=name)
            continue
        n = None
        for c in cols:
            if c.name not in table:
                yield DataError("missing required column", file=f, table=name, column=c.name)
                continue
            values = np.asarray(table[c.name])
            if values.ndim != 1:
                yield DataError(f"column must be 1-D, has shape {values.shape}", file=f, table=name, column=c.name)
                continue
            if n is None:
                n = len(values)
            elif len(values) != n:
                yield DataError(f"column has {len(values)} rows, the table's first column has {n}", file=f, table=name, column=c.name)
            kind = values.dtype.kind
            ok = {"int64": kind in "iu", "float64": kind in "fiu", "string": kind in "OUS"}[c.dtype]
            if not ok:
                yield DataError(f"column must hold {c.dtype}, holds {values.dtype}", file=f, table=name, column=c.name)


def _check_values(name: str, table, f) -> Iterator[DataError]:
    for c in schema.TABLES[name]:
        values = np.asarray(table[c.name])
        if c.dtype == "float64":
            bad = np.flatnonzero(~np.isfinite(values.astype(np.float64)))
            if bad.size:
                yield DataError("NaN or infinite value", file=f, table=name, row=bad[0], column=c.name, value=values[bad[0]])
        if c.dtype == "string":
            bad = [i for i, v in enumerate(values) if not isinstance(v, str)]
            if bad:
                yield DataError("not a string", file=f, table=name, row=bad[0], column=c.name, value=values[bad[0]])
    for col in schema.POSITION_COLUMNS.get(name, ()):
        values = np.asarray(table[col], np.float64)
        bad = np.flatnonzero(np.isfinite(values) & (np.abs(values) > MAX_ABS_POSITION))
        if bad.size:
            v = values[bad[0]]
            hint = " (looks like millimetres: give metres)" if abs(v) / 1000.0 <= MAX_ABS_POSITION else ""
            yield DataError(f"position beyond {MAX_ABS_POSITION:g} m of the table centre{hint}", file=f, table=name, row=bad[0], column=col, value=v)
    if name in ("observations", "events"):
        z = np.asarray(table["z"], np.float64)
        bad = np.flatnonzero(np.isfinite(z) & (z < schema.FLOOR_Z - 0.1))
        if bad.size:
            yield DataError(
                f"ball below the floor (z = {schema.FLOOR_Z} m in the canonical frame): is the table surface at z = 0?",
                file=f, table=name, row=bad[0], column="z", value=z[bad[0]],
            )
    if "spin_conf" in table:
        conf = np.asarray(table["spin_conf"], np.float64)
        bad = np.flatnonzero((conf < 0) | (conf > 1))
        if bad.size:
            yield DataError("spin confidence must be in [0, 1]", file=f, table=name, row=bad[0], column="spin_conf", value=conf[bad[0]])
    if name == "events":
        bad = [i for i, k in enumerate(table["kind"]) if k not in schema.EVENT_CODES]
        if bad:
            yield DataError(f"unknown event kind; kinds: {', '.join(schema.EVENT_KINDS)}", file=f, table=name, row=bad[0], column="kind", value=table["kind"][bad[0]])
    if name == "rackets":
        q = np.stack([np.asarray(table[k], np.float64) for k in ("qw", "qx", "qy", "qz")], axis=-1)
        norm = np.linalg.norm(q, axis=-1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_TOL)
        if bad.size:
            yield DataError(f"orientation quaternion must have norm 1, has {norm[bad[0]]:.6g}", file=f, table=name, row=bad[0], column="qw", value=q[bad[0]].tolist())
    if name == "segments":
        bad = np.flatnonzero(np.asarray(table["t_end"]) < np.asarray(table["t_start"]))
        if bad.size:
            yield DataError("segment ends before it starts", file=f, table=name, row=bad[0], column="t_end", value=table["t_end"][bad[0]])


def _check_ids(ds: Dataset, files) -> Iterator[DataError]:
    for name, col in schema.ID_COLUMNS.items():
        ids = np.asarray(ds.table(name)[col])
        if ids.size == 0:
            continue
        order = np.argsort(ids, kind="stable")
        dup = np.flatnonzero(ids[order][1:] == ids[order][:-1])
        if dup.size:
            row = order[dup[0] + 1]
            first = order[dup[0]]
            what = "racket state for this event" if name == "rackets" else "id"
            yield DataError(f"duplicate {what}; also in row {first}", file=_file_of(files, name), table=name, row=row, column=col, value=ids[row])


def _check_time_order(obs, f) -> Iterator[DataError]:
    sid = np.asarray(obs["session_id"])
    t = np.asarray(obs["t"], np.float64)
    if len(sid) < 2:
        return
    change = np.flatnonzero(sid[1:] != sid[:-1]) + 1
    starts = np.concatenate([[0], change])
    block_ids = sid[starts]
    order = np.argsort(block_ids, kind="stable")
    rep = np.flatnonzero(block_ids[order][1:] == block_ids[order][:-1])
    if rep.size:
        row = starts[order[rep[0] + 1]]
        yield DataError("rows of a session must be contiguous; this session already appeared above", file=f, table="observations", row=row, column="session_id", value=sid[row])
        return
    bad = np.flatnonzero((sid[1:] == sid[:-1]) & (t[1:] <= t[:-1])) + 1
    if bad.size:
        i = bad[0]
        yield DataError(
            f"time does not increase within session {sid[i]} (the previous sample has t = {float(t[i - 1])!r})",
            file=f, table="observations", row=i, column="t", value=t[i],
        )


def _check_references(ds: Dataset, files) -> Iterator[DataError]:
    sessions = np.asarray(ds.sessions["session_id"])
    for name in ("observations", "events", "segments"):
        sid = np.asarray(ds.table(name)["session_id"])
        bad = np.flatnonzero(~np.isin(sid, sessions))
        if bad.size:
            yield DataError("session_id not in the sessions table", file=_file_of(files, name), table=name, row=bad[0], column="session_id", value=sid[bad[0]])
    ev = ds.events
    rk = ds.rackets
    f_ev, f_rk = _file_of(files, "events"), _file_of(files, "rackets")
    racket_events = np.asarray(ev["event_id"])[np.asarray([k == "racket" for k in ev["kind"]], bool)]
    rk_ids = np.asarray(rk["event_id"])
    missing = np.flatnonzero(~np.isin(racket_events, rk_ids))
    if missing.size:
        row = int(np.flatnonzero(np.asarray(ev["event_id"]) == racket_events[missing[0]])[0])
        yield DataError("racket contact event without a racket state (no row in the rackets table)", file=f_ev, table="events", row=row, column="event_id", value=racket_events[missing[0]])
    stray = np.flatnonzero(~np.isin(rk_ids, racket_events))
    if stray.size:
        yield DataError("racket state whose event_id is not a racket contact event", file=f_rk, table="rackets", row=stray[0], column="event_id", value=rk_ids[stray[0]])

    seg = ds.segments
    f_obs, f_seg = _file_of(files, "observations"), _file_of(files, "segments")
    seg_ids = np.asarray(seg["segment_id"])
    obs_seg = np.asarray(ds.observations["segment_id"])
    bad = np.flatnonzero((obs_seg != -1) & ~np.isin(obs_seg, seg_ids))
    if bad.size:
        yield DataError("segment_id not in the segments table (use -1 for none)", file=f_obs, table="observations", row=bad[0], column="segment_id", value=obs_seg[bad[0]])
        return
    ev_ids = np.asarray(ev["event_id"])
    for col in ("start_event_id", "end_event_id"):
        ref = np.asarray(seg[col])
        bad = np.flatnonzero((ref != -1) & ~np.isin(ref, ev_ids))
        if bad.size:
            yield DataError("event id not in the events table (use -1 for none)", file=f_seg, table="segments", row=bad[0], column=col, value=ref[bad[0]])
    rows = np.flatnonzero(obs_seg != -1)
    if rows.size and seg_ids.size:
        order = np.argsort(seg_ids)
        k = order[np.searchsorted(seg_ids[order], obs_seg[rows])]
        t = np.asarray(ds.observations["t"])[rows]
        wrong_session = np.flatnonzero(np.asarray(seg["session_id"])[k] != np.asarray(ds.observations["session_id"])[rows])
        if wrong_session.size:
            r = rows[wrong_session[0]]
            yield DataError("observation's segment belongs to another session", file=f_obs, table="observations", row=r, column="segment_id", value=obs_seg[r])
        outside = np.flatnonzero((t < np.asarray(seg["t_start"])[k]) | (t > np.asarray(seg["t_end"])[k]))
        if outside.size:
            r = rows[outside[0]]
            yield DataError("observation time outside its segment's [t_start, t_end]", file=f_obs, table="observations", row=r, column="t", value=ds.observations["t"][r])


def _check_table_level(ds: Dataset, files) -> Iterator[DataError]:
    ev = ds.events
    r = schema.BALL_RADIUS
    is_table = np.asarray([k == "table" for k in ev["kind"]], bool)
    z = np.asarray(ev["z"], np.float64)
    # Only a contact over the playing surface says where the surface is: a ball that hits the
    # table's edge or end face has its centre beyond the surface's outline and lower than r.
    over = ((np.abs(np.asarray(ev["x"], np.float64)) <= 0.5 * schema.TABLE_LENGTH)
            & (np.abs(np.asarray(ev["y"], np.float64)) <= 0.5 * schema.TABLE_WIDTH))
    # A frame whose surface is not at z = 0 moves every such contact; a single contact off the
    # surface's height is a ball meeting the underside of the table (an opponent digging a low
    # ball up under the end can send it there), not evidence about the frame.
    on_top = is_table & over
    bad = np.flatnonzero(on_top & (np.abs(z - r) > TABLE_CONTACT_TOL))
    if bad.size and 2 * bad.size > on_top.sum():
        level = float(np.median(z[on_top]))
        yield DataError(
            f"table contact with the ball centre at z = {z[bad[0]]:.4f} m ({bad.size} of {int(on_top.sum())} contacts over "
            f"the playing surface are off its height; median z = {level:.4f} m); in the canonical frame the centre sits "
            f"at the ball radius ({r} m): the table surface of this frame seems to be at z = {level - r:.3f} m, not 0",
            file=_file_of(files, "events"), table="events", row=bad[0], column="z", value=z[bad[0]],
        )
        return
    # Unlabelled bounces: z-velocity reversals, judged together so a racket lift cannot trip it.
    obs = ds.observations
    sid = np.asarray(obs["session_id"])
    t = np.asarray(obs["t"], np.float64)
    zo = np.asarray(obs["z"], np.float64)
    w = 2
    if len(zo) < 2 * w + 1:
        return
    i = np.arange(w, len(zo) - w)
    same = sid[i - w] == sid[i + w]
    with np.errstate(divide="ignore", invalid="ignore"):
        vin = (zo[i] - zo[i - w]) / (t[i] - t[i - w])
        vout = (zo[i + w] - zo[i]) / (t[i + w] - t[i])
    cand = i[same & (zo[i] <= zo[i - 1]) & (zo[i] < zo[i + 1]) & (vin < -1.0) & (vout > 1.0)]
    if cand.size < 3:
        return
    h = zo[cand]
    at_table = np.abs(h - r) <= 0.04
    at_floor = np.abs(h - (schema.FLOOR_Z + r)) <= 0.05
    other = ~(at_table | at_floor)
    if other.sum() > 0.5 * len(h) and other.sum() >= 3:
        level = float(np.median(h[other]))
        if np.median(np.abs(h[other] - level)) < 0.02:
            row = int(cand[other][0])
            yield DataError(
                f"the ball bounces at z = {level:.3f} m (median of {int(other.sum())} bounces) instead of at the ball radius "
                f"({r} m): the table surface of this frame is not at z = 0 (shift z by {r - level:+.3f} m?)",
                file=_file_of(files, "observations"), table="observations", row=row, column="z", value=zo[row],
            )
