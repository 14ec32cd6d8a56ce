"""Physical plausibility of measured data: impossible values are errors naming file, line, column and
value; values beyond what has been measured in play, and flights no physics explains, are warnings."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from ttsim_jax.cli import main
from ttsim_jax.data import DataError, Dataset, read_csv, validate
from ttsim_jax.data.errors import DataWarning
from ttsim_jax.data.validate import FASTEST_BALL, FASTEST_SPIN, MAX_SPIN, ROOM, borderline

RACKETS_HEADER = "event_id,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,d_y,d_z\n"


def write_log(folder, t, pos, spin=None, racket=None, bounces=()):
    """observations.csv (with a spin column when ``spin`` is given: (T, 3)) and, with ``racket``
    (a rackets.csv data line), events.csv: the ``bounces`` ((time, position) of the table contacts)
    and a racket event after the last sample."""
    head = "session_id,t,x,y,z" + (",spin_x,spin_y,spin_z,spin_conf" if spin is not None else "")
    lines = [head]
    for i, (ti, p) in enumerate(zip(t, pos)):
        line = f"0,{float(ti)!r},{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}"
        if spin is not None:
            line += "," + ",".join(repr(float(v)) for v in spin[i]) + ",1.0"
        lines.append(line)
    (folder / "observations.csv").write_text("\n".join(lines) + "\n")
    if racket is not None:
        rows = [(float(tb), "table", pb) for tb, pb in bounces] + [(float(t[-1]) + 0.002, "racket", pos[-1])]
        (folder / "events.csv").write_text("session_id,t,kind,x,y,z,event_id\n" + "".join(
            f"0,{tb!r},{kind},{float(p[0])!r},{float(p[1])!r},{float(p[2])!r},{k}\n" for k, (tb, kind, p) in enumerate(rows)))
        (folder / "rackets.csv").write_text(RACKETS_HEADER + racket + "\n")


def read_recording(folder):
    """read_csv(folder) and the DataWarnings it emitted."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = read_csv(folder)
    return ds, [w.message for w in caught if isinstance(w.message, DataWarning)]


def spins(n, value, row=None):
    s = np.zeros((n, 3))
    if row is None:
        s[:, 1] = value
    else:
        s[:, 1] = 150.0
        s[row, 1] = value
    return s


def test_an_impossible_spin_on_every_sample_is_refused_naming_its_line(rally, tmp_path, capsys):
    t, pos, _, _ = rally
    write_log(tmp_path, t, pos, spins(len(t), 1e9))  # every sample: a unit, not a glitch
    with pytest.raises(DataError) as e:
        read_csv(tmp_path)
    err = e.value
    assert err.row == 2 and err.row_label == "line" and err.column == "spin_y" and err.value == 1e9
    assert "observations.csv" in str(err) and f"{MAX_SPIN:.0f} rad/s" in str(err)
    assert main(["data", "import", str(tmp_path), "--source", "csv", "--out", str(tmp_path / "ds")]) == 2
    msg = capsys.readouterr().err
    assert msg.startswith("error: ") and "line 2" in msg and "'spin_y'" in msg and "1000000000.0" in msg
    assert not (tmp_path / "ds").exists()


def test_one_impossible_spin_is_dropped_from_its_sample_naming_its_line(rally, tmp_path):
    from ttsim_jax.data.glitches import SPIN

    t, pos, _, _ = rally
    write_log(tmp_path, t, pos, spins(len(t), 1e9, row=8))  # data row 8 is line 10
    ds, found = read_recording(tmp_path)
    assert len(ds.observations["t"]) == len(t) and ds.metadata.left_out == {SPIN: 1}
    assert ds.observations["spin_conf"][8] == 0.0 and ds.observations["spin_y"][8] == 0.0
    assert ds.observations["spin_y"][7] == 150.0
    assert any("line 10" in str(w) and "spin dropped" in str(w) for w in found)


def test_a_spin_beyond_those_measured_in_play_warns_naming_its_line(rally, tmp_path, capsys):
    t, pos, _, _ = rally
    write_log(tmp_path, t, pos, spins(len(t), 1500.0))
    ds, found = read_recording(tmp_path)
    assert len(found) == 1
    w = found[0]
    assert w.row == 2 and w.row_label == "line" and w.column == "spin_y" and w.value == 1500.0
    assert f"{len(t)} rows have a spin above {FASTEST_SPIN:g} rad/s" in str(w) and "observations.csv" in str(w)
    assert main(["data", "import", str(tmp_path), "--source", "csv", "--out", str(tmp_path / "ds")]) == 0
    out = capsys.readouterr().out
    assert "validation:    ok, 1 warning(s)" in out and "warning: file" in out and "line 2" in out
    # a spin within the measured range: no warning
    write_log(tmp_path, t, pos, spins(len(t), 900.0))
    assert read_recording(tmp_path)[1] == []


