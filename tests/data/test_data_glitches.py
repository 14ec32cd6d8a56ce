"""A tracker's glitches are mended or left out at import, each counted; a unit error still refuses the log."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from ttsim_jax.data import DataError, io, read_csv
from ttsim_jax.data import glitches
from ttsim_jax.data.errors import DataWarning
from ttsim_jax.data.summary import format_info, info
from ttsim_jax.data.speeds import implausible_segments


def throws(simulate, n=6):
    """A multi-throw log: ``n`` serves 2 s apart, one session, 180 Hz, 1 mm noise."""
    ts, ps = [], []
    for k in range(n):
        t, p, _, _ = simulate([-1.5, 0.1 * (k % 3 - 1), 0.30], [3.5 + 0.2 * k, -0.1, 0.2], duration=0.9, t0=2.0 * k,
                              noise=1e-3, seed=k)
        ts.append(t)
        ps.append(p)
    return np.concatenate(ts), np.concatenate(ps)


def write(path, t, pos):
    lines = ["session_id,t,x,y,z"] + [f"0,{float(a)!r},{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}" for a, p in zip(t, pos)]
    path.write_text("\n".join(lines) + "\n")
    return path


def imported(path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        ds = read_csv(path, **kw)
    return ds, [str(w.message) for w in caught if isinstance(w.message, DataWarning)]


def test_jittered_time_stamps_sorted_by_the_logger_import_with_every_throw(simulate_flight, tmp_path):
    t, pos = throws(simulate_flight)
    clean, _ = imported(write(tmp_path / "clean.csv", t, pos))
    rng = np.random.default_rng(0)
    tj = t + rng.normal(0.0, 2e-3, len(t))  # a 5.6 ms frame: neighbours swap now and then
    order = np.argsort(tj, kind="stable")  # the logger sorts by its stamps
    raw = np.linalg.norm(np.diff(pos[order], axis=0), axis=-1) / np.diff(tj[order])
    assert raw.max() > 100.0  # some stamps nearly coincide: the step between them reads as a ball beyond 100 m/s
    ds, _ = imported(write(tmp_path / "jitter.csv", tj[order], pos[order]))
    assert not len(implausible_segments(ds)[0])
    assert abs(len(ds.segments["segment_id"]) - len(clean.segments["segment_id"])) <= 2
    assert info(ds)["speed_p1_p50_p99"][2] < 15.0  # steps measured against at least a frame


def test_frames_out_of_order_by_less_than_a_frame_are_reordered_and_counted(simulate_flight, tmp_path):
    t, pos = throws(simulate_flight)
    tj = t + np.random.default_rng(1).normal(0.0, 1.5e-3, len(t))  # written in the order taken: stamps go back
    assert (np.diff(tj) < 0).any()
    ds, said = imported(write(tmp_path / "log.csv", tj, pos))
    n = int(np.count_nonzero(np.argsort(tj, kind="stable") != np.arange(len(tj))))
    assert ds.metadata.left_out == {glitches.REORDERED: n}
    assert any(f"{n} samples reordered" in w and "log.csv" in w for w in said)
    assert np.all(np.diff(ds.observations["t"]) > 0)
    io.save(ds, tmp_path / "ds")
    again = io.load(tmp_path / "ds")
    assert again.metadata.left_out == ds.metadata.left_out
    assert f"left out:      {n} samples reordered" in format_info(info(again))


def test_time_going_back_by_a_frame_or_more_is_still_refused(simulate_flight, tmp_path):
    t, pos = throws(simulate_flight, 2)
    t = t.copy()
    t[40] = t[37]  # three frames back: no jitter
    with pytest.raises(DataError) as e:
        read_csv(write(tmp_path / "log.csv", t, pos))
    assert "time does not increase" in str(e.value) and e.value.row == 42


def test_duplicated_frames_are_dropped_and_counted(simulate_flight, tmp_path):
    t, pos = throws(simulate_flight, 3)
    dup = np.sort(np.random.default_rng(2).choice(len(t), 12, replace=False))
    rows = np.sort(np.r_[np.arange(len(t)), dup])
    ds, said = imported(write(tmp_path / "log.csv", t[rows], pos[rows]))
    assert ds.metadata.left_out == {glitches.DUPLICATES: 12}
    np.testing.assert_array_equal(ds.observations["t"], t)
    assert any("12 samples dropped" in w for w in said)


def test_a_few_teleports_are_left_out_with_their_lines(simulate_flight, tmp_path):
    t, pos = throws(simulate_flight, 3)
    far = pos.copy()
    bad = np.array([50, 200, 333])
    far[bad, 0] += 25.0  # a frame 25 m away: something else picked up
    ds, said = imported(write(tmp_path / "log.csv", t, far))
    assert ds.metadata.left_out == {glitches.FAR: 3}
    assert len(ds.observations["t"]) == len(t) - 3
    assert any(f"log.csv line {bad[0] + 2}" in w and "left out" in w for w in said)
    small = pos.copy()
    small[bad, 0] += 1.5  # a jump within the room: a break between tracks, no sample dropped
    ds, _ = imported(write(tmp_path / "near.csv", t, small))
    assert glitches.FAR not in ds.metadata.left_out


def test_a_log_in_millimetres_is_still_refused_whole(simulate_flight, tmp_path):
    t, pos = throws(simulate_flight, 2)
    with pytest.raises(DataError) as e:
        read_csv(write(tmp_path / "log.csv", t, pos * 1000.0))
    assert "millimetres" in str(e.value)


def test_segments_faster_than_any_ball_are_left_out_unless_most_are(small_dataset):
    ds = small_dataset
    obs = dict(ds.observations)
    seg = np.asarray(obs["segment_id"])
    ids = np.asarray(ds.segments["segment_id"])
    fast = ids[0]
    rows = np.flatnonzero(seg == fast)
    for c in ("x", "y", "z"):  # 100x the motion within one segment: a glitch at 300 m/s
        v = np.asarray(obs[c], np.float64).copy()
        v[rows] = v[rows[0]] + 100.0 * (v[rows] - v[rows[0]])
        obs[c] = v
    odd = ds.replace(observations=obs)
    assert list(implausible_segments(odd)[0]) == [fast]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        kept, counts = glitches.leave_out_too_fast(odd)
    assert counts == {glitches.TOO_FAST: 1}
    assert fast not in kept.segments["segment_id"] and len(kept.segments["segment_id"]) == len(ids) - 1
    assert np.all(np.asarray(kept.observations["segment_id"])[rows] == -1)
    assert any(f"segment {fast} (session" in str(w.message) and "left out" in str(w.message) for w in caught)
    # most segments that fast: a unit error, not glitches; the dataset comes back whole for validation to refuse
    every = dict(ds.observations)
    for c in ("x", "y", "z"):
        every[c] = np.asarray(every[c], np.float64) * 100.0
    whole, counts = glitches.leave_out_too_fast(ds.replace(observations=every))
    assert counts == {} and len(whole.segments["segment_id"]) == len(ids)


def test_data_import_keeps_a_log_with_one_far_sample_and_data_info_counts_it(simulate_flight, tmp_path, capsys):
    from ttsim_jax.cli import main

    t, pos = throws(simulate_flight, 2)
    pos = pos.copy()
    pos[4, 2] = 250.0  # one frame of something else, 250 m up
    write(tmp_path / "observations.csv", t, pos)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        assert main(["data", "import", "--source", "csv", str(tmp_path), "--out", str(tmp_path / "ds")]) == 0
    said = capsys.readouterr().out
    assert "observations.csv line 6" in said and "left out" in said
    assert main(["data", "info", str(tmp_path / "ds")]) == 0
    assert f"left out:      1 {glitches.FAR}" in capsys.readouterr().out
