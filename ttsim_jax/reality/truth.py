"""The ground-truth files of a generated dataset: :func:`write` and :func:`load_truth`.

Files written by :func:`write` (``DIR`` is a normal dataset directory, see
``docs/data_format.md``; the truth files sit beside the five tables and are ignored by
:func:`ttsim_jax.data.load`):

``truth.json``
    ``dataset_id`` (that of ``metadata.json``; every truth Parquet file carries it too, and
    :func:`load_truth` checks it), generator version, seed, configuration, model, racket face,
    counts, and the true
    effect parameters: ``effects[name] = {"scope", "where", "units", "params"}`` for effects drawn
    once per dataset and ``sessions[i]["effects"][name]`` for those drawn per game (session).
``truth_events.parquet``
    one row per dataset event (same ``event_id``): ``session_id``, ``rally``, ``t``, ``kind`` (as
    in the dataset), ``true_kind`` (toss, serve, hit, table, net, floor, lost), ``player``
    (robot, opponent, or empty), ``shot`` (shot type of racket contacts), the true ball state just
    before (``pre_*``) and after (``post_*``) the event (x, y, z, vx, vy, vz, spin_x, spin_y,
    spin_z), and for racket contacts the aimed outgoing velocity and spin (``aim_*``; NaN
    otherwise).
``truth_rackets.parquet``
    the true racket state of every racket contact of both players (``event_id``, ``player``,
    x, y, z, qw, qx, qy, qz, vx, vy, vz, wx, wy, wz, d_y, d_z), in the rackets table's columns.
``truth_observations.parquet`` (unless ``truth_observations = false``)
    row by row the true state of every observation (``session_id``, ``t``, x, y, z, vx, vy, vz,
    spin_x, spin_y, spin_z); the states are float32 when the simulation ran in float32 (exact).

Use :func:`load_truth` to read them back.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ttsim_jax.data.io import ID_KEY, dataset_id, read_parquet, read_truth_json, save, verify_files, write_parquet

from .assembly import Generated


def _truth_parquet(table: dict, path: Path, ident: str):
    """Writes a column table (dict of numpy arrays; object columns as strings) as a Parquet file
    carrying the dataset id ``ident``."""
    import pyarrow as pa

    arrays, fields = [], []
    for k, v in table.items():
        v = np.asarray(v)
        if v.dtype == object:
            arrays.append(pa.array([str(x) for x in v], pa.string()))
        else:
            arrays.append(pa.array(v))
        fields.append(k)
    write_parquet(pa.Table.from_arrays(arrays, names=fields), path, ident)


def write(gen: Generated, out: str | Path, *, overwrite: bool = False) -> Path:
    """Writes the dataset directory ``out`` and the truth files beside its tables, atomically
    (all files appear together, carrying one dataset id; see :func:`ttsim_jax.data.io.save`).

    Arguments:
        gen: from :func:`~ttsim_jax.reality.generate`.
        out: dataset directory.
        overwrite: replace an existing dataset there.

    Returns:
        The directory.
    """

    def truth_files(directory: Path, ident: str):
        info = dict(gen.truth, **{ID_KEY: ident})
        (directory / "truth.json").write_text(json.dumps(info, indent=1, sort_keys=False) + "\n")
        _truth_parquet(gen.truth_events, directory / "truth_events.parquet", ident)
        _truth_parquet(gen.truth_rackets, directory / "truth_rackets.parquet", ident)
        if gen.truth_observations is not None:
            _truth_parquet(gen.truth_observations, directory / "truth_observations.parquet", ident)

    return save(gen.dataset, out, overwrite=overwrite, extra=truth_files)


@dataclasses.dataclass
class Truth:
    """Ground truth read back by :func:`load_truth`: the ``truth.json`` dict and the truth tables
    (column dicts; ``observations`` is None when it was not written)."""

    info: dict
    events: dict
    rackets: dict
    observations: dict | None

    def effect_params(self, name: str, session_id: int | None = None) -> dict:
        """True parameters of effect ``name`` (of a session, for per-session effects)."""
        e = self.info["effects"].get(name)
        if e is None:
            raise KeyError(f"effect {name!r} was not on; effects: {list(self.info['effects'])}")
        if e["scope"] == "dataset":
            return e["params"]
        if session_id is None:
            raise ValueError(f"effect {name!r} is drawn per session: give session_id")
        return self.info["sessions"][session_id]["effects"][name]


def load_truth(path: str | Path) -> Truth:
    """Reads the truth files of a generated dataset directory, checking that they carry the id of
    the dataset's ``metadata.json`` (a :class:`~ttsim_jax.data.DataError` names a file that does
    not, or a corrupted one).

    Arguments:
        path: the dataset directory :func:`write` wrote.

    Returns:
        A :class:`Truth`.
    """
    path = Path(path)
    file = path / "truth.json"
    if not file.is_file():
        raise FileNotFoundError(f"{file}: missing; is {path} a generated dataset?")
    ident = dataset_id(path)
    info = read_truth_json(path, ident)
    info.pop(ID_KEY, "")

    def table(name):
        p = path / name
        if not p.is_file():
            return None
        t = read_parquet(p, ident, name.removesuffix(".parquet"))
        return {c: (np.array(t.column(c).to_pylist(), object) if str(t.column(c).type) == "string" else t.column(c).to_numpy())
                for c in t.column_names}

    out = Truth(info=info, events=table("truth_events.parquet"),
                rackets=table("truth_rackets.parquet"), observations=table("truth_observations.parquet"))
    verify_files(path, ["truth.json", "truth_events.parquet", "truth_rackets.parquet", "truth_observations.parquet"])
    return out
