"""TT3D reconstructed rallies (cogsys-tuebingen/tt3d, arXiv:2504.10035, 2025).

Files: ``NNN.csv`` with header ``Timestamp,X,Y,Z`` (s, m). No spin. Frame constants measured as
described in ``docs/data_format.md``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..dataset import Dataset, Metadata
from ..csvlog import read_text
from ..errors import DataError
from ..frames import table_frame
from . import RawSession, build_dataset, read_numeric_rows

#: Source Y runs along the table: canonical x = -Y, y = X (a +90 deg turn about z), as for SpinDOE.
AXES = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
#: Plane of the ball centres at bounces in the turned axes, z = a x + b y + c [m].
PLANE = (-0.00213, 0.00069, 0.01644)
SHIFT_XY = (0.0, 0.0)
FRAME = table_frame(AXES, PLANE, SHIFT_XY)

CITATION = "TT3D (github.com/cogsys-tuebingen/tt3d, data/evaluation/3D_gt): 'TT3D: table tennis match 3D reconstruction', arXiv:2504.10035, 2025"


def read_raw(path) -> list[RawSession]:
    """Reads one TT3D csv or a folder of them, source frame."""
    path = Path(path)
    files = sorted(path.glob("*.csv")) if path.is_dir() else [path]
    if not files:
        raise DataError("no .csv files found", file=path)
    out = []
    for f in files:
        header = read_text(f).partition("\n")[0].strip()
        if header.replace(" ", "") != "Timestamp,X,Y,Z":
            raise DataError("expected the header 'Timestamp,X,Y,Z'", file=f, row=1, row_label="line", value=header)
        a = read_numeric_rows(f, delimiter=",", n_cols=4, skip_header=True, names=("Timestamp", "X", "Y", "Z"))
        out.append(RawSession(name=f"tt3d/{f.name}", t=a[:, 0], pos=a[:, 1:4]))
    return out


def load(path) -> Dataset:
    """TT3D folder or file -> canonical :class:`Dataset` (no spin)."""
    meta = Metadata(
        source=CITATION,
        equipment={"tracking": "monocular video 3D reconstruction (ground truth set), ~179 Hz", "play": "amateur rallies"},
        notes="frame: source axes turned +90 deg about z, table tilt removed, bounces moved to z = 0.02 (docs/data_format.md)",
    )
    return build_dataset(read_raw(path), FRAME, meta)
