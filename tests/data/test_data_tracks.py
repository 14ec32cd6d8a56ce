"""A tracker's log as it comes: sessions of many throws with unrecorded pauses, dropped frames,
tracking jumps, no labelled events; read through the CSV import as a user would."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from ttsim_jax.data import read_csv
from ttsim_jax.data.segment import segments_from_events
from ttsim_jax.data.tracks import find_breaks, tracking_report
from ttsim_jax.fit.flightfit import ballistic_rmse_many


def throws(simulate, n, *, seed, t0=0.0, pause=(1.5, 3.0), noise=0.002, rate=120.0):
    """``n`` launcher throws (each one bounce or two, then off the table), with pauses between them:
    a list of (t, pos, bounce_times)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        p0 = [-1.6 + rng.normal(0, 0.05), rng.normal(0, 0.2), 0.25 + rng.normal(0, 0.03)]
        v0 = [5.5 + rng.normal(0, 0.5), rng.normal(0, 0.3), 1.0 + rng.normal(0, 0.3)]
        t, pos, bt, _ = simulate(p0, v0, duration=0.6, rate=rate, noise=noise, seed=int(rng.integers(1 << 30)), t0=t0)
        out.append((t, pos, bt))
        t0 = t[-1] + rng.uniform(*pause)
    return out


def write_sessions(path, sessions):
    """``observations.csv`` with one (t, pos) per session, as a tracker writes it."""
    path.mkdir(parents=True, exist_ok=True)
    lines = ["session_id,t,x,y,z"]
    for sid, (t, pos) in enumerate(sessions):
        lines += [f"{sid},{float(a)!r},{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}" for a, p in zip(t, pos)]
    (path / "observations.csv").write_text("\n".join(lines) + "\n")
    return path


def signature(ds):
    """The segments as (samples, t_start, t_end, opening kind, closing kind), in time order."""
    kind = {int(e): k for e, k in zip(ds.events["event_id"], ds.events["kind"])}
    counts = dict(zip(*np.unique(ds.observations["segment_id"], return_counts=True)))
    s = ds.segments
    rows = sorted(
        (int(counts[i]), round(float(a), 6), round(float(b), 6), kind.get(int(e0), "-"), kind.get(int(e1), "-"))
        for i, a, b, e0, e1 in zip(s["segment_id"], s["t_start"], s["t_end"], s["start_event_id"], s["end_event_id"])
    )
    return rows


@pytest.fixture
def logs(tmp_path, simulate_flight):
    """The same 24 throws written as 3 multi-throw sessions and as one session per throw."""
    root = tmp_path
    sessions = [throws(simulate_flight, 8, seed=s, t0=100.0 * s) for s in range(3)]
    multi = write_sessions(root / "multi", [(np.concatenate([t for t, _, _ in th]), np.concatenate([p for _, p, _ in th]))
                                            for th in sessions])
    single = write_sessions(root / "single", [(t, p) for th in sessions for t, p, _ in th])
    bounces = sum(len(b) for th in sessions for _, _, b in th)
    return SimpleNamespace(multi=multi, single=single, throws=24, bounces=bounces)


def test_multi_throw_sessions_segment_as_one_session_per_throw(logs):
    multi, single = read_csv(logs.multi), read_csv(logs.single)
    assert len(multi.sessions["session_id"]) == 3 and len(single.sessions["session_id"]) == logs.throws
    assert signature(multi) == signature(single)
    # every throw: a flight before each detected bounce and one after the last
    assert len(multi.segments["segment_id"]) == logs.throws + len(multi.events["t"])
    assert set(multi.events["kind"]) == {"table"}
    assert len(multi.events["t"]) >= logs.bounces - 2  # a bounce right at a throw's last samples can go unseen


