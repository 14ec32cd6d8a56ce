"""Saving and loading datasets: a directory of Parquet files plus ``metadata.json``.

Layout of a dataset directory (see ``docs/data_format.md``)::

    NAME/
      metadata.json          Metadata (source, equipment, frame, units, schema_version, notes)
                             and dataset_id
      sessions.parquet       one file per table, columns and dtypes as in schema.py
      observations.parquet
      events.parquet
      rackets.parquet
      segments.parquet
      contact_states.parquet (from schema 1.2; an older dataset without it reads it as empty)

Every Parquet file also carries the schema version (``ttsim.schema_version``) and the dataset id
(``ttsim.dataset_id``, a fresh uuid per write, also in ``metadata.json``) in its key-value
metadata, so a lone file can be identified and files of two datasets are never mixed: load checks
that every file carries the id of ``metadata.json``. Parquet pages carry CRC checksums, verified
on reading, so a corrupted file is reported rather than loaded. Save then load is exact: float64,
int64 and strings are stored as such.

Datasets written before schema 1.1 have no checksums: a flipped bit in them loads as a changed
value. :func:`load` says so (one :class:`~ttsim_jax.data.errors.DataWarning` per dataset and
process), :func:`unprotected_files` lists such files and :func:`upgrade` rewrites a dataset with
checksums, every value and every other file kept.

A directory is written in a temporary sibling and swapped in whole (:mod:`ttsim_jax.files.atomic`),
so a crash leaves the old dataset or the new one, never a mix.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ttsim_jax.files.atomic import atomic_directory
from ttsim_jax.files.checksum import json_sum

from . import schema
from .dataset import Dataset, Metadata
from .errors import DataError, DataWarning
from .pages import has_checksums

METADATA_FILE = "metadata.json"
#: Ground-truth files a generated dataset holds beside its tables (see :func:`ttsim_jax.reality.write`).
TRUTH_FILES = ("truth.json", "truth_events.parquet", "truth_rackets.parquet", "truth_observations.parquet")
#: Key of the dataset id in metadata.json and truth.json.
ID_KEY = "dataset_id"
#: metadata.json's keys of the SHA-256 of every other file of the dataset ({name: hex}) and of its
#: own content (from schema 1.4): a flip anywhere is refused on load, not only in data pages.
FILE_SUMS_KEY, METADATA_SUM_KEY = "file_sha256", "metadata_sha256"
_VERSION_KEY = b"ttsim.schema_version"
_ID_KEY = b"ttsim.dataset_id"
_ARROW = {"int64": pa.int64(), "float64": pa.float64(), "string": pa.string()}
# The first version whose files carry a dataset id and page checksums.
_ID_VERSION = (1, 1)
# (directory, dataset id) of the datasets whose warnings this process has shown: each once.
_WARNED: set = set()


def table_path(path, table: str) -> Path:
    """Path of ``table``'s Parquet file inside dataset directory ``path``."""
    return Path(path) / f"{table}.parquet"


def owned_files() -> tuple[str, ...]:
    """Names of the entries of a dataset directory that a write replaces (all others are kept)."""
    return (METADATA_FILE, *(f"{name}.parquet" for name in schema.TABLES), *TRUTH_FILES)


def write_parquet(data: pa.Table, file, dataset_id: str, **meta: str) -> None:
    """Writes one Parquet file with page checksums, tagged with the schema version and dataset id.

    Arguments:
        data: the Arrow table.
        file: destination (inside a directory being written by :func:`save`).
        dataset_id: the dataset's id (``ttsim.dataset_id``).
        meta: further ``ttsim.<key>`` key-value metadata.
    """
    kv = dict(data.schema.metadata or {})
    kv.update({_VERSION_KEY: schema.SCHEMA_VERSION.encode(), _ID_KEY: dataset_id.encode()})
    kv.update({f"ttsim.{k}".encode(): v.encode() for k, v in meta.items()})
    pq.write_table(data.replace_schema_metadata(kv), file, write_page_checksum=True)


