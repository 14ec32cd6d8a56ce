"""Import of users' own logs from CSV (layout in ``docs/data_format.md``, "CSV import").

``observations.csv`` (required), header line then one sample per line, comma-separated::

    session_id,t,x,y,z[,spin_x,spin_y,spin_z,spin_conf]

``events.csv`` (optional)::  ``session_id,t,kind,x,y,z[,event_id]``

``rackets.csv`` (optional, one line per racket event)::
``event_id,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,d_y,d_z``

Positions in the canonical frame, in metres (or millimetres with ``length_unit="mm"``), times in
seconds (or milliseconds with ``time_unit="ms"``). Files are UTF-8 text (a byte-order mark is
skipped). Errors name the file, line (1-based, the header is line 1, blank lines counted), column and
value of the bad cell; a log whose ball hardly moves (times in milliseconds read as seconds) or
bounces at table height beside the table (x and y swapped) is refused before contacts are detected.
"""

from __future__ import annotations

import csv
import io
import math
import re
import warnings
from pathlib import Path

import numpy as np

from . import schema
from .dataset import Dataset, Metadata
from .errors import DataError, DataWarning
from .glitches import far_samples, leave_out_too_fast, noted, time_order

OBSERVATION_COLUMNS = ("session_id", "t", "x", "y", "z", "spin_x", "spin_y", "spin_z", "spin_conf")
EVENT_COLUMNS = ("session_id", "t", "kind", "x", "y", "z", "event_id")
RACKET_COLUMNS = tuple(c.name for c in schema.RACKETS)
_REQUIRED = {
    "observations": ("session_id", "t", "x", "y", "z"),
    "events": ("session_id", "t", "kind", "x", "y", "z"),
    "rackets": tuple(c.name for c in schema.RACKETS if c.required),
}
_INTS = {"session_id", "event_id"}
_STRINGS = {"kind", "config"}
_INT_RANGE = (int(np.iinfo(np.int64).min), int(np.iinfo(np.int64).max))
#: Rows read between two applications of the row rules while a file streams in.
BLOCK_ROWS = 65_536
#: Columns that come all together or not at all.
_TOGETHER = {"observations": (("spin_x", "spin_y", "spin_z"),)}
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3}
TIME_UNITS = {"s": 1.0, "ms": 1e-3}
#: Below this 90th percentile of sample-to-sample speeds [m/s] the log shows no ball in play (a ball
#: in flight moves at metres per second); typically the times are milliseconds read as seconds.
MIN_PLAY_SPEED = 0.25


def read_text(file: Path) -> str:
    """The text of a UTF-8 file (a leading byte-order mark dropped); binary content is an error.

    Arguments:
        file: path of the file.

    Returns:
        The decoded text. Raises :class:`DataError` naming the file, the line and the offending
        byte for a NUL byte (binary content) or bytes that are not UTF-8.
    """
    data = Path(file).read_bytes()
    nul = data.find(b"\x00")
    if nul >= 0:
        line = data[:nul].count(b"\n") + 1
        raise DataError("binary content (a NUL byte), not comma-separated text", file=file, row=line, row_label="line", value=data[nul : nul + 1])
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise DataError(
            "not UTF-8 text (a binary file, or text in another encoding: save it as UTF-8)",
            file=file, row=line, row_label="line", value=data[e.start : e.start + 1],
        ) from None


