"""A write that fails for want of room or permission (a full disk, a read-only place) ends in one
error line naming the path, leaves no temporary behind and keeps any previous output whole."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from ttsim_jax.cli import main
from ttsim_jax.files import atomic
from ttsim_jax.files.atomic import WriteError, atomic_directory, atomic_write

SAMPLE = Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games"


@pytest.fixture
def full_disk(monkeypatch):
    """Every flush to disk fails as on a full filesystem (``ENOSPC``)."""
    def fsync(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.os, "fsync", fsync)


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_a_file_written_on_a_full_disk_keeps_the_old_one_and_no_temporary(tmp_path, full_disk):
    target = tmp_path / "model.toml"
    target.write_bytes(b"old")
    with pytest.raises(WriteError, match=r"cannot write .*model\.toml \(a model\): No space left on device"):
        atomic_write(target, b"new" * 1000, "a model")
    assert target.read_bytes() == b"old" and leftovers(tmp_path) == []


def test_a_directory_whose_writer_finds_the_disk_full_is_not_swapped_in(tmp_path):
    target = tmp_path / "dataset"
    target.mkdir()
    (target / "a.parquet").write_bytes(b"old")
    # pyarrow's error carries no errno, only the system's message
    with pytest.raises(WriteError, match="No space left on device"):
        with atomic_directory(target) as tmp:
            (tmp / "a.parquet").write_bytes(b"half")
            raise OSError("IOError: No space left on device. Detail: [errno 28]")
    assert (target / "a.parquet").read_bytes() == b"old" and leftovers(tmp_path) == []


def test_other_os_errors_are_not_taken_for_a_full_disk(tmp_path):
    with pytest.raises(OSError) as caught:
        with atomic_directory(tmp_path / "d"):
            raise OSError(errno.EIO, "Input/output error")
    assert not isinstance(caught.value, WriteError)


def test_a_command_on_a_full_disk_says_so_in_one_line(tmp_path, full_disk, capsys):
    out = tmp_path / "upgraded"
    assert main(["data", "upgrade", str(SAMPLE), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: cannot write {out}"), err
    assert "No space left on device" in err[0]
    assert leftovers(tmp_path) == [] and not out.exists()


def test_a_figure_is_written_whole_or_not_at_all(tmp_path, full_disk):
    from ttsim_jax.plots import pyplot, save_figure

    fig, ax = pyplot().subplots()
    ax.plot(np.arange(3))
    with pytest.raises(WriteError, match="a figure"):
        save_figure(fig, tmp_path / "f.png")
    assert list(tmp_path.iterdir()) == []


def test_a_read_only_folder_is_one_error_too(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(WriteError, match="Permission denied"):
            atomic_write(ro / "x.json", b"{}", "a report")
    finally:
        ro.chmod(0o700)
        shutil.rmtree(ro)


def test_any_write_the_atomic_writers_miss_still_ends_in_one_line(tmp_path, monkeypatch, capsys):
    from ttsim_jax.cli import data as data_cli

    def refuse(args):  # a command writing a report with plain open() on a full disk
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "report.md"))

    monkeypatch.setattr(data_cli, "cmd_info", refuse)
    assert main(["data", "info", str(SAMPLE)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: cannot write {tmp_path / 'report.md'}: No space left on device"]


@pytest.fixture
def small_filesystem(tmp_path):
    """A real filesystem of 1 MiB (a tmpfs mounted for the test: needs root, skipped without)."""
    where = tmp_path / "small"
    where.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a size-limited tmpfs needs root (the failing-fsync tests above cover the logic)")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    yield where
    subprocess.run(["umount", "-l", str(where)], check=False)


def fault_script():
    """benchmarks/faults.py, the fault table's script, as a module (its filling of a disk and its
    rows of writers are the tests' too)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("faults", SAMPLE.parents[3] / "benchmarks" / "faults.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_an_import_onto_a_really_full_disk_says_so_and_keeps_the_earlier_dataset(small_filesystem, tmp_path, capsys):
    """The whole path on a real full filesystem (not an emulated one): ``ttsim data import`` of a
    CSV log onto a 1 MiB tmpfs filled to the brim ends in one error line; the earlier dataset
    there loads unchanged and no temporary is left."""
    from ttsim_jax.data import load, read_csv, save

    tau = np.arange(60) / 200.0  # a throw down the table, 200 Hz
    log = tmp_path / "observations.csv"
    log.write_text("session_id,t,x,y,z\n" + "".join(f"0,{t!r},{-1.2 + 6 * t!r},{0.1 - 0.5 * t!r},{0.3 + 1.5 * t - 4.905 * t * t!r}\n"
                                                   for t in tau.tolist()))
    earlier = read_csv(log)
    target = small_filesystem / "dataset"
    save(earlier, target)
    before = {p.name: p.read_bytes() for p in target.iterdir()}
    fault_script().fill(small_filesystem)
    assert main(["data", "import", "--source", "csv", str(log), "--out", str(target), "--force"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(err) == 1 and "No space left on device" in err[0] and str(target) in err[0], err
    assert {p.name: p.read_bytes() for p in target.iterdir()} == before
    assert leftovers(small_filesystem) == []
    load(target)


@pytest.mark.slow  # twelve commands, each compiling its programs: about 7 minutes
def test_every_writer_on_a_really_full_disk_says_so_and_leaves_nothing(small_filesystem):
    """Each writer of the fault table (benchmarks/faults.py: simulate --save and --plot, data
    import, upgrade, generate, fit, evaluate, diagnose, play --gif, sensitivity, train ppo and residual) on a
    tmpfs filled to the brim: exit 2, one ``error:`` line saying so, no traceback, no temporary,
    nothing half-written, an earlier output kept."""
    import tempfile

    faults = fault_script()
    with tempfile.TemporaryDirectory() as tmp:
        rows = faults.disk_rows(faults.prepare(Path(tmp)), Path(tmp))
    assert len(rows) == len(faults.writers({k: Path() for k in ("log", "sample", "ppo", "contacts", "residual")},
                                           Path()))
    for r in rows:
        assert r["rc"] == 2 and r["error_lines"] == 1 and not r["traceback"], r
        assert "No space left on device" in r["error"] and r["temporaries"] == [] and r["left"] == [], r
        assert r["earlier_output_kept"] is not False, r
