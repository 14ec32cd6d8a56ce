"""Each kind of malformed input gets a DataError naming row, column and value."""

from __future__ import annotations

import numpy as np
import pytest

from ttsim_jax.data import DataError, Dataset, problems, segment_batch, validate
from ttsim_jax.data.dataset import select_rows


def edit(ds, table, column, row, value):
    """A copy of ``ds`` with one cell changed."""
    t = {k: v.copy() for k, v in ds.table(table).items()}
    t[column][row] = value
    return ds.replace(**{table: t})


def raises(ds, *, row, column, value_text=None, words=()):
    with pytest.raises(DataError) as e:
        validate(ds)
    msg = str(e.value)
    assert e.value.row == row, msg
    assert e.value.column == column, msg
    assert f"row {row}" in msg and f"'{column}'" in msg
    if value_text is not None:
        assert value_text in msg, msg
    for w in words:
        assert w in msg, msg
    return e.value


def test_valid_dataset_passes(small_dataset):
    validate(small_dataset)
    assert problems(small_dataset) == []


def test_missing_column(small_dataset):
    obs = dict(small_dataset.observations)
    del obs["t"]
    with pytest.raises(DataError) as e:
        validate(small_dataset.replace(observations=obs))
    assert e.value.column == "t" and "missing required column" in str(e.value) and "observations" in str(e.value)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_or_inf(small_dataset, bad):
    ds = edit(small_dataset, "observations", "y", 12, bad)
    raises(ds, row=12, column="y", value_text=repr(float(bad)), words=("NaN or infinite",))


def test_time_not_increasing(small_dataset):
    t = small_dataset.observations["t"]
    ds = edit(small_dataset, "observations", "t", 20, t[19])
    err = raises(ds, row=20, column="t", value_text=repr(float(t[19])), words=("does not increase",))
    assert "session 0" in str(err)


def test_sessions_must_be_contiguous(small_dataset):
    sid = small_dataset.observations["session_id"]
    last0 = int(np.flatnonzero(sid == 0)[-1])
    obs = {k: v.copy() for k, v in small_dataset.observations.items()}
    order = np.r_[np.arange(0, 10), np.arange(last0 + 1, last0 + 5), np.arange(10, last0 + 1), np.arange(last0 + 5, len(sid))]
    obs = select_rows(obs, order)
    with pytest.raises(DataError) as e:
        validate(small_dataset.replace(observations=obs))
    assert e.value.column == "session_id" and e.value.row == 14


def test_millimetres_given_as_metres(small_dataset):
    obs = {k: v.copy() for k, v in small_dataset.observations.items()}
    for c in "xyz":
        obs[c] = obs[c] * 1000.0
    ds = small_dataset.replace(observations=obs)
    with pytest.raises(DataError) as e:
        validate(ds)
    msg = str(e.value)
    assert "millimetres" in msg and e.value.column == "x" and e.value.row == 0
    assert repr(float(obs["x"][0])) in msg


def test_table_surface_not_at_zero_labelled(small_dataset):
    # A frame with the floor at z = 0: bounces sit at 0.78, not 0.02.
    ds = small_dataset
    shift = {k: v.copy() for k, v in ds.observations.items()}
    shift["z"] = shift["z"] + 0.76
    ev = {k: v.copy() for k, v in ds.events.items()}
    ev["z"] = ev["z"] + 0.76
    rk = {k: v.copy() for k, v in ds.rackets.items()}
    bad = ds.replace(observations=shift, events=ev, rackets=rk)
    row = int(np.flatnonzero(ev["kind"] == "table")[0])
    err = raises(bad, row=row, column="z", words=("table surface", "not 0"))
    assert "0.76" in str(err)


