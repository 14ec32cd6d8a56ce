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


def test_a_dataset_written_before_the_sums_still_loads():
    meta = json.loads((SAMPLE / METADATA_FILE).read_text())
    assert FILE_SUMS_KEY not in meta  # the bundled sample is of schema 1.1
    assert len(load(SAMPLE).observations["t"]) > 0


def test_a_flipped_bit_in_a_truth_file_is_refused(tmp_path):
    from ttsim_jax.reality import Generated, load_truth, write

    truth = load_truth(SAMPLE)
    out = tmp_path / "generated"
    write(Generated(dataset=load(SAMPLE), truth=truth.info, truth_events=truth.events, truth_rackets=truth.rackets,
                    truth_observations=truth.observations, wall_time_s=0.0), out)
    load_truth(out)  # as written
    for name in ("truth.json", "truth_events.parquet"):
        copy = tmp_path / name
        shutil.copytree(out, copy)
        data = bytearray((copy / name).read_bytes())
        data[len(data) // 2] ^= 4
        (copy / name).write_bytes(bytes(data))
        with pytest.raises(DataError, match=name.replace(".", r"\.")):
            load_truth(copy)
