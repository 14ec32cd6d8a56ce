"""Validation of a :class:`~ttsim_jax.data.dataset.Dataset` with errors that point at the bad cell.

Every check yields :class:`~ttsim_jax.data.errors.DataError` s naming the file, table, row, column
and value. :func:`validate` raises the first; :func:`problems` lists them (for ``data info``).
Loading, saving, importing and batching all validate, so a bad row stops the pipeline where it is
read instead of silently corrupting a batch.

Physical plausibility: a value no table tennis ball, racket or room produces (a spin of 1e9 rad/s,
a racket at 80 m/s, a ball 20 m from the table) is an error; one beyond what has been measured in
play but still possible (a 40 m/s ball, a 1,500 rad/s spin, a ball beyond the ITTF playing space)
is a :class:`~ttsim_jax.data.errors.DataWarning` from :func:`borderline`, one per check with the
count and the first case. Speeds are judged per flight segment (the median of its sample-to-sample
speeds, which a tracking jump does not move; jumps themselves are breaks, see
:mod:`ttsim_jax.data.tracks`), accelerations per segment too (a fitted parabola's, against gravity
plus the most drag and Magnus force the segment's speed allows, beyond its fit's noise): a warning
only, since jitter and hidden contacts make single frames unreliable.
"""

from __future__ import annotations

from typing import Iterator, Mapping

import numpy as np

from . import schema
from .dataset import Dataset
from .errors import DataError, DataWarning
from .speeds import acceleration_excess, run_speeds
from .tracks import MAX_SPEED, MIN_SAMPLES

#: Largest plausible |coordinate| of a ball or racket in a table-tennis room [m]; a larger value
#: almost always means millimetres were given as metres.
MAX_ABS_POSITION = 10.0
#: Half-length, half-width [m] and height above the table surface [m] of the ITTF playing space
#: (at least 14 m x 7 m x 5 m high around the table): beyond it is borderline, since halls are
#: often larger (MAX_ABS_POSITION is the error).
ROOM = (7.0, 3.5, 5.0 + schema.FLOOR_Z)
#: Fastest ball measured in play [m/s] (smashes; Tang 2002, the paper's range): a faster segment
#: or racket is borderline; tracks.MAX_SPEED (50 m/s), which nothing in the game reaches, is the error.
FASTEST_BALL = 35.0
#: Largest spin measured in play [rad/s] (loops; Tang 2002, the paper's range): more is borderline.
FASTEST_SPIN = 1000.0
#: Spin [rad/s] whose surface speed (omega r) exceeds MAX_SPEED: friction at a contact drives the
#: ball's surface towards the other surface's speed and no surface in the game moves that fast, so
#: no contact can give it (2,500 rad/s; SpinDOE's largest estimate is 2,362 rad/s).
MAX_SPIN = MAX_SPEED / schema.BALL_RADIUS
#: Half the width of a blade [m] (about 15 cm wide): a racket turning at omega moves some point of
#: its blade at least this times omega, whatever the axis; so a rate whose rim speed exceeds
#: FASTEST_BALL (467 rad/s) is borderline, one beyond MAX_SPEED (667 rad/s) an error.
BLADE_HALF_WIDTH = 0.075
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
    found = False
    for name, table in ds.tables().items():
        for err in _check_values(name, table, _file_of(files, name)):
            found = True
            yield err
    for check in (_check_ids(ds, files), _check_time_order(ds.observations, _file_of(files, "observations")),
                  _check_references(ds, files), _check_table_level(ds, files)):
        for err in check:
            found = True
            yield err
    if found:  # the plausibility checks need finite values and grouped, time-ordered rows
        return
    yield from _plausibility(ds, files, "error")


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