def test_edge_and_underside_contacts_are_valid_a_shifted_surface_is_not(small_dataset):
    rows = np.flatnonzero(small_dataset.events["kind"] == "table")
    assert len(rows) == 2 and np.all(np.abs(small_dataset.events["x"][rows]) <= 1.37)
    base = small_dataset.events
    # A ball hitting the table's end edge: centre 17 mm beyond the end, 10.6 mm below the surface
    # level (distance r to the edge).
    ev = {k: v.copy() for k, v in base.items()}
    ev["x"][rows[0]], ev["y"][rows[0]], ev["z"][rows[0]] = 1.37 + 0.017, 0.1, -0.0106
    validate(small_dataset.replace(events=ev))
    # A ball under the table meeting its underside 25 mm below the surface, inside the outline
    # (the reality generator makes these when an opponent digs a low ball up under the end),
    # beside a contact on top: one contact off the surface's height does not name the frame.
    ev = {k: v.copy() for k, v in base.items()}
    ev["x"][rows[1]], ev["y"][rows[1]], ev["z"][rows[1]] = -1.13, -0.42, -0.045
    validate(small_dataset.replace(events=ev))
    # Every contact over the surface 4 cm low: the frame's surface is not at z = 0.
    ev = {k: v.copy() for k, v in base.items()}
    ev["z"][rows] -= 0.04
    raises(small_dataset.replace(events=ev), row=int(rows[0]), column="z", words=("table surface", "not 0", "median"))


def test_table_surface_not_at_zero_unlabelled(simulate_flight):
    # No events at all: the bounces are found in the observations.
    sessions, ts, ps = [], [], []
    for k in range(3):
        t, p, _, _ = simulate_flight([-1.5, 0.1 * k, 0.30], [5.5, 0.0, 0.5], duration=0.8, t0=2.0 * k)
        sessions.append(np.full(len(t), k))
        ts.append(t)
        ps.append(p + [0.0, 0.0, 0.76])
    ds = Dataset.from_arrays(np.concatenate(sessions), np.concatenate(ts), np.concatenate(ps), segments=None)
    with pytest.raises(DataError) as e:
        validate(ds)
    assert e.value.table == "observations" and e.value.column == "z"
    assert "table surface" in str(e.value) and "0.78" in str(e.value)
    z = ds.observations["z"]
    assert abs(z[e.value.row] - 0.78) < 0.02  # the row named is a bounce sample


def test_duplicate_ids(small_dataset):
    ev_ids = small_dataset.events["event_id"]
    ds = edit(small_dataset, "events", "event_id", 1, ev_ids[0])
    raises(ds, row=1, column="event_id", value_text=repr(int(ev_ids[0])), words=("duplicate",))
    ds = edit(small_dataset, "sessions", "session_id", 1, 0)
    raises(ds, row=1, column="session_id", words=("duplicate",))


def test_racket_event_without_racket_state(small_dataset):
    rk = {k: v[:0] for k, v in small_dataset.rackets.items()}
    ds = small_dataset.replace(rackets=rk)
    row = int(np.flatnonzero(small_dataset.events["kind"] == "racket")[0])
    raises(ds, row=row, column="event_id", value_text=repr(int(small_dataset.events["event_id"][row])), words=("without a racket state",))


def test_unknown_event_kind(small_dataset):
    raises(edit(small_dataset, "events", "kind", 0, "floor"), row=0, column="kind", value_text="'floor'")


def test_bad_quaternion(small_dataset):
    raises(edit(small_dataset, "rackets", "qw", 0, 2.0), row=0, column="qw", words=("norm 1",))


def test_spin_confidence_range(small_dataset):
    raises(edit(small_dataset, "observations", "spin_conf", 3, 1.5), row=3, column="spin_conf", value_text="1.5")


def test_unknown_segment_reference(small_dataset):
    raises(edit(small_dataset, "observations", "segment_id", 5, 999), row=5, column="segment_id", value_text="999")


def test_wrong_frame_in_metadata(small_dataset):
    import dataclasses

    ds = small_dataset.replace(metadata=dataclasses.replace(small_dataset.metadata, frame="camera"))
    with pytest.raises(DataError) as e:
        validate(ds)
    assert e.value.column == "frame" and "'camera'" in str(e.value)


def test_bad_row_never_reaches_a_batch(small_dataset):
    ds = edit(small_dataset, "observations", "x", 4, np.nan)
    with pytest.raises(DataError):
        segment_batch(ds)


def test_problems_lists_several(small_dataset):
    ds = edit(small_dataset, "observations", "x", 4, np.nan)
    ds = edit(ds, "rackets", "qw", 0, 3.0)
    found = problems(ds)
    assert {(p.table, p.column) for p in found} >= {("observations", "x"), ("rackets", "qw")}
