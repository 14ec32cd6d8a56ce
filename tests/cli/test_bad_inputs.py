"""Bad inputs over every subcommand (``tests/cli/cli_bad_inputs.toml``): each ends in exit status 2
with exactly one ``error:`` line naming the option, file, line or value, and no traceback."""

from __future__ import annotations

import itertools
import tomllib
from pathlib import Path

import jax
import numpy as np
import pytest

from ttsim_jax.cli import main

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
SAMPLE = str(REPO / "ttsim_jax" / "data" / "sample" / "games")
SPEC = tomllib.loads((HERE / "cli_bad_inputs.toml").read_text())
CSV_HEADER = ["session_id", "t", "x", "y", "z", "spin_x", "spin_y", "spin_z", "spin_conf"]


def flight_lines() -> list[list[str]]:
    """A clean 0.6 s ballistic flight at 200 Hz over the table, with a topspin estimate: header and rows."""
    t = np.arange(121) * 0.005
    pos = np.stack([-1.0 + 5.0 * t, 0.1 + 0.2 * t, 0.3 + 2.0 * t - 4.905 * t**2], -1)
    rows = [["0", repr(float(ti)), *(repr(float(v)) for v in p), "0.0", "-150.0", "0.0", "0.9"]
            for ti, p in zip(t, pos)]
    return [list(CSV_HEADER)] + rows


def write_csv(path: Path, spec: dict) -> None:
    lines = flight_lines()
    for line, column, value in spec.get("set", []):
        lines[line - 1][CSV_HEADER.index(column)] = value
    lines = lines[:spec.get("lines", len(lines))]
    path.write_text("\n".join(",".join(cells) for cells in lines) + "\n")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """The files the cases name: a directory, a binary file, a text file that is not TOML, a
    conti2026 residual checkpoint, and the configs and logs of the spec."""
    from ttsim_jax.fit.network_config import load_residual_config
    from ttsim_jax.params import config_dir
    from ttsim_jax.physics.network import init_model
    from ttsim_jax.physics.network_checkpoint import save_residual

    root = tmp_path_factory.mktemp("bad")
    (root / "dir").mkdir()
    (root / "bin").write_bytes(bytes(range(256)) * 4)
    (root / "text.txt").write_text("hello\n")
    config = load_residual_config(config_dir() / "residual" / "conti2026.toml")
    save_residual(root / "conti.ttres", init_model(config, jax.random.key(0)), metadata={"model": "conti2026"})
    for name, text in SPEC["files"].items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    for name, spec in SPEC["derived"].items():
        text = (REPO / spec["from"]).read_text()
        for old, new in spec["replace"]:
            assert old in text, (name, old)
            text = text.replace(old, new)
        (root / name).write_text(text)
    for name, spec in SPEC["csv"].items():
        write_csv(root / f"{name}.csv", spec)
    return root


def fill(text: str, folder: Path) -> str:
    return text.replace("{P}", str(folder)).replace("{SAMPLE}", SAMPLE)


def test_the_list_covers_every_subcommand():
    from ttsim_jax.cli import build_parser

    def leaves(parser, prefix=()):
        import argparse

        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or prefix in {("evaluate",), ("diagnose",)}:  # these run on their own too
            yield prefix
        for sub in subs:
            for name, child in sub.choices.items():
                yield from leaves(child, prefix + (name,))

    commands = {c for c in leaves(build_parser()) if c}
    covered = set()
    for case in SPEC["case"].values():
        words = tuple(itertools.takewhile(lambda a: not a.startswith("-"), case["argv"]))
        covered.add(max((c for c in commands if words[:len(c)] == c), key=len, default=()))
    assert commands <= covered, sorted(commands - covered)
    assert len(SPEC["case"]) >= 150


@pytest.mark.parametrize("case", sorted(SPEC["case"]))
def test_bad_input_exits_2_with_one_error_line(case, folder, capsys, monkeypatch):
    monkeypatch.delenv("TTSIM_MEMORY_BUDGET", raising=False)
    argv = [fill(a, folder) for a in SPEC["case"][case]["argv"]]
    status = main(argv)
    err = capsys.readouterr().err
    assert status == 2, (argv, status, err)
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1, err
    for fragment in SPEC["case"][case]["expect"]:
        assert fill(fragment, folder) in lines[0], (fragment, lines[0])
