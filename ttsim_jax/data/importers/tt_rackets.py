"""tt_rackets racket bounces (gossardt/tt_rackets, MIT licence; Gossard, "Learning Racket-Ball
Bounce Dynamics Across Diverse Rubbers for Robotic Table Tennis", arXiv:2604.11349, 2026).

Files: ``racket_NN.csv`` (NN = 01..10, one racket configuration each: :data:`CONFIGS`), header
:data:`HEADER`; one row per bounce, velocities [m/s] and spins [rad/s] just before and after it,
in the racket's frame (z the face normal towards the ball, x the in-plane direction of the
motion), the racket at rest; ``racket_angle`` the racket's tilt [deg] in the rig.

What the import writes (no trajectories: the rig measured states, not positions):

* one session per file and tilt (``name`` ``tt_rackets/<split>/racket_NN.csv@<tilt>deg``,
  ``notes`` JSON with ``config``, ``tilt_deg``, ``split``: the folder the file was in);
* one racket event per bounce, ``event_id = NN * 10000 + tilt index * 1000 + traj_dir`` (so the
  source's row key stays readable), one second apart within a session (the rig gives no time);
* the racket at rest at :data:`RACKET_POSITION`, its face normal along world +z and its in-plane
  x along world x (:data:`RACKET_QUAT`), so the world frame of the states *is* the source's racket
  frame; the ball centre one radius above the face centre; ``config`` = ``racket_NN``;
* the states in ``contact_states`` (spin confidence 1), which :class:`~ttsim_jax.data.Contacts`
  reads instead of estimating them.

The metadata's ``equipment["rackets"]`` describes each configuration (blade, sponge, rubber, its
type); :mod:`ttsim_jax.data.racket_configs` reads it back.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..csvlog import read_text
from ..dataset import Dataset, Metadata
from ..errors import DataError
from ..schema import BALL_RADIUS
from . import read_numeric_rows

HEADER = ("racket_angle", "traj_dir", "spin_before_x", "spin_before_y", "spin_before_z", "spin_after_x", "spin_after_y",
          "spin_after_z", "v_in_x", "v_in_y", "v_in_z", "v_out_x", "v_out_y", "v_out_z")
CITATION = ("tt_rackets (github.com/gossardt/tt_rackets, MIT licence, (c) 2026 Thomas Gossard): T. Gossard, 'Learning "
            "Racket-Ball Bounce Dynamics Across Diverse Rubbers for Robotic Table Tennis', arXiv:2604.11349, 2026")
#: Configuration name -> (blade, sponge [mm], rubber, rubber type), from the source's README.
CONFIGS = {
    "racket_01": ("offensive (Donic Holz Original Carbospeed)", 2.1, "andro Hexer Duro", "inverted"),
    "racket_02": ("offensive (Donic Holz Original Carbospeed)", 1.8, "andro Power 3", "inverted"),
    "racket_03": ("defensive (Tibhar Holz Defense Plus)", 2.1, "andro Hexer Duro", "inverted"),
    "racket_04": ("defensive (Tibhar Holz Defense Plus)", 1.8, "andro Power 3", "inverted"),
    "racket_05": ("allround (DONIC Appelgren Allplay Senso V1)", 1.2, "Tibhar Grass D.TecS", "long_pips"),
    "racket_06": ("allround (DONIC Appelgren Allplay Senso V1)", 0.0, "Tibhar Grass D.TecS", "long_pips"),
    "racket_07": ("allround (DONIC Appelgren Allplay Senso V1)", 1.2, "Dr. Neubauer Diamant", "medium_pips"),
    "racket_08": ("allround (DONIC Appelgren Allplay Senso V1)", 2.0, "andro Blowfish", "short_pips"),
    "racket_09": ("allround (DONIC Appelgren Allplay Senso V1)", 2.1, "andro Hexer Duro", "inverted"),
    "racket_10": ("allround (DONIC Appelgren Allplay Senso V1)", 2.1, "Dr. Neubauer A-B-S II soft", "anti_spin"),
}
#: The tilts [deg] the rig used, in the order of their index in the event ids.
TILTS = (0.0, 10.0, 20.0)
#: Where the racket's face centre is put [m]: behind one end of the table, clear of it.
RACKET_POSITION = (-2.0, 0.0, 0.3)
#: Racket -> world rotation (w, x, y, z): the racket's face normal (its x) along world z, its y along
#: world x, its z (handle -> tip) along world y; the source's (x, y, z) are then world (x, y, z).
RACKET_QUAT = (0.5, -0.5, -0.5, -0.5)


def read_files(path) -> list[Path]:
    """The racket CSVs of ``path``: one file, a folder of ``racket_*.csv``, or the source's folder
    with ``train/`` (and ``test/``, if present) inside."""
    path = Path(path)
    if path.is_file():
        return [path]
    files = sorted(path.glob("racket_*.csv"))
    for split in ("train", "test"):
        files += sorted((path / split).glob("racket_*.csv"))
    if not files:
        raise DataError("no racket_*.csv files found (here, or in its train/ and test/ folders)", file=path)
    return files


def _config_of(f: Path) -> str:
    name = f.stem
    if name not in CONFIGS:
        raise DataError("not a tt_rackets file name: expected racket_01.csv ... racket_10.csv", file=f, value=f.name)
    return name


def _rows(f: Path) -> np.ndarray:
    header = read_text(f).partition("\n")[0].strip()
    if tuple(h.strip() for h in header.split(",")) != HEADER:
        raise DataError(f"expected the header '{','.join(HEADER)}'", file=f, row=1, row_label="line", value=header)
    a = read_numeric_rows(f, delimiter=",", n_cols=len(HEADER), skip_header=True, names=HEADER)
    col = {name: k for k, name in enumerate(HEADER)}
    checks = (("racket_angle", ~np.isin(a[:, 0], TILTS), f"a tilt of {', '.join(f'{t:g}' for t in TILTS)} degrees"),
              ("traj_dir", (a[:, 1] < 0) | (a[:, 1] > 999) | (a[:, 1] != np.round(a[:, 1])), "an integer 0..999"),
              ("v_in_z", a[:, col["v_in_z"]] >= 0.0, "< 0 (the ball moving into the face)"),
              ("v_out_z", a[:, col["v_out_z"]] <= 0.0, "> 0 (the ball leaving the face)"))
    for name, bad, want in checks:
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise DataError(f"must be {want}", file=f, row=k + 2, row_label="line", column=name, value=a[k, col[name]])
    return a


def load(path) -> Dataset:
    """tt_rackets folder or file -> :class:`Dataset` of racket contacts with measured states."""
    from ..validate import validate

    sessions, events, rackets, states = [], [], [], []
    for f in read_files(path):
        config, a = _config_of(f), _rows(f)
        split = f.parent.name if f.parent.name in ("train", "test") else ""
        for ti, tilt in enumerate(TILTS):
            rows = a[a[:, 0] == tilt]
            if not len(rows):
                continue
            sid = len(sessions)
            sessions.append((sid, f"tt_rackets/{split + '/' if split else ''}{f.name}@{tilt:g}deg",
                             json.dumps(dict(config=config, tilt_deg=tilt, split=split))))
            ids = int(config[-2:]) * 10000 + ti * 1000 + rows[:, 1].astype(np.int64)
            events.append((ids, np.full(len(ids), sid), np.arange(len(ids), dtype=np.float64)))
            rackets.append(np.full(len(ids), config, object))
            states.append(rows[:, 2:])
    if not sessions:
        raise DataError("no bounces in the files", file=path)
    ids = np.concatenate([e[0] for e in events])
    n = len(ids)
    order = np.argsort(ids, kind="stable")
    dup = np.flatnonzero(np.diff(ids[order]) == 0)
    if dup.size:
        e = int(ids[order][dup[0]])
        raise DataError("the same bounce (racket, tilt, traj_dir) appears twice: pass train/ and test/ once each",
                        file=path, column="traj_dir", value=f"racket_{e // 10000:02d}, tilt {TILTS[e // 1000 % 10]:g}, "
                        f"traj_dir {e % 1000:03d}")
    s = np.concatenate(states)  # (n, 12): spin before, spin after, v_in, v_out
    face = np.broadcast_to(np.asarray(RACKET_POSITION, np.float64), (n, 3))
    ball = face + np.array([0.0, 0.0, BALL_RADIUS])
    zeros = np.zeros((n, 3))
    meta = Metadata(
        source=CITATION,
        equipment={"rackets": {k: dict(blade=b, sponge_mm=sp, rubber=r, rubber_type=ty) for k, (b, sp, r, ty)
                               in CONFIGS.items()},
                   "rig": "racket at rest, tilted 0, 10 or 20 degrees; ball states measured just before and after"},
        notes=("states in the source's racket frame: the racket is placed at rest with its face normal along world z "
               "(ttsim_jax.data.importers.tt_rackets); events are one second apart, the rig gives no times"),
    )
    ds = Dataset.from_arrays(
        np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)),
        events=dict(event_id=ids, session_id=np.concatenate([e[1] for e in events]),
                    t=np.concatenate([e[2] for e in events]), kind="racket", pos=ball),
        rackets=dict(event_id=ids, pos=face, quat=np.broadcast_to(np.asarray(RACKET_QUAT), (n, 4)), vel=zeros,
                     ang_vel=zeros, contact=np.zeros((n, 2)), config=np.concatenate(rackets)),
        sessions=dict(session_id=[x[0] for x in sessions], name=[x[1] for x in sessions], notes=[x[2] for x in sessions]),
        segments=None, metadata=meta,
        contact_states=dict(event_id=ids, w_in=s[:, 0:3], w_out=s[:, 3:6], v_in=s[:, 6:9], v_out=s[:, 9:12]),
    )
    validate(ds)
    return ds

