"""Memory estimates and the budget (ttsim_jax.sizes): absurd sizes are refused before allocating."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ttsim_jax import sizes
from ttsim_jax.sizes import SizeError, parse_size, require

SAMPLE = Path(__file__).resolve().parents[1] / "ttsim_jax" / "data" / "sample" / "games"


@pytest.mark.parametrize("text, value", [("512", 512), ("1K", 1024), ("16G", 16 * 2**30), ("2.5GiB", int(2.5 * 2**30)),
                                         ("3MB", 3_000_000), ("1t", 2**40)])
def test_sizes_parse(text, value):
    assert parse_size(text) == value


@pytest.mark.parametrize("text", ["", "lots", "-4G", "0", "1x", "nan", "G"])
def test_nonsense_sizes_are_refused(text):
    with pytest.raises(ValueError, match="size"):
        parse_size(text)


def test_require_names_the_job_the_estimate_the_budget_and_the_remedy(monkeypatch):
    monkeypatch.delenv(sizes.ENV, raising=False)
    require("--shots 10", 1000, budget=2000)  # within: nothing happens
    with pytest.raises(SizeError) as e:
        require("--shots 10", 3 * 2**30, remedy="ask for fewer shots", budget=2**30)
    msg = str(e.value)
    assert "--shots 10" in msg and "3 GiB" in msg and "1 GiB" in msg and "ask for fewer shots" in msg
    assert "--memory-budget" in msg


def test_the_budget_comes_from_the_argument_then_the_variable_then_the_free_memory(monkeypatch):
    monkeypatch.setenv(sizes.ENV, "2G")
    assert sizes.budget_bytes()[0] == 2 * 2**30
    assert sizes.budget_bytes(5)[0] == 5
    monkeypatch.setenv(sizes.ENV, "plenty")
    with pytest.raises(SizeError, match=sizes.ENV):
        sizes.budget_bytes()
    monkeypatch.delenv(sizes.ENV)
    budget, source = sizes.budget_bytes()
    assert 0 < budget < sizes.available_bytes() + 1 and "available" in source


def test_the_generator_estimate_follows_the_rows_it_writes():
    """The bundled sample's games (3 games of 6 rallies) wrote 18,820 observation rows; the estimate
    must be within a factor of 2 of what the rows take at the measured bytes per row."""
    from ttsim_jax import reality
    from ttsim_jax.data.io import read_table

    truth = json.loads((SAMPLE / "truth.json").read_text())
    keys = ("games", "rallies_per_game", "rally_hits_mean", "dt", "obs_every")
    cfg = reality.GeneratorConfig(**{k: truth["config"][k] for k in keys})
    rows = len(read_table(SAMPLE / "observations.parquet", "observations")["t"])
    ratio = reality.memory_bytes(cfg) / (rows * reality.BYTES_PER_ROW)
    assert 0.5 < ratio < 2.0, ratio
    with pytest.raises(SizeError, match="1000000000 games"):
        reality.generate(reality.GeneratorConfig(games=10**9), progress=False)


def test_the_simulate_estimate_is_the_kernels_per_shot_memory():
    from ttsim_jax.cli.simulate import simulate_bytes
    from ttsim_jax.kernel.rollout import memory_bytes

    one = memory_bytes(1, 1500, 5, 8, np.float32)["total"]
    assert simulate_bytes(10**6, 1500, 5, chunk=16384, aim=False) >= 2 * 10**6 * one
    assert simulate_bytes(10**9, 1500, 0, chunk=16384, aim=True) > 2**40  # a billion shots: terabytes
