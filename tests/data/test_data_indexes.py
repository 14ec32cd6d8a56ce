"""The dataset's indexes and its contacts (:meth:`Dataset.contacts`): the one place where measured
contact states are estimated, checked against the per-contact estimation and against maps built
over the tables' rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ttsim_jax.data import io
from ttsim_jax.data.contact_states import SKIP_REASONS, ContactFit, Contacts, estimate_contact

SAMPLE = Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games"


@pytest.fixture(scope="module")
def ds():
    return io.load(SAMPLE)


def test_event_and_racket_rows_are_those_of_the_tables(ds):
    ev, rk = ds.events, ds.rackets
    ids = np.asarray(ev["event_id"], np.int64)
    assert len(ids) > 100 and len(rk["event_id"]) > 10
    wanted = np.concatenate([ids[::-1], [ids.max() + 1, -5]])  # two ids no event has
    rows = ds.event_rows(wanted)
    np.testing.assert_array_equal(ids[rows[:-2]], wanted[:-2])
    np.testing.assert_array_equal(rows[-2:], [-1, -1])
    r = ds.racket_rows(ids)
    has = r >= 0
    assert has.sum() == len(rk["event_id"])
    np.testing.assert_array_equal(np.asarray(rk["event_id"])[r[has]], ids[has])
    assert set(np.asarray(ev["kind"]).astype(str)[has]) == {"racket"}


def test_segments_around_an_event_are_those_ending_and_starting_there(ds):
    seg = ds.segments
    ids = np.asarray(ds.events["event_id"], np.int64)
    in_rows, out_rows = ds.segments_around(ids)
    ends = {int(e): i for i, e in enumerate(seg["end_event_id"]) if e >= 0}
    starts = {int(e): i for i, e in enumerate(seg["start_event_id"]) if e >= 0}
    np.testing.assert_array_equal(in_rows, [ends.get(int(e), -1) for e in ids])
    np.testing.assert_array_equal(out_rows, [starts.get(int(e), -1) for e in ids])
    assert (in_rows >= 0).sum() > 0.8 * len(ids) and (out_rows < 0).any()
    # a segment's end without an event (-1) is no event's
    np.testing.assert_array_equal(ds.segments_around([-1]), ([-1], [-1]))


def test_segment_rows_group_the_observations_in_time_order(ds):
    rows = ds.segment_rows()
    sid = np.asarray(ds.observations["segment_id"])
    for k in (0, len(rows) // 2, len(rows) - 1):
        np.testing.assert_array_equal(rows[k], np.flatnonzero(sid == ds.segments["segment_id"][k]))
    assert ds.observation_index() is ds.observation_index()  # built once


@pytest.mark.parametrize("fit", [ContactFit(), ContactFit(max_fit_rmse=0.002, min_spin_conf=0.97, n_samples=6)],
                         ids=["default", "strict"])
def test_contacts_are_the_per_contact_estimates(ds, fit):
    """Every table and racket contact, its states and its reason, with and without the spin
    required: what :func:`estimate_contact` gives contact by contact (the strict fit skips many for
    their fit and for their spin, so the reasons' order is checked too)."""
    c = ds.contacts(fit)
    kinds = np.asarray(ds.events["kind"]).astype(str)
    assert len(c) == int(np.isin(kinds, ("table", "racket")).sum())
    index = ds.observation_index()
    for need_spin in (False, True):
        reasons = c.skip_reasons(need_spin)
        for i in range(len(c)):
            why, est = estimate_contact(index, int(c.in_row[i]), int(c.out_row[i]), float(c.t[i]), fit,
                                        need_spin=need_spin)
            assert reasons[i] == why, (i, need_spin)
            if est is not None:
                np.testing.assert_array_equal(c.vel_in[i], est.vel_in)
                np.testing.assert_array_equal(c.vel_out[i], est.vel_out)
                np.testing.assert_array_equal(c.spin_in[i], est.spin_in)
                np.testing.assert_array_equal(c.spin_out[i], est.spin_out)
                np.testing.assert_array_equal(c.spin_known[i], est.spin_known)
                np.testing.assert_array_equal(c.rmse[i], est.rmse)
    found = set(c.skip_reasons(True)) - {None}
    assert found <= set(SKIP_REASONS)
    if fit.max_fit_rmse < 0.01:
        assert {"bad_fit", "low_spin_conf_in"} <= found


def test_contacts_are_estimated_once_per_fit(ds, monkeypatch):
    c = ds.contacts(ContactFit(n_samples=8))
    calls = []
    monkeypatch.setattr(Contacts, "estimate", classmethod(lambda cls, *a, **k: calls.append(a)))
    assert ds.contacts(ContactFit(n_samples=8)) is c  # an equal fit: the same contacts
    assert ds.contacts(ContactFit(n_samples=9)) is None and len(calls) == 1  # another fit: estimated anew
    assert ds.replace(metadata=ds.metadata).contacts(ContactFit(n_samples=8)) is None  # a copy starts afresh


def test_states_of_contacts_fill_the_skipped_lists(ds):
    c = ds.contacts()
    table = np.asarray(ds.events["event_id"])[np.asarray(ds.events["kind"]).astype(str) == "table"]
    skipped = {k: [] for k in SKIP_REASONS}
    vin, win, vout, wout, rmse, good = c.states(table, skipped)
    assert len(good) + sum(len(v) for v in skipped.values()) == len(table)
    assert (vin[good, 2] < 0).mean() > 0.9 and (vout[good, 2] > 0).mean() > 0.9  # down in, up out
    bad = np.setdiff1d(np.arange(len(table)), good)
    assert not vin[bad].any()
    with pytest.raises(ValueError, match="is not a contact"):
        c.states([int(np.max(ds.events["event_id"])) + 1], skipped)