def read_parquet(file, dataset_id: str | None = None, table: str | None = None) -> pa.Table:
    """Reads one Parquet file, verifying page checksums and (optionally) the dataset id.

    Arguments:
        file: the file.
        dataset_id: the id the file must carry (``""``: it must carry none, as in datasets written
            before ids existed); None skips the check.
        table: table name for error messages.

    Returns:
        The Arrow table. Raises :class:`DataError` naming the file if it is missing, unreadable,
        corrupted (checksum mismatch) or belongs to another dataset.
    """
    file = Path(file)
    if not file.exists():
        raise DataError(f"table file '{table or file.name}' is missing", file=file, table=table)
    try:
        t = pq.read_table(file, page_checksum_verification=True)
        found = (t.schema.metadata or {}).get(_ID_KEY, b"").decode()
    except (pa.ArrowException, OSError, UnicodeDecodeError, ValueError) as e:
        # a damaged footer or schema fails in many ways (thrift, flatbuffers, a bit width beyond 64,
        # undecodable metadata): each is the same damage to the user
        why = " ".join(str(e).split())  # one line
        if "checksum" in why.lower():
            raise DataError(f"corrupted: a page checksum does not match its data; restore the file from a copy "
                            f"or write the dataset again ({why})", file=file, table=table) from None
        raise DataError(f"not a readable Parquet file; corrupted or truncated? ({why})", file=file, table=table) from None
    if dataset_id is not None:
        if found != dataset_id:
            where = f"dataset {found}" if found else "no dataset (it carries no id)"
            expected = f"dataset {dataset_id}" if dataset_id else "a dataset written without ids"
            raise DataError(f"file belongs to {where}, but {METADATA_FILE} is of {expected}: files of two datasets "
                            "are mixed; write the dataset again", file=file, table=table, column=_ID_KEY.decode())
    return t


def save(ds: Dataset, path, *, overwrite: bool = False, validate: bool = True,
         extra: Callable[[Path, str], None] | None = None) -> Path:
    """Writes ``ds`` as a dataset directory, atomically.

    The directory is built beside ``path`` and swapped in whole, so a crash at any moment leaves
    the old dataset or the new one. Entries of an overwritten directory that are not dataset files
    (see :func:`owned_files`) are kept; old dataset files the new write does not produce are gone.

    Arguments:
        ds: the dataset.
        path: directory to create (or to overwrite with ``overwrite=True``).
        overwrite: replace an existing dataset directory (or an empty directory).
        validate: check ``ds`` first, so that no invalid dataset is ever written.
        extra: optional ``fn(directory, dataset_id)`` writing more files of the same dataset into
            the directory before it is swapped in (the generator's truth files).

    Returns:
        The directory path.
    """
    path = Path(path)
    if validate:
        from .validate import validate as check

        check(ds)
    keep = kept_entries(path, overwrite)
    dataset_id = str(uuid.uuid4())
    with atomic_directory(path, keep=keep) as tmp:
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
            write_parquet(pa.Table.from_arrays(arrays, schema=pa.schema(fields)), table_path(tmp, name), dataset_id,
                          table=name)
        if extra is not None:
            extra(tmp, dataset_id)
        _write_metadata(tmp, ds.metadata.to_dict(), dataset_id)  # last: it holds every file's checksum
    return path


def kept_entries(path: Path, overwrite: bool) -> list[str]:
    """Entries of an existing directory ``path`` that replacing its dataset keeps (see :func:`save`);
    raises if it may not be replaced."""
    if not path.exists():
        return []
    if not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True (or --force) to replace it")
    if not path.is_dir():
        raise NotADirectoryError(f"{path} exists and is not a directory")
    entries = sorted(p.name for p in path.iterdir())
    if entries and METADATA_FILE not in entries:
        raise FileExistsError(f"{path} is not empty and holds no {METADATA_FILE} (not a dataset directory, "
                              f"e.g. it holds {entries[0]!r}); refusing to replace it")
    return [name for name in entries if name not in owned_files()]


