"""Importers of public measured datasets into the canonical frame and format.

One entry point, :func:`import_source`. Each source module holds its reader (``read_raw``), the
frame constants measured from its data (``AXES``, ``PLANE``, ``SHIFT_XY`` -> ``FRAME``), and
``load``. ``docs/data_format.md`` says how each frame was established, with the numbers.
"""

from __future__ import annotations

import dataclasses
import importlib
import io
import warnings
from pathlib import Path

import numpy as np

from ..csvlog import read_csv, read_text
from ..dataset import Dataset, Metadata
from ..errors import DataError
from ..frames import FrameTransform, fit_bounce_plane
from ..segment import detect_events, find_bounces, segments_from_events

SOURCES = ("spindoe", "tt3d", "mpi", "tt_rackets", "csv")


@dataclasses.dataclass
class RawSession:
    """One recording as read from a source, still in the source's frame.

    Attributes:
        name: label, e.g. ``"spindoe/004.csv"``.
        t: (T,) times [s].
        pos: (T, 3) positions [m], source frame.
        spin: optional (3,) measured spin [rad/s], source frame.
        notes: free text (e.g. launcher settings).
    """

    name: str
    t: np.ndarray
    pos: np.ndarray
    spin: np.ndarray | None = None
    notes: str = ""


def import_source(path, source: str, *, length_unit: str = "m", time_unit: str = "s") -> Dataset:
    """Reads a public dataset (or a CSV log) and returns it in the canonical frame and format.

    Arguments:
        path: the source's folder (e.g. ``.../real/spindoe``) or one of its files.
        source: ``spindoe``, ``tt3d``, ``mpi``, ``tt_rackets`` (racket bounces with measured
            states: :mod:`~ttsim_jax.data.importers.tt_rackets`) or ``csv`` (see
            :mod:`ttsim_jax.data.csvlog`).
        length_unit, time_unit: units of a CSV log (``"m"``/``"mm"``, ``"s"``/``"ms"``); the
            public sources have known units.

    Returns:
        Validated, segmented :class:`Dataset` (events detected from the observations; tt_rackets:
        racket events with their measured states).
    """
    if source not in SOURCES:
        raise ValueError(f"unknown source {source!r}; known: {', '.join(SOURCES)}")
    if source != "csv" and (length_unit, time_unit) != ("m", "s"):
        raise DataError(f"length and time units apply to CSV logs only; the {source} importer knows its source's units",
                        file=path)
    path = Path(path)
    if not path.exists():
        raise DataError("no such file or directory", file=path)
    if source == "csv":
        return read_csv(path, length_unit=length_unit, time_unit=time_unit)
    module = importlib.import_module(f".{source}", __name__)
    return module.load(path)


def clean_times(t, pos) -> tuple[np.ndarray, np.ndarray, int]:
    """Drops samples whose time does not increase (duplicated camera timestamps).

    Arguments:
        t: (T,) times; pos: (T, 3) positions.

    Returns:
        (t, pos, n_dropped) keeping each sample only when its time exceeds the last kept one.
    """
    keep = np.ones(len(t), bool)
    last = -np.inf
    for i, ti in enumerate(t):
        if ti > last:
            last = ti
        else:
            keep[i] = False
    return t[keep], pos[keep], int((~keep).sum())