def row_rules(name: str, table: Mapping, f=None) -> Iterator[DataError]:
    """The rules each row of table ``name`` keeps or breaks on its own, whatever the other rows
    hold: finite numbers, strings where strings belong, a ball above the floor, spin confidences
    in [0, 1], known event kinds, unit quaternions. So a reader can apply them to a part of a file
    as it streams (the CSV import does, per block of rows), and a bad row near the end of a large
    log is refused before the work on the rest. Columns the table lacks are skipped.

    The bound on positions (:data:`MAX_ABS_POSITION`) is a row's too, but not among these: where a
    few samples break it they are a tracker's glitches (left out on import), where most do the
    units are wrong (:func:`ttsim_jax.data.glitches.far_samples` tells which), so it needs the whole
    log.

    Arguments:
        name: the table (``"observations"``, ``"events"``, ...); table: its columns (rows are the
            table's own: a caller checking a block maps them to its lines); f: the file, for the
            messages.

    Yields:
        A :class:`DataError` per broken rule, at its first row.
    """
    for c in schema.TABLES[name]:
        if c.name not in table:
            continue
        values = np.asarray(table[c.name])
        if c.dtype == "float64":
            bad = np.flatnonzero(~np.isfinite(values.astype(np.float64)))
            if bad.size:
                yield DataError("NaN or infinite value", file=f, table=name, row=bad[0], column=c.name, value=values[bad[0]])
        if c.dtype == "string":
            bad = [i for i, v in enumerate(values) if not isinstance(v, str)]
            if bad:
                yield DataError("not a string", file=f, table=name, row=bad[0], column=c.name, value=values[bad[0]])
    if name in ("observations", "events") and "z" in table:
        z = np.asarray(table["z"], np.float64)
        bad = np.flatnonzero(np.isfinite(z) & (z < schema.FLOOR_Z - 0.1))
        if bad.size:
            yield DataError(
                f"ball below the floor (z = {schema.FLOOR_Z} m in the canonical frame): is the table surface at z = 0?",
                file=f, table=name, row=bad[0], column="z", value=z[bad[0]],
            )
    for col in ("spin_conf", "spin_conf_in", "spin_conf_out"):
        if col not in table:
            continue
        conf = np.asarray(table[col], np.float64)
        bad = np.flatnonzero((conf < 0) | (conf > 1))
        if bad.size:
            yield DataError("spin confidence must be in [0, 1]", file=f, table=name, row=bad[0], column=col, value=conf[bad[0]])
    if name == "events" and "kind" in table:
        bad = [i for i, k in enumerate(table["kind"]) if k not in schema.EVENT_CODES]
        if bad:
            yield DataError(f"unknown event kind; kinds: {', '.join(schema.EVENT_KINDS)}", file=f, table=name, row=bad[0], column="kind", value=table["kind"][bad[0]])
    if name == "rackets" and all(k in table for k in ("qw", "qx", "qy", "qz")):
        q = np.stack([np.asarray(table[k], np.float64) for k in ("qw", "qx", "qy", "qz")], axis=-1)
        norm = np.linalg.norm(q, axis=-1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_TOL)
        if bad.size:
            yield DataError(f"orientation quaternion must have norm 1, has {norm[bad[0]]:.6g}", file=f, table=name, row=bad[0], column="qw", value=q[bad[0]].tolist())


def _check_values(name: str, table, f) -> Iterator[DataError]:
    yield from row_rules(name, table, f)
    for col in schema.POSITION_COLUMNS.get(name, ()):
        values = np.asarray(table[col], np.float64)
        bad = np.flatnonzero(np.isfinite(values) & (np.abs(values) > MAX_ABS_POSITION))
        if bad.size:
            v = values[bad[0]]
            hint = " (looks like millimetres: give metres)" if abs(v) / 1000.0 <= MAX_ABS_POSITION else ""
            yield DataError(f"position beyond {MAX_ABS_POSITION:g} m of the table centre{hint}", file=f, table=name, row=bad[0], column=col, value=v)
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
    kinds = np.asarray(ev["kind"]).astype(str)
    contact_events = np.asarray(ev["event_id"])[np.isin(kinds, ("table", "racket"))]
    cs_ids = np.asarray(ds.contact_states["event_id"])
    stray = np.flatnonzero(~np.isin(cs_ids, contact_events))
    if stray.size:
        yield DataError("contact state whose event_id is not a table or racket contact event",
                        file=_file_of(files, "contact_states"), table="contact_states", row=stray[0], column="event_id",
                        value=cs_ids[stray[0]])

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


