"""Measured ball states just after a hit: Google DeepMind's rally and serve states (D'Ambrosio et
al., "Achieving Human Level Competitive Robot Table Tennis", ICRA 2025, arXiv:2408.03906; data of
``google-deepmind/competitive_robot_table_tennis``, CC-BY-4.0), read into the world frame and sent
towards the +x end, with a held-out split.

The files (``rallies.json``, ``serves.json``) are lists of ``{id, pos_x, pos_y, pos_z, vel_x, vel_y,
vel_z, w_vel_x, w_vel_y, w_vel_z}`` in metres, m/s and rad/s, with the origin at the centre of the
table's surface, **x across the table, y along it**, z up. Our x is their y and our y is minus
their x (a rotation about z, so spins turn as velocities do). A ball hit from the +x end is turned
half a turn about z, which leaves the physics unchanged, so that every shot comes from the -x end as
the environment's opponent plays.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ttsim_jax.data.errors import DataError
from ttsim_jax.data.frames import FrameTransform

#: The files of a folder and the shot type of each.
FILES = {"serve": "serves.json", "rally": "rallies.json"}
#: The keys of one state.
KEYS = ("id", "pos_x", "pos_y", "pos_z", "vel_x", "vel_y", "vel_z", "w_vel_x", "w_vel_y", "w_vel_z")
#: DeepMind's frame (x across, y along the table) to ours (x along, y across).
DEEPMIND_FRAME = FrameTransform(rotation=np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                                translation=np.zeros(3))
#: Held-out share of the states and the size of the id blocks the split draws (consecutive ids of
#: one rally are alike: a block goes to one side whole).
TEST_FRACTION, BLOCK = 0.2, 10
#: Largest plausible speed [m/s] and spin [rad/s] of a state after a hit (a smash reaches 30 m/s,
#: a loop 1,000 rad/s): beyond it a row is a tracking error and is refused by name.
MAX_SPEED, MAX_SPIN = 40.0, 1500.0


@dataclasses.dataclass(frozen=True)
class PostHitStates:
    """Ball states just after a hit, in the world frame, every one travelling towards +x.

    Attributes:
        kind: (n,) str, "serve" or "rally".
        id: (n,) int, the source's id.
        pos, vel, spin: (n, 3) float64 [m, m/s, rad/s].
        mirrored: (n,) bool, hit from the +x end and turned half a turn about z.
        test: (n,) bool, in the held-out split (:func:`held_out`).
    """

    kind: np.ndarray
    id: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    spin: np.ndarray
    mirrored: np.ndarray
    test: np.ndarray

    def __len__(self) -> int:
        return len(self.id)

    def select(self, keep) -> "PostHitStates":
        """The states where ``keep`` (a boolean mask or indexes)."""
        return PostHitStates(**{f.name: getattr(self, f.name)[keep] for f in dataclasses.fields(self)})


def held_out(ids, fraction: float = TEST_FRACTION, block: int = BLOCK) -> np.ndarray:
    """Whether each id is held out: its block of ``block`` consecutive ids is, for a fixed hash of
    the block number below ``fraction`` (the same split on every machine and for every task)."""
    b = np.asarray(ids, np.uint64) // np.uint64(block)
    with np.errstate(over="ignore"):  # Fibonacci hashing: the product modulo 2^64, its high 32 bits
        h = (b * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(32)
    return h.astype(np.float64) / 2.0**32 < fraction


def _read(path: Path) -> np.ndarray:
    """(n, 10) float64 of :data:`KEYS` from one file; refuses a malformed row by file, row and key."""
    try:
        rows = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"cannot read it ({e})", file=path) from None
    except json.JSONDecodeError as e:
        raise DataError(f"not JSON ({e})", file=path) from None
    if not isinstance(rows, list) or not rows:
        raise DataError("expected a non-empty list of ball states", file=path)
    out = np.empty((len(rows), len(KEYS)), np.float64)
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise DataError("expected an object {id, pos_x, ...}", file=path, row=i, value=row)
        for j, key in enumerate(KEYS):
            if key not in row:
                raise DataError(f"missing key (a state holds {', '.join(KEYS)})", file=path, row=i, column=key)
            v = row[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise DataError("expected a finite number", file=path, row=i, column=key, value=v)
            out[i, j] = v
    for cols, limit, what in (((4, 5, 6), MAX_SPEED, "m/s"), ((7, 8, 9), MAX_SPIN, "rad/s")):
        size = np.linalg.norm(out[:, cols], axis=1)
        bad = np.flatnonzero(size > limit)
        if bad.size:
            i = int(bad[0])
            raise DataError(f"|{KEYS[cols[0]][:-2]}| = {size[i]:.1f} {what}: above {limit:g} {what}, no ball after a "
                            f"hit (are these {what}?)", file=path, row=i, column=KEYS[cols[0]], value=out[i, cols[0]])
    return out


def read_post_hit_states(folder, kinds=tuple(FILES)) -> PostHitStates:
    """The states of ``kinds`` in a folder of DeepMind's ``serves.json`` and ``rallies.json``.

    Arguments:
        folder: the folder; kinds: which files ("serve", "rally").

    Returns:
        :class:`PostHitStates`; raises :class:`~ttsim_jax.data.errors.DataError` naming the file,
        row, key and value of a bad state, or the missing file.
    """
    folder = Path(folder)
    parts = []
    for kind in kinds:
        if kind not in FILES:
            raise ValueError(f"unknown kind {kind!r}; known: {list(FILES)}")
        path = folder / FILES[kind]
        if not path.is_file():
            raise DataError(f"no {FILES[kind]} here (DeepMind's post-hit states: {', '.join(FILES.values())})",
                            file=folder)
        a = _read(path)
        parts.append((np.full(len(a), kind, object), a))
    kind = np.concatenate([k for k, _ in parts])
    a = np.concatenate([x for _, x in parts])
    pos = DEEPMIND_FRAME.points(a[:, 1:4])
    vel, spin = DEEPMIND_FRAME.vectors(a[:, 4:7]), DEEPMIND_FRAME.vectors(a[:, 7:10])
    mirrored = vel[:, 0] < 0.0
    half_turn = np.where(mirrored[:, None], np.array([-1.0, -1.0, 1.0]), 1.0)
    ids = a[:, 0].astype(np.int64)
    return PostHitStates(kind=kind, id=ids, pos=pos * half_turn, vel=vel * half_turn, spin=spin * half_turn,
                         mirrored=mirrored, test=held_out(ids))
