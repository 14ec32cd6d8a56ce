"""SpinDOE trajectories with measured spin (Gossard, Tebbe, Ziegler, Zell, arXiv:2303.03879, 2023).

Files: ``NNN.csv`` (``t; x; y; z``, no header, ``;``-separated) and ``index.csv`` (``traj_file,
x_spin, y_spin, z_spin`` in rad/s). How the frame constants below were measured is in
``docs/data_format.md``; :func:`ttsim_jax.data.importers.survey` re-measures them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..dataset import Dataset, Metadata
from ..errors import DataError
from ..frames import table_frame
from . import RawSession, build_dataset, read_numeric_rows

#: Source y runs along the table: canonical x = -y_s, y = x_s (a +90 deg turn about z), so the
#: launched balls travel towards +x.
AXES = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
#: Plane of the ball centres at bounces in the turned axes, z = a x + b y + c [m] (179 clean bounces).
PLANE = (-0.00802, 0.00236, -0.00402)
#: The source origin is already at the table centre in x and y (bounces and off-table drops agree).
SHIFT_XY = (0.0, 0.0)
FRAME = table_frame(AXES, PLANE, SHIFT_XY)

CITATION = (
    "SpinDOE trajectories (github.com/cogsys-tuebingen/spindoe, data/trajectories): Gossard, Tebbe, "
    "Ziegler, Zell, 'SpinDOE: A ball spin estimation method for table tennis robot', arXiv:2303.03879, 2023"
)


def read_index(path: Path) -> dict[int, np.ndarray]:
    """``index.csv`` -> {trajectory number: (3,) spin [rad/s] in the source frame}."""
    rows = read_numeric_rows(path, delimiter=",", n_cols=4, skip_header=True, names=("traj_file", "x_spin", "y_spin", "z_spin"))
    out = {}
    for line, r in enumerate(rows, start=2):
        key = int(r[0])
        if key != r[0] or key in out:
            raise DataError("trajectory number must be a unique integer", file=path, row=line, row_label="line", column="traj_file", value=r[0])
        out[key] = r[1:4]
    return out


def read_raw(path) -> list[RawSession]:
    """Reads one ``NNN.csv`` (with ``index.csv`` beside it) or a folder of them, source frame."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    files = sorted(p for p in folder.glob("[0-9]*.csv")) if path.is_dir() else [path]
    if not files:
        raise DataError("no trajectory files NNN.csv found", file=folder)
    index_path = folder / "index.csv"
    if not index_path.exists():
        raise DataError("index.csv with the measured spins is missing", file=index_path)
    spins = read_index(index_path)
    out = []
    for f in files:
        number = int(f.stem)
        if number not in spins:
            raise DataError("trajectory has no spin in index.csv", file=index_path, column="traj_file", value=number)
        a = read_numeric_rows(f, delimiter=";", n_cols=4, skip_header=False, names=("t", "x", "y", "z"))
        out.append(RawSession(name=f"spindoe/{f.name}", t=a[:, 0], pos=a[:, 1:4], spin=spins[number]))
    return out


def load(path) -> Dataset:
    """SpinDOE folder or file -> canonical :class:`Dataset` (spin on each first segment, conf 1)."""
    meta = Metadata(
        source=CITATION,
        equipment={"ball": "40 mm table tennis ball with a printed dot pattern", "tracking": "stereo cameras, ~143 Hz", "spin": "SpinDOE dot-pattern estimate"},
        notes="frame: source axes turned +90 deg about z, table tilt removed, bounces moved to z = 0.02 (docs/data_format.md)",
    )
    return build_dataset(read_raw(path), FRAME, meta)
