"""Any single bit flipped in a policy (PPO checkpoint) or a racket's residual network file is
refused on load, naming the file: the container's header and payload each carry a SHA-256. The
flips lie at evenly spread offsets over the whole file, magic bytes, header and payload alike.
(Datasets: tests/data/test_data_integrity.py and test_data_file_sums.py.)"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from ttsim_jax.files.checkpoint import CheckpointError
from ttsim_jax.physics.network_checkpoint import load_residual
from ttsim_jax.rl.checkpoint import BUNDLED_POLICY, read_checkpoint

REPO = Path(__file__).resolve().parents[2]
FLIPS = 48

CASES = {"policy": (BUNDLED_POLICY, read_checkpoint),
         "racket residual": (REPO / "configs" / "rackets" / "racket_01.ttres", load_residual)}


@pytest.mark.parametrize("kind", list(CASES))
def test_every_bit_flip_is_refused_naming_the_file(kind, tmp_path):
    source, read = CASES[kind]
    copy = tmp_path / source.name
    shutil.copyfile(source, copy)
    clean = copy.read_bytes()
    read(copy)  # the undamaged copy loads
    header_end = clean.index(b"\n", clean.index(b"\n") + 1)
    offsets = sorted({int(i * (len(clean) - 1) / (FLIPS - 1)) for i in range(FLIPS)} | {0, header_end // 2})
    assert any(o < header_end for o in offsets[1:]) and any(o > header_end for o in offsets)
    for k, off in enumerate(offsets):
        damaged = bytearray(clean)
        damaged[off] ^= 1 << (k % 8)
        copy.write_bytes(bytes(damaged))
        with pytest.raises(CheckpointError, match=re.escape(str(copy))):
            read(copy)
