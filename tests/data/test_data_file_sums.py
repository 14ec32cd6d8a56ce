"""Every file of a written dataset carries its SHA-256 in metadata.json (and the metadata its own):
a single flipped bit anywhere, in a data page, a footer, a schema or the metadata, is refused on
load naming the file; datasets written before (schema 1.3 and older) still load."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ttsim_jax.data import DataError, load, save
from ttsim_jax.data.io import FILE_SUMS_KEY, METADATA_FILE

SAMPLE = Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games"


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "sample"
    save(load(SAMPLE), out)
    return out


def test_every_file_is_summed(written):
    sums = json.loads((written / METADATA_FILE).read_text())[FILE_SUMS_KEY]
    assert sorted(sums) == sorted(p.name for p in written.iterdir() if p.name != METADATA_FILE)
    load(written)  # and it loads as written


@pytest.mark.parametrize("seed", range(4))
def test_a_flipped_bit_anywhere_is_refused_naming_the_file(written, tmp_path, seed):
    rng = np.random.default_rng(seed)
    for file in sorted(p.name for p in written.iterdir()):
        copy = tmp_path / f"{file}-{seed}"
        shutil.copytree(written, copy)
        data = bytearray((copy / file).read_bytes())
        at = int(rng.integers(len(data)))
        data[at] ^= 1 << int(rng.integers(8))
        (copy / file).write_bytes(bytes(data))
        with pytest.raises(DataError) as caught:
            load(copy)
        assert file in str(caught.value), (file, at, str(caught.value))


def test_the_bundled_sample_sums_every_file():
    meta = json.loads((SAMPLE / METADATA_FILE).read_text())
    assert sorted(meta[FILE_SUMS_KEY]) == sorted(p.name for p in SAMPLE.iterdir() if p.name != METADATA_FILE)


def test_every_bit_of_a_metadata_byte_flipped_is_refused_naming_the_file(written, tmp_path):
    """Bit 7 makes an ASCII byte one that is not UTF-8 text: refused as damaged, as the others are
    (by the metadata's own checksum or as JSON), never a decoding traceback."""
    at = len((written / METADATA_FILE).read_bytes()) // 2
    for bit in range(8):
        copy = tmp_path / str(bit)
        shutil.copytree(written, copy)
        data = bytearray((copy / METADATA_FILE).read_bytes())
        data[at] ^= 1 << bit
        (copy / METADATA_FILE).write_bytes(bytes(data))
        with pytest.raises(DataError, match=METADATA_FILE.replace(".", r"\.")):
            load(copy)


def test_a_dataset_written_before_the_sums_still_loads(written, tmp_path):
    old = tmp_path / "old"
    shutil.copytree(written, old)
    meta = json.loads((old / METADATA_FILE).read_text())
    meta = {k: v for k, v in meta.items() if k not in (FILE_SUMS_KEY, "metadata_sha256")}
    (old / METADATA_FILE).write_text(json.dumps(dict(meta, schema_version="1.3")))
    assert len(load(old).observations["t"]) == len(load(written).observations["t"]) > 0


def test_an_upgraded_generated_dataset_sums_its_truth_too(tmp_path):
    from ttsim_jax.data.io import upgrade

    old = tmp_path / "old"
    shutil.copytree(SAMPLE, old)
    meta = json.loads((old / METADATA_FILE).read_text())
    meta = {k: v for k, v in meta.items() if k not in (FILE_SUMS_KEY, "metadata_sha256")}
    (old / METADATA_FILE).write_text(json.dumps(dict(meta, schema_version="1.3")))
    upgrade(old)
    sums = json.loads((old / METADATA_FILE).read_text())[FILE_SUMS_KEY]
    assert "truth.json" in sums and sorted(sums) == sorted(p.name for p in old.iterdir() if p.name != METADATA_FILE)


def damaged_copy(src: Path, dst: Path, name: str, where: float, mask: int) -> Path:
    """A copy of dataset ``src`` at ``dst`` whose file ``name`` has the bits ``mask`` of the byte
    at the fraction ``where`` of its length flipped."""
    shutil.copytree(src, dst)
    data = bytearray((dst / name).read_bytes())
    data[int(len(data) * where)] ^= mask
    (dst / name).write_bytes(bytes(data))
    return dst


def test_a_flipped_bit_in_a_truth_file_is_refused(tmp_path):
    from ttsim_jax.reality import Generated, load_truth, write

    truth = load_truth(SAMPLE)
    out = tmp_path / "generated"
    write(Generated(dataset=load(SAMPLE), truth=truth.info, truth_events=truth.events, truth_rackets=truth.rackets,
                    truth_observations=truth.observations, wall_time_s=0.0), out)
    load_truth(out)  # as written
    for name in ("truth.json", "truth_events.parquet"):
        copy = damaged_copy(out, tmp_path / name, name, 1 / 2, 4)
        with pytest.raises(DataError, match=name.replace(".", r"\.")):
            load_truth(copy)


def test_data_info_checks_every_recorded_file_the_truth_too(tmp_path, capsys):
    """``ttsim data info``, the integrity check a user runs, verifies the files ``load`` leaves to
    their own readers (a generator's truth files), naming the damaged one."""
    from ttsim_jax.cli import main

    for name in ("truth.json", "truth_events.parquet"):
        copy = damaged_copy(SAMPLE, tmp_path / name, name, 1 / 3, 2)
        assert main(["data", "info", str(copy)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0] and "corrupted" in err[0], err