# ------------------------------------------------------------------------------------ plausibility
def borderline(ds: Dataset, files=None) -> list[DataWarning]:
    """Values beyond what has been measured in table tennis but not beyond what it can produce, and
    accelerations no flight explains (see the module docstring); one warning per check.

    Arguments:
        ds: a valid dataset (:func:`validate` passes).
        files: where the tables came from, for messages (as for :func:`validate`).

    Returns:
        :class:`DataWarning` s naming the count, the first file, table, row, column and value.
    """
    return list(_plausibility(ds, files, "warning"))


def _session_of(ds: Dataset, table: str, row: int) -> str:
    """' (session S, NAME)': where an observation or segment row was recorded."""
    sid = int(ds.table(table)["session_id"][row])
    names = dict(zip(np.asarray(ds.sessions["session_id"]).tolist(), ds.sessions["name"]))
    name = names.get(sid, "")
    return f" (session {sid}{', ' + str(name) if name else ''})"


def _magnitudes(table, cols) -> np.ndarray:
    return np.linalg.norm(np.stack([np.asarray(table[c], np.float64) for c in cols], -1), axis=-1)


def _plausibility(ds: Dataset, files, want: str):
    """The DataErrors (``want`` = "error") or the DataWarnings (``want`` = "warning") of the
    plausibility checks; the work of the other level is skipped."""

    def over(table, cols, magnitude, limit, level, quantity, unit, reason):
        """Rows whose ``magnitude`` exceeds ``limit``: the first, named by its largest column."""
        bad = np.flatnonzero(magnitude > limit)
        if level != want or not bad.size:
            return
        row = int(bad[0])
        t = ds.table(table)
        col = max(cols, key=lambda c: abs(float(t[c][row])))
        where = _session_of(ds, table, row) if "session_id" in t else ""
        if level == "error":
            text = f"{quantity} of {magnitude[row]:.4g} {unit}{where}: {reason}"
        else:
            text = (f"{bad.size} rows have {quantity} above {limit:.4g} {unit}, up to {magnitude[bad].max():.4g} {unit}: "
                    f"{reason}; the first{where}: {magnitude[row]:.4g} {unit}")
        cls = DataWarning if level == "warning" else DataError
        yield cls(text, file=_file_of(files, table), table=table, row=row, column=col, value=t[col][row])

    spin_cols = ("spin_x", "spin_y", "spin_z")
    warned = False
    for table in ("observations", "segments"):
        spin = _magnitudes(ds.table(table), spin_cols)
        yield from over(table, spin_cols, spin, MAX_SPIN, "error", "a spin", "rad/s",
                        f"beyond what any contact can give a ball ({MAX_SPIN:.0f} rad/s would move its surface faster "
                        f"than {MAX_SPEED:g} m/s); is it in rad/s?")
        if not warned:  # segment spins are usually their observations' mean: one warning for both
            found = list(over(table, spin_cols, spin, FASTEST_SPIN, "warning", "a spin", "rad/s",
                              "more than the largest measured in play (Tang 2002)"))
            warned = bool(found)
            yield from found
    cs = ds.contact_states
    for side in ("in", "out"):
        v_cols, w_cols = tuple(f"v_{side}_{a}" for a in "xyz"), tuple(f"w_{side}_{a}" for a in "xyz")
        v, w = _magnitudes(cs, v_cols), _magnitudes(cs, w_cols)
        yield from over("contact_states", v_cols, v, MAX_SPEED, "error", "a ball speed", "m/s",
                        "beyond what the game produces; is it in m/s?")
        yield from over("contact_states", w_cols, w, MAX_SPIN, "error", "a spin", "rad/s",
                        f"beyond what any contact can give a ball ({MAX_SPIN:.0f} rad/s); is it in rad/s?")
        yield from over("contact_states", v_cols, v, FASTEST_BALL, "warning", "a ball speed", "m/s",
                        "more than the fastest ball measured in play")
        yield from over("contact_states", w_cols, w, FASTEST_SPIN, "warning", "a spin", "rad/s",
                        "more than the largest measured in play (Tang 2002)")
    rk = ds.rackets
    for cols, unit, scale, what in ((("vx", "vy", "vz"), "m/s", 1.0, "a face speed"),
                                    (("wx", "wy", "wz"), "rad/s", BLADE_HALF_WIDTH, "a rotation rate")):
        m = _magnitudes(rk, cols)
        yield from over("rackets", cols, m, MAX_SPEED / scale, "error", what, unit,
                        f"beyond what a racket reaches (its blade would move faster than {MAX_SPEED:g} m/s); "
                        f"is it in {unit}?")
        yield from over("rackets", cols, m, FASTEST_BALL / scale, "warning", what, unit,
                        f"its blade would move faster than the fastest ball measured in play ({FASTEST_BALL:g} m/s)")
    for table, cols in schema.POSITION_COLUMNS.items() if want == "warning" else ():
        t = ds.table(table)
        p = np.stack([np.asarray(t[c], np.float64) for c in cols], -1).reshape(-1, 3)
        beyond = np.abs(p) / np.asarray(ROOM[:2] + (np.inf,))
        beyond[:, 2] = p[:, 2] / ROOM[2]
        bad = np.flatnonzero(beyond.max(-1, initial=0.0) > 1.0)
        if bad.size:
            row, col = int(bad[0]), cols[int(np.argmax(beyond[bad[0]]))]
            where = _session_of(ds, table, row) if "session_id" in t else ""
            text = (f"{bad.size} rows lie outside the ITTF playing space around the table (|x| <= {ROOM[0]:g} m, "
                    f"|y| <= {ROOM[1]:g} m, z <= {ROOM[2]:.2f} m; halls may be larger); the first{where}")
            yield DataWarning(text, file=_file_of(files, table), table=table, row=row, column=col, value=t[col][row])
    yield from _segment_motion(ds, files, want)