def build_dataset(raw: list[RawSession], frame: FrameTransform, metadata: Metadata, *, spin_conf: float = 1.0) -> Dataset:
    """Converts raw sessions to a segmented, validated dataset in the canonical frame.

    Measured spins are rotated into the canonical frame and given (with ``spin_conf``) to the
    observations before the session's first contact: a contact changes the spin, and the sources
    give one spin per recording.

    Arguments:
        raw: sessions in the source frame.
        frame: source -> canonical transform.
        metadata: dataset metadata.
        spin_conf: confidence given to measured spins.

    Returns:
        The dataset.
    """
    from ..glitches import leave_out_too_fast, noted
    from ..validate import borderline, validate

    sid, ts, ps, names, notes, spins = [], [], [], [], [], []
    dropped = 0
    for k, s in enumerate(raw):
        t, p, n = clean_times(np.asarray(s.t, np.float64), np.asarray(s.pos, np.float64))
        dropped += n
        sid.append(np.full(len(t), k, np.int64))
        ts.append(t)
        ps.append(frame.points(p))
        names.append(s.name)
        notes.append(s.notes)
        spins.append(None if s.spin is None else frame.vectors(s.spin))
    if dropped:
        metadata = dataclasses.replace(
            metadata, notes=(metadata.notes + "\n" if metadata.notes else "") + f"import dropped {dropped} samples whose time did not increase"
        )
    ds = Dataset.from_arrays(
        np.concatenate(sid),
        np.concatenate(ts),
        np.concatenate(ps),
        sessions={"session_id": np.arange(len(raw)), "name": names, "notes": notes},
        segments=None,
        metadata=metadata,
    )
    ds = detect_events(ds)
    if any(s is not None for s in spins):
        obs = dict(ds.observations)
        first_event = {}
        for sid_, t_ in zip(ds.events["session_id"], ds.events["t"]):
            first_event[int(sid_)] = min(first_event.get(int(sid_), np.inf), float(t_))
        for k, s in enumerate(spins):
            if s is None:
                continue
            rows = (obs["session_id"] == k) & (obs["t"] < first_event.get(k, np.inf))
            obs["spin_x"][rows], obs["spin_y"][rows], obs["spin_z"][rows] = s
            obs["spin_conf"][rows] = spin_conf
        ds = segments_from_events(ds.replace(observations=obs))
    ds, too_fast = leave_out_too_fast(ds)
    ds = noted(ds, too_fast)
    validate(ds)
    for w in borderline(ds):
        warnings.warn(w, stacklevel=2)
    return ds


def survey(raw: list[RawSession], axes) -> dict:
    """Measures where the bounces of a source sit after rotating by ``axes`` (no translation).

    Used to establish and re-check the frame constants: finds z-velocity reversals at any height,
    keeps the ones with evenly spaced samples, and fits the plane of their contact points.

    Arguments:
        raw: sessions in the source frame.
        axes: (3, 3) rotation source -> table-aligned axes.

    Returns:
        dict with ``points`` (N, 3) contact points (clean bounces) and the fits ``tilted`` and
        ``level`` (see :func:`ttsim_jax.data.frames.fit_bounce_plane`), plus ``n_all`` (all
        bounces found, including ones next to dropped frames).
    """
    rot = FrameTransform(np.asarray(axes, np.float64), np.zeros(3))
    pts, n_all = [], 0
    for s in raw:
        t, p, _ = clean_times(np.asarray(s.t, np.float64), np.asarray(s.pos, np.float64))
        found = find_bounces(t, rot.points(p), height=None, on_table=False)
        n_all += len(found)
        pts += [c.pos for c in found if c.clean]
    pts = np.asarray(pts).reshape(-1, 3)
    return {"points": pts, "n_all": n_all, "tilted": fit_bounce_plane(pts, tilt=True), "level": fit_bounce_plane(pts, tilt=False)}


def read_numeric_rows(path: Path, *, delimiter: str, n_cols: int, skip_header: bool, names: tuple[str, ...]) -> np.ndarray:
    """Reads a numeric text table, naming the line, column and text of any bad cell.

    Arguments:
        path: file to read.
        delimiter: column separator.
        n_cols: expected number of columns.
        skip_header: whether line 1 is a header.
        names: column names (for messages).

    Returns:
        (rows, n_cols) float64 array.
    """
    rows = []
    with io.StringIO(read_text(path), newline="") as f:
        for line_no, line in enumerate(f, start=1):
            if skip_header and line_no == 1:
                continue
            line = line.strip()
            if not line:
                continue
            cells = line.split(delimiter)
            if len(cells) != n_cols:
                raise DataError(f"expected {n_cols} columns ({', '.join(names)}), found {len(cells)}", file=path, row=line_no, row_label="line", value=line)
            row = []
            for name, cell in zip(names, cells):
                try:
                    v = float(cell)
                except ValueError:
                    raise DataError("not a number", file=path, row=line_no, row_label="line", column=name, value=cell) from None
                if not np.isfinite(v):
                    raise DataError("not a finite number", file=path, row=line_no, row_label="line", column=name, value=cell)
                row.append(v)
            rows.append(row)
    if not rows:
        raise DataError("no data rows", file=path)
    return np.asarray(rows, np.float64)
