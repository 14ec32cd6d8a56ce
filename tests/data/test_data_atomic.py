"""No data loss, no silent corruption: atomic dataset writes, page checksums, one id per dataset."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from ttsim_jax.data import DataError, load, save
from ttsim_jax.reality import Generated, load_truth, write
from ttsim_jax.data.io import FILE_SUMS_KEY, METADATA_FILE, METADATA_SUM_KEY, dataset_id, table_path

ROOT = Path(__file__).resolve().parents[2]

# Forks one writer per round from a process that imported the package once (a fresh interpreter
# per round would spend seconds importing). The writer loads the datasets A and B and overwrites
# TARGET with them in turn until it is killed; it prints its pid once it is about to write.
_WRITER = """
import os, sys
from ttsim_jax.data.io import load, save
a, b, target = sys.argv[1:4]
for _ in sys.stdin:
    pid = os.fork()
    if pid == 0:
        ds = [load(a, validate=False), load(b, validate=False)]
        print(os.getpid(), flush=True)
        i = 0
        while True:
            save(ds[i % 2], target, overwrite=True, validate=False)
            i += 1
    os.waitpid(pid, 0)
"""


def _variant(ds, dx: float, source: str):
    obs = dict(ds.observations, x=ds.observations["x"] + dx)
    return ds.replace(observations=obs, metadata=dataclasses.replace(ds.metadata, source=source))


def _same(a, b) -> bool:
    if a.metadata != b.metadata:
        return False
    return all(np.array_equal(np.asarray(a.table(n)[c]), np.asarray(b.table(n)[c]))
               for n in a.tables() for c in a.table(n))


def _leftovers(target: Path) -> list[str]:
    return sorted(p.name for p in target.parent.iterdir() if p.name.startswith(f".{target.name}."))


def _wait_gone(pid: int, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.005)
    raise AssertionError(f"writer {pid} survived SIGKILL")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs fork and a one-step directory swap")
def test_kill_during_overwrite_leaves_old_or_new_dataset(small_dataset, tmp_path):
    a, b = _variant(small_dataset, 0.0, "A"), _variant(small_dataset, 0.25, "B")
    save(a, tmp_path / "a")
    save(b, tmp_path / "b")
    target = tmp_path / "target"
    save(a, target)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp_path / "a"), str(tmp_path / "b"), str(target)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    rng = np.random.default_rng(5)
    mid_write = 0
    try:
        for _ in range(4):
            proc.stdin.write("go\n")
            proc.stdin.flush()
            pid = int(proc.stdout.readline())
            time.sleep(rng.uniform(0.01, 0.15))
            os.kill(pid, signal.SIGKILL)
            _wait_gone(pid)
            mid_write += bool(_leftovers(target))  # killed while a new directory was being built
            back = load(target)
            assert _same(back, a) or _same(back, b), "a killed write left a mix of two datasets"
    finally:
        proc.stdin.close()
        proc.wait(timeout=30)
    assert mid_write >= 1  # the kills did land inside writes
    # the next write removes what the killed writers left
    save(b, target, overwrite=True)
    assert _leftovers(target) == [] and _same(load(target), b)


def test_leftovers_of_dead_writers_are_removed_but_not_of_live_ones(small_dataset, tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        target = tmp_path / "ds"
        stale = tmp_path / f".ds.{dead.pid}.0badc0de.tmp"
        busy = tmp_path / f".ds.{live.pid}.0badc0de.tmp"
        other = tmp_path / f".ds.v2.{dead.pid}.0badc0de.tmp"  # of another target, ds.v2
        for d in (stale, busy, other):
            d.mkdir()
            (d / "observations.parquet").write_bytes(b"half a file")
        save(small_dataset, target)
        assert not stale.exists() and busy.exists() and other.exists()
    finally:
        live.kill()
        live.wait()


def test_overwrite_keeps_other_files_and_drops_stale_dataset_files(small_dataset, tmp_path):
    target = tmp_path / "ds"
    save(small_dataset, target)
    (target / "README.txt").write_text("my notes")
    (target / "truth.json").write_text("{}")  # e.g. left by an earlier generated dataset
    save(small_dataset, target, overwrite=True)
    assert (target / "README.txt").read_text() == "my notes"
    assert not (target / "truth.json").exists()
    assert _same(load(target), small_dataset)


def test_overwrite_refuses_a_directory_that_is_not_a_dataset(small_dataset, tmp_path):
    target = tmp_path / "notes"
    target.mkdir()
    (target / "thesis.tex").write_text("x")
    with pytest.raises(FileExistsError, match="thesis.tex"):
        save(small_dataset, target, overwrite=True)
    assert sorted(os.listdir(target)) == ["thesis.tex"] and _leftovers(target) == []
    empty = tmp_path / "empty"
    empty.mkdir()
    save(small_dataset, empty, overwrite=True)
    assert _same(load(empty), small_dataset)


def test_overwrite_without_an_exchange_call_still_replaces_whole(small_dataset, tmp_path, monkeypatch):
    import ttsim_jax.files.atomic as A

    monkeypatch.setattr(A, "_exchange", lambda a, b: False)  # a system without renameat2
    target = tmp_path / "ds"
    save(small_dataset, target)
    b = _variant(small_dataset, 0.5, "B")
    save(b, target, overwrite=True)
    assert _same(load(target), b) and _leftovers(target) == []


def test_failed_write_leaves_the_old_dataset(small_dataset, tmp_path):
    target = tmp_path / "ds"
    save(small_dataset, target)
    before = dataset_id(target)

    def boom(directory, ident):
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        save(_variant(small_dataset, 1.0, "B"), target, overwrite=True, extra=boom)
    assert dataset_id(target) == before and _same(load(target), small_dataset) and _leftovers(target) == []


def test_flipped_byte_in_a_page_is_reported_not_loaded(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "ds")
    f = table_path(tmp_path / "ds", "observations")
    md = pq.ParquetFile(f).metadata.row_group(0)
    col = md.column(pq.ParquetFile(f).schema_arrow.get_field_index("x"))
    start = col.dictionary_page_offset or col.data_page_offset
    end = col.data_page_offset if col.dictionary_page_offset else start + col.total_compressed_size
    data = bytearray(f.read_bytes())
    data[(start + end) // 2] ^= 0x01  # inside the page holding the values
    f.write_bytes(bytes(data))
    # without verification the flip goes unnoticed: a value silently changes
    silent = pq.read_table(f, page_checksum_verification=False).column("x").to_numpy()
    assert not np.array_equal(silent, small_dataset.observations["x"])
    with pytest.raises(DataError) as e:
        load(tmp_path / "ds")
    assert str(f) in str(e.value) and "checksum" in str(e.value)


def test_table_of_another_dataset_is_refused(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "a")
    save(small_dataset, tmp_path / "b")
    assert dataset_id(tmp_path / "a") != dataset_id(tmp_path / "b")
    shutil.copy(table_path(tmp_path / "b", "events"), table_path(tmp_path / "a", "events"))
    with pytest.raises(DataError) as e:
        load(tmp_path / "a")
    msg = str(e.value)
    assert str(table_path(tmp_path / "a", "events")) in msg and dataset_id(tmp_path / "b") in msg and "mixed" in msg


def _strip_ids(path: Path, version: str = "1.0") -> None:
    """Turns a dataset into one as written before ids existed."""
    meta = json.loads((path / METADATA_FILE).read_text())
    meta.pop("dataset_id")
    meta.pop(FILE_SUMS_KEY, None)  # nor whole-file checksums
    meta.pop(METADATA_SUM_KEY, None)
    meta["schema_version"] = version
    (path / METADATA_FILE).write_text(json.dumps(meta))
    for f in path.glob("*.parquet"):
        t = pq.read_table(f)
        kv = {k: v for k, v in t.schema.metadata.items() if k != b"ttsim.dataset_id"}
        pq.write_table(t.replace_schema_metadata(kv), f)


def test_datasets_written_before_ids_still_load_but_do_not_mix(small_dataset, tmp_path):
    save(small_dataset, tmp_path / "old")
    _strip_ids(tmp_path / "old")
    old = small_dataset.replace(metadata=dataclasses.replace(small_dataset.metadata, schema_version="1.0"))
    assert dataset_id(tmp_path / "old") == "" and _same(load(tmp_path / "old"), old)
    save(small_dataset, tmp_path / "new")
    shutil.copy(table_path(tmp_path / "new", "rackets"), table_path(tmp_path / "old", "rackets"))
    with pytest.raises(DataError, match="rackets.parquet"):
        load(tmp_path / "old")
    # a current-version metadata.json must carry the id
    save(small_dataset, tmp_path / "noid")
    _strip_ids(tmp_path / "noid", version="1.1")
    with pytest.raises(DataError) as e:
        load(tmp_path / "noid")
    assert METADATA_FILE in str(e.value) and "dataset_id" in str(e.value)


def _generated(ds, shift=0.0) -> Generated:
    n = len(ds.events["event_id"])
    events = dict(event_id=ds.events["event_id"], true_kind=np.array(["table"] * n, object),
                  pre_x=ds.events["x"] + shift)
    rackets = dict(event_id=ds.rackets["event_id"], x=ds.rackets["x"])
    return Generated(dataset=ds, truth={"seed": 0, "effects": {}}, truth_events=events, truth_rackets=rackets,
                     truth_observations=None, wall_time_s=0.0)


def test_truth_files_carry_the_dataset_id_and_do_not_mix(small_dataset, tmp_path):
    write(_generated(small_dataset), tmp_path / "a")
    write(_generated(small_dataset, 1.0), tmp_path / "b")
    truth = load_truth(tmp_path / "a")
    assert truth.info == {"seed": 0, "effects": {}} and truth.observations is None
    assert np.array_equal(truth.events["pre_x"], small_dataset.events["x"])
    ident = dataset_id(tmp_path / "a")
    assert json.loads((tmp_path / "a" / "truth.json").read_text())["dataset_id"] == ident
    for name in ("truth_events.parquet", "truth_rackets.parquet"):
        assert pq.read_schema(tmp_path / "a" / name).metadata[b"ttsim.dataset_id"].decode() == ident
    for name in ("truth.json", "truth_events.parquet"):
        mixed = tmp_path / f"mixed_{name}"
        shutil.copytree(tmp_path / "a", mixed)
        shutil.copy(tmp_path / "b" / name, mixed / name)
        with pytest.raises(DataError) as e:
            load_truth(mixed)
        assert str(mixed / name) in str(e.value)
