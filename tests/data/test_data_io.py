"""Save/load of the Parquet dataset format: exact round trip, clear errors on bad files."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from ttsim_jax.data import DataError, load, save, schema, validate
from ttsim_jax.data.io import METADATA_FILE, table_path


def assert_same(a, b):
    assert a.metadata == b.metadata
    for name in schema.TABLES:
        ta, tb = a.table(name), b.table(name)
        assert list(ta) == list(tb) or set(ta) == set(tb)
        for col in ta:
            va, vb = np.asarray(ta[col]), np.asarray(tb[col])
            assert va.dtype == vb.dtype, (name, col)
            assert va.shape == vb.shape, (name, col)
            assert (va == vb).all(), (name, col)  # bitwise-equal floats, equal strings


def test_save_then_load_is_exact(small_dataset, tmp_path):
    ds = small_dataset
    validate(ds)
    save(ds, tmp_path / "ds")
    back = load(tmp_path / "ds")
    assert_same(ds, back)
    assert len(back.rackets["event_id"]) == 1 and len(back.segments["segment_id"]) >= 4
    # The values are not merely close: a pathological float survives too.
    assert back.observations["t"][1] == ds.observations["t"][1]


def test_save_refuses_to_overwrite(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "ds")
    with pytest.raises(FileExistsError):
        save(small_dataset, tmp_path / "ds")
    save(small_dataset, tmp_path / "ds", overwrite=True)


def _drop_column(file, column):
    t = pq.read_table(file)
    pq.write_table(t.drop_columns([column]).replace_schema_metadata(t.schema.metadata), file)


def test_missing_column_names_file_and_column(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "ds")
    f = table_path(tmp_path / "ds", "observations")
    _drop_column(f, "z")
    with pytest.raises(DataError) as e:
        load(tmp_path / "ds")
    msg = str(e.value)
    assert str(f) in msg and "'z'" in msg and "missing" in msg
    assert e.value.column == "z"


def test_null_cell_names_row(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "ds")
    f = table_path(tmp_path / "ds", "observations")
    t = pq.read_table(f)
    x = t.column("x").to_pylist()
    x[7] = None
    t = t.set_column(t.column_names.index("x"), "x", pa.array(x, pa.float64()))
    pq.write_table(t, f)
    with pytest.raises(DataError) as e:
        load(tmp_path / "ds")
    assert e.value.row == 7 and e.value.column == "x" and "row 7" in str(e.value)


def test_nan_in_file_names_row_column_value(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "ds")
    f = table_path(tmp_path / "ds", "events")
    t = pq.read_table(f)
    z = t.column("z").to_numpy().copy()
    z[1] = np.nan
    pq.write_table(t.set_column(t.column_names.index("z"), "z", pa.array(z)), f)
    with pytest.raises(DataError) as e:
        load(tmp_path / "ds")
    msg = str(e.value)
    assert str(f) in msg and "row 1" in msg and "'z'" in msg and "nan" in msg.lower()


def test_schema_version_is_checked(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "ds")
    meta_file = tmp_path / "ds" / METADATA_FILE
    d = json.loads(meta_file.read_text())
    d["schema_version"] = "2.0"
    meta_file.write_text(json.dumps(d))
    with pytest.raises(DataError) as e:
        load(tmp_path / "ds")
    assert "schema" in str(e.value) and "'2.0'" in str(e.value) and METADATA_FILE in str(e.value)


def test_newer_minor_version_with_extra_column_loads(small_dataset, tmp_path, forget_sums):
    save(small_dataset, tmp_path / "ds")
    forget_sums(tmp_path / "ds")  # its files edited below, as another writer would write them
    meta_file = tmp_path / "ds" / METADATA_FILE
    d = json.loads(meta_file.read_text())
    d["schema_version"] = "1.7"
    meta_file.write_text(json.dumps(d))
    f = table_path(tmp_path / "ds", "sessions")
    t = pq.read_table(f)
    pq.write_table(t.append_column("operator", pa.array(["a", "b"])), f)
    back = load(tmp_path / "ds")
    assert "operator" not in back.sessions and back.metadata.schema_version == "1.7"


def test_wrong_column_type_is_named(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "ds")
    f = table_path(tmp_path / "ds", "events")
    t = pq.read_table(f)
    ids = t.column("event_id").to_numpy().astype(float) + 0.5
    pq.write_table(t.set_column(0, "event_id", pa.array(ids)), f)
    with pytest.raises(DataError) as e:
        load(tmp_path / "ds")
    assert e.value.column == "event_id" and "integer" in str(e.value)


def test_not_a_dataset_directory(tmp_path):
    with pytest.raises(DataError) as e:
        load(tmp_path)
    assert METADATA_FILE in str(e.value)
