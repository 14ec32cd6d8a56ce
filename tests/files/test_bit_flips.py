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


def test_every_bit_flip_in_a_model_file_ttsim_wrote_is_refused_or_changes_nothing(tmp_path):
    """A model TOML as ``ttsim fit`` writes it (the checksum line first, ``files.toml.signed``):
    a bit flipped anywhere after that line is refused naming the file; one flipped on that line is
    refused, or (a line no longer read as a checksum) loads the same model; a hand-written file
    without the line loads as before."""
    import jax
    import numpy as np

    from ttsim_jax.errors import UserError
    from ttsim_jax.files.toml import signed
    from ttsim_jax.params import load_model

    text = (REPO / "configs" / "models" / "conti2026.toml").read_text()
    path = tmp_path / "fitted.toml"
    clean = signed(text).encode()
    path.write_bytes(clean)
    same = load_model(path)
    first_line = clean.index(b"\n")
    offsets = sorted({int(i * (len(clean) - 1) / (FLIPS - 1)) for i in range(FLIPS)} | {first_line + 40})
    refused = 0
    for k, off in enumerate(offsets):
        damaged = bytearray(clean)
        damaged[off] ^= 1 << (k % 8)
        path.write_bytes(bytes(damaged))
        try:
            back = load_model(path)
        except UserError as e:
            assert str(path) in str(e)
            refused += 1
            continue
        assert off < first_line, off  # only a flip on the checksum line may load, and then unchanged
        assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(same)))
    assert refused >= len([o for o in offsets if o > first_line])
    (tmp_path / "hand.toml").write_text(text)
    load_model(tmp_path / "hand.toml")