def _sha256(file: Path) -> str:
    h = hashlib.sha256()
    with open(file, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_metadata(directory: Path, meta: dict, dataset_id: str) -> None:
    """Writes ``metadata.json`` of the current schema version with ``dataset_id`` and the SHA-256
    of every other file in ``directory`` and of its own content."""
    meta = dict(meta, schema_version=schema.SCHEMA_VERSION)
    meta[ID_KEY] = dataset_id
    meta[FILE_SUMS_KEY] = {p.name: _sha256(p) for p in sorted(directory.iterdir())
                           if p.is_file() and p.name != METADATA_FILE}
    meta[METADATA_SUM_KEY] = json_sum(meta, METADATA_SUM_KEY)
    (directory / METADATA_FILE).write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


def verify_files(path, names=None) -> None:
    """Refuses any of the files ``names`` (default: every file it records) of dataset directory
    ``path`` whose SHA-256 is not the one its metadata.json recorded (:func:`check_file_sums`;
    nothing to check before schema 1.4)."""
    check_file_sums(path, _metadata_dict(path)[0].get(FILE_SUMS_KEY, {}), names)


def check_file_sums(path, sums: dict, names=None) -> None:
    """Refuses a file of dataset directory ``path`` whose SHA-256 is not the one ``metadata.json``
    recorded (``sums``) when the dataset was written: a bit flipped where no page checksum looks
    (a footer, a schema, a truth file). ``names``: the files to check (default: all recorded)."""
    for name in sorted(sums if names is None else set(names) & set(sums)):
        file = Path(path) / name
        if file.is_file() and _sha256(file) != sums[name]:
            raise DataError("corrupted: its checksum differs from the one recorded in metadata.json when the dataset "
                            "was written; restore it from a copy or write the dataset again (a file rewritten on "
                            f"purpose: remove its entry from {METADATA_FILE}'s {FILE_SUMS_KEY} and the "
                            f"{METADATA_SUM_KEY} line)", file=file)


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


def _json_file(file: Path):
    """The JSON document in ``file``; a byte that is not UTF-8 text or text that is not JSON (a
    damaged copy) is a :class:`DataError` naming the file and the place."""
    raw = file.read_bytes()
    try:
        return json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise DataError(f"not UTF-8 text (byte {raw[e.start:e.start + 1]!r} at offset {e.start}): corrupted?",
                        file=file) from None
    except json.JSONDecodeError as e:
        raise DataError(f"not valid JSON ({e.msg} at line {e.lineno})", file=file) from None


def _metadata_dict(path) -> tuple[dict, Path]:
    file = Path(path) / METADATA_FILE
    if not file.exists():
        raise DataError(f"not a dataset directory: {METADATA_FILE} is missing", file=file)
    d = _json_file(file)
    if not isinstance(d, dict):
        raise DataError("must hold a JSON object", file=file)
    if "schema_version" not in d:
        raise DataError("missing key", file=file, column="schema_version")
    _check_version(d["schema_version"], file)
    if schema.parse_version(d["schema_version"]) >= _ID_VERSION and not isinstance(d.get(ID_KEY), str):
        raise DataError(f"missing or invalid dataset id (required from schema version "
                        f"{'.'.join(map(str, _ID_VERSION))} on)", file=file, column=ID_KEY, value=d.get(ID_KEY))
    if METADATA_SUM_KEY in d and d[METADATA_SUM_KEY] != json_sum(d, METADATA_SUM_KEY):
        raise DataError("corrupted or edited: its content differs from the checksum recorded when the dataset was "
                        "written; restore it from a copy or write the dataset again (edited on purpose: remove the "
                        f"{METADATA_SUM_KEY} line)", file=file, column=METADATA_SUM_KEY)
    if not isinstance(d.get(FILE_SUMS_KEY, {}), dict):
        raise DataError("must map file names to checksums", file=file, column=FILE_SUMS_KEY)
    return d, file


def _metadata_and_id(path) -> tuple[Metadata, str]:
    d, file = _metadata_dict(path)
    d = dict(d)
    ident = d.pop(ID_KEY, "")  # identifies the files on disk, not the data
    d.pop(FILE_SUMS_KEY, None)  # so do the checksums
    d.pop(METADATA_SUM_KEY, None)
    return Metadata.from_dict(d, file=file), ident


def read_metadata(path) -> Metadata:
    """Reads and checks ``metadata.json`` of dataset directory ``path``."""
    return _metadata_and_id(path)[0]


def dataset_id(path) -> str:
    """The id of the dataset directory ``path`` (``""`` for datasets written before ids existed).

    Every file of the dataset carries it; :func:`load` refuses files whose id differs.
    """
    return _metadata_dict(path)[0].get(ID_KEY, "")


def read_table(file, name: str, dataset_id: str | None = None) -> dict[str, np.ndarray]:
    """Reads one table's Parquet file, checking checksums, dataset id, version, columns, types
    and nulls.

    Arguments:
        file: Parquet file.
        name: table name in :data:`schema.TABLES`.
        dataset_id: the id the file must carry (see :func:`read_parquet`); None skips the check.

    Returns:
        Column dict with the schema's numpy dtypes (unknown extra columns are dropped).
    """
    file = Path(file)
    t = read_parquet(file, dataset_id, name)
    kv = t.schema.metadata or {}
    if _VERSION_KEY in kv:
        _check_version(kv[_VERSION_KEY].decode(), file, column=_VERSION_KEY.decode())
    out = {}
    for c in schema.TABLES[name]:
        if c.name not in t.column_names:
            if not c.required:  # an optional column added by a later minor version
                out[c.name] = np.full(t.num_rows, c.default, dtype=c.numpy_dtype)
                continue
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
    # One read of metadata.json: a writer swapping the directory meanwhile makes the ids differ.
    meta, ident = _metadata_and_id(path)
    tables = {name: read_table(table_path(path, name), name, ident) for name in schema.TABLES
              if name not in schema.OPTIONAL_TABLES or table_path(path, name).exists()}
    ds = Dataset(metadata=meta, **tables)
    files = {name: table_path(path, name) for name in schema.TABLES}
    files["metadata"] = path / METADATA_FILE
    if validate:
        from .validate import validate as check

        check(ds, files)
    # after the reads and the checks, which say where inside a table the damage lies
    verify_files(path, [table_path(path, n).name for n in tables])
    key = (os.path.realpath(path), ident)
    if key not in _WARNED:
        _WARNED.add(key)
        for w in _doubts(path, ds if validate else None, files):
            warnings.warn(w, stacklevel=2)
    return ds


def _doubts(path: Path, ds: Dataset | None, files: dict) -> list[DataWarning]:
    """What :func:`load` warns about: missing checksums, and the borderline values of ``ds``
    (see :func:`ttsim_jax.data.validate.borderline`; None: not looked for)."""
    from .validate import borderline

    out = []
    bare = unprotected_files(path)
    if bare:
        out.append(DataWarning(
            f"dataset without page checksums ({len(bare)} of {len(parquet_files(path))} Parquet files, as written before "
            f"schema 1.1 or by another writer): a damaged file would load with changed values unnoticed; add them with "
            f"'ttsim data upgrade {path}'", file=path))
    return out + (borderline(ds, files) if ds is not None else [])


def parquet_files(path) -> list[Path]:
    """The Parquet files of dataset directory ``path``: its tables and the truth files it holds."""
    path = Path(path)
    names = [f"{name}.parquet" for name in schema.TABLES] + [n for n in TRUTH_FILES if n.endswith(".parquet")]
    return [path / n for n in names if (path / n).is_file()]


def unprotected_files(path) -> list[Path]:
    """The Parquet files of dataset directory ``path`` (:func:`parquet_files`) whose pages carry no
    CRC checksums: damage to them goes unnoticed on reading. :func:`upgrade` adds the checksums.

    Raises :class:`DataError` naming a file whose page headers cannot be read (a damaged file).
    """
    out = []
    for file in parquet_files(path):
        try:
            if not has_checksums(file):
                out.append(file)
        except (ValueError, IndexError, OSError, RecursionError) as e:  # page headers that are not Thrift
            raise DataError(f"not a readable Parquet file; corrupted or truncated? ({e})", file=file) from None
    return out


def unsummed_files(path) -> list[Path]:
    """The files of dataset directory ``path`` whose SHA-256 its metadata does not record (all of
    them before schema 1.4; after, a file a writer added behind the metadata's back, as
    :func:`upgrade` once did with ``truth.json``): a bit flipped there is not noticed on loading.
    :func:`upgrade` records them."""
    sums = _metadata_dict(path)[0].get(FILE_SUMS_KEY, {})
    return [p for p in sorted(Path(path).iterdir())
            if p.is_file() and p.name in owned_files() and p.name != METADATA_FILE and p.name not in sums]


def read_truth_json(path, dataset_id: str) -> dict:
    """``truth.json`` of the generated dataset directory ``path``, as written (its id included).

    Raises :class:`DataError` when it is not a JSON object or does not carry ``dataset_id`` (it
    belongs to another dataset).
    """
    file = Path(path) / "truth.json"
    info = _json_file(file)
    if not isinstance(info, dict) or info.get(ID_KEY, "") != dataset_id:
        raise DataError(f"truth file belongs to another dataset than {METADATA_FILE}; write the dataset again",
                        file=file, column=ID_KEY)
    return info


def identical(a: pa.Table, b: pa.Table) -> bool:
    """Whether two Arrow tables hold the same columns, types and values, bit for bit (NaNs with
    their payloads, -0.0 apart from 0.0, nulls where they were); key-value metadata is not compared."""
    if a.num_rows != b.num_rows or not a.schema.equals(b.schema, check_metadata=False):
        return False
    for x, y in zip(a.columns, b.columns):
        if not pa.types.is_floating(x.type):
            if not x.equals(y):
                return False
        elif not (x.is_null().equals(y.is_null())
                  and np.asarray(x.fill_null(0).to_numpy()).tobytes() == np.asarray(y.fill_null(0).to_numpy()).tobytes()):
            return False
    return True


def upgrade(path, out=None, *, overwrite: bool = False) -> Path:
    """Rewrites dataset directory ``path`` in the current schema version, with page checksums and a
    new dataset id in every file; every value, column type and other file is kept.

    Every file is read (and its id checked) before anything is written, and every file written is
    read back and compared with what was read; the new directory then replaces the target in one
    step (:func:`ttsim_jax.files.atomic.atomic_directory`), so a failure at any point leaves the
    original untouched.

    Arguments:
        path: the dataset directory.
        out: where to write the upgraded copy (default: ``path`` itself, in place).
        overwrite: with ``out``, replace a dataset already there.

    Returns:
        The directory written. Raises :class:`DataError` for a file that cannot be read or that
        differs after writing, ``FileExistsError`` for an ``out`` that exists without ``overwrite``.
    """
    path = Path(path)
    if not path.is_dir():
        raise DataError("no such dataset directory", file=path)
    meta, meta_file = _metadata_dict(path)
    ident = meta.get(ID_KEY, "")
    tables = {file.name: read_parquet(file, ident, file.stem) for file in parquet_files(path)}
    truth = read_truth_json(path, ident) if (path / "truth.json").is_file() else None
    target = path if out is None else Path(out)
    if out is None:
        keep = [p.name for p in path.iterdir() if p.name not in owned_files()]
    elif os.path.realpath(target) == os.path.realpath(path):
        raise FileExistsError(f"{target} is the dataset being upgraded; leave out the output to upgrade in place")
    else:
        keep = kept_entries(target, overwrite)
    new_id = str(uuid.uuid4())
    with atomic_directory(target, keep=keep) as tmp:
        for name, data in tables.items():
            write_parquet(data, tmp / name, new_id)
            back = read_parquet(tmp / name, new_id, Path(name).stem)
            if not (identical(back, data) and has_checksums(tmp / name)):
                raise DataError("the rewritten copy differs from the original or has no checksums; the original "
                                "is left as it was", file=path / name)
        if truth is not None:
            (tmp / "truth.json").write_text(json.dumps(dict(truth, **{ID_KEY: new_id}), indent=1) + "\n")
        meta = {k: v for k, v in meta.items() if k not in (ID_KEY, FILE_SUMS_KEY, METADATA_SUM_KEY)}
        Metadata.from_dict(meta, file=meta_file)  # only known keys are carried over
        _write_metadata(tmp, meta, new_id)  # last: it holds every file's checksum, truth.json's too
    return target
