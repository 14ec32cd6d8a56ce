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


def _error_of(path, **kw) -> DataError:
    with pytest.raises(DataError) as e:
        read_csv(path, **kw)
    assert "np." not in str(e.value), str(e.value)  # plain values, as in the file
    return e.value


def test_csv_header_only_observations(tmp_path):
    (tmp_path / "observations.csv").write_text("session_id,t,x,y,z\n")
    e = _error_of(tmp_path)
    assert "observations.csv" in str(e) and "line 1" in str(e) and "only its header" in str(e)


def test_csv_events_of_unknown_session(rally, tmp_path):
    t, pos, bt, bp = rally
    write_obs(tmp_path / "observations.csv", t, pos)
    rows = ["session_id,t,kind,x,y,z"] + [f"{sid},{float(b)!r},table,{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}" for sid, b, p in zip((0, 5), bt, bp)]
    (tmp_path / "events.csv").write_text("\n".join(rows) + "\n")
    e = _error_of(tmp_path)
    assert "events.csv" in str(e) and e.row == 3 and e.column == "session_id" and e.value == 5


def test_csv_time_in_milliseconds(rally, tmp_path):
    t, pos, _, _ = rally
    write_obs(tmp_path / "observations.csv", t * 1000.0, pos)
    e = _error_of(tmp_path)
    assert "--time-unit ms" in str(e) and "observations.csv" in str(e) and e.row == 3 and e.column == "t"
    assert e.value == pytest.approx(t[1] * 1000.0)
    ds = read_csv(tmp_path, time_unit="ms")
    np.testing.assert_allclose(ds.observations["t"], t, rtol=1e-12)


def test_csv_long_axis_along_y_is_refused(simulate_flight, tmp_path):
    # A serve bouncing at x = -0.98, 0.30 and 1.12: two of three bounces lie beyond the table's
    # half-width, so with x and y swapped they land beside the table.
    t, pos, bt, bp = simulate_flight([-1.6, 0.05, 0.3], [4.0, 0.0, -1.0], duration=1.0)
    assert sum(abs(b[0]) > 0.8 for b in bp) == 2
    write_obs(tmp_path / "observations.csv", t, pos)
    assert list(read_csv(tmp_path).events["kind"]) == ["table"] * 3
    write_obs(tmp_path / "observations.csv", t, pos[:, [1, 0, 2]])
    e = _error_of(tmp_path)
    assert "long axis must be x" in str(e) and e.column == "y" and "observations.csv" in str(e)
    k = int(np.argmin(np.abs(t - bt[0])))
    assert abs(e.row - (k + 2)) <= 1  # the sample at the first bounce beside the table


def test_csv_with_byte_order_mark_is_read(rally, tmp_path):
    t, pos, bt, _ = rally
    write_obs(tmp_path / "observations.csv", t, pos)
    text = (tmp_path / "observations.csv").read_text()
    (tmp_path / "observations.csv").write_bytes(b"\xef\xbb\xbf" + text.encode())
    ds = read_csv(tmp_path)
    np.testing.assert_array_equal(ds.positions, pos)
    assert len(ds.events["kind"]) == len(bt)


@pytest.mark.parametrize("content,line,fragment", [
    (bytes(range(256)), 1, "binary content"),
    (b"session_id,t,x,y,z\n0,0.0,0.1,0.2,\xe9\n", 2, "not UTF-8"),
])
def test_csv_binary_or_non_utf8_names_file_and_line(tmp_path, content, line, fragment):
    (tmp_path / "observations.csv").write_bytes(content)
    e = _error_of(tmp_path)
    assert "observations.csv" in str(e) and e.row == line and e.row_label == "line" and fragment in str(e)


def test_csv_errors_count_blank_lines_and_print_plain_values(rally, tmp_path):
    t, pos, _, _ = rally
    t = t.copy()
    t[30] = t[28]
    write_obs(tmp_path / "log.csv", t, pos)
    lines = (tmp_path / "log.csv").read_text().splitlines()
    lines[5:5] = ["", " , , , , "]  # two blank lines before the bad row
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    e = _error_of(tmp_path / "log.csv")
    assert e.row == 34 and lines[33].startswith("0,") and float(lines[33].split(",")[1]) == e.value
    assert f"t = {float(t[29])!r}" in str(e)


@pytest.mark.filterwarnings("ignore:.*accelerate more than gravity")
@pytest.mark.parametrize("reader", ["arrow", "lines"])
@pytest.mark.parametrize("column, cell, problem", [("spin_conf", "1.5", r"spin confidence must be in \[0, 1\]"),
                                                   ("z", "-1.2", "below the floor")])
def test_a_row_rule_broken_near_the_end_of_a_long_log_refuses_it_as_it_is_read(tmp_path, monkeypatch, column, cell,
                                                                               problem, reader):
    """A rule a row breaks on its own refuses the log as it is read (Arrow's reader: the whole
    file; the line-by-line reader, which a blank line selects: the block that holds the row):
    nothing after the reading (time order, validation, segmentation) runs; the line and the file's
    value are named."""
    from ttsim_jax.data import csvlog, glitches

    monkeypatch.setattr(csvlog, "BLOCK_ROWS", 1000)
    n = 5500
    t = np.arange(n) / 200.0
    rows = [f"0,{float(ti)!r},{-1.0 + 0.01 * (i % 200)!r},0.1,{0.3 + 0.001 * (i % 50)!r},0.0,150.0,0.0,0.9" for i, ti in enumerate(t)]
    blank = [""] if reader == "lines" else []
    bad = 5200  # in the last, partial block
    good = rows[bad]
    cells = good.split(",")
    cells[{"z": 4, "spin_conf": 8}[column]] = cell
    rows[bad] = ",".join(cells)
    path = tmp_path / "observations.csv"
    head = "session_id,t,x,y,z,spin_x,spin_y,spin_z,spin_conf\n"
    path.write_text(head + "\n".join(blank + rows) + "\n")
    read_lines = csvlog._read_lines
    used = []
    monkeypatch.setattr(csvlog, "_read_lines", lambda *a: used.append(1) or read_lines(*a))

    def no_work(*a, **k):
        raise AssertionError("the log was worked on after its reading")

    monkeypatch.setattr(csvlog, "time_order", no_work)
    with pytest.raises(DataError, match=problem) as e:
        read_csv(path)
    assert (e.value.row, e.value.row_label, e.value.column, e.value.value) == (bad + 2 + len(blank), "line", column,
                                                                               float(cell))
    assert "observations.csv" in str(e.value) and bool(used) == (reader == "lines")
    # a sample far from the table is a glitch, left to its own rule: not refused as it is read
    rows[bad] = good.replace(",0.1,", ",-30.0,")
    path.write_text(head + "\n".join(blank + rows) + "\n")
    monkeypatch.setattr(csvlog, "time_order", glitches.time_order)
    with pytest.warns(UserWarning, match="where no ball is"):
        read_csv(path)