def _segment_motion(ds: Dataset, files, want: str):
    """Speed (error and warning) checks per run of samples of one segment (or, outside segments,
    of one session: data not yet segmented), acceleration (warning) checks per segment; those of
    level ``want``."""
    obs = ds.observations
    seg = np.asarray(obs["segment_id"])
    if len(seg) < 2:
        return
    start, count, group, speed = run_speeds(ds)
    t, pos = np.asarray(obs["t"], np.float64), ds.positions
    f = _file_of(files, "observations")

    def at(k):
        row = int(start[k])
        return dict(file=f, table="observations", row=row, column="t", value=obs["t"][row])

    def run(k):
        where = _session_of(ds, "observations", int(start[k]))
        return (f"segment {int(seg[start[k]])}{where}" if seg[start[k]] >= 0 else f"the samples{where} outside segments") \
            + " starting here"

    if want == "error":
        bad = np.flatnonzero(speed > MAX_SPEED)
        if bad.size:
            k = int(bad[0])
            yield DataError(
                f"{run(k)} fly at {speed[k]:.4g} m/s (median of their sample-to-sample speeds), beyond any ball in the "
                f"game ({MAX_SPEED:g} m/s; the fastest measured is about {FASTEST_BALL:g} m/s): are t in seconds and "
                "positions in metres?", **at(k))
        return
    bad = np.flatnonzero(speed > FASTEST_BALL)
    if bad.size:
        k = int(bad[0])
        yield DataWarning(
            f"{bad.size} segments (or stretches outside segments) fly faster than the fastest ball measured in play "
            f"({FASTEST_BALL:g} m/s, median of their sample-to-sample speeds); the first: {run(k)}, at {speed[k]:.4g} m/s",
            **at(k))
    fit = (count >= MIN_SAMPLES) & (seg[start] >= 0)
    if not fit.any():
        return
    a, bound, sigma, excess = acceleration_excess(group, t, pos, speed, fit)
    bad = np.flatnonzero(excess > 0)
    if bad.size:
        k = int(bad[np.argmax(excess[bad])])
        yield DataWarning(
            f"{bad.size} of {int(fit.sum())} segments accelerate more than gravity plus drag and Magnus force allow, "
            f"beyond their fit's noise; the worst, {run(k)}: |a - g| = {a[k]:.3g} m/s^2 (+- {sigma[k]:.2g}) where "
            f"its speed allows at most {bound[k]:.3g} m/s^2: a contact or a tracking error inside it, wrong time stamps "
            "or units, or z not up?", **at(k))