def test_pauses_are_breaks_midway_and_nothing_else(simulate_flight):
    th = throws(simulate_flight, 5, seed=7)
    t = np.concatenate([a for a, _, _ in th])
    pos = np.concatenate([p for _, p, _ in th])
    br = find_breaks(t, pos)
    assert [b.reason for b in br] == ["pause"] * 4
    for b, (a, _, _), (c, _, _) in zip(br, th[:-1], th[1:]):
        assert b.t == pytest.approx(0.5 * (a[-1] + c[0]))
        assert b.size == pytest.approx(c[0] - a[-1])


def test_a_jump_without_a_pause_is_a_break_not_a_contact(simulate_flight):
    # The tracker switches to another ball 0.3 m away mid-flight, at the regular frame rate.
    t, pos, bt, _ = simulate_flight([-1.5, 0.1, 0.30], [4.0, 0.0, 0.5], duration=0.5, rate=150.0, noise=0.001, seed=3)
    k = 25
    assert all(abs(b - t[k]) > 0.05 for b in bt)
    pos = pos.copy()
    pos[k:, 1] += 0.3
    br = find_breaks(t, pos)
    assert [(b.reason, b.index) for b in br] == [("jump", k)]
    assert br[0].size == pytest.approx(0.3, abs=0.02)


def test_dropped_frames_without_a_jump_are_no_break(simulate_flight):
    t, pos, _, _ = simulate_flight([-1.5, 0.1, 0.30], [4.0, 0.0, 0.5], duration=0.6, rate=150.0, noise=0.001, seed=4)
    keep = np.ones(len(t), bool)
    keep[30:40] = False  # 66 ms occluded mid-flight
    assert find_breaks(t[keep], pos[keep]) == []
    # ... but the same hole with the flight after it shifted is a gap
    shifted = pos.copy()
    shifted[40:, 0] += 0.4
    br = find_breaks(t[keep], shifted[keep])
    assert [b.reason for b in br] == ["gap"]


def test_a_bounce_hidden_in_dropped_frames_is_no_break(simulate_flight):
    t, pos, bt, _ = simulate_flight([-1.5, 0.1, 0.30], [4.0, 0.0, -0.5], duration=0.6, rate=150.0, noise=0.001, seed=5)
    assert len(bt) >= 1
    keep = np.abs(t - bt[0]) > 0.02  # the frames around the bounce lost
    assert find_breaks(t[keep], pos[keep]) == []


def test_jittered_timestamps_are_no_jump(simulate_flight):
    # Some trackers stamp frames with millisecond jitter: two samples 1 ms apart a frame's travel apart.
    t, pos, _, _ = simulate_flight([-1.5, 0.1, 0.30], [8.0, 0.0, 0.5], duration=0.3, rate=140.0, seed=6)
    t = t.copy()
    t[10] = t[11] - 0.001
    assert find_breaks(t, pos) == []


def test_short_tracks_are_left_out_and_reported(tmp_path, simulate_flight):
    th = throws(simulate_flight, 2, seed=8)
    (t1, p1, _), (t2, p2, _) = th
    lone_t = t1[-1] + 1.0 + np.arange(3) / 120.0  # three samples of something between two pauses
    lone_p = np.tile([0.2, 0.5, 0.6], (3, 1)) + np.arange(3)[:, None] * 0.01
    t2 = t2 + 2.0
    ds = read_csv(write_sessions(tmp_path, [(np.r_[t1, lone_t, t2], np.r_[p1, lone_p, p2])]))
    left = ds.observations["segment_id"] < 0
    np.testing.assert_array_equal(np.flatnonzero(left), len(t1) + np.arange(3))
    rep = tracking_report(ds)
    (s,) = rep.sessions
    assert s["tracks"] == 3 and s["breaks"]["pause"] == 2 and s["left_out"] == 3
    assert "3 samples left out (in tracks of fewer than 5 samples between breaks)" in str(rep)


