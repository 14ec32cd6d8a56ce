"""From games that have run to a measured-format dataset and its ground truth.

:func:`assemble` applies the effects that act on the record (missing frames, position noise, the
tracker's camera scale and clock, racket-state errors, spin-estimate noise) to what the games
recorded, never to the truth; derives the segments and measures each one's spin (the mean true spin
over its samples, with :class:`~ttsim_jax.effects.SpinNoise` if enabled); validates the dataset;
and builds the truth tables and counts that :mod:`ttsim_jax.reality.truth` writes.
"""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import effects as fx
from ttsim_jax.data import schema
from ttsim_jax.data.dataset import Dataset, Metadata
from ttsim_jax.data.validate import validate
from ttsim_jax.physics.rotations import matrix_to_quat
from ttsim_jax.shots import SHOT_TYPES

from .game import PLAYERS, Game

GENERATOR_VERSION = "1"
_STATE = ("x", "y", "z", "vx", "vy", "vz", "spin_x", "spin_y", "spin_z")


@dataclasses.dataclass
class Generated:
    """What :func:`~ttsim_jax.reality.generate` returns.

    Attributes:
        dataset: the measured-format :class:`~ttsim_jax.data.Dataset` (validated).
        truth: JSON-able dict (written as ``truth.json``): configuration, effects, counts.
        truth_events, truth_rackets: column tables (dicts of numpy arrays), see :mod:`ttsim_jax.reality.truth`.
        truth_observations: column table aligned row by row with ``dataset.observations``, or None.
        wall_time_s: how long the generation took (not written: the files depend only on the seed
            and the configuration).
    """

    dataset: Dataset
    truth: dict
    truth_events: dict
    truth_rackets: dict
    truth_observations: dict | None
    wall_time_s: float = 0.0
    _game: "Game | None" = dataclasses.field(default=None, repr=False, compare=False)


def _record(game: Game, name: str, sid: int):
    if name not in game.record:
        return None
    return game.effect(sid, name)


