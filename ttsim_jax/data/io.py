"""Saving and loading datasets: a directory of Parquet files plus ``metadata.json``.

Layout of a dataset directory (see ``docs/data_format.md``)::

    NAME/
      metadata.json          Metadata (source, equipment, frame, units, schema_version, notes)
      sessions.parquet       one file per table, columns and dtypes as in schema.py
      observations.parquet
      events.parquet
      rackets.parquet
      segments.parquet

Every Parquet file also carries the schema version in its key-value metadata
(``ttsim.schema_version``), so a lone file can be identified. Save then load is exact: float64,
int64 and strings are stored as such.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from . import schema
from .dataset import Dataset, Metadata
from .errors import DataError

METADATA_FILE = "metadata.json"
_VERSION_KEY = b"ttsim.schema_version"
_TABLE_KEY = b"ttsim.table"
_ARROW = {"int64": pa.int64(), "float64": pa.float64(), "string": pa.string()}


def table_path(path, table: str) -> Path:
    """Path of ``table``'s Parquet file inside dataset directory ``path``."""
    return Path(path) / f"{table}.parquet"


def save(ds: Dataset, path, *, overwrite: bool = False, validate: bool = True) -> Path:
    """Writes ``ds`` as a dataset directory.

    Arguments:
        ds: the dataset.
        path: directory to create (or to overwrite with ``overwrite=True``).
        overwrite: replace the dataset files of an existing directory.
        validate: check ``ds`` first, so that no invalid dataset is ever written.

    Returns:
        The directory path.
    """
    path = Path(path)
    if validate:
        from .validate import validate as check

        check(ds)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True (or --force) to replace it")
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{path} exists and is not a directory")
    path.mkdir(parents=True, exist_ok=True)
    for name, cols in schema.TABLES.items():
        table = ds.table(name)
        arrays = []
        for c in cols:
            values = table[c.name]
            if c.dtype == "string":
                arrays.append(pa.array([str(v) for v in values], pa.string()))
            else:
                arrays.append(pa.array(np.asarray(values, c.numpy_dtype), _ARROW[c.dtype]))
        fields = [pa.field(c.name, _ARROW[c.dtype], nullable=False) for c in cols]
        meta = {_VERSION_KEY: schema.SCHEMA_VERSION.encode(), _TABLE_KEY: name.encode()}
        pq.write_table(pa.Table.from_arrays(arrays, schema=pa.schema(fields, metadata=meta)), table_path(path, name))
    with open(path / METADATA_FILE, "w") as f:
        json.dump(ds.metadata.to_dict(), f, indent=2, sort_keys=True)
        f.write("\n")
    return path


def _check_version(version, file, column="schema_version") -> None:
    try:
        major, _ = schema.parse_version(version)
    except (ValueError, TypeError):
        raise DataError("schema version must look like 'MAJOR.MINOR'", file=file, column=column, value=version) from None
    if major != schema.parse_version(schema.SCHEMA_VERSION)[0]:
        raise DataError(
            f"unsupported schema version; this reader understands {schema.SCHEMA_VERSION.split('.')[0]}.x "
            f"(written by a {'newer' if major > schema.parse_version(schema.SCHEMA_VERSION)[0] else 'older'} ttsim_jax?)",
            file=file,
            column=column,
            value=version,
        )


def read_metadata(path) -> Metadata:
    """Reads and checks ``metadata.json`` of dataset directory ``path``."""
    file = Path(path) / METADATA_FILE
    if not file.exists():
        raise DataError(f"not a dataset directory: {METADATA_FILE} is missing", file=file)
    try:
        d = json.loads(file.read_text())
    except json.JSONDecodeError as e:
        raise DataError(f"not valid JSON ({e.msg} at line {e.lineno})", file=file) from None
    if not isinstance(d, dict):
        raise DataError("must hold a JSON object", file=file)
    if "schema_version" not in d:
        raise DataError("missing key", file=file, column="schema_version")
    _check_version(d["schema_version"], file)
    return Metadata.from_dict(d, file=file)


def read_table(file, name: str) -> dict[str, np.ndarray]:
    """Reads one table's Parquet file, checking version, columns, types and nulls.

    Arguments:
        file: Parquet file.
        name: table name in :data:`schema.TABLES`.

    Returns:
        Column dict with the schema's numpy dtypes (unknown extra columns are dropped).
    """
    file = Path(file)
    if not file.exists():
        raise DataError(f"table file '{name}' is missing", file=file, table=name)
    try:
        t = pq.read_table(file)
    except (pa.ArrowInvalid, OSError) as e:
        raise DataError(f"not a readable Parquet file ({e})", file=file, table=name) from None
    kv = t.schema.metadata or {}
    if _VERSION_KEY in kv:
        _check_version(kv[_VERSION_KEY].decode(), file, column=_VERSION_KEY.decode())
    out = {}
    for c in schema.TABLES[name]:
        if c.name not in t.column_names:
            raise DataError("missing required column", file=file, table=name, column=c.name)
        col = t.column(c.name)
        if col.null_count:
            row = int(np.flatnonzero(np.asarray(col.is_null()))[0])
            raise DataError("missing value (null)", file=file, table=name, row=row, column=c.name, value=None)
        typ = col.type
        if c.dtype == "string":
            if not (pa.types.is_string(typ) or pa.types.is_large_string(typ)):
                raise DataError(f"column must hold strings, holds {typ}", file=file, table=name, column=c.name)
            out[c.name] = np.array(col.to_pylist(), dtype=object)
        elif c.dtype == "int64":
            if not pa.types.is_integer(typ):
                raise DataError(f"column must hold integers, holds {typ}", file=file, table=name, column=c.name)
            out[c.name] = np.asarray(col.to_numpy(), np.int64)
        else:
            if not (pa.types.is_floating(typ) or pa.types.is_integer(typ)):
                raise DataError(f"column must hold numbers, holds {typ}", file=file, table=name, column=c.name)
            out[c.name] = np.asarray(col.to_numpy(), np.float64)
    return out


def load(path, *, validate: bool = True) -> Dataset:
    """Reads a dataset directory written by :func:`save` (or by any Parquet writer).

    Arguments:
        path: dataset directory.
        validate: run every check of :mod:`ttsim_jax.data.validate`, naming file, row, column
            and value of the first problem.

    Returns:
        The :class:`Dataset`.
    """
    path = Path(path)
    if not path.is_dir():
        raise DataError("no such dataset directory", file=path)
    meta = read_metadata(path)
    tables = {name: read_table(table_path(path, name), name) for name in schema.TABLES}
    ds = Dataset(metadata=meta, **tables)
    if validate:
        from .validate import validate as check

        files = {name: table_path(path, name) for name in schema.TABLES}
        files["metadata"] = path / METADATA_FILE
        check(ds, files)
    return ds
