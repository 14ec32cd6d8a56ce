"""``data import`` and ``data info`` through argparse, as ``ttsim`` calls them (ttsim_jax/cli/data.py)."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from ttsim_jax.cli import data as commands
from ttsim_jax.cli import main
from ttsim_jax.data import load


@pytest.fixture
def parser():
    p = argparse.ArgumentParser(prog="ttsim")
    commands.register(p.add_subparsers(dest="command"))
    return p


def run(parser, argv):
    """Runs ``ttsim ARGV`` in-process (``parser`` checks that the commands register)."""
    return main(argv)


def test_every_option_has_help(parser):
    data = next(a for a in parser._subparsers._group_actions[0].choices.values())
    sub = data._subparsers._group_actions[0]
    assert set(sub.choices) == {"import", "info", "upgrade"}
    for name, p in sub.choices.items():
        for action in p._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help, f"data {name}: {action.dest} has no help"


def test_import_csv_then_info(parser, rally, tmp_path, capsys):
    t, pos, bt, _ = rally
    lines = ["session_id,t,x,y,z"] + [f"0,{float(a)!r},{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}" for a, p in zip(t, pos)]
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "ds"
    assert run(parser, ["data", "import", str(tmp_path / "log.csv"), "--source", "csv", "--out", str(out)]) == 0
    ds = load(out)
    np.testing.assert_array_equal(ds.observations["t"], t)
    assert run(parser, ["data", "import", str(tmp_path / "log.csv"), "--source", "csv", "--out", str(out)]) == 2  # exists
    (out / "notes.txt").write_text("keep me")
    assert run(parser, ["data", "import", str(tmp_path / "log.csv"), "--source", "csv", "--out", str(out), "--force"]) == 0
    assert (out / "notes.txt").read_text() == "keep me"
    (tmp_path / "a_file").write_text("x")
    capsys.readouterr()
    assert run(parser, ["data", "import", str(tmp_path / "log.csv"), "--source", "csv", "--out", str(tmp_path / "a_file"),
                        "--force"]) == 2
    assert "a_file" in capsys.readouterr().err and (tmp_path / "a_file").read_text() == "x"
    assert run(parser, ["data", "info", str(out), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["sessions"] == 1 and d["events"]["table"] == len(bt) and d["segments"] == len(bt) + 1
    assert d["problems"] == [] and 1.0 < d["speed_p1_p50_p99"][1] < 6.0
    assert run(parser, ["data", "info", str(out)]) == 0
    assert "validation:    ok" in capsys.readouterr().out


def test_info_reports_problems(parser, small_dataset, tmp_path, capsys, forget_sums):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from ttsim_jax.data import save
    from ttsim_jax.data.io import table_path

    save(small_dataset, tmp_path / "ds")
    f = table_path(tmp_path / "ds", "observations")
    t = pq.read_table(f)
    x = t.column("x").to_numpy().copy()
    x[3] = np.inf
    pq.write_table(t.set_column(t.column_names.index("x"), "x", pa.array(x)), f)
    forget_sums(tmp_path / "ds")  # rewritten on purpose
    assert run(parser, ["data", "info", str(tmp_path / "ds")]) == 1
    text = capsys.readouterr().out
    assert "1 problem" in text and "row 3" in text and "'x'" in text


def test_import_bad_path_is_an_error(parser, tmp_path, capsys):
    assert run(parser, ["data", "import", str(tmp_path / "nope"), "--source", "tt3d", "--out", str(tmp_path / "o")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_import_csv_in_millimetres_and_milliseconds(parser, rally, tmp_path, capsys):
    t, pos, bt, _ = rally
    lines = ["session_id,t,x,y,z"] + [f"0,{float(a) * 1e3!r},{float(p[0]) * 1e3!r},{float(p[1]) * 1e3!r},{float(p[2]) * 1e3!r}" for a, p in zip(t, pos)]
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "ds"
    argv = ["data", "import", str(tmp_path / "log.csv"), "--source", "csv", "--out", str(out)]
    assert run(parser, argv + ["--length-unit", "mm"]) == 2
    assert "--time-unit ms" in capsys.readouterr().err
    assert run(parser, argv + ["--length-unit", "mm", "--time-unit", "ms"]) == 0
    ds = load(out)
    np.testing.assert_allclose(ds.observations["t"], t, rtol=1e-12)
    np.testing.assert_allclose(ds.positions, pos, rtol=1e-12, atol=1e-15)
    assert len(ds.events["kind"]) == len(bt)
    capsys.readouterr()
    assert run(parser, ["data", "import", str(tmp_path), "--source", "tt3d", "--out", str(tmp_path / "o"), "--time-unit", "ms"]) == 2
    assert "CSV logs only" in capsys.readouterr().err
