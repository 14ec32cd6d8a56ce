"""Frames of a rally (``ttsim_jax.env.render``): the racket face's outline, the frames drawn by
blitting, and the host-side paths the gymnasium adapters keep (no simulation here)."""

from types import SimpleNamespace

import numpy as np
import pytest

from ttsim_jax.env import racket as racket_kin
from ttsim_jax.env.gym import _Trails
from ttsim_jax.env.render import RallyFrames, episode_frames, face_outline, progress_text, save_gif
from ttsim_jax.env.rally_rules import LEGAL, RUNNING, Rally

FACE = np.array([0.0775, 0.0755])


@pytest.fixture(scope="module")
def frames():
    return RallyFrames(FACE)


@pytest.mark.parametrize("angle", [(0.0, 0.0), (0.6, -0.4), (-1.2, 1.0)])
def test_face_outline_is_the_ellipse_of_the_face_in_its_plane(angle):
    rot = np.asarray(racket_kin.rotation(np.asarray(angle, np.float32)))
    centre = np.array([2.0, -0.3, 0.4])
    edge = face_outline(centre, rot, FACE)
    rel = edge - centre
    np.testing.assert_allclose(rel @ rot[:, 0], 0.0, atol=1e-6)  # in the face plane
    y, z = rel @ rot[:, 1], rel @ rot[:, 2]
    np.testing.assert_allclose((y / FACE[0]) ** 2 + (z / FACE[1]) ** 2, 1.0, rtol=1e-5)  # on the ellipse
    assert y.max() == pytest.approx(FACE[0], rel=1e-3) and z.max() == pytest.approx(FACE[1], rel=1e-2)


def orange(frame):
    """Pixels of the ball's colour (#d95f02)."""
    return np.sum((np.abs(frame.astype(int) - [0xd9, 0x5f, 0x02]) < 12).all(-1))


def test_a_frame_shows_the_path_and_blitting_leaves_nothing_behind(frames):
    rot = np.asarray(racket_kin.rotation(np.zeros(2, np.float32)))
    path = np.array([[-1.5, 0.0, 0.3], [-0.5, 0.1, 0.4], [0.8, 0.2, 0.05]])
    empty = frames.frame(path[:1], [2.0, 0.0, 0.2], rot, "a")
    first = frames.frame(path, [2.0, 0.0, 0.2], rot, "b")
    assert empty.shape == (560, 640, 3) and empty.dtype == np.uint8
    assert orange(first) > orange(empty) > 0  # a longer path draws more of the ball's colour
    moved = frames.frame(path, [1.5, 0.3, 0.5], rot, "b")
    assert not np.array_equal(moved, first)  # the racket moved
    np.testing.assert_array_equal(frames.frame(path, [2.0, 0.0, 0.2], rot, "b"), first)  # nothing accumulates


def test_progress_text_says_where_the_rally_stands():
    assert progress_text(0.25, False, False, RUNNING) == "t = 0.25 s, incoming"
    assert progress_text(1.0, True, True, LEGAL) == "t = 1.00 s, returned, ended: legal"


def test_paths_restart_only_for_finished_environments():
    """The vector environment's autoreset: a finished environment's path starts with its new episode."""
    env = SimpleNamespace(period=0.01)
    params = SimpleNamespace(limits=SimpleNamespace(face=FACE), model=SimpleNamespace(
        table=SimpleNamespace(length=2.74, width=1.525)))
    trails = _Trails(env, params, 2)

    def state(x):
        b = 3  # one more environment than are drawn
        pos = np.stack([np.full(3, x), np.full(3, -x), np.zeros(3)])
        return SimpleNamespace(
            rally=SimpleNamespace(ball=SimpleNamespace(pos=pos)),
            racket=racket_kin.RacketState(pos=np.ones((b, 3)), vel=np.zeros((b, 3)), angle=np.zeros((b, 2)),
                                          rate=np.zeros((b, 2))),
            progress=Rally(bounced=np.zeros(b, bool), hit=np.zeros(b, bool), outcome=np.zeros(b, int),
                           landing=np.zeros((b, 2))),
            t=np.arange(b) + int(round(10 * x)))

    trails.update(state(0.1))
    trails.update(state(0.2), restart=np.array([False, False, False]))
    trails.update(state(0.3), restart=np.array([False, True, False]))
    assert [len(p) for p in trails.paths] == [3, 1]
    np.testing.assert_allclose(trails.paths[1][0], -0.3)
    drawn = trails.draw()
    assert len(drawn) == 2 and drawn[0].shape == (560, 640, 3)
    # next-step autoreset: an ended episode is held (path and clock) until its new one is shown
    trails.update(state(0.4), restart=np.array([False, False, False]), hold=np.array([True, False, False]))
    assert [len(p) for p in trails.paths] == [3, 2] and list(trails.now[3]) == [3, 5]
    trails.update(state(0.5), restart=np.array([True, False, False]))
    assert [len(p) for p in trails.paths] == [1, 3]
    np.testing.assert_allclose(trails.paths[0][0], 0.5)


def test_an_episode_is_animated_up_to_its_end(frames, tmp_path):
    """A recorded episode ending at step 6 of 10: frames every 2 steps and the last, a looping GIF
    whose frames last the steps they cover (GIF time is in hundredths of a second)."""
    from PIL import Image

    t = np.arange(10)
    ball = np.stack([-1.5 + 0.3 * t, 0.02 * t, 0.3 - 0.01 * t], -1)
    racket = np.tile([2.0, 0.0, 0.2], (10, 1))
    progress = np.zeros((10, 3), int)
    progress[4:, 0] = 1
    progress[6:, 2] = LEGAL
    shots = episode_frames(frames, ball, racket, np.zeros((10, 2)), progress, period=0.01, every=4)
    assert len(shots) == 3  # steps 0, 4 and 6, where it ended
    path = save_gif(shots, tmp_path / "a" / "rally.gif", seconds_per_frame=0.04, hold=0.5)
    with Image.open(path) as im:
        assert im.n_frames == 3 and im.size == (640, 560) and im.info.get("loop") == 0
        durations = []
        for k in range(im.n_frames):
            im.seek(k)
            durations.append(im.info["duration"])
    assert durations == [40, 40, 500]
