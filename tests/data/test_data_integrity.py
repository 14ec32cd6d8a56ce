"""Page checksums: the bundled sample has them, a dataset without them says so once, ``data upgrade``
adds them without changing a value, ``data info`` tells which is which."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from ttsim_jax.data import schema

from ttsim_jax.cli import main
from ttsim_jax.data import DataError, load, save
from ttsim_jax.data import io as data_io
from ttsim_jax.data.errors import DataWarning
from ttsim_jax.data.pages import pages

from conftest import forget_file_sums

SAMPLE = Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games"
FLIPS = 8


def flip_offsets(file, n: int = FLIPS) -> list[int]:
    """``n`` byte offsets spread evenly over the page data of a Parquet file (never a header or the
    footer): the midpoints of ``n`` equal slices of all its page-data bytes laid end to end."""
    spans = [(p.data, p.end) for p in pages(file)]
    total = sum(b - a for a, b in spans)
    out = []
    for k in range(n):
        left = (2 * k + 1) * total // (2 * n)
        for a, b in spans:
            if left < b - a:
                out.append(a + left)
                break
            left -= b - a
    return out


def load_quietly(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        return load(path, **kw)


def strip_checksums(path: Path) -> None:
    """Rewrites every Parquet file of dataset ``path`` without page checksums (as before schema 1.1),
    keeping its values and key-value metadata."""
    for file in data_io.parquet_files(path):
        pq.write_table(pq.read_table(file), file, write_page_checksum=False)
    forget_file_sums(path)  # nor whole-file ones


def recorded(fn):
    """(result of fn(), the DataWarnings it emitted), every warning recorded (none deduplicated)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fn()
    return out, [w.message for w in caught if isinstance(w.message, DataWarning)]


def test_the_sample_is_protected_and_every_bit_flip_in_its_observations_is_refused(tmp_path):
    assert json.loads((SAMPLE / "metadata.json").read_text())["schema_version"] == schema.SCHEMA_VERSION
    assert data_io.unprotected_files(SAMPLE) == [] and data_io.unsummed_files(SAMPLE) == []
    copy = tmp_path / "games"
    shutil.copytree(SAMPLE, copy)
    file = copy / "observations.parquet"
    clean = file.read_bytes()
    offsets = flip_offsets(file)
    assert len(set(offsets)) == FLIPS and min(offsets) > 4 and max(offsets) < len(clean) - 8
    refused = 0
    for k, off in enumerate(offsets):
        damaged = bytearray(clean)
        damaged[off] ^= 1 << (k % 8)
        file.write_bytes(bytes(damaged))
        with pytest.raises(DataError) as e:
            load_quietly(copy)
        assert "checksum" in str(e.value) and "observations.parquet" in str(e.value)
        refused += 1
    assert refused == FLIPS
    file.write_bytes(clean)
    load_quietly(copy)  # the undamaged copy loads


def test_a_dataset_without_checksums_warns_once_and_upgrade_protects_it(small_dataset, tmp_path):
    path = tmp_path / "old"
    save(small_dataset, path)
    (path / "README.md").write_text("my notes\n")
    strip_checksums(path)
    assert len(data_io.unprotected_files(path)) == len(schema.TABLES)
    # a flipped bit in such a file goes unnoticed: that is what the warning is about
    before, found = recorded(lambda: load(path))
    assert len(found) == 1
    assert str(path) in str(found[0]) and "without page checksums" in str(found[0]) and f"ttsim data upgrade {path}" in str(found[0])
    _, again = recorded(lambda: load(path))
    assert again == []  # once per dataset and process
    old_id = data_io.dataset_id(path)
    assert data_io.upgrade(path) == path
    assert data_io.unprotected_files(path) == [] and data_io.dataset_id(path) != old_id
    assert (path / "README.md").read_text() == "my notes\n"  # other files kept
    after, found = recorded(lambda: load(path))
    assert found == []
    for name, table in before.tables().items():
        for col, values in table.items():
            assert values.dtype == after.table(name)[col].dtype
            if values.dtype == object:
                assert list(values) == list(after.table(name)[col]), (name, col)
            else:
                assert values.tobytes() == after.table(name)[col].tobytes(), (name, col)
    assert after.metadata == before.metadata


def test_a_failed_upgrade_leaves_the_original(small_dataset, tmp_path, monkeypatch):
    path = tmp_path / "old"
    save(small_dataset, path)
    strip_checksums(path)
    files = {p.name: p.read_bytes() for p in path.iterdir()}
    real = data_io.write_parquet
    calls = []

    def failing(data, file, dataset_id, **meta):
        calls.append(file)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        real(data, file, dataset_id, **meta)

    monkeypatch.setattr(data_io, "write_parquet", failing)
    with pytest.raises(OSError):
        data_io.upgrade(path)
    assert {p.name: p.read_bytes() for p in path.iterdir()} == files
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]  # no temporary left behind


def test_data_info_shows_protection_and_data_upgrade_adds_it(small_dataset, tmp_path, capsys):
    path = tmp_path / "old"
    save(small_dataset, path)
    strip_checksums(path)
    assert main(["data", "info", str(path)]) == 0
    out = capsys.readouterr().out
    n = len(schema.TABLES)
    assert f"checksums:     none in {n} of {n} Parquet files (not protected" in out and "ttsim data upgrade" in out
    copy = tmp_path / "new"
    assert main(["data", "upgrade", str(path), "--out", str(copy)]) == 0
    assert f"page checksums in all {n} Parquet files" in capsys.readouterr().out
    assert len(data_io.unprotected_files(path)) == len(schema.TABLES)  # --out leaves the original as it was
    assert main(["data", "info", str(copy), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["checksums"] == {"protected": True, "unprotected_files": [], "parquet_files": n}
    assert main(["data", "upgrade", str(path), "--out", str(copy)]) == 2  # exists: needs --force
    assert "--force" in capsys.readouterr().err
    assert main(["data", "upgrade", str(path)]) == 0
    assert data_io.unprotected_files(path) == []
    assert main(["data", "upgrade", str(path)]) == 0
    assert "nothing to do" in capsys.readouterr().out
    assert main(["data", "upgrade", str(tmp_path / "nope")]) == 2
    assert "no such directory" in capsys.readouterr().err