def _read(file: Path, table: str, allowed: tuple[str, ...], check=None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Columns of one CSV file and the file line of each data row.

    ``check(columns, lines)``, where given, is applied to the rows as they are read (the columns as
    arrays, the rows' file lines), so that a rule a row breaks on its own refuses the file before
    the work on the rest. A plain file (no quotes, no blank lines) is parsed by Arrow's CSV reader,
    about ten times faster than Python's, and checked whole; any other file, or one Arrow refuses,
    line by line in blocks of :data:`BLOCK_ROWS` rows, which names the line, column and cell of
    the first bad one."""
    text = read_text(file)
    first = text.split("\n", 1)[0]
    header = [h.strip() for h in next(csv.reader([first]), [])] if first.strip() else []
    if not header:
        raise DataError("empty file (a header line is required)", file=file)
    for h in header:
        if h not in allowed:
            raise DataError(f"unknown column; allowed: {', '.join(allowed)}", file=file, row=1, row_label="line", column=h)
    for h in _REQUIRED[table]:
        if h not in header:
            raise DataError("missing required column", file=file, row=1, row_label="line", column=h)
    if len(set(header)) != len(header):
        raise DataError("duplicate column names in the header", file=file, row=1, row_label="line", value=",".join(header))
    for group in _TOGETHER.get(table, ()):
        given = [h for h in group if h in header]
        if given and len(given) != len(group):
            missing = [h for h in group if h not in header]
            raise DataError(f"{', '.join(given)} without {', '.join(missing)}: a spin needs all three "
                            "components (or none: the spin is then unmeasured)", file=file, row=1,
                            row_label="line", column=missing[0])
    dtypes = {h: object if h in _STRINGS else (np.int64 if h in _INTS else np.float64) for h in header}
    read = _read_plain(text, file, header, dtypes)
    if read is not None:
        arrays, lines = read
        if check is not None and len(lines):
            check(arrays, lines)
    else:
        arrays, lines = _read_lines(text, file, header, dtypes, check)
    if table == "observations" and not lines.size:
        raise DataError("no data rows: the file holds only its header", file=file, row=1, row_label="line", value=",".join(header))
    return arrays, lines


def _read_plain(text: str, file: Path, header: list[str], dtypes: dict):
    """A file without quotes, carriage returns or blank lines (each data row is then line
    ``row + 2``) parsed by Arrow's CSV reader: (columns, lines), or None where the file is not
    plain or Arrow refuses a cell (the line-by-line reader then names it). A NaN or infinite value
    is refused here, naming its line and cell as that reader would."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    body = text[len(text.split("\n", 1)[0]) + 1:]
    if not body.strip() or '"' in text or "\r" in text or "\n\n" in body.rstrip("\n") or body.startswith("\n"):
        return None
    types = {h: pa.string() if dtypes[h] is object else (pa.int64() if dtypes[h] is np.int64 else pa.float64())
             for h in header}
    try:
        t = pacsv.read_csv(pa.py_buffer(body.encode("utf-8")),
                           read_options=pacsv.ReadOptions(column_names=header, use_threads=True),
                           parse_options=pacsv.ParseOptions(newlines_in_values=False, ignore_empty_lines=False),
                           convert_options=pacsv.ConvertOptions(column_types=types, null_values=[],
                                                                strings_can_be_null=False,
                                                                quoted_strings_can_be_null=False))
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return None
    arrays = {h: (np.asarray([c.strip() for c in t.column(h).to_pylist()], object) if dtypes[h] is object
                  else t.column(h).to_numpy().astype(dtypes[h], copy=False)) for h in header}
    lines = np.arange(t.num_rows, dtype=np.int64) + 2
    floats = [h for h in header if dtypes[h] is np.float64]
    bad = np.stack([~np.isfinite(arrays[h]) for h in floats], -1) if floats else np.zeros((len(lines), 0), bool)
    if bad.any():  # the first in the file: the first row, its first such cell
        row = int(np.flatnonzero(bad.any(-1))[0])
        h = floats[int(np.argmax(bad[row]))]
        cell = text.split("\n", row + 2)[row + 1].split(",")[header.index(h)].strip()
        raise DataError("NaN or infinite value", file=file, row=int(lines[row]), row_label="line", column=h, value=cell)
    return arrays, lines


def _read_lines(text: str, file: Path, header: list[str], dtypes: dict, check) -> tuple[dict, np.ndarray]:
    """The rows of a CSV text read one by one (Python's csv module), ``check`` applied to each
    block of :data:`BLOCK_ROWS` rows: (columns, lines). The first bad cell is refused naming its
    line, column and text."""
    lines, blocks, block_lines = [], [], []
    cols: dict[str, list] = {h: [] for h in header}

    def close_block():
        block = {h: np.asarray(v, dtypes[h]) for h, v in cols.items()}
        where = np.asarray(lines, np.int64)
        if check is not None and len(where):
            check(block, where)
        blocks.append(block)
        block_lines.append(where)
        for v in cols.values():
            v.clear()
        lines.clear()

    with io.StringIO(text, newline="") as f:
        reader = csv.reader(f)
        next(reader)  # the header, checked by the caller
        for row in reader:
            line_no = reader.line_num
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise DataError(f"expected {len(header)} cells, found {len(row)}", file=file, row=line_no, row_label="line", value=",".join(row))
            for h, cell in zip(header, row):
                cell = cell.strip()
                if h in _STRINGS:
                    cols[h].append(cell)
                    continue
                try:
                    v = int(cell) if h in _INTS else float(cell)
                except ValueError:
                    raise DataError("not a number" if h not in _INTS else "not an integer", file=file, row=line_no, row_label="line", column=h, value=cell) from None
                if h not in _INTS and not math.isfinite(v):  # refused here, at its line, not after the whole file
                    raise DataError("NaN or infinite value", file=file, row=line_no, row_label="line", column=h,
                                    value=cell)
                if h in _INTS and not _INT_RANGE[0] <= v <= _INT_RANGE[1]:
                    raise DataError(f"an id must lie within {_INT_RANGE[0]}..{_INT_RANGE[1]} (64 bits)", file=file,
                                    row=line_no, row_label="line", column=h, value=cell)
                cols[h].append(v)
            lines.append(line_no)
            if len(lines) == BLOCK_ROWS:
                close_block()
        close_block()
    arrays = {h: np.concatenate([b[h] for b in blocks]).astype(dtypes[h], copy=False) for h in header}
    return arrays, np.concatenate(block_lines)


def _row_check(file: Path, table: str, scale: float):
    """The ``check`` of :func:`_read` for ``table``: :func:`~ttsim_jax.data.validate.row_rules`
    on each block, its positions in metres; a sample beyond the positions' bound is left to the
    glitch rules (a few such samples are left out of the import, many refuse it as a unit error)."""
    from .validate import MAX_ABS_POSITION, row_rules

    def check(block: dict, lines: np.ndarray) -> None:
        columns = dict(block)
        rows = np.arange(len(lines))
        if all(k in columns for k in ("x", "y", "z")):
            for k in ("x", "y", "z"):
                columns[k] = columns[k] * scale
            near = np.all(np.abs(np.stack([columns[k] for k in ("x", "y", "z")], -1)) <= MAX_ABS_POSITION, -1)
            columns, rows = {k: v[near] for k, v in columns.items()}, rows[near]
        for e in row_rules(table, columns, file):
            row = rows[e.row]
            raw = block[e.column][row] if e.column in ("x", "y", "z") else e.value  # as in the file's units
            raise DataError(e.problem, file=file, row=int(lines[row]), row_label="line", column=e.column, value=raw)

    return check


def _check_sessions(ev_sid, obs_sid, ev_file, ev_lines, obs_file) -> None:
    """Every event must belong to a session that has observations."""
    bad = np.flatnonzero(~np.isin(ev_sid, obs_sid))
    if bad.size:
        raise DataError(
            f"event of a session that has no observations in {Path(obs_file).name}",
            file=ev_file, row=ev_lines[bad[0]], row_label="line", column="session_id", value=int(ev_sid[bad[0]]),
        )


def _check_speeds(sid, t, pos, raw_t, file, lines, time_unit) -> None:
    """Refuses a log whose ball hardly moves: most likely its times are not in ``time_unit``."""
    same = np.flatnonzero(sid[1:] == sid[:-1])
    if same.size < 5:
        return
    speed = np.linalg.norm(pos[same + 1] - pos[same], axis=-1) / (t[same + 1] - t[same])
    fast = float(np.percentile(speed, 90))
    if fast >= MIN_PLAY_SPEED:
        return
    hint = "is t in milliseconds? Import with --time-unit ms (time_unit='ms')" if time_unit == "s" else "check the time and length units"
    row = same[0] + 1
    raise DataError(
        f"the ball hardly moves: 90 % of the sample-to-sample speeds are below {fast:.3g} m/s (median sample interval "
        f"{float(np.median(t[same + 1] - t[same])):.3g} s), but a ball in play moves at metres per second; {hint}",
        file=file, row=lines[row], row_label="line", column="t", value=float(raw_t[row]),
    )


def _check_long_axis(sid, t, pos, raw_y, file, lines) -> None:
    """Refuses a log whose bounces at table height lie beside the table but would be on it with x
    and y swapped: the table's long axis must be x.

    Nothing beside the table is at its height, so such bounces are rare in canonical data (a low
    racket lift at most); a quarter of all table-height bounces is taken as proof.
    """
    from .segment import find_bounces
    from .tracks import session_slices

    half_l = schema.TABLE_LENGTH / 2 + schema.BALL_RADIUS
    half_w = schema.TABLE_WIDTH / 2 + schema.BALL_RADIUS
    on, swapped = 0, []
    for _, a, b in session_slices(sid):
        for c in find_bounces(t[a:b], pos[a:b], on_table=False):
            x, y = abs(c.pos[0]), abs(c.pos[1])
            if x <= half_l and y <= half_w:
                on += 1
            elif y <= half_l and x <= half_w:
                swapped.append((a + c.index, float(c.pos[1])))
    if swapped and len(swapped) >= 0.25 * (len(swapped) + on):
        row, y = swapped[0]
        raise DataError(
            f"the ball bounces at table height at y = {y:.3f} m, beyond the table's half-width ({schema.TABLE_WIDTH / 2} m) "
            f"but within its half-length ({schema.TABLE_LENGTH / 2} m), and {len(swapped)} of {len(swapped) + on} table-height "
            "bounces do so: the table's long axis must be x and y must run across it (turn the axes by 90 deg about z: "
            "new x = old y, new y = -old x)",
            file=file, row=lines[row], row_label="line", column="y", value=float(raw_y[row]),
        )


def read_csv(
    path, *, events=None, rackets=None, length_unit: str = "m", time_unit: str = "s", metadata: Metadata | None = None, detect: bool = True
) -> Dataset:
    """Reads a CSV log into a validated, segmented :class:`Dataset`.

    Arguments:
        path: ``observations.csv``, or a folder holding ``observations.csv`` and optionally
            ``events.csv`` and ``rackets.csv``.
        events: optional events CSV (default: ``events.csv`` beside the observations, if present).
        rackets: optional rackets CSV (default: ``rackets.csv`` beside them, if present).
        length_unit: ``"m"`` or ``"mm"`` for the positions in the files.
        time_unit: ``"s"`` or ``"ms"`` for the times in the files.
        metadata: dataset metadata (default: source = the file name).
        detect: detect contacts in sessions that have no labelled events.

    Returns:
        The dataset.
    """
    from .segment import detect_events, segments_from_events
    from .validate import borderline, validate

    path = Path(path)
    obs_file = path / "observations.csv" if path.is_dir() else path
    folder = obs_file.parent
    ev_file = Path(events) if events is not None else (folder / "events.csv" if (folder / "events.csv").exists() else None)
    rk_file = Path(rackets) if rackets is not None else (folder / "rackets.csv" if (folder / "rackets.csv").exists() else None)
    if length_unit not in LENGTH_UNITS:
        raise ValueError(f"length_unit must be one of {', '.join(LENGTH_UNITS)}, got {length_unit!r}")
    if time_unit not in TIME_UNITS:
        raise ValueError(f"time_unit must be one of {', '.join(TIME_UNITS)}, got {time_unit!r}")
    scale, t_scale = LENGTH_UNITS[length_unit], TIME_UNITS[time_unit]
    for f in (obs_file, ev_file, rk_file):
        if f is not None and not f.is_file():
            raise DataError("no such file", file=f)

    o, o_lines = _read(obs_file, "observations", OBSERVATION_COLUMNS, _row_check(obs_file, "observations", scale))
    keep, mended = time_order(o["session_id"], o["t"])
    if mended:
        o, o_lines = {k: v[keep] for k, v in o.items()}, o_lines[keep]
        warnings.warn(DataWarning("; ".join(f"{n} {what}" for what, n in mended.items()), file=obs_file,
                                  table="observations"), stacklevel=2)
    pos = np.stack([o["x"], o["y"], o["z"]], axis=-1) * scale
    spin = np.stack([o[k] for k in ("spin_x", "spin_y", "spin_z")], axis=-1) if "spin_x" in o else None
    keep, unspun, far = far_samples(pos, spin, lambda row: f"{obs_file.name} line {o_lines[row]}, session "
                                    f"{o['session_id'][row]}, t = {o['t'][row] * t_scale:.4f} s")
    if far:
        if unspun.any():
            spin = np.where(unspun[:, None], 0.0, spin)
            o["spin_conf"] = np.where(unspun, 0.0, o["spin_conf"]) if "spin_conf" in o else np.where(unspun, 0.0, 1.0)
        o, o_lines, pos = {k: v[keep] for k, v in o.items()}, o_lines[keep], pos[keep]
        spin = None if spin is None else spin[keep]
        mended.update(far)
    ev = rk = None
    lines = {"observations": o_lines}
    if ev_file is not None:
        e, lines["events"] = _read(ev_file, "events", EVENT_COLUMNS, _row_check(ev_file, "events", scale))
        _check_sessions(e["session_id"], o["session_id"], ev_file, lines["events"], obs_file)
        ev = {"session_id": e["session_id"], "t": e["t"] * t_scale, "kind": e["kind"], "pos": np.stack([e["x"], e["y"], e["z"]], -1) * scale}
        if "event_id" in e:
            ev["event_id"] = e["event_id"]
    if rk_file is not None:
        r, lines["rackets"] = _read(rk_file, "rackets", RACKET_COLUMNS, _row_check(rk_file, "rackets", scale))
        for k in ("x", "y", "z", "d_y", "d_z"):
            r[k] = r[k] * scale
        rk = {
            "event_id": r["event_id"],
            "pos": np.stack([r["x"], r["y"], r["z"]], -1),
            "quat": np.stack([r["qw"], r["qx"], r["qy"], r["qz"]], -1),
            "vel": np.stack([r["vx"], r["vy"], r["vz"]], -1),
            "ang_vel": np.stack([r["wx"], r["wy"], r["wz"]], -1),
            "contact": np.stack([r["d_y"], r["d_z"]], -1),
        }
        if "config" in r:
            rk["config"] = r["config"]
    t = o["t"] * t_scale
    ds = Dataset.from_arrays(
        o["session_id"],
        t,
        pos,
        spin=spin,
        spin_conf=o.get("spin_conf"),
        events=ev,
        rackets=rk,
        segments=None,
        metadata=metadata if metadata is not None else Metadata(source=f"CSV log {obs_file.name}"),
    )
    # Validate before any reordering, so that rows map to the files' lines.
    files = {"observations": obs_file, "events": ev_file, "rackets": rk_file}
    try:
        validate(ds)
    except DataError as e:
        raise _on_lines(e, files, lines) from None
    _check_speeds(o["session_id"], t, pos, o["t"], obs_file, o_lines, time_unit)
    _check_long_axis(o["session_id"], t, pos, o["y"], obs_file, o_lines)
    ds = detect_events(ds) if detect else segments_from_events(ds)
    ds, too_fast = leave_out_too_fast(ds, lambda row: f"{obs_file.name} line {o_lines[row]}")
    ds = noted(ds, {**mended, **too_fast})
    # Segmenting keeps the observations' and rackets' rows in file order (events are re-sorted and
    # joined by detected ones): the checks that need segments still name those files' lines.
    same_rows = {k: files[k] for k in ("observations", "rackets")}
    try:
        validate(ds)
    except DataError as e:
        raise _on_lines(e, same_rows, lines) from None
    for w in borderline(ds):
        warnings.warn(_on_lines(w, same_rows, lines), stacklevel=2)
    return ds


def _on_lines(e, files: dict, lines: dict):
    """``e`` (a DataError or DataWarning about a table's rows) located in that table's CSV file by
    line; unchanged for tables not in ``files`` (or without a file)."""
    if files.get(e.table) is None:
        return e
    # Rows named inside the message (a duplicate's first row) are rows of the same table.
    problem = re.sub(r"\brow (\d+)\b", lambda m: f"line {lines[e.table][int(m.group(1))]}", e.problem)
    return type(e)(problem, file=files[e.table], table=e.table, row=None if e.row is None else lines[e.table][e.row],
                   row_label="line", column=e.column, value=e.value)




def write_csv(ds: Dataset, folder, *, rows=None) -> Path:
    """Writes a dataset's observations as a tracker's log, ``folder/observations.csv`` (the layout
    :func:`read_csv` reads), without events: what a tracker that labels nothing writes.

    Arguments:
        ds: the dataset.
        folder: where to write (created if missing); an existing ``observations.csv`` is replaced
            atomically.
        rows: optional boolean mask or indices of the observations to write (e.g. only one direction
            of play); the others are left out, as a tracker that did not follow the ball.

    Returns:
        The path of the file written.
    """
    from ttsim_jax.files.atomic import atomic_write

    obs = ds.observations
    keep = np.arange(len(obs["t"])) if rows is None else np.asarray(rows)
    if keep.dtype == bool:
        keep = np.flatnonzero(keep)
    out = io.StringIO()
    out.write(",".join(OBSERVATION_COLUMNS) + "\n")
    floats = [np.asarray(obs[c], np.float64)[keep] for c in OBSERVATION_COLUMNS[1:]]
    for sid, *values in zip(np.asarray(obs["session_id"])[keep], *floats):
        out.write(f"{int(sid)}," + ",".join(repr(float(v)) for v in values) + "\n")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "observations.csv"
    atomic_write(path, out.getvalue().encode())
    return path
