"""Contact states measured directly: the contact_states table, its round trip, its validation, the
Contacts seam reading it, and the tt_rackets importer (real data where present)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ttsim_jax.data import Dataset, DataError, import_source, load, save, validate
from ttsim_jax.data import racket_configs, schema
from ttsim_jax.data.importers import tt_rackets
from ttsim_jax.fit.racket_arrays import contact_arrays

RADIUS = 0.02


def _rig(n=5, seed=0, config="r1"):
    """A dataset of ``n`` racket bounces with measured states, built by hand: the racket at rest,
    face normal along world z, so the racket-frame state is the world state with axes permuted."""
    rng = np.random.default_rng(seed)
    v_in = np.stack([rng.uniform(-1, 1, n), np.zeros(n), -rng.uniform(3, 8, n)], -1)
    v_out = np.stack([rng.uniform(-1, 1, n), np.zeros(n), rng.uniform(2, 6, n)], -1)
    w_in = np.stack([np.zeros(n), rng.uniform(-200, 200, n), np.zeros(n)], -1)
    w_out = np.stack([np.zeros(n), rng.uniform(-100, 100, n), np.zeros(n)], -1)
    face = np.tile([-2.0, 0.0, 0.3], (n, 1))
    ids = np.arange(n) + 100
    ds = Dataset.from_arrays(
        np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)),
        events=dict(event_id=ids, session_id=0, t=np.arange(n, dtype=float), kind="racket", pos=face + [0, 0, RADIUS]),
        rackets=dict(event_id=ids, pos=face, quat=np.tile(tt_rackets.RACKET_QUAT, (n, 1)), vel=np.zeros((n, 3)),
                     ang_vel=np.zeros((n, 3)), contact=np.zeros((n, 2)), config=config),
        sessions=dict(session_id=[0], notes=[json.dumps(dict(tilt_deg=10.0))]), segments=None,
        contact_states=dict(event_id=ids, v_in=v_in, w_in=w_in, v_out=v_out, w_out=w_out),
    )
    return ds, (v_in, w_in, v_out, w_out)


def test_round_trip_and_seam(tmp_path):
    ds, (v_in, w_in, v_out, w_out) = _rig()
    validate(ds)
    back = load(save(ds, tmp_path / "rig"))
    for c in schema.CONTACT_STATES:
        np.testing.assert_array_equal(back.contact_states[c.name], ds.contact_states[c.name])
    assert list(back.rackets["config"]) == ["r1"] * 5
    c = back.contacts()
    assert c.measured.all() and all(r is None for r in c.skip_reasons())
    np.testing.assert_array_equal(c.vel_in, v_in)
    np.testing.assert_array_equal(c.spin_out, w_out)
    # the racket frame: x~ = world z (the face normal), y~ = world x, z~ = world y
    a = contact_arrays(back, "conti2026")
    assert len(a) == 5 and a.in_segment_id.tolist() == [-1] * 5
    np.testing.assert_allclose(a.x[:, :3], v_in[:, [2, 0, 1]], rtol=1e-6)
    np.testing.assert_allclose(a.x[:, 3:6], w_in[:, [2, 0, 1]], rtol=1e-6)
    np.testing.assert_allclose(a.y_obs, np.concatenate([v_out, w_out], 1)[:, [2, 0, 1, 5, 3, 4]], rtol=1e-5, atol=1e-5)
    names, types, tilts = racket_configs.of_events(back, back.rackets["event_id"])
    assert names.tolist() == ["r1"] * 5 and types.tolist() == [racket_configs.UNKNOWN_TYPE] * 5
    np.testing.assert_array_equal(tilts, 10.0)


def test_older_dataset_reads_without_the_new_table(tmp_path):
    ds, _ = _rig()
    path = save(ds.replace(contact_states=schema.empty_table("contact_states")), tmp_path / "old")
    (path / "contact_states.parquet").unlink()  # as written before schema 1.2
    back = load(path)
    assert len(back.contact_states["event_id"]) == 0


def test_bad_contact_states_are_named():
    ds, _ = _rig()
    cs = dict(ds.contact_states)
    cs["event_id"] = cs["event_id"].copy()
    cs["event_id"][2] = 7  # no such event
    with pytest.raises(DataError, match="contact state whose event_id is not a table or racket contact") as e:
        validate(ds.replace(contact_states=cs))
    assert e.value.row == 2
    cs = dict(ds.contact_states)
    cs["w_out_y"] = cs["w_out_y"].copy()
    cs["w_out_y"][3] = 1e5
    with pytest.raises(DataError, match="spin of 1e.05 rad/s") as e:
        validate(ds.replace(contact_states=cs))
    assert (e.value.row, e.value.column) == (3, "w_out_y")
    cs = dict(ds.contact_states)
    cs["spin_conf_in"] = np.full(5, 1.5)
    with pytest.raises(DataError, match=r"spin confidence must be in \[0, 1\]"):
        validate(ds.replace(contact_states=cs))


HEADER = ",".join(tt_rackets.HEADER)


def test_tt_rackets_file_errors(tmp_path):
    good = "0,037,3.9,-61.6,1.4,-3.1,9.0,5.0,-0.117,0.0,-4.257,-0.792,0.0,3.475"
    f = tmp_path / "racket_03.csv"
    f.write_text(HEADER + "\n" + good + "\n" + good.replace("-4.257", "4.257").replace("037", "038") + "\n")
    with pytest.raises(DataError, match=r"must be < 0") as e:
        import_source(f, "tt_rackets")
    assert (e.value.row, e.value.column) == (3, "v_in_z")
    f.write_text(HEADER.replace("traj_dir", "trajectory") + "\n" + good + "\n")
    with pytest.raises(DataError, match="expected the header"):
        import_source(f, "tt_rackets")
    g = tmp_path / "rackets.csv"
    g.write_text(HEADER + "\n" + good + "\n")
    with pytest.raises(DataError, match="not a tt_rackets file name"):
        import_source(g, "tt_rackets")
    f.write_text(HEADER + "\n" + good + "\n" + good + "\n")
    with pytest.raises(DataError, match="appears twice"):
        import_source(f, "tt_rackets")
    f.write_text(HEADER + "\n" + good + "\n" + good.replace("037", "040").replace("0,040", "10,040") + "\n")
    ds = import_source(f, "tt_rackets")
    assert ds.events["event_id"].tolist() == [30037, 31040]
    assert racket_configs.summary(ds)["racket_03"]["tilts_deg"] == {"0": 1, "10": 1}


@pytest.mark.realdata
def test_tt_rackets_real(real_root):
    folder = real_root / "tt_rackets"
    if not folder.is_dir():
        pytest.skip(f"tt_rackets data not found at {folder}")
    ds = import_source(folder, "tt_rackets")
    counts = {k: v["n"] for k, v in racket_configs.summary(ds).items()}
    assert counts == {f"racket_{k:02d}": n for k, n in
                      enumerate((794, 622, 616, 660, 603, 592, 674, 685, 612, 632), start=1)}
    # every row back from the dataset, in the source's racket frame (an independent CSV read)
    raw = np.genfromtxt(folder / "train" / "racket_01.csv", delimiter=",", skip_header=1)
    ids = 10000 + np.searchsorted(tt_rackets.TILTS, raw[:, 0]) * 1000 + raw[:, 1].astype(int)
    c = ds.contacts()
    rows = c.rows(ids)
    np.testing.assert_array_equal(c.vel_in[rows], raw[:, 8:11])
    np.testing.assert_array_equal(c.spin_out[rows], raw[:, 5:8])
    a = contact_arrays(ds, "conti2026")
    assert len(a) == 6490
    cos = -a.x[:, 0] / np.linalg.norm(a.x[:, :3], axis=1)
    assert np.all(cos > 0.7)  # within 45 deg of the face normal: the rig's tilts are 0-20 deg