def assemble(game: Game, wall: float) -> Generated:
    """The dataset and its truth from games that have run: record effects applied, spins measured.

    Arguments:
        game: a :class:`~ttsim_jax.reality.game.Game` after :meth:`~ttsim_jax.reality.game.Game.run`.
        wall: seconds the generation took so far (kept in :attr:`Generated.wall_time_s`).

    Returns:
        A :class:`Generated`; its dataset is validated.
    """
    cfg = game.cfg
    dt = cfg.dt
    radius = float(game.plain.ball.radius)
    obs_cols = {k: [] for k in ("session_id", "t") + _STATE}
    ev_rows: list[dict] = []
    for s in game.sessions:
        rng = np.random.default_rng([cfg.seed, 3, s.sid])
        o = np.concatenate(s.obs) if s.obs else np.zeros((0, 10))
        order = np.argsort(o[:, 0], kind="stable")
        o = o[order]
        t = o[:, 0] * dt
        drop = _record(game, "missing_frames", s.sid)
        keep = drop.drop_frames(t, rng) if drop is not None else np.ones(len(t), bool)
        o, t = o[keep], t[keep]
        obs_cols["session_id"].append(np.full(len(t), s.sid, np.int64))
        obs_cols["t"].append(t)
        for i, k in enumerate(_STATE):
            obs_cols[k].append(o[:, 1 + i])
        for e in sorted(s.events, key=lambda e: e["t"]):
            ev_rows.append(dict(e, session_id=s.sid))
    obs = {k: np.concatenate(v) if v else np.zeros(0) for k, v in obs_cols.items()}
    obs["session_id"] = obs["session_id"].astype(np.int64)
    true_pos = np.stack([obs["x"], obs["y"], obs["z"]], -1)
    n_ev = len(ev_rows)
    ev_sid = np.array([e["session_id"] for e in ev_rows], np.int64)
    ev_pos_true = np.array([e["pos"] for e in ev_rows], np.float64).reshape(-1, 3)

    # --- sensor effects on positions (observations and the event positions derived from them)
    pos_obs, ev_pos = true_pos.copy(), ev_pos_true.copy()
    for s in game.sessions:
        noise = _record(game, "position_noise", s.sid)
        if noise is None:
            continue
        rng = np.random.default_rng([cfg.seed, 4, s.sid])
        i, j = obs["session_id"] == s.sid, ev_sid == s.sid
        pos_obs[i] = noise.observe_positions(true_pos[i], rng)
        ev_pos[j] = noise.observe_positions(ev_pos_true[j], rng)
    # --- the tracker's calibration and clock (no random draws): scaled positions, skewed times
    ev_t = np.array([e["t"] for e in ev_rows], np.float64)
    obs_t_rec, ev_t_rec = obs["t"].copy(), ev_t.copy()
    for s in game.sessions:
        scale, clock = _record(game, "camera_scale", s.sid), _record(game, "clock_rate", s.sid)
        i, j = obs["session_id"] == s.sid, ev_sid == s.sid
        if scale is not None:
            pos_obs[i], ev_pos[j] = scale.observe_positions(pos_obs[i]), scale.observe_positions(ev_pos[j])
        if clock is not None:
            obs_t_rec[i], ev_t_rec[j] = clock.record_times(obs["t"][i]), clock.record_times(ev_t[j])

    # --- racket states of the robot's contacts, as recorded
    is_robot = np.array([e["kind"] == "racket" for e in ev_rows], bool)
    r_idx = np.flatnonzero(is_robot)
    true_r = [ev_rows[i]["racket"] for i in r_idx]
    rpos = np.array([r["pos"] for r in true_r]).reshape(-1, 3)
    rrot = np.array([r["rot"] for r in true_r]).reshape(-1, 3, 3)
    rvel = np.array([r["vel"] for r in true_r]).reshape(-1, 3)
    rang = np.array([r["ang_vel"] for r in true_r]).reshape(-1, 3)
    rec = [rpos.copy(), rrot.copy(), rvel.copy(), rang.copy()]
    for s in game.sessions:
        err = _record(game, "racket_state_error", s.sid)
        if err is None:
            continue
        rng = np.random.default_rng([cfg.seed, 5, s.sid])
        m = ev_sid[r_idx] == s.sid
        if m.any():
            out = err.record_racket(rpos[m], rrot[m], rvel[m], rang[m], rng)
            for a, b in zip(rec, out):
                a[m] = b
    # the contact point as the robot computes it: ball position at contact and recorded racket pose
    n_rec = rec[1][:, :, 0]
    local = np.einsum("nji,nj->ni", rec[1], ev_pos[r_idx] - radius * n_rec - rec[0])
    rackets = dict(event_id=r_idx.astype(np.int64), pos=rec[0], quat=matrix_to_quat(rec[1]), vel=rec[2], ang_vel=rec[3],
                   contact=local[:, 1:3])
    events = dict(event_id=np.arange(n_ev, dtype=np.int64), session_id=ev_sid, t=ev_t_rec,
                  kind=np.array([e["kind"] for e in ev_rows], object), pos=ev_pos)
    sessions = dict(session_id=np.arange(cfg.games, dtype=np.int64),
                    name=np.array([f"game_{s.sid:04d}" for s in game.sessions], object),
                    notes=np.array([json.dumps({"rallies": s.n_rallies, "robot_end": "+x" if cfg.robot_end > 0 else "-x",
                                                "first_server": PLAYERS[s.first_server]}) for s in game.sessions], object))
    meta = Metadata(
        source=f"ttsim-jax reality generator v{GENERATOR_VERSION}: {cfg.model} + effects [{', '.join(cfg.effects) or 'none'}], "
               f"seed {cfg.seed}",
        equipment={"ball": f"simulated 40+ ball ({cfg.model}, radius {radius} m)", "racket_face_semi_axes_m": list(cfg.face),
                   "robot_end": "+x" if cfg.robot_end > 0 else "-x", "observation_rate_hz": 1.0 / (dt * cfg.obs_every),
                   "tracking": "simulated; see truth.json for the sensor effects"},
        notes="Synthetic data from ttsim_jax.reality. Sessions are games; 'racket' events are the robot's contacts "
              "(with racket states), 'other' events are the opponent's contacts and the serve tosses. Ground truth: "
              "truth.json, truth_events.parquet, truth_rackets.parquet, truth_observations.parquet.",
    )
    ds = Dataset.from_arrays(obs["session_id"], obs_t_rec, pos_obs, events=events, rackets=rackets, sessions=sessions,
                             metadata=meta)

    # --- spin measurements per segment
    true_spin = np.stack([obs["spin_x"], obs["spin_y"], obs["spin_z"]], -1)
    seg = dict(ds.segments)
    seg_id = ds.observations["segment_id"]
    n_seg = len(seg["segment_id"])
    sums = np.zeros((n_seg, 3))
    counts = np.zeros(n_seg)
    np.add.at(sums, seg_id, true_spin)
    np.add.at(counts, seg_id, 1.0)
    mean_spin = sums / np.maximum(counts, 1.0)[:, None]
    spin_m, conf = mean_spin.copy(), np.ones(n_seg)
    for s in game.sessions:
        noise = _record(game, "spin_noise", s.sid)
        if noise is None:
            continue
        m = seg["session_id"] == s.sid
        rng = np.random.default_rng([cfg.seed, 6, s.sid])
        spin_m[m], conf[m] = noise.measure_spin(mean_spin[m], seg["t_end"][m] - seg["t_start"][m], rng)
    for s in game.sessions:  # after the noise: a miscalibrated estimator, then a tracker without spin
        calibration, unmeasured = _record(game, "spin_calibration", s.sid), _record(game, "spin_unmeasured", s.sid)
        m = seg["session_id"] == s.sid
        if calibration is not None:
            spin_m[m] = calibration.measure_spin(spin_m[m], np.random.default_rng([cfg.seed, 7, s.sid]))
        if unmeasured is not None:
            spin_m[m], conf[m] = unmeasured.measure_spin(spin_m[m], conf[m], np.random.default_rng([cfg.seed, 8, s.sid]))
    seg.update(spin_x=spin_m[:, 0], spin_y=spin_m[:, 1], spin_z=spin_m[:, 2], spin_conf=conf)
    o = dict(ds.observations)
    o.update(spin_x=spin_m[seg_id, 0], spin_y=spin_m[seg_id, 1], spin_z=spin_m[seg_id, 2], spin_conf=conf[seg_id])
    ds = ds.replace(observations=o, segments=seg)
    validate(ds)

    # --- truth tables
    nan3 = np.full(3, np.nan)
    tev = {"event_id": np.arange(n_ev, dtype=np.int64), "session_id": ev_sid,
           "rally": np.array([e["rally"] for e in ev_rows], np.int64), "t": ev_t, "kind": events["kind"],
           "true_kind": np.array([e["true_kind"] for e in ev_rows], object),
           "player": np.array([e["player"] for e in ev_rows], object), "shot": np.array([e["shot"] for e in ev_rows], object)}
    pre = np.array([e["pre"] for e in ev_rows]).reshape(-1, 9)
    post = np.array([e["post"] for e in ev_rows]).reshape(-1, 9)
    aim_ = np.array([e["aim"] if e["aim"] is not None else np.concatenate([nan3, nan3]) for e in ev_rows]).reshape(-1, 6)
    for i, k in enumerate(_STATE):
        tev[f"pre_{k}"] = pre[:, i]
    for i, k in enumerate(_STATE):
        tev[f"post_{k}"] = post[:, i]
    for i, k in enumerate(("vx", "vy", "vz", "spin_x", "spin_y", "spin_z")):
        tev[f"aim_{k}"] = aim_[:, i]
    hit_idx = np.flatnonzero([e["racket"] is not None for e in ev_rows])
    hr = [ev_rows[i]["racket"] for i in hit_idx]
    q = matrix_to_quat(np.array([r["rot"] for r in hr]).reshape(-1, 3, 3))
    trk = {"event_id": hit_idx.astype(np.int64), "session_id": ev_sid[hit_idx],
           "player": np.array([ev_rows[i]["player"] for i in hit_idx], object)}
    for name, arr in (("", "pos"), ("v", "vel"), ("w", "ang_vel")):
        a = np.array([r[arr] for r in hr]).reshape(-1, 3)
        for i, ax in enumerate("xyz"):
            trk[f"{name}{ax}"] = a[:, i]
    for i, k in enumerate(("qw", "qx", "qy", "qz")):
        trk[k] = q[:, i]
    dd = np.array([r["d"] for r in hr]).reshape(-1, 2)
    trk["d_y"], trk["d_z"] = dd[:, 0], dd[:, 1]
    tobs = None
    if cfg.truth_observations:
        # states come from the simulation: float32 ones are stored as float32, exactly and at half the size
        sim = np.float32 if cfg.dtype == "float32" else np.float64
        tobs = {"session_id": obs["session_id"], "t": obs["t"], **{k: obs[k].astype(sim) for k in _STATE}}

    # --- summary
    kinds = {k: int(np.sum(events["kind"] == k)) for k in schema.EVENT_KINDS}
    robot_d = dd[trk["player"] == "robot"]
    dist = np.linalg.norm(robot_d, axis=-1)
    logo = fx.RacketLogo.default()
    in_logo = np.asarray(jax.vmap(logo.weight)(jnp.asarray(robot_d))) > 0.5 if len(robot_d) else np.zeros(0, bool)
    shots = {k: int(np.sum(tev["shot"] == k)) for k in SHOT_TYPES}
    counts = {
        "games": cfg.games, "rallies": game.total_rallies, "observations": len(obs["t"]),
        "segments": len(seg["segment_id"]), "events": kinds, "table_contacts": kinds["table"],
        "robot_racket_contacts": kinds["racket"], "opponent_racket_contacts": int(np.sum(trk["player"] == "opponent")),
        "shots": shots,
        "robot_contact_bands": {"0-5cm": int(np.sum(dist < 0.05)), "5-8cm": int(np.sum((dist >= 0.05) & (dist < 0.08))),
                                ">8cm": int(np.sum(dist >= 0.08)), "logo": int(np.sum(in_logo))},
        "segments_with_spin_conf>=0.5": int(np.sum(conf >= 0.5)),
        "simulated_ball_steps": int(game.steps_simulated), "chunks": int(game.chunks),
    }
    eff_info = {}
    for name in cfg.effects:
        cls = fx.effect_class(name)
        info = {"scope": cls.SCOPE, "where": cls.WHERE, "description": cls.DESCRIPTION,
                "units": {k: p.unit for k, p in cls.PARAMS.items()}}
        if cls.SCOPE == "dataset":
            info["params"] = game.dataset_effects[name].to_dict()
        eff_info[name] = info
    truth = {
        "generator": f"ttsim_jax.reality v{GENERATOR_VERSION}", "seed": cfg.seed, "model": cfg.model,
        "config": cfg.to_dict(), "face_semi_axes_m": list(cfg.face), "robot_end": cfg.robot_end,
        "dt": dt, "observation_rate_hz": 1.0 / (dt * cfg.obs_every), "effects": eff_info,
        "sessions": [{"session_id": s.sid, "rallies": s.n_rallies, "first_server": PLAYERS[s.first_server],
                      "effects": {n: e.to_dict() for n, e in game.session_effects[s.sid].items()}} for s in game.sessions],
        "counts": counts,
    }
    return Generated(dataset=ds, truth=truth, truth_events=tev, truth_rackets=trk, truth_observations=tobs, wall_time_s=wall,
                     _game=game)
