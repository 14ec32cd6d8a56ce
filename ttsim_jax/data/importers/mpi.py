"""MPI ball-launcher recordings (intelligent-soft-robots/ball_prediction, BSD-3-Clause).

HDF5 files with groups ``originals/<i>/`` holding ``launch_param`` (5,), ``time_stamps`` (T,),
``positions`` (T, 3) and ``velocities`` (T, 3). The velocities are finite differences with zeros
where a frame was missing, so they are not imported (they follow from the positions). Frame
constants measured as described in ``docs/data_format.md``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import schema
from ..dataset import Dataset, Metadata
from ..errors import DataError
from ..frames import table_frame
from ..segment import find_bounces
from . import RawSession, build_dataset

#: Source x already runs along the table, in the launch direction; z is up.
AXES = np.eye(3)
#: Height of the ball centres at bounces [m]; too few bounces spread across the table to fit a tilt.
PLANE = (0.0, 0.0, 0.7594)
#: The table centre lies at source x = 1.44 +- 0.25 m (only bounded by the data, see
#: :func:`centre_bounds`); y = 0 is assumed to be the centre line.
SHIFT_XY = (-1.44, 0.0)
FRAME = table_frame(AXES, PLANE, SHIFT_XY)

CITATION = "MPI-IS ball-launcher recordings (github.com/intelligent-soft-robots/ball_prediction, data/*.hdf5, BSD-3-Clause)"


def read_raw(path) -> list[RawSession]:
    """Reads one .hdf5 file or a folder of them, source frame."""
    import h5py

    path = Path(path)
    files = sorted(path.glob("*.hdf5")) if path.is_dir() else [path]
    if not files:
        raise DataError("no .hdf5 files found", file=path)
    out = []
    for f in files:
        with h5py.File(f, "r") as h:
            if "originals" not in h:
                raise DataError("missing group 'originals'", file=f)
            group = h["originals"]
            for key in sorted(group.keys(), key=lambda k: (len(k), k)):
                g = group[key]
                for name in ("time_stamps", "positions", "launch_param"):
                    if name not in g:
                        raise DataError("missing dataset", file=f, table=f"originals/{key}", column=name)
                t = np.asarray(g["time_stamps"][:], np.float64)
                p = np.asarray(g["positions"][:], np.float64)
                if p.ndim != 2 or p.shape[1] != 3 or len(p) != len(t):
                    raise DataError(f"positions must be (T, 3) with T = {len(t)}", file=f, table=f"originals/{key}", column="positions", value=p.shape)
                bad = np.flatnonzero(~np.isfinite(p).all(axis=1) | ~np.isfinite(t))
                if bad.size:
                    raise DataError("not finite", file=f, table=f"originals/{key}", row=bad[0], column="positions", value=p[bad[0]].tolist())
                launch = np.asarray(g["launch_param"][:], np.float64).tolist()
                out.append(RawSession(name=f"mpi/{f.stem}/{key}", t=t, pos=p, notes=json.dumps({"launch_param": launch})))
    return out


def centre_bounds(raw: list[RawSession], surface_z: float = PLANE[2] - schema.BALL_RADIUS) -> tuple[float, float]:
    """Bounds on the source x of the table centre, from the data alone.

    The far end of the table lies beyond the farthest bounce, so the centre is at least
    ``max bounce x - length / 2``; every launched ball clears the net (ball centre at least
    net height + radius above the surface where it crosses the net line), so the net, which is
    at the centre, lies before the first x at which some ball would be lower than that.

    Arguments:
        raw: the recordings, source frame.
        surface_z: source z of the table surface [m].

    Returns:
        (lowest, highest) possible source x of the table centre [m].
    """
    bounce_x = [c.pos[0] for s in raw for c in find_bounces(s.t, s.pos, height=None, on_table=False)]
    lowest = max(bounce_x) - schema.TABLE_LENGTH / 2
    clear = surface_z + schema.NET_HEIGHT + schema.BALL_RADIUS
    highest = np.inf
    for s in raw:
        x, z = s.pos[:, 0], s.pos[:, 2]
        below = np.flatnonzero(z[1:] < clear) + 1
        # First crossing of the net height on the way out: the net cannot be beyond it.
        inside = below[x[below] > x[0]]
        if inside.size:
            k = inside[0]
            highest = min(highest, float(np.interp(clear, [z[k], z[k - 1]], [x[k], x[k - 1]])))
    return float(lowest), float(highest)


def load(path) -> Dataset:
    """MPI folder or file -> canonical :class:`Dataset` (no measured spin)."""
    meta = Metadata(
        source=CITATION,
        equipment={"launcher": "pneumatic ball launcher (5 settings in sessions.notes)", "tracking": "multi-camera tennicam, ~178 Hz"},
        notes="frame: source axes kept, bounces moved to z = 0.02, table centre assumed at source x = 1.44 (docs/data_format.md)",
    )
    return build_dataset(read_raw(path), FRAME, meta)