def test_labelled_events_and_a_pause(tmp_path, simulate_flight):
    th = throws(simulate_flight, 2, seed=9)
    (t1, p1, b1), (t2, p2, b2) = th
    path = write_sessions(tmp_path, [(np.r_[t1, t2], np.r_[p1, p2])])
    rows = ["session_id,t,kind,x,y,z"] + [f"0,{float(b)!r},table,0.5,0.0,0.02" for b in b1 + b2]
    (path / "events.csv").write_text("\n".join(rows) + "\n")
    ds = read_csv(path)
    seg = ds.segments
    # the pause closes the flight after the first throw's last bounce and opens the second throw
    assert len(seg["segment_id"]) == len(b1) + len(b2) + 2
    first_after_pause = np.flatnonzero(seg["t_start"] >= t2[0])[0]
    assert seg["start_event_id"][first_after_pause] == -1 and seg["end_event_id"][first_after_pause - 1] == -1
    assert seg["t_end"][first_after_pause - 1] == t1[-1] and seg["t_start"][first_after_pause] == t2[0]


def test_report_warns_about_a_segment_no_flight_fits(rally, tmp_path):
    t, pos, bt, _ = rally
    ds = read_csv(write_sessions(tmp_path, [(t, pos)]), detect=False)  # the bounces stay inside one segment
    rep = tracking_report(ds, rmse_many=ballistic_rmse_many)
    assert rep.unfit == [0]
    assert "session 0, t = 0.000 to" in rep.warnings[0] and "fits no ballistic flight" in rep.warnings[0]
    assert "import with --filter" in str(rep)
    assert tracking_report(read_csv(tmp_path), rmse_many=ballistic_rmse_many).unfit == []
    assert tracking_report(ds).unfit == []  # no fit asked for


def test_diagnosis_refuses_a_phase_with_non_finite_errors():
    from ttsim_jax.diagnose.diagnosis import NoData, refuse_non_finite

    class Table(SimpleNamespace):
        def __len__(self):
            return len(self.event_id)

    errors = np.zeros((4, 6))
    errors[2, 1] = np.nan
    pb = SimpleNamespace(phases=("table",), base={"table": errors}, data={})
    ph = SimpleNamespace(table=Table(event_id=np.array([10, 11, 12, 13])))
    with pytest.raises(NoData) as e:
        refuse_non_finite(pb, ph)
    msg = str(e.value)
    assert "table: the model's error is not finite on 1 of 4 table contacts (event ids 12)" in msg
    assert "ttsim data import" in msg and "--filter" in msg
    errors[2, 1] = 0.0
    refuse_non_finite(pb, ph)  # finite: no complaint


def test_generated_games_through_a_tracker_log_segment_as_labelled(tmp_path):
    """The bundled games written as a tracker writes them (no events: rallies with unrecorded pauses,
    dropped frames, racket hits, net and floor contacts) and imported: the segments of the labelled
    dataset within 1 %."""
    from pathlib import Path

    from ttsim_jax.data import load, write_csv

    ds = load(Path(__file__).resolve().parents[2] / "ttsim_jax" / "data" / "sample" / "games")
    got = read_csv(write_csv(ds, tmp_path))
    assert len(got.events["t"]) and "racket" not in set(got.events["kind"])
    n, m = len(ds.segments["segment_id"]), len(got.segments["segment_id"])
    assert abs(m - n) <= 0.01 * n, (m, n)
    assert np.sum(got.events["kind"] == "table") == np.sum(ds.events["kind"] == "table")
    np.testing.assert_array_equal(got.observations["t"], ds.observations["t"])


def test_data_import_prints_what_it_found_per_session(tmp_path, simulate_flight, capsys):
    from ttsim_jax.cli import main

    th = throws(simulate_flight, 4, seed=11)
    src = write_sessions(tmp_path / "log", [(np.concatenate([t for t, _, _ in th]), np.concatenate([p for _, p, _ in th]))])
    assert main(["data", "import", str(src), "--source", "csv", "--out", str(tmp_path / "ds")]) == 0
    out = capsys.readouterr().out
    bounces = sum(len(b) for _, _, b in th)
    assert "segmentation: 1 sessions: 4 tracks (3 pauses)" in out
    assert f"session 0: 4 tracks (3 pauses), {bounces} table bounces, 0 other contacts, {4 + bounces} segments" in out
    assert "warning" not in out and "validation:    ok" in out
