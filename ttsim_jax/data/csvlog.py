"""Import of users' own logs from CSV (layout in ``docs/data_format.md``, "CSV import").

``observations.csv`` (required), header line then one sample per line, comma-separated::

    session_id,t,x,y,z[,spin_x,spin_y,spin_z,spin_conf]

``events.csv`` (optional)::  ``session_id,t,kind,x,y,z[,event_id]``

``rackets.csv`` (optional, one line per racket event)::
``event_id,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,d_y,d_z``

Positions in the canonical frame, in metres (or millimetres with ``length_unit="mm"``). Errors
name the file, line (1-based, the header is line 1), column and text of the bad cell.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from . import schema
from .dataset import Dataset, Metadata
from .errors import DataError

OBSERVATION_COLUMNS = ("session_id", "t", "x", "y", "z", "spin_x", "spin_y", "spin_z", "spin_conf")
EVENT_COLUMNS = ("session_id", "t", "kind", "x", "y", "z", "event_id")
RACKET_COLUMNS = tuple(c.name for c in schema.RACKETS)
_REQUIRED = {
    "observations": ("session_id", "t", "x", "y", "z"),
    "events": ("session_id", "t", "kind", "x", "y", "z"),
    "rackets": RACKET_COLUMNS,
}
_INTS = {"session_id", "event_id"}
_STRINGS = {"kind"}


def _read(file: Path, table: str, allowed: tuple[str, ...]) -> dict[str, np.ndarray]:
    with open(file, newline="") as f:
        reader = csv.reader(f)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise DataError("empty file (a header line is required)", file=file) from None
        for h in header:
            if h not in allowed:
                raise DataError(f"unknown column; allowed: {', '.join(allowed)}", file=file, row=1, row_label="line", column=h)
        for h in _REQUIRED[table]:
            if h not in header:
                raise DataError("missing required column", file=file, row=1, row_label="line", column=h)
        if len(set(header)) != len(header):
            raise DataError("duplicate column names in the header", file=file, row=1, row_label="line", value=",".join(header))
        cols: dict[str, list] = {h: [] for h in header}
        for line_no, row in enumerate(reader, start=2):
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
                cols[h].append(v)
    return {h: np.asarray(v, object if h in _STRINGS else (np.int64 if h in _INTS else np.float64)) for h, v in cols.items()}


def read_csv(path, *, events=None, rackets=None, length_unit: str = "m", metadata: Metadata | None = None, detect: bool = True) -> Dataset:
    """Reads a CSV log into a validated, segmented :class:`Dataset`.

    Arguments:
        path: ``observations.csv``, or a folder holding ``observations.csv`` and optionally
            ``events.csv`` and ``rackets.csv``.
        events: optional events CSV (default: ``events.csv`` beside the observations, if present).
        rackets: optional rackets CSV (default: ``rackets.csv`` beside them, if present).
        length_unit: ``"m"`` or ``"mm"`` for the positions in the files.
        metadata: dataset metadata (default: source = the file name).
        detect: detect contacts in sessions that have no labelled events.

    Returns:
        The dataset.
    """
    from .segment import detect_events, segments_from_events
    from .validate import validate

    path = Path(path)
    obs_file = path / "observations.csv" if path.is_dir() else path
    folder = obs_file.parent
    ev_file = Path(events) if events is not None else (folder / "events.csv" if (folder / "events.csv").exists() else None)
    rk_file = Path(rackets) if rackets is not None else (folder / "rackets.csv" if (folder / "rackets.csv").exists() else None)
    if length_unit not in ("m", "mm"):
        raise ValueError(f"length_unit must be 'm' or 'mm', got {length_unit!r}")
    scale = 1e-3 if length_unit == "mm" else 1.0
    if not obs_file.exists():
        raise DataError("no such file", file=obs_file)

    o = _read(obs_file, "observations", OBSERVATION_COLUMNS)
    pos = np.stack([o["x"], o["y"], o["z"]], axis=-1) * scale
    spin = np.stack([o[k] for k in ("spin_x", "spin_y", "spin_z")], axis=-1) if "spin_x" in o else None
    ev = rk = None
    if ev_file is not None:
        e = _read(ev_file, "events", EVENT_COLUMNS)
        ev = {"session_id": e["session_id"], "t": e["t"], "kind": e["kind"], "pos": np.stack([e["x"], e["y"], e["z"]], -1) * scale}
        if "event_id" in e:
            ev["event_id"] = e["event_id"]
    if rk_file is not None:
        r = _read(rk_file, "rackets", RACKET_COLUMNS)
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
    ds = Dataset.from_arrays(
        o["session_id"],
        o["t"],
        pos,
        spin=spin,
        spin_conf=o.get("spin_conf"),
        events=ev,
        rackets=rk,
        segments=None,
        metadata=metadata if metadata is not None else Metadata(source=f"CSV log {obs_file.name}"),
    )
    # Validate before any reordering, so rows map to lines: line = row + 2 (header is line 1).
    files = {"observations": obs_file, "events": ev_file, "rackets": rk_file}
    try:
        validate(ds)
    except DataError as e:
        if e.table in files and files[e.table] is not None:
            raise DataError(
                e.problem,
                file=files[e.table],
                table=e.table,
                row=None if e.row is None else e.row + 2,
                row_label="line",
                column=e.column,
                value=e.value,
            ) from None
        raise
    ds = detect_events(ds) if detect else segments_from_events(ds)
    validate(ds)
    return ds


