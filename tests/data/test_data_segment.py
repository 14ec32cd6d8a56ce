"""Contact detection and segmentation on synthetic trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from ttsim_jax.data import Dataset, detect_events, find_bounces, validate
from ttsim_jax.data.segment import detect_contacts, find_kinks


def test_finds_the_bounces_of_a_synthetic_trajectory(rally):
    t, pos, bt, bp = rally
    assert len(bt) == 2
    found = find_bounces(t, pos)
    assert len(found) == len(bt)
    for c, t_true, p_true in zip(found, bt, bp):
        assert abs(c.t - t_true) < 1e-3  # well inside one 5.6 ms sample interval
        assert abs(c.pos[2] - 0.02) < 2e-3
        assert np.linalg.norm(c.pos[:2] - p_true[:2]) < 0.01
        assert c.kind == "table" and c.clean


def test_bounces_with_noise_and_no_false_kinks(simulate_flight):
    t, pos, bt, _ = simulate_flight([-1.5, 0.1, 0.30], [3.5, -0.1, 0.2], duration=0.9, noise=0.002, seed=3)
    found = find_bounces(t, pos)
    assert [round(c.t, 2) for c in found] == [round(b, 2) for b in bt]
    assert find_kinks(t, pos, exclude=[c.index for c in found] + [c.index + 1 for c in found]) == []


def test_racket_hit_is_an_other_contact(simulate_flight):
    # Falls after its bounce, then is struck back at 0.5 s, well above the table.
    t, pos, bt, _ = simulate_flight([-0.5, 0.0, 0.3], [3.0, 0.0, 0.0], duration=0.8, hit_at=0.5, hit_vel=[-6.0, 0.5, 1.5])
    sid = np.zeros(len(t), int)
    ds = detect_events(Dataset.from_arrays(sid, t, pos, segments=None))
    validate(ds)
    kinds = list(ds.events["kind"])
    assert kinds.count("table") == len(bt) >= 1
    other = np.flatnonzero(ds.events["kind"] == "other")
    assert len(other) == 1 and abs(ds.events["t"][other[0]] - 0.5) < 0.006
    # Segments: before bounce, bounce -> hit, after hit.
    assert len(ds.segments["segment_id"]) == len(kinds) + 1
    assert (ds.observations["segment_id"] >= 0).all()


def test_segments_split_at_events(rally):
    t, pos, bt, bp = rally
    ds = Dataset.from_arrays(np.zeros(len(t), int), t, pos, events=dict(session_id=0, t=bt, kind=["table"] * len(bt), pos=np.array(bp)))
    validate(ds)
    seg = ds.segments
    assert len(seg["segment_id"]) == 3
    assert list(seg["start_event_id"]) == [-1, 0, 1] and list(seg["end_event_id"]) == [0, 1, -1]
    for k, sid in enumerate(seg["segment_id"]):
        ts = ds.observations["t"][ds.observations["segment_id"] == sid]
        assert seg["t_start"][k] <= ts.min() and ts.max() <= seg["t_end"][k]


@pytest.mark.parametrize("after", [0.017, 0.022, 0.028])
def test_a_hit_a_few_frames_after_a_bounce_is_a_contact(simulate_flight, after):
    # Blocked or half-volleyed 3-5 frames after the bounce: the wide velocity fits would straddle
    # the bounce there, yet the bounce's segment must not hold the hit.
    t, pos, bt, _ = simulate_flight([-1.2, 0.0, 0.25], [5.0, 0.2, -1.0], duration=0.5, noise=0.001, seed=2)
    assert len(bt) >= 1
    hit = bt[0] + after
    t, pos, bt, _ = simulate_flight([-1.2, 0.0, 0.25], [5.0, 0.2, -1.0], duration=0.5, noise=0.001, seed=2,
                                    hit_at=hit, hit_vel=[-6.0, 0.3, 1.5])
    found = detect_contacts(t, pos)
    assert [c.kind for c in found][:2] == ["table", "other"]
    assert abs(found[0].t - bt[0]) < 1e-3
    assert abs(found[1].t - hit) < 1.0 / 180  # within a frame
    assert len(found) == 2  # no echo of the hit further on


def _flight_through(pc, v_in, v_out, rate=200.0, span=0.15, noise=0.001, seed=0):
    """Samples of a ball (gravity only) through the point ``pc`` at t = 0, its velocity changing
    there from ``v_in`` to ``v_out``."""
    g = np.array([0.0, 0.0, -9.81])
    t = np.arange(-span, span, 1.0 / rate) + 0.4 / rate
    v = np.where((t < 0)[:, None], np.asarray(v_in, float), np.asarray(v_out, float))
    pos = np.asarray(pc, float) + v * t[:, None] + 0.5 * g * t[:, None] ** 2
    return t, pos + np.random.default_rng(seed).normal(0.0, noise, pos.shape)


def test_a_ball_that_clips_the_tables_edge_is_a_contact():
    # A ball rising past the side edge glances off it: a velocity change of a third of its speed,
    # which away from the table reads as timestamp jitter and is no contact.
    v_in, v_out = [7.0, -1.0, 3.0], [6.6, 1.4, 2.2]
    rel = np.linalg.norm(np.subtract(v_out, v_in)) / np.linalg.norm(v_in)
    assert 0.2 < rel < 0.5
    t, pos = _flight_through([-1.1, 0.78, 0.0], v_in, v_out)
    found = detect_contacts(t, pos)
    assert [c.kind for c in found] == ["other"] and abs(found[0].t) < 0.005
    t, pos = _flight_through([-1.1, 1.5, 0.6], v_in, v_out)
    assert detect_contacts(t, pos) == []


@pytest.mark.parametrize("seed", range(6))
def test_noisy_bounces_make_no_contact_beside_them(simulate_flight, seed):
    rng = np.random.default_rng(seed)
    v0 = [rng.uniform(3.0, 8.0), rng.uniform(-0.5, 0.5), rng.uniform(-1.0, 1.0)]
    t, pos, bt, _ = simulate_flight([-1.4, 0.0, 0.3], v0, duration=0.8, noise=0.002, seed=seed)
    found = detect_contacts(t, pos)
    assert [c.kind for c in found if c.kind != "out"] == ["table"] * len(bt)