def test_a_ball_faster_than_anything_in_the_game_is_refused(rally, tmp_path):
    t, pos, _, _ = rally
    write_log(tmp_path, t / 20.0, pos)  # a clock 20 times too slow: the serve flies at 55 m/s
    with pytest.raises(DataError) as e:
        read_csv(tmp_path)
    assert e.value.row == 2 and e.value.column == "t" and "observations.csv" in str(e.value)
    assert "beyond any ball in the game (50 m/s" in str(e.value)
    write_log(tmp_path, t / 13.0, pos)  # 36 m/s: faster than any measured smash, a warning
    ds, found = read_recording(tmp_path)  # (and gravity reads as 13^2 g: a second one)
    assert [w.column for w in found] == ["t", "t"]
    assert f"faster than the fastest ball measured in play ({FASTEST_BALL:g} m/s" in str(found[0])
    assert "accelerate more than gravity" in str(found[1])


def test_accelerations_no_flight_explains_warn(rally, tmp_path):
    t, pos, bt, _ = rally
    write_log(tmp_path, t, pos)
    assert read_recording(tmp_path)[1] == []  # a clean flight with drag
    write_log(tmp_path, 2.0 * t, pos)  # times in the wrong unit: gravity reads as 2.45 m/s^2
    ds, found = read_recording(tmp_path)
    assert len(ds.segments["segment_id"]) == 3
    (w,) = found
    assert "3 of 3 segments accelerate more than gravity plus drag and Magnus force allow" in str(w)
    first_lines = [int(np.flatnonzero(ds.observations["segment_id"] == s)[0]) + 2 for s in ds.segments["segment_id"]]
    assert w.column == "t" and w.row_label == "line" and w.row in first_lines
    # z pointing down: the serve's first flight rises as it should fall
    before = t < bt[0]
    up = Dataset.from_arrays(np.zeros(before.sum(), int), t[before], pos[before])
    down = Dataset.from_arrays(np.zeros(before.sum(), int), t[before], pos[before] * [1.0, 1.0, -1.0] + [0.0, 0.0, 1.0])
    assert borderline(up) == []
    (w,) = borderline(down)
    assert "1 of 1 segments accelerate more than gravity" in str(w) and w.row == 0


def test_racket_states_beyond_a_racket_are_refused_or_warned(rally, tmp_path):
    t, pos, bt, bp = rally
    bounces = list(zip(bt, bp))
    ok = f"{len(bounces)},0.9,0.0,0.2,1,0,0,0,-2,0,0.5,0,1,0,0.01,0.02"
    write_log(tmp_path, t, pos, racket=ok, bounces=bounces)
    assert read_recording(tmp_path)[1] == []
    # the bounces left unlabelled: one segment across both, which no flight explains
    write_log(tmp_path, t, pos, racket="0" + ok[ok.index(","):])
    assert ["accelerate more than gravity" in str(w) for w in read_recording(tmp_path)[1]] == [True]
    write_log(tmp_path, t, pos, racket=ok.replace(",-2,", ",-80,"), bounces=bounces)  # 80 m/s
    with pytest.raises(DataError) as e:
        read_csv(tmp_path)
    assert "rackets.csv" in str(e.value) and e.value.row == 2 and e.value.column == "vx" and e.value.value == -80.0
    write_log(tmp_path, t, pos, racket=ok.replace(",0,1,0,0.01", ",0,0,1000,0.01"), bounces=bounces)  # 1000 rad/s
    with pytest.raises(DataError) as e:
        read_csv(tmp_path)
    assert e.value.column == "wz" and "what a racket reaches" in str(e.value)
    write_log(tmp_path, t, pos, racket=ok.replace(",-2,", ",-40,"), bounces=bounces)  # 40 m/s
    _, found = read_recording(tmp_path)
    assert [(w.file.endswith("rackets.csv"), w.row, w.column) for w in found] == [(True, 2, "vx")]


def test_positions_beyond_the_playing_space_warn(small_dataset):
    ds = small_dataset
    assert borderline(ds) == []
    rk = dict(ds.rackets)
    rk["x"] = np.array([ROOM[0] + 0.5])
    ds = ds.replace(rackets=rk)
    validate(ds)  # not an error: halls may be larger
    (w,) = borderline(ds)
    assert w.table == "rackets" and w.row == 0 and w.column == "x" and "ITTF playing space" in str(w)
    rk["x"] = np.array([25.0])
    with pytest.raises(DataError, match="beyond 10 m"):
        validate(ds.replace(rackets=rk))


@pytest.mark.realdata
@pytest.mark.parametrize("source, folder, expected", [
    # SpinDOE's dot-pattern estimates reach 2,362 rad/s; one throw ends against something in its last 5 samples
    ("spindoe", "spindoe", {"a spin above 1000 rad/s": 1, "accelerate more than gravity": 1}),
    ("tt3d", "tt3d", {"accelerate more than gravity": 1}),  # one segment of a monocular reconstruction
    ("mpi", "mpi_ball_prediction", {}),
])
def test_the_public_datasets_import_without_errors_and_with_only_justified_warnings(real_root, source, folder, expected):
    from ttsim_jax.data import import_source

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import_source(real_root / folder, source)
    found = [str(w.message) for w in caught if isinstance(w.message, DataWarning)]
    assert {k: sum(k in w for w in found) for k in expected} == expected and len(found) == sum(expected.values()), found
