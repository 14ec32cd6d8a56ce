"""Frames of a ReturnBall rally for gymnasium's ``render_mode="rgb_array"``.

A frame shows the table from above (x, y) and from the side (x, z) in the world frame, the ball's
path since the episode began, the ball now and the agent's racket face (the ellipse of its
``[racket] face`` semi-axes, drawn in its current pose), with the episode's time and progress as
the title. The table and the axes are drawn once per renderer; a frame restores that background and
draws only what moves on it (blitting), so recording every control step of an episode stays cheap
next to the simulation.
"""

from __future__ import annotations

import jax
import numpy as np

from ttsim_jax.env.racket import rotation
from ttsim_jax.env.rally_rules import OUTCOME_NAMES, RUNNING
from ttsim_jax.physics.dimensions import TABLE_LENGTH, TABLE_WIDTH
from ttsim_jax.plots import draw_table

#: Points of the racket face's outline.
FACE_POINTS = 32


def rotations(angle) -> np.ndarray:
    """(N, 3, 3) racket frames of face angles (N, 2) (:func:`~ttsim_jax.env.racket.rotation`)."""
    return np.asarray(_rotations(np.asarray(angle, np.float32)))


_rotations = jax.jit(jax.vmap(rotation))


def face_outline(pos, rot, face):
    """(FACE_POINTS, 3) points of the racket face's edge in the world frame.

    Arguments:
        pos: (3,) face centre [m]; rot: (3, 3) racket frame -> world (first column the face normal,
            :func:`~ttsim_jax.env.racket.rotation`); face: (2,) semi-axes along the frame's y and z [m].
    """
    t = np.linspace(0.0, 2.0 * np.pi, FACE_POINTS)
    rot = np.asarray(rot, np.float64)
    local = face[0] * np.cos(t)[:, None] * rot[:, 1] + face[1] * np.sin(t)[:, None] * rot[:, 2]
    return np.asarray(pos, np.float64) + local


class RallyFrames:
    """Draws frames of one environment's rally (pure numpy in, uint8 RGB out).

    Arguments:
        face: (2,) racket face semi-axes [m]; table_length, table_width [m]: the model's table.
        size: (width, height) of a frame in pixels.
    """

    def __init__(self, face, table_length: float = TABLE_LENGTH, table_width: float = TABLE_WIDTH,
                 size=(640, 560)):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        dpi = 80
        self.face = np.asarray(face, np.float64)
        self.fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        top, side = self.fig.subplots(2, 1, gridspec_kw={"height_ratios": [1.0, 1.0]})
        draw_table(top, side, table_length, table_width)
        top.set(xlabel="x [m]", ylabel="y [m]", aspect="equal", xlim=(-3.2, 3.2), ylim=(-1.6, 1.6))
        side.set(xlabel="x [m]", ylabel="z [m]", aspect="equal", xlim=(-3.2, 3.2), ylim=(-0.8, 1.6))
        side.grid(alpha=0.3)
        self.axes = (top, side)
        self.trail = [ax.plot([], [], color="#d95f02", lw=1.2, animated=True)[0] for ax in self.axes]
        self.ball = [ax.plot([], [], "o", color="#d95f02", ms=6, mec="k", mew=0.6, animated=True)[0]
                     for ax in self.axes]
        self.racket = [ax.fill([0.0], [0.0], color="#b2182b", alpha=0.8, ec="#67001f", lw=2.0, animated=True)[0]
                       for ax in self.axes]
        self.title = self.fig.suptitle("", fontsize=11, animated=True)
        self.fig.tight_layout()
        # blitting: the table and the axes are drawn once; a frame draws only what moves on a copy
        self.canvas.draw()
        self.background = self.canvas.copy_from_bbox(self.fig.bbox)

    def frame(self, trail, racket_pos, racket_rot, text: str = "") -> np.ndarray:
        """One frame.

        Arguments:
            trail: (N, 3) the ball's positions since the episode began, the last one now [m].
            racket_pos: (3,) face centre [m]; racket_rot: (3, 3) its frame (:func:`face_outline`).
            text: the title (time, progress).

        Returns:
            (height, width, 3) uint8 RGB.
        """
        trail = np.asarray(trail, np.float64).reshape(-1, 3)
        trail = trail[np.isfinite(trail).all(-1)]
        edge = face_outline(racket_pos, racket_rot, self.face)
        for k, (i, j) in enumerate(((0, 1), (0, 2))):  # top: (x, y); side: (x, z)
            self.trail[k].set_data(trail[:, i], trail[:, j])
            self.ball[k].set_data(trail[-1:, i], trail[-1:, j])
            self.racket[k].set_xy(edge[:, [i, j]])
        self.title.set_text(text)
        self.canvas.restore_region(self.background)
        for k, ax in enumerate(self.axes):
            for artist in (self.trail[k], self.racket[k], self.ball[k]):
                ax.draw_artist(artist)
        self.fig.draw_artist(self.title)
        return np.array(self.canvas.buffer_rgba())[..., :3]


def progress_text(t_seconds: float, bounced: bool, hit: bool, outcome: int) -> str:
    """A frame's title: the episode's time and how far the rally got."""
    stage = "incoming" if not bounced else "bounced" if not hit else "returned"
    end = "" if outcome == RUNNING else f", ended: {OUTCOME_NAMES[outcome]}"
    return f"t = {t_seconds:.2f} s, {stage}{end}"


def episode_frames(frames: RallyFrames, ball, racket, angle, progress, period: float, every: int = 1) -> list:
    """The frames of one recorded episode, up to the step where it ended.

    Arguments:
        frames: a :class:`RallyFrames`.
        ball, racket: (T, 3) positions after each control step [m]; angle: (T, 2) the racket's
            pitch and yaw [rad]; progress: (T, 3) bounced, hit, outcome (as
            :func:`ttsim_jax.rl.ppo.make_evaluate` records them).
        period: control step [s]; every: draw every that many steps (and the last).

    Returns:
        A list of (H, W, 3) uint8 frames.
    """
    ball, racket, progress = (np.asarray(a) for a in (ball, racket, progress))
    ended = np.nonzero(progress[:, 2] != RUNNING)[0]
    last = int(ended[0]) if len(ended) else len(ball) - 1
    rots = rotations(np.asarray(angle)[:last + 1])
    steps = sorted(set(range(0, last + 1, every)) | {last})
    return [frames.frame(ball[:k + 1], racket[k], rots[k],
                         progress_text((k + 1) * period, bool(progress[k, 0]), bool(progress[k, 1]),
                                       int(progress[k, 2])))
            for k in steps]


def save_gif(frames: list, path, seconds_per_frame: float, hold: float = 1.0):
    """Writes ``frames`` as an animated GIF (Pillow, which matplotlib installs), looping, the last
    frame held ``hold`` seconds; returns the path. GIF timing is in hundredths of a second."""
    from pathlib import Path

    from PIL import Image

    import io

    from ttsim_jax.files.atomic import atomic_write

    path = Path(path)
    images = [Image.fromarray(f) for f in frames]
    ms = max(20, int(round(seconds_per_frame * 100)) * 10)
    durations = [ms] * (len(images) - 1) + [max(ms, int(hold * 1000))]
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=durations, loop=0,
                   optimize=False)
    atomic_write(path, buf.getvalue(), "an animation")
    return path
