"""CSV import of users' own logs."""

from __future__ import annotations

import numpy as np
import pytest

from ttsim_jax.data import DataError, read_csv, validate


def write_obs(path, t, pos, *, scale=1.0, session=0, extra_header="", extra=lambda i: ""):
    lines = ["session_id,t,x,y,z" + extra_header]
    for i, (ti, p) in enumerate(zip(t, pos)):
        lines.append(f"{session},{float(ti)!r},{float(p[0] * scale)!r},{float(p[1] * scale)!r},{float(p[2] * scale)!r}" + extra(i))
    path.write_text("\n".join(lines) + "\n")


def test_csv_log_is_imported_and_segmented(rally, tmp_path):
    t, pos, bt, _ = rally
    write_obs(tmp_path / "observations.csv", t, pos)
    ds = read_csv(tmp_path)
    validate(ds)
    np.testing.assert_array_equal(ds.observations["t"], t)
    np.testing.assert_array_equal(ds.positions, pos)
    assert list(ds.events["kind"]) == ["table"] * len(bt)
    assert len(ds.segments["segment_id"]) == len(bt) + 1


def test_csv_in_millimetres(rally, tmp_path):
    t, pos, _, _ = rally
    write_obs(tmp_path / "log.csv", t, pos, scale=1000.0)
    with pytest.raises(DataError) as e:
        read_csv(tmp_path / "log.csv")
    assert "millimetres" in str(e.value) and "line 2" in str(e.value) and "log.csv" in str(e.value)
    ds = read_csv(tmp_path / "log.csv", length_unit="mm")
    np.testing.assert_allclose(ds.positions, pos, atol=1e-12)


def test_csv_bad_cell_names_line_column_value(rally, tmp_path):
    t, pos, _, _ = rally
    write_obs(tmp_path / "log.csv", t, pos)
    lines = (tmp_path / "log.csv").read_text().splitlines()
    cells = lines[9].split(",")
    cells[3] = "0.1O5"
    lines[9] = ",".join(cells)
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError) as e:
        read_csv(tmp_path / "log.csv")
    msg = str(e.value)
    assert "line 10" in msg and "'y'" in msg and "'0.1O5'" in msg and "log.csv" in msg


def test_csv_time_going_back_names_its_line(rally, tmp_path):
    t, pos, _, _ = rally
    t = t.copy()
    t[30] = t[28]
    write_obs(tmp_path / "log.csv", t, pos)
    with pytest.raises(DataError) as e:
        read_csv(tmp_path / "log.csv")
    assert e.value.row == 32 and e.value.row_label == "line" and e.value.column == "t"


def test_csv_missing_column(tmp_path):
    (tmp_path / "log.csv").write_text("session_id,t,x,y\n0,0.0,0.1,0.2\n")
    with pytest.raises(DataError) as e:
        read_csv(tmp_path / "log.csv")
    assert e.value.column == "z" and "missing" in str(e.value)


def test_csv_with_spin_events_and_rackets(rally, tmp_path):
    t, pos, bt, bp = rally
    write_obs(tmp_path / "observations.csv", t, pos, extra_header=",spin_x,spin_y,spin_z,spin_conf", extra=lambda i: ",0,120.5,0,0.8")
    rows = ["session_id,t,kind,x,y,z"] + [f"0,{float(b)!r},table,{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}" for b, p in zip(bt, bp)]
    rows.append(f"0,{float(t[-1] + 0.002)!r},racket,{float(pos[-1][0])!r},{float(pos[-1][1])!r},{float(pos[-1][2])!r}")
    (tmp_path / "events.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "rackets.csv").write_text(
        "event_id,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,d_y,d_z\n" + f"{len(bt)},0.9,0.0,0.2,1,0,0,0,-2,0,0.5,0,1,0,0.01,0.02\n"
    )
    ds = read_csv(tmp_path)
    assert list(ds.events["kind"]) == ["table"] * len(bt) + ["racket"]
    assert ds.segments["spin_y"][0] == pytest.approx(120.5) and ds.segments["spin_conf"][0] == 0.8
    assert ds.rackets["d_z"][0] == 0.02
    # A racket event whose state is missing is caught, naming the events file.
    (tmp_path / "rackets.csv").write_text("event_id,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,d_y,d_z\n")
    with pytest.raises(DataError) as e:
        read_csv(tmp_path)
    assert "events.csv" in str(e.value) and f"line {len(bt) + 2}" in str(e.value)
