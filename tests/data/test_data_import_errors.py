"""Importers name the file, line, column and text of malformed source files (no real data needed)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from ttsim_jax.data import DataError, import_source
from ttsim_jax.data.importers import spindoe


def _spindoe_folder(tmp_path, rally, bad_line=None):
    t, pos, _, _ = rally
    f = spindoe.FRAME
    src = (pos - f.translation) @ f.rotation  # inverse of the importer's transform
    rows = [f"{a:.4f};{p[0]:.4f};{p[1]:.4f};{p[2]:.4f}" for a, p in zip(t, src)]
    if bad_line is not None:
        cells = rows[bad_line - 1].split(";")
        cells[2] = "1.2.3"
        rows[bad_line - 1] = ";".join(cells)
    (tmp_path / "007.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "index.csv").write_text("traj_file,x_spin,y_spin,z_spin\n7,10.0,-150.0,20.0\n")
    return tmp_path


def test_spindoe_synthetic_folder_imports(tmp_path, rally):
    ds = import_source(_spindoe_folder(tmp_path, rally), "spindoe")
    assert list(ds.sessions["name"]) == ["spindoe/007.csv"]
    zt = ds.events["z"][ds.events["kind"] == "table"]
    assert len(zt) == 2 and np.all(np.abs(zt - 0.02) < 0.002)
    # Spin turned with the axes: (x, y, z) = (-y_s, x_s, z_s).
    assert ds.segments["spin_x"][0] == pytest.approx(150.0, rel=0.01)
    assert ds.segments["spin_conf"][0] == 1.0


def test_spindoe_bad_cell(tmp_path, rally):
    folder = _spindoe_folder(tmp_path, rally, bad_line=12)
    with pytest.raises(DataError) as e:
        import_source(folder, "spindoe")
    msg = str(e.value)
    assert "007.csv" in msg and "line 12" in msg and "column 'y'" in msg and "'1.2.3'" in msg


def test_spindoe_missing_spin(tmp_path, rally):
    folder = _spindoe_folder(tmp_path, rally)
    (folder / "index.csv").write_text("traj_file,x_spin,y_spin,z_spin\n8,1,2,3\n")
    with pytest.raises(DataError) as e:
        import_source(folder, "spindoe")
    assert "index.csv" in str(e.value) and "traj_file" in str(e.value) and "7" in str(e.value)


def test_tt3d_wrong_header(tmp_path):
    (tmp_path / "001.csv").write_text("time,X,Y,Z\n0.0,0,0,0.3\n")
    with pytest.raises(DataError) as e:
        import_source(tmp_path, "tt3d")
    assert "001.csv" in str(e.value) and "line 1" in str(e.value) and "Timestamp,X,Y,Z" in str(e.value)


def test_mpi_missing_dataset(tmp_path):
    with h5py.File(tmp_path / "x.hdf5", "w") as f:
        g = f.create_group("originals/0")
        g["time_stamps"] = np.arange(5) * 0.005
        g["launch_param"] = np.zeros(5)
    with pytest.raises(DataError) as e:
        import_source(tmp_path, "mpi")
    assert "x.hdf5" in str(e.value) and "positions" in str(e.value) and "originals/0" in str(e.value)


def test_unknown_source(tmp_path):
    with pytest.raises(ValueError, match="unknown source"):
        import_source(tmp_path, "wimbledon")


def test_spindoe_file_with_byte_order_mark_is_read(tmp_path, rally):
    folder = _spindoe_folder(tmp_path, rally)
    f = folder / "007.csv"
    f.write_bytes(b"\xef\xbb\xbf" + f.read_bytes())
    ds = import_source(folder, "spindoe")
    assert len(ds.observations["t"]) == len(rally[0])


def test_tt3d_binary_file_names_file_and_line(tmp_path):
    (tmp_path / "001.csv").write_bytes(b"Timestamp,X,Y,Z\n0.0,0\x00\x01,0,0.3\n")
    with pytest.raises(DataError) as e:
        import_source(tmp_path, "tt3d")
    assert "001.csv" in str(e.value) and "line 2" in str(e.value) and "binary content" in str(e.value)
