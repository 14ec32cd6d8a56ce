"""The reality generator: synthetic measured data with a known truth.

Games between a robot (at the +x end by default) and an opponent are simulated with a *truth
model*: ``conti2026`` plus a chosen set of effects from :mod:`ttsim_jax.effects` (each switchable
by name, parameterised, drawn once per dataset or once per game). The result is a
:class:`~ttsim_jax.data.Dataset` in the measured-data format, written with the ground truth next
to it, so that fitting, evaluation and the sim-to-real gap diagnosis can be checked against
known answers.

How a game is made:

* A rally starts with the server's toss (an ``other`` event: the ball leaves the hand), then the
  serve, a racket contact on the falling ball. Every racket contact is made by inverting the
  contact model: the hitter picks a shot (serve, topspin or backspin drive, push, block, smash,
  lob; the ranges of :data:`ttsim_jax.shots.SHOT_TYPES`, up to 35 m/s and 1000 rad/s) suited to
  where the ball is, aims it through the flight model (Newton iterations on heading and vertical
  speed so that the aimed bounce lands on the target), and solves for the racket state that
  produces that outgoing ball with the *plain* model: face normal, then normal racket speed from
  the restitution law, then tangential racket speed from the grip law (exact for the plain
  model). The racket face is placed at the ball with the contact point d sampled over the face
  (most hits near the centre, some in every band 0-5, 5-8 and beyond 8 cm). The *true* contact
  (truth model, with its effects) then decides what the ball really does.
* Flights are simulated with :func:`ttsim_jax.kernel.simulate` (dt = 1 ms, RK4), every game in its
  own lane of one batch (each lane with its game's truth model: ``model_batched``), in chunks of
  ``chunk_steps`` steps recorded at every step (so that contacts can be placed on the 1 ms grid,
  between the 200 Hz frames); the host reads the event log and trajectory of each chunk, decides
  hits and ends of rallies, and restarts each lane from its new state. A ball is hit after it bounced on the receiver's half, when it reaches the receiver's
  hitting distance (sampled per shot) or falls low. A rally ends when a ball hits the net, misses
  the table, bounces on the wrong half, or after a sampled number of shots (the receiver misses);
  the ball is then followed until it hits the floor (``out``).
* Observations are the ball centre at 200 Hz (every ``obs_every`` steps of a session clock; racket
  contacts fall between frames). The robot's racket contacts are ``racket`` events with a racket
  state; the opponent's contacts and the tosses are ``other`` events (no racket state).
  Effects acting on the record (racket-state error, position noise, spin-estimate noise with
  confidences and outliers, missing frames, the tracker's clock rate and latency, a camera
  scale error) are applied to what is written, never to the truth: the truth tables keep the
  true positions and the true session clock's times.
* Segments are derived from the events; each segment's spin is a measurement of the mean true
  spin over its samples (with :class:`~ttsim_jax.effects.SpinNoise` if enabled, else exact with
  confidence 1), and its samples carry the same spin.

Everything is deterministic for a seed and a configuration: every game has its own random
streams (``numpy`` generators seeded by (seed, stream, game)).

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

import copy
import dataclasses
import json
import math
import time
import tomllib
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax import effects as fx
from ttsim_jax.params import load_model, stack_models
from ttsim_jax.physics import events as ev
from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.numerics import safe_norm, safe_unit
from ttsim_jax.kernel import ball_properties, simulate
from ttsim_jax.shots import DRAG_AIM, MAGNUS_AIM, SHOT_TYPES, aim, aim_batch
from ttsim_jax.sizes import require as require_memory
from ttsim_jax.state import Ball, Racket

from . import schema
from .dataset import Dataset, Metadata

GENERATOR_VERSION = "1"
#: Step [s] and horizon [s] of the light flight used to aim shots.
AIM_STEP, AIM_HORIZON = 0.02, 1.8
#: Height of the ball centre [m] that just touches the top of the net.
NET_TOP = 0.1525 + 0.02
ROBOT, OPPONENT = 0, 1
PLAYERS = ("robot", "opponent")


class GeneratorError(ValueError):
    """A bad generator configuration; the message names the file, the key and the value."""


# ============================================================================ configuration
@dataclasses.dataclass
class GeneratorConfig:
    """What to generate. Every field has a default; presets (:data:`PRESETS`) change a few.

    Attributes:
        games: number of games (sessions).
        seed: seed of every random stream.
        model: base of the truth model (bundled name or TOML path).
        effects: names of the effects that are on (catalogue order), see :mod:`ttsim_jax.effects`.
        effect_params: ``{name: {parameter: value}}`` fixed values; parameters not given are drawn
            by the effect's ``sample`` (once per dataset or per game, by its scope).
        rallies_per_game: (low, high) number of rallies of a game, uniform.
        rally_hits_mean: mean planned number of racket contacts of a rally including the serve
            (geometric); rallies also end early on misses.
        max_rally_hits: cap of the planned number.
        rally_gap: (low, high) pause between rallies [s] (not recorded).
        robot_end: +1 if the robot plays from the +x end, -1 from the -x end.
        dt: simulation step [s].
        obs_every: an observation every that many steps (5 at 1 ms: 200 Hz).
        face: (y, z) semi-axes of the racket face outline [m]; contacts are sampled inside it.
        contact_bands: probabilities of contact points at 0-5 cm, 5-8 cm and beyond 8 cm from the
            face centre.
        hit_distance: (low, high) distance behind the net [m] where a player meets the ball.
        shot_weights: relative frequency of each return shot type where it is possible.
        lanes: games simulated in parallel (one batch lane each).
        chunk_steps: steps simulated between host decisions.
        aim_iters: quasi-Newton (Broyden) iterations of the aiming through the flight model.
        max_flight_time: a flight without a hit is ended (``out``) after this long [s].
        truth_observations: write ``truth_observations.parquet``.
        dtype: float type of the simulation (``float32`` or ``float64``).
    """

    games: int = 4
    seed: int = 0
    model: str = "conti2026"
    effects: tuple = tuple(fx.names())
    effect_params: dict = dataclasses.field(default_factory=dict)
    rallies_per_game: tuple = (11, 20)
    rally_hits_mean: float = 6.8
    max_rally_hits: int = 60
    rally_gap: tuple = (3.0, 8.0)
    robot_end: int = 1
    dt: float = 1e-3
    obs_every: int = 5
    face: tuple = (0.08, 0.09)
    contact_bands: tuple = (0.6, 0.28, 0.12)
    hit_distance: tuple = (1.3, 2.6)
    shot_weights: dict = dataclasses.field(default_factory=lambda: {
        "topspin_drive": 4.0, "backspin_drive": 1.5, "push": 2.0, "block": 2.0, "smash": 3.0, "lob": 1.5})
    lanes: int = 256
    chunk_steps: int = 100
    aim_iters: int = 4
    max_flight_time: float = 3.0
    truth_observations: bool = True
    dtype: str = "float32"

    def replace(self, **changes) -> "GeneratorConfig":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["effects"] = list(self.effects)
        return json.loads(json.dumps(d))  # tuples -> lists, numpy -> plain


#: Named configurations: ``sample`` (the bundled sample dataset, ~1 MB) and ``paper`` (the scale of
#: the paper's dataset: 277 games, ~58,000 segments, ~25,000 table and ~11,000 robot contacts).
PRESETS: dict[str, dict] = {
    "sample": dict(games=3, rallies_per_game=(6, 6), truth_observations=False),
    "paper": dict(games=277, rallies_per_game=(11, 19)),
}


def _check_config(cfg: GeneratorConfig, where: str = "generator config") -> GeneratorConfig:
    def bad(key, why):
        raise GeneratorError(f"{where}: key '{key}' = {getattr(cfg, key)!r}: {why}")

    if not isinstance(cfg.games, int) or cfg.games < 1:
        bad("games", "must be a positive integer")
    if not isinstance(cfg.seed, int) or cfg.seed < 0:
        bad("seed", "must be a non-negative integer")
    lo, hi = cfg.rallies_per_game
    if not (1 <= lo <= hi):
        bad("rallies_per_game", "must be [low, high] with 1 <= low <= high")
    if cfg.rally_hits_mean < 1:
        bad("rally_hits_mean", "must be at least 1")
    if cfg.robot_end not in (1, -1):
        bad("robot_end", "must be +1 or -1")
    if not (0 < cfg.dt <= 0.005):
        bad("dt", "must be in (0, 0.005] s")
    if cfg.obs_every < 1 or cfg.chunk_steps < 10 or cfg.lanes < 1:
        bad("chunk_steps", "obs_every >= 1, chunk_steps >= 10 and lanes >= 1 are needed")
    if len(cfg.contact_bands) != 3 or min(cfg.contact_bands) < 0 or sum(cfg.contact_bands) <= 0:
        bad("contact_bands", "must be three non-negative probabilities")
    if not (0.05 < cfg.face[0] < 0.2 and 0.05 < cfg.face[1] < 0.2):
        bad("face", "semi-axes must be in (0.05, 0.2) m")
    unknown = set(cfg.shot_weights) - set(SHOT_TYPES)
    if unknown:
        bad("shot_weights", f"unknown shot types {sorted(unknown)}; known: {list(SHOT_TYPES)}")
    if cfg.dtype not in ("float32", "float64"):
        bad("dtype", "must be float32 or float64")
    try:
        cfg.effects = tuple(fx.parse_names(cfg.effects))
    except fx.EffectError as e:
        raise GeneratorError(f"{where}: key 'effects': {e}") from None
    for name, values in cfg.effect_params.items():
        try:
            cls = fx.effect_class(name)
            cls.from_dict(values, where=f"{where}: [effects.{name}]")
        except fx.EffectError as e:
            raise GeneratorError(str(e)) from None
        # the config states a lab's reality: a value no lab meets (spin growing in flight, a table
        # tilted by degrees) is a typing mistake more often than an intended stress test
        for bad_value in cls.implausible(values):
            at = f"[{', '.join(map(str, bad_value['index']))}]" if bad_value["index"] else ""
            raise GeneratorError(
                f"{where}: [effects.{name}] {bad_value['param']}{at} = {bad_value['value']:g}: outside its "
                f"plausible range [{bad_value['low']:g}, {bad_value['high']:g}] {bad_value['unit']} "
                f"(python -m ttsim_jax.effects describes every parameter)")
    return cfg


#: Memory the generator holds per observation row until the dataset is written: the row in the
#: observations and truth tables and the per-rally lists they are built from. Measured: 8 games
#: (96,082 rows) held 67 MB more than 2 games (23,378 rows), 0.92 KiB per row.
BYTES_PER_ROW = 1024
#: Observed flight per planned racket contact [s]: the default games record 12,000 rows per game
#: at 200 Hz for 15.5 rallies of 6.8 planned contacts (0.57 s each).
SECONDS_PER_HIT = 0.6


def memory_bytes(cfg: GeneratorConfig) -> int:
    """What :func:`generate` will hold at once for ``cfg`` [bytes], from its sizes (an estimate
    within a factor of about 2: rallies end early or run long)."""
    rallies = cfg.games * 0.5 * (cfg.rallies_per_game[0] + cfg.rallies_per_game[1])
    rows = rallies * cfg.rally_hits_mean * SECONDS_PER_HIT / (cfg.dt * cfg.obs_every)
    return int(rows * BYTES_PER_ROW * (1.0 if cfg.truth_observations else 0.6))


def make_config(preset: str | None = None, config_file: str | Path | None = None, **overrides) -> GeneratorConfig:
    """Builds a checked configuration: defaults, then a preset, then a TOML file, then overrides.

    Arguments:
        preset: ``"sample"`` or ``"paper"`` (:data:`PRESETS`), or None.
        config_file: TOML file (see :func:`config_from_toml`), or None.
        **overrides: field values (``None`` values are ignored); ``effects`` may be a string
            (``"all"``, ``"none"``, ``"a,b"``).

    Returns:
        A :class:`GeneratorConfig`.
    """
    cfg = GeneratorConfig()
    if preset is not None:
        if preset not in PRESETS:
            raise GeneratorError(f"unknown preset {preset!r}; presets: {sorted(PRESETS)}")
        cfg = cfg.replace(**PRESETS[preset])
    if config_file is not None:
        cfg = config_from_toml(config_file, cfg)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    unknown = set(overrides) - {f.name for f in dataclasses.fields(GeneratorConfig)}
    if unknown:
        raise GeneratorError(f"unknown generator setting(s) {sorted(unknown)}")
    cfg = cfg.replace(**overrides)
    return _check_config(cfg)


def config_from_toml(path: str | Path, base: GeneratorConfig | None = None) -> GeneratorConfig:
    """Reads a generator configuration file.

    Layout::

        [generator]                 # any GeneratorConfig field
        games = 20
        seed = 3
        rallies_per_game = [11, 20]

        [effects]
        enabled = ["air_flow", "racket_logo"]     # or "all" / "none"

        [effects.air_flow]          # fixed parameter values; the others are drawn
        wind = [0.3, 0.0, 0.0]

    Arguments:
        path: the TOML file.
        base: configuration the file modifies (default: :class:`GeneratorConfig` defaults).

    Returns:
        The (checked) configuration.
    """
    path = Path(path)
    if not path.is_file():
        raise GeneratorError(f"{path}: no such generator config file")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise GeneratorError(f"{path}: not valid TOML: {e}") from None
    cfg = base or GeneratorConfig()
    unknown = set(data) - {"generator", "effects"}
    if unknown:
        k = sorted(unknown)[0]
        raise GeneratorError(f"{path}: key '{k}': unknown section; sections: [generator], [effects]")
    fields = {f.name: f for f in dataclasses.fields(GeneratorConfig)}
    gen = data.get("generator", {})
    changes: dict[str, Any] = {}
    for key, value in gen.items():
        if key not in fields or key in ("effects", "effect_params"):
            raise GeneratorError(f"{path}: key 'generator.{key}' = {value!r}: unknown setting; settings: "
                                 f"{sorted(set(fields) - {'effects', 'effect_params'})}")
        default = getattr(cfg, key)
        if isinstance(default, tuple):
            value = tuple(value) if isinstance(value, list) else value
        elif isinstance(default, bool) and not isinstance(value, bool):
            raise GeneratorError(f"{path}: key 'generator.{key}' = {value!r}: expected true or false")
        elif isinstance(default, int) and not isinstance(default, bool) and not isinstance(value, int):
            raise GeneratorError(f"{path}: key 'generator.{key}' = {value!r}: expected an integer")
        elif isinstance(default, float) and not isinstance(value, (int, float)):
            raise GeneratorError(f"{path}: key 'generator.{key}' = {value!r}: expected a number")
        changes[key] = value
    eff = data.get("effects", {})
    if "enabled" in eff:
        changes["effects"] = eff["enabled"]
    params = dict(cfg.effect_params)
    for key, value in eff.items():
        if key == "enabled":
            continue
        if key not in fx.CATALOGUE or not isinstance(value, dict):
            raise GeneratorError(f"{path}: key 'effects.{key}' = {value!r}: expected a table of parameters of one of "
                                 f"the effects {list(fx.CATALOGUE)}")
        params[key] = dict(value)
    changes["effect_params"] = params
    try:
        cfg = cfg.replace(**changes)
    except TypeError as e:  # pragma: no cover - guarded above
        raise GeneratorError(f"{path}: {e}") from None
    return _check_config(cfg, where=str(path))


# ============================================================================ jax kernels
def _dtype(cfg: GeneratorConfig):
    return jnp.float64 if cfg.dtype == "float64" else jnp.float32


def _normal_for(dv, dw, k):
    """(n, a): unit normal and a = Dv . n with Dv = a n + k n x Dw (Newton from n = Dv / |Dv|)."""
    dtype = dv.dtype

    def residual(x):
        n, a = x[:3], x[3]
        return jnp.concatenate([a * n + k * jnp.cross(n, dw) - dv, (jnp.dot(n, n) - 1.0)[None]])

    x = jnp.concatenate([safe_unit(dv, jnp.array([1.0, 0.0, 0.0], dtype)), safe_norm(dv)[None]])
    for _ in range(8):
        jac = jax.jacfwd(residual)(x)
        ok = jnp.abs(jnp.linalg.det(jac)) > 1e-12
        x = x - jnp.where(ok, jnp.linalg.solve(jnp.where(ok, jac, jnp.eye(4, dtype=dtype)), residual(x)), 0.0)
    n = safe_unit(x[:3], jnp.array([1.0, 0.0, 0.0], dtype))
    return n, jnp.dot(dv, n), safe_norm(residual(x)[:3])


def invert_contact(params, radius, mass, pos, v_in, w_in, v_out, w_out, d, roll, ang_vel, max_spin_ratio=0.8):
    """A racket state that turns (v_in, w_in) into (v_out, w_out) under the plain contact model.

    Arguments:
        params: :class:`~ttsim_jax.physics.racket.RacketParams` of the model the player believes.
        radius, mass: ball radius [m] and mass [kg] of that model.
        pos: (3,) ball centre at the contact.
        v_in, w_in: (3,) incoming velocity and spin.
        v_out, w_out: (3,) wanted outgoing velocity and spin. Only the spin's tangential part can
            be chosen, and only as much of its change as a point contact can give
            (|Dw| r / kappa <= max_spin_ratio |Dv|; less if that has no solution).
        d: (2,) contact point on the face (d_y, d_z) [m].
        roll: angle [rad] of the racket's z-axis (handle -> tip) about the normal, from "up".
        ang_vel: (3,) racket angular velocity [rad/s].

    Returns:
        dict with ``pos``, ``rot`` (columns: normal, y, z), ``vel``, ``ang_vel`` of the racket.

    The point contact changes the spin by (kappa / r) Dv_t x n, so the tangential velocity change
    fixes the normal: Dv = a n + (r / kappa) n x Dw with a > 0 (Newton). The normal racket speed
    then follows from v_n+ = -e_n v_n- and the tangential one from Dv_t = -alpha u- (u: slip
    velocity of the contact point), with e_n(|v_n|) and alpha(|u|) solved in closed form (they are
    linear laws, clipped). The outgoing velocity is then exact for the plain model.
    """
    dtype = pos.dtype
    kappa = params.kappa
    k = radius / kappa
    dv = v_out - v_in
    dw = w_out - w_in
    ndv = safe_norm(dv)
    cap = jnp.minimum(1.0, max_spin_ratio * ndv / jnp.maximum(k * safe_norm(dw), 1e-9))
    # the full (capped) spin change, half of it, or none: the first whose solution has the ball
    # arriving at the face (a well above 0) is used
    sols = [_normal_for(dv, dw * cap * f, k) for f in (1.0, 0.5, 0.0)]
    n, a = sols[2][0], sols[2][1]
    for cand_n, cand_a, res in reversed(sols[:2]):
        good = (cand_a > 0.3 * ndv) & (res < 1e-3 * (1.0 + ndv))
        n, a = jnp.where(good, cand_n, n), jnp.where(good, cand_a, a)

    up = jnp.array([0.0, 0.0, 1.0], dtype)
    ref = jnp.where(jnp.abs(n[2]) > 0.95, jnp.array([1.0, 0.0, 0.0], dtype), up)
    z0 = safe_unit(ref - jnp.dot(ref, n) * n, up)
    y0 = jnp.cross(z0, n)
    z_axis = jnp.cos(roll) * z0 + jnp.sin(roll) * y0
    y_axis = jnp.cross(z_axis, n)
    rot = jnp.stack([n, y_axis, z_axis], axis=1)
    offset = d[0] * y_axis + d[1] * z_axis
    racket_pos = pos - radius * n - offset

    # e = e0 + e1 |v_n-| with |v_n-| = a / (1 + e): e^2 + (1 - e0) e - (e0 + e1 a) = 0, clipped
    disc = (1.0 - params.e0) ** 2 + 4.0 * (params.e0 + params.e1 * a)
    e = jnp.clip(0.5 * (-(1.0 - params.e0) + jnp.sqrt(jnp.maximum(disc, 0.0))), 0.0, params.e_max)
    vs_n = jnp.dot(v_in, n) + a / (1.0 + e)

    w_surf = ang_vel if racket_stage.uses_racket_spin(params) else jnp.zeros_like(ang_vel)
    w_rel = w_in - w_surf
    dv_t = dv - a * n
    ndv_t = safe_norm(dv_t)
    if params.kind == "updated":
        # alpha = (1 + e_t) / (1 + kappa), e_t = et0 + et1 |u|, |u| = |Dv_t| / alpha: a quadratic in |u|
        c = ndv_t * (1.0 + kappa)
        b = 1.0 + params.et0
        small = jnp.abs(params.et1) < 1e-12
        disc = b * b + 4.0 * params.et1 * c
        s = jnp.where(small, c / b, (-b + jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.where(small, 1.0, 2.0 * params.et1))
        e_t = jnp.clip(params.et0 + params.et1 * s, 0.0, 1.0)
        alpha = (1.0 + e_t) / (1.0 + kappa)
    else:
        alpha = params.k_p / mass
    u = -dv_t / alpha
    v_in_t = v_in - jnp.dot(v_in, n) * n
    vs = v_in_t + radius * jnp.cross(n, w_rel) - u + vs_n * n
    vel = vs - jnp.cross(w_surf, offset)
    return dict(pos=racket_pos, rot=rot, vel=vel, ang_vel=ang_vel)


@jax.jit
def _invert_batch(params, radius, mass, pos, v_in, w_in, v_out, w_out, d, roll, ang_vel):
    return jax.vmap(invert_contact, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0, 0, 0))(
        params, radius, mass, pos, v_in, w_in, v_out, w_out, d, roll, ang_vel)


def _true_contact_one(model, rpos, rrot, rvel, rang, face, pos, vel, spin, v_target, iters):
    """The truth model's racket contact, after ``iters`` Newton steps on the racket velocity.

    The players know their equipment: the racket velocity from the plain-model inversion is
    corrected through the true contact (with the model's effects) until the outgoing velocity is
    ``v_target`` (the face orientation, and so the spin, is left as inverted).

    Returns:
        (racket velocity, outgoing velocity, outgoing spin, contact point d (2,)).
    """
    radius, mass = ball_properties(model)

    def contact(rv):
        racket = Racket(pos=rpos, rot=rrot, vel=rv, ang_vel=rang, face=face)
        return racket_stage.racket_contact(model.racket, racket, radius, mass, pos, vel, spin, model.effects)

    def newton(_, rv):
        jac = jax.jacfwd(lambda r: contact(r)[0])(rv)
        ok = jnp.abs(jnp.linalg.det(jac)) > 1e-9
        step = jnp.linalg.solve(jnp.where(ok, jac, jnp.eye(3, dtype=rv.dtype)), contact(rv)[0] - v_target)
        return rv - jnp.where(ok, jnp.clip(step, -5.0, 5.0), 0.0)

    rvel = jax.lax.fori_loop(0, iters, newton, rvel)
    v, w, state = contact(rvel)
    return rvel, v, w, state["d"]


@jax.jit
def _true_contact_batch(models, rpos, rrot, rvel, rang, face, pos, vel, spin, v_target, iters):
    return jax.vmap(_true_contact_one, in_axes=(0, 0, 0, 0, 0, None, 0, 0, 0, 0, None))(
        models, rpos, rrot, rvel, rang, face, pos, vel, spin, v_target, iters)


@jax.jit
def _lane_models(stacked, index, time_origin):
    """Per-lane truth models: the sessions' models, with time-varying effects on each lane's clock."""
    models = jax.tree.map(lambda a: a[index], stacked)
    effects = tuple(e.replace(time_origin=time_origin.astype(e.time_origin.dtype)) if hasattr(e, "time_origin") else e
                    for e in models.effects)
    return models.replace(effects=effects)


def _bucket(n: int) -> int:
    """Padded batch size for n items: powers of two from 16 (few sizes, so few compilations)."""
    return max(16, 1 << (max(n, 1) - 1).bit_length())


def _pad(arrays: dict, size: int) -> dict:
    out = {}
    for k, a in arrays.items():
        a = np.asarray(a)
        reps = size - len(a)
        out[k] = np.concatenate([a, np.repeat(a[:1], reps, axis=0)]) if reps > 0 else a
    return out


# ============================================================================ host: helpers
def matrix_to_quat(m) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N, 4) unit quaternions (w, x, y, z) with w >= 0."""
    m = np.asarray(m, np.float64).reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    k = np.argmax(cand, -1)
    q = np.zeros((len(m), 4))
    r = m
    for case in range(4):
        i = k == case
        if not i.any():
            continue
        rr = r[i]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[i])
            q[i] = np.stack([0.25 * s, (rr[:, 2, 1] - rr[:, 1, 2]) / s, (rr[:, 0, 2] - rr[:, 2, 0]) / s,
                             (rr[:, 1, 0] - rr[:, 0, 1]) / s], -1)
        elif case == 1:
            s = 2.0 * np.sqrt(np.maximum(1.0 + rr[:, 0, 0] - rr[:, 1, 1] - rr[:, 2, 2], 1e-300))
            q[i] = np.stack([(rr[:, 2, 1] - rr[:, 1, 2]) / s, 0.25 * s, (rr[:, 0, 1] + rr[:, 1, 0]) / s,
                             (rr[:, 0, 2] + rr[:, 2, 0]) / s], -1)
        elif case == 2:
            s = 2.0 * np.sqrt(np.maximum(1.0 + rr[:, 1, 1] - rr[:, 0, 0] - rr[:, 2, 2], 1e-300))
            q[i] = np.stack([(rr[:, 0, 2] - rr[:, 2, 0]) / s, (rr[:, 0, 1] + rr[:, 1, 0]) / s, 0.25 * s,
                             (rr[:, 1, 2] + rr[:, 2, 1]) / s], -1)
        else:
            s = 2.0 * np.sqrt(np.maximum(1.0 + rr[:, 2, 2] - rr[:, 0, 0] - rr[:, 1, 1], 1e-300))
            q[i] = np.stack([(rr[:, 1, 0] - rr[:, 0, 1]) / s, (rr[:, 0, 2] + rr[:, 2, 0]) / s,
                             (rr[:, 1, 2] + rr[:, 2, 1]) / s, 0.25 * s], -1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def sample_contact_points(rng: np.random.Generator, n: int, face, bands) -> np.ndarray:
    """(n, 2) contact points (d_y, d_z) inside the elliptic face, drawn by distance band.

    Band 0: 0-5 cm, band 1: 5-8 cm, band 2: beyond 8 cm (up to the outline), with probabilities
    ``bands``; uniform over the area of each band's part of the face.
    """
    a, b = face
    p = np.asarray(bands, np.float64) / np.sum(bands)
    which = rng.choice(3, size=n, p=p)
    out = np.zeros((n, 2))
    edges = ((0.0, 0.05), (0.05, 0.08), (0.08, max(a, b)))
    for i in range(n):
        lo, hi = edges[which[i]]
        for _ in range(200):
            r = math.sqrt(rng.uniform(lo * lo, hi * hi))
            th = rng.uniform(0.0, 2.0 * math.pi)
            dy, dz = r * math.cos(th), r * math.sin(th)
            if (dy / a) ** 2 + (dz / b) ** 2 <= 0.97:
                break
        else:  # the band does not fit this face: fall back to the centre band
            r = math.sqrt(rng.uniform(0.0, 0.05**2))
            dy, dz = r * math.cos(th), r * math.sin(th)
        out[i] = dy, dz
    return out


def _choose_shot(rng, weights: dict, dist: float, z: float) -> str:
    """A return shot type plausible for a ball met ``dist`` behind the net at height ``z``."""
    ok = {
        "topspin_drive": 1.2 <= dist <= 3.0,
        "backspin_drive": dist >= 1.7,
        "push": dist <= 1.8 and z <= 0.4,
        "block": dist <= 2.0,
        "smash": z >= 0.3 and dist <= 2.4,
        "lob": dist >= 2.3,
    }
    names = [k for k, v in ok.items() if v and weights.get(k, 0) > 0]
    if not names:
        return "topspin_drive" if weights.get("topspin_drive", 0) > 0 else max(weights, key=weights.get)
    w = np.asarray([weights[k] for k in names], np.float64)
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def _clear_net(start, target, speed, top, min_speed=2.0, clearance=0.05, net=0.1525 + 0.02):
    """Lowers horizontal speeds until the closed-form arc clears the net by ``clearance``."""
    speed = speed.copy()
    for _ in range(12):
        d = target - start
        dist = np.hypot(d[:, 0], d[:, 1])
        t = dist / (DRAG_AIM * speed)
        g_eff = np.maximum(9.81 + MAGNUS_AIM * top * speed, 2.0)
        vz = d[:, 2] / t + 0.5 * g_eff * t
        frac = np.clip(-start[:, 0] / np.where(np.abs(d[:, 0]) > 1e-9, d[:, 0], 1e-9), 0.0, 1.0)
        tn = frac * t
        zn = start[:, 2] + vz * tn - 0.5 * g_eff * tn**2
        low = (zn < net + clearance) & (speed > min_speed)
        if not low.any():
            break
        speed = np.where(low, np.maximum(speed * 0.9, min_speed), speed)
    return speed


# ============================================================================ host: bookkeeping
@dataclasses.dataclass
class _Session:
    sid: int
    rng: np.random.Generator
    n_rallies: int
    first_server: int
    models_index: int
    rally: int = -1
    obs: list = dataclasses.field(default_factory=list)       # arrays (n, 10): step, pos, vel, spin
    events: list = dataclasses.field(default_factory=list)    # dicts
    done: bool = False


@dataclasses.dataclass
class _Lane:
    session: _Session | None = None
    step: int = 0
    pos: Any = None
    vel: Any = None
    spin: Any = None
    mode: str = "idle"          # toss | flight | await | ending | idle
    hitter: int = ROBOT
    serve: bool = False
    bounces: int = 0
    hit_step: int = -1          # toss: the serve's step
    await_step: int = 0         # await: first (global) step eligible for the hit
    bounce_step: int = 0        # await: step of the bounce on the receiver's half
    plane: float = 0.0          # await: |x| where the receiver meets the ball
    flight_start: int = 0
    shots: int = 0
    planned: int = 1


def _row(pos, vel, spin):
    return np.concatenate([np.asarray(pos, np.float64), np.asarray(vel, np.float64), np.asarray(spin, np.float64)])


class _Game:
    """Runs all games: lanes, chunks, hits, rally bookkeeping. Internal to :func:`generate`."""

    def __init__(self, cfg: GeneratorConfig, progress: bool):
        self.cfg = cfg
        self.dtype = _dtype(cfg)
        self.np_dtype = np.float64 if cfg.dtype == "float64" else np.float32
        self.plain = load_model(cfg.model, dtype=self.dtype)
        self.face = np.asarray(cfg.face, np.float64)
        self._draw_effects()
        self.sessions = []
        for sid in range(cfg.games):
            rng = np.random.default_rng([cfg.seed, 1, sid])
            n_r = int(rng.integers(cfg.rallies_per_game[0], cfg.rallies_per_game[1] + 1))
            self.sessions.append(_Session(sid=sid, rng=rng, n_rallies=n_r, first_server=int(rng.integers(0, 2)),
                                          models_index=sid))
        self.total_rallies = sum(s.n_rallies for s in self.sessions)
        self.progress = progress
        self.steps_simulated = 0
        self.chunks = 0

    # ------------------------------------------------------------------ effects
    def _draw_effects(self):
        cfg = self.cfg
        self.dataset_effects: dict[str, fx.Effect] = {}
        self.session_effects: list[dict[str, fx.Effect]] = [dict() for _ in range(cfg.games)]
        for name in cfg.effects:
            cls = fx.effect_class(name)
            fixed = cfg.effect_params.get(name, {})
            # one stream per effect (and game): switching one effect on or off leaves the others' draws
            index = list(fx.CATALOGUE).index(name)
            if cls.SCOPE == "dataset":
                rng = np.random.default_rng([cfg.seed, 0, index])
                self.dataset_effects[name] = cls.from_dict(fixed, base=cls.sample(rng, self.dtype), dtype=self.dtype)
            else:
                for sid in range(cfg.games):
                    rng = np.random.default_rng([cfg.seed, 2, sid, index])
                    self.session_effects[sid][name] = cls.from_dict(fixed, base=cls.sample(rng, self.dtype), dtype=self.dtype)
        models = []
        for sid in range(cfg.games):
            effs = tuple(self.effect(sid, n) for n in cfg.effects if fx.effect_class(n).WHERE == "simulator")
            models.append(self.plain.replace(effects=effs))
        self.truth_models = stack_models(models)
        self.any_racket_effect = any(callable(getattr(fx.effect_class(n), "racket_coefficients", None)) for n in cfg.effects)
        self.record = {n: None for n in cfg.effects if fx.effect_class(n).WHERE == "record"}

    def effect(self, sid: int, name: str):
        """The effect ``name`` as it acts in game ``sid``."""
        if name in self.dataset_effects:
            return self.dataset_effects[name]
        return self.session_effects[sid][name]

    # ------------------------------------------------------------------ rallies
    def _start_rally(self, lane: _Lane, start_step: int):
        s = lane.session
        s.rally += 1
        rng = s.rng
        server = s.first_server ^ ((s.rally // 2) % 2)
        side = self._end(server)
        every = self.cfg.obs_every
        if start_step % every == 0:
            start_step += 1
        pos = np.array([side * rng.uniform(1.42, 1.62), rng.uniform(-0.6, 0.6), rng.uniform(0.0, 0.12)])
        vz = rng.uniform(2.2, 3.2)
        vel = np.array([rng.normal(0.0, 0.05), rng.normal(0.0, 0.05), vz])
        spin = rng.normal(0.0, 3.0, 3)
        apex = pos[2] + vz * vz / (2 * 9.81)
        z_hit = min(rng.uniform(0.12, 0.3), apex - 0.05)  # struck on the way down
        t_hit = (vz + math.sqrt(vz * vz + 2 * 9.81 * (pos[2] - z_hit))) / 9.81
        hit = start_step + max(int(round(t_hit / self.cfg.dt)), 20)
        if hit % every == 0:
            hit += 1
        lane.step, lane.mode, lane.hitter, lane.serve, lane.bounces = start_step, "toss", server, True, 0
        lane.pos, lane.vel, lane.spin = (pos.astype(self.np_dtype), vel.astype(self.np_dtype), spin.astype(self.np_dtype))
        lane.hit_step, lane.flight_start, lane.shots = hit, start_step, 0
        mean = self.cfg.rally_hits_mean
        lane.planned = int(min(rng.geometric(1.0 / mean), self.cfg.max_rally_hits))
        self._event(s, start_step * self.cfg.dt, "other", "toss", pos, _row(pos, vel, spin), _row(pos, vel, spin), "")

    def _end(self, player: int) -> int:
        """+1 / -1: the end of the table a player stands at."""
        return self.cfg.robot_end if player == ROBOT else -self.cfg.robot_end

    def _event(self, s: _Session, t, kind, true_kind, pos, pre, post, player, shot="", racket=None, aim_=None):
        s.events.append(dict(t=float(t), kind=kind, true_kind=true_kind, pos=np.asarray(pos, np.float64), pre=pre, post=post,
                             player=player, shot=shot, rally=s.rally, racket=racket, aim=aim_))

    def _finish_rally(self, lane: _Lane, end_step: int):
        s = lane.session
        if s.rally + 1 < s.n_rallies:
            gap = s.rng.uniform(*self.cfg.rally_gap)
            self._start_rally(lane, end_step + int(round(gap / self.cfg.dt)))
        else:
            s.done = True
            lane.session, lane.mode = None, "idle"
        self.bar.update(1)

    def _assign(self, lanes, queue):
        for lane in lanes:
            if lane.session is None and queue:
                lane.session = queue.pop(0)
                self._start_rally(lane, int(lane.session.rng.integers(1, 1000)))

    # ------------------------------------------------------------------ main loop
    def run(self):
        from tqdm.auto import tqdm

        cfg = self.cfg
        n_lanes = min(cfg.lanes, cfg.games)
        lanes = [_Lane() for _ in range(n_lanes)]
        queue = list(self.sessions)
        if self.progress:  # the bar stays at 0 while the first chunk compiles
            print("generating (the first chunk compiles the game's kernels: up to a minute the first time) ...",
                  flush=True)
        self.bar = tqdm(total=self.total_rallies, desc="generating", unit="rally", disable=not self.progress)
        self._assign(lanes, queue)
        C = cfg.chunk_steps
        dt = cfg.dt
        while any(lane.session is not None for lane in lanes):
            idx = np.array([ln.session.models_index if ln.session else 0 for ln in lanes])
            origin = np.array([ln.step * dt if ln.session else 0.0 for ln in lanes])
            models = _lane_models(self.truth_models, jnp.asarray(idx), jnp.asarray(origin, self.dtype))
            ball = Ball(*(jnp.asarray(np.stack([getattr(ln, f) if ln.session else np.array([0, 0, 1.0]) for ln in lanes])
                                      .astype(self.np_dtype)) for f in ("pos", "vel", "spin")))
            res = simulate(models, ball, C, dt, record_every=1, max_events=6, model_batched=True)
            self.steps_simulated += C * sum(ln.session is not None for ln in lanes)
            self.chunks += 1
            traj = np.concatenate([np.asarray(res.trajectory.pos), np.asarray(res.trajectory.vel),
                                   np.asarray(res.trajectory.spin)], axis=-1)  # (B, C, 9)
            log = jax.tree.map(np.asarray, res.events)
            hits = []
            for b, lane in enumerate(lanes):
                if lane.session is not None:
                    h = self._advance(lane, traj[b], jax.tree.map(lambda a: a[b], log))
                    if h is not None:
                        hits.append((lane, *h))
            if hits:
                self._hit(hits)
            self._assign(lanes, queue)
        self.bar.close()

    def _advance(self, lane: _Lane, traj, log):
        """Reads one lane's chunk; returns (k, incoming state) when a racket contact is due."""
        cfg = self.cfg
        dt, C, s0 = cfg.dt, cfg.chunk_steps, lane.step
        s = lane.session
        n_ev = int(min(log.count, log.kind.shape[0]))
        cut = None  # ("hit", k) or ("end", t_end)
        k_from = 0
        for i in range(n_ev + 1):
            if i < n_ev:
                t_loc = float(log.time[i])
                k_e = max(int(math.ceil(t_loc / dt - 1e-6)) - 1, 0)
            else:
                t_loc, k_e = None, C
            k_hit = self._trigger(lane, traj, k_from, k_e)
            if k_hit is not None:
                cut = ("hit", k_hit)
                break
            if i == n_ev:
                break
            kind = int(log.kind[i])
            pre = _row(log.pre.pos[i], log.pre.vel[i], log.pre.spin[i])
            post = _row(log.post.pos[i], log.post.vel[i], log.post.spin[i])
            t_abs = s0 * dt + t_loc
            if kind == ev.TABLE:
                self._event(s, t_abs, "table", "table", pre[:3], pre, post, "")
                self._on_bounce(lane, float(pre[0]), s0 + k_e + 1)
                k_from = k_e + 1
            elif kind == ev.NET:
                self._event(s, t_abs, "net", "net", pre[:3], pre, post, "")
                cut = ("end", t_abs)
                break
            elif kind in (ev.FLOOR, ev.OUT, ev.INVALID):
                self._event(s, t_abs, "out", "floor" if kind == ev.FLOOR else "lost", pre[:3], pre, post, "")
                cut = ("end", t_abs)
                break
            else:  # pragma: no cover - no rackets in these simulations
                k_from = k_e + 1
        if cut is None and (s0 + C - lane.flight_start) * dt > cfg.max_flight_time and lane.mode != "toss":
            # followed long enough without a contact: the ball is lost to the tracker, half a step on
            x = traj[C - 1].astype(np.float64)
            t_abs = (s0 + C + 0.5) * dt
            self._event(s, t_abs, "out", "lost", x[:3], x, x, "")
            cut = ("end", t_abs)
        # observations up to the cut
        if cut is None:
            k_last = C - 1
        elif cut[0] == "hit":
            k_last = cut[1]
        else:
            k_last = int(math.ceil(cut[1] / dt - s0 - 1e-9)) - 2
        steps = s0 + 1 + np.arange(k_last + 1)
        keep = steps % cfg.obs_every == 0
        if cut is not None and cut[0] == "end":
            keep &= steps * dt < cut[1]
        if keep.any():
            s.obs.append(np.concatenate([steps[keep, None].astype(np.float64), traj[: k_last + 1][keep].astype(np.float64)], 1))
        if cut is None:
            lane.step = s0 + C
            lane.pos, lane.vel, lane.spin = traj[-1, :3], traj[-1, 3:6], traj[-1, 6:9]
            return None
        if cut[0] == "end":
            self._finish_rally(lane, int(math.ceil(cut[1] / dt)))
            return None
        k = cut[1]
        lane.step = s0 + k + 1
        return k, traj[k]

    def _on_bounce(self, lane: _Lane, x: float, step: int):
        """Rules after a table bounce at ``x`` (the state at global ``step`` is just after it)."""
        receiver = 1 - lane.hitter
        side = 1 if x >= 0 else -1
        if lane.mode == "flight":
            want = self._end(lane.hitter) if (lane.serve and lane.bounces == 0) else self._end(receiver)
            if side != want:
                lane.mode = "ending"
            elif lane.serve and lane.bounces == 0:
                lane.bounces = 1
            elif lane.shots >= lane.planned:
                lane.mode = "ending"
            else:
                lane.mode = "await"
                lane.await_step = step + 1
                lane.bounce_step = step
                lane.plane = lane.session.rng.uniform(*self.cfg.hit_distance)
        elif lane.mode == "await":
            lane.mode = "ending"  # bounced twice: the receiver missed it

    def _trigger(self, lane: _Lane, traj, k_from: int, k_to: int):
        """First step in [k_from, k_to) where the hitter meets the ball, or None."""
        if k_to <= k_from:
            return None
        if lane.mode == "toss":
            k = lane.hit_step - lane.step - 1
            return k if k_from <= k < k_to else None
        if lane.mode != "await":
            return None
        k0 = max(k_from, lane.await_step - lane.step - 1)
        seg = traj[k0:k_to]
        if len(seg) == 0:
            return None
        ax, z, vz = np.abs(seg[:, 0]), seg[:, 2], seg[:, 5]
        over = ax <= 1.37
        low = (vz < 0) & (z < np.where(over, 0.08, -0.25))
        waited = (lane.step + k0 + 1 + np.arange(len(seg)) - lane.bounce_step) * self.cfg.dt > 1.0
        fire = (ax >= lane.plane) | low | waited
        if not fire.any():
            return None
        k = k0 + int(np.argmax(fire))
        if (lane.step + k + 1) % self.cfg.obs_every == 0:  # keep contacts between frames
            k = k + 1 if k + 1 < k_to else k - 1 if k - 1 >= k0 else k
        return k

    # ------------------------------------------------------------------ racket contacts
    def _achievable_spin(self, v_in, w_in, v_out, w_want):
        """The spin a racket can give along with v_out: the point contact changes only the
        tangential spin, by at most (kappa / r) |Dv| (see :func:`invert_contact`), and damps the
        normal spin by e_s; the face normal is taken along Dv here (close enough to aim)."""
        p = self.plain.racket
        k = float(self.plain.ball.radius) / float(p.kappa)
        dv = v_out - v_in
        n = dv / np.maximum(np.linalg.norm(dv, axis=-1, keepdims=True), 1e-9)
        dw = w_want - w_in
        dw_t = dw - np.sum(dw * n, -1, keepdims=True) * n
        cap = np.minimum(1.0, 0.8 * np.linalg.norm(dv, axis=-1) / np.maximum(k * np.linalg.norm(dw_t, axis=-1), 1e-9))
        e_s = float(p.e_s) if p.kind == "updated" else 1.0
        return w_in + cap[:, None] * dw_t + (e_s - 1.0) * np.sum(w_in * n, -1, keepdims=True) * n

    def _aim(self, start, target, speed, top, side_spin, vz, first_x, serve, v_in, w_in):
        """Aimed outgoing velocities and spins of n shots (numpy in, numpy out).

        A shot whose aimed path would touch the net is aimed again, up to twice: slower (regular
        shots) or with both bounces farther from the net (serves), as a player clears the net.
        """
        n = len(start)
        speed, first_x, target = speed.copy(), first_x.copy(), target.copy()
        regular = ~serve
        speed[regular] = _clear_net(start[regular], target[regular], speed[regular], top[regular])
        v_out, spin_out = np.zeros((n, 3)), np.zeros((n, 3))
        todo = np.arange(n)
        for attempt in range(3):
            v0 = aim(start[todo], target[todo], speed[todo], top[todo])
            vz0 = np.where(serve[todo], vz[todo], v0[:, 2])
            heading = v0[:, :2] / np.linalg.norm(v0[:, :2], axis=-1, keepdims=True)
            across = np.stack([-heading[:, 1], heading[:, 0], np.zeros(len(todo))], -1)
            want = top[todo, None] * across + side_spin[todo, None] * np.array([0.0, 0.0, 1.0])
            spin_out[todo] = self._achievable_spin(v_in[todo], w_in[todo], v0, want)
            pad = _pad(dict(pos=start[todo], spin=spin_out[todo], speed=speed[todo], vz=vz0, target=target[todo, :2],
                            first_x=first_x[todo], serve=serve[todo]), _bucket(len(todo)))
            j = lambda a: jnp.asarray(np.asarray(a).astype(self.np_dtype))  # noqa: E731
            v, _miss, net = aim_batch(self.plain, j(pad["pos"]), j(pad["spin"]), j(pad["speed"]), j(pad["vz"]), j(pad["target"]),
                                       j(pad["first_x"]), jnp.asarray(pad["serve"]), jnp.asarray(AIM_STEP, self.dtype),
                                       int(round(AIM_HORIZON / AIM_STEP)), jnp.asarray(self.cfg.aim_iters))
            v_out[todo] = np.asarray(v)[: len(todo)]
            low = np.asarray(net)[: len(todo)] < NET_TOP + 0.02
            if attempt == 2 or not low.any():
                break
            todo = todo[low]
            speed[todo] = np.where(serve[todo], speed[todo], np.maximum(0.85 * speed[todo], 2.0))
            back = np.sign(first_x[todo])
            first_x[todo] = np.where(serve[todo], back * np.minimum(np.abs(first_x[todo]) + 0.15, 1.3), first_x[todo])
            tx = target[todo, 0]
            target[todo, 0] = np.where(serve[todo], np.sign(tx) * np.minimum(np.abs(tx) + 0.15, 1.25), tx)
        return v_out, spin_out

    def _hit(self, hits):
        """Racket contacts of all lanes due in this chunk: choose, aim, invert, apply the truth."""
        cfg = self.cfg
        n = len(hits)
        start, target = np.zeros((n, 3)), np.zeros((n, 3))
        speed, top, side_spin, vz, first_x = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        serve = np.zeros(n, bool)
        d, roll, ang = np.zeros((n, 2)), np.zeros(n), np.zeros((n, 3))
        shot = []
        for i, (lane, k, x) in enumerate(hits):
            rng = lane.session.rng
            hitter = lane.hitter if lane.mode == "toss" else 1 - lane.hitter
            end = self._end(hitter)
            name = "serve" if lane.mode == "toss" else _choose_shot(rng, cfg.shot_weights, abs(float(x[0])), float(x[2]))
            st = SHOT_TYPES[name]
            u = lambda r: rng.uniform(r[0], r[1])  # noqa: E731
            start[i] = x[:3]
            target[i] = [-end * u(st.target_x), u(st.target_y), 0.02]
            speed[i], top[i], side_spin[i] = u(st.speed), u(st.topspin), u(st.sidespin)
            serve[i] = name == "serve"
            vz[i] = u((-1.0, 0.5))
            first_x[i] = end * u((0.7, 1.15))  # a serve's first bounce, on the server's half
            d[i] = sample_contact_points(rng, 1, cfg.face, cfg.contact_bands)[0]
            roll[i] = rng.uniform(-1.75, 1.75)
            ang[i] = rng.normal(0.0, 4.0, 3)
            shot.append(name)
            lane.hitter = hitter
        w_in = np.stack([h[2][6:9] for h in hits]).astype(np.float64)
        v_in = np.stack([h[2][3:6] for h in hits]).astype(np.float64)
        v_out, spin_out = self._aim(start, target, speed, top, side_spin, vz, first_x, serve, v_in, w_in)
        size = _bucket(n)
        pad = _pad(dict(pos=start, spin=spin_out, v_out=v_out, d=d, roll=roll, ang=ang, v_in=v_in, w_in=w_in,
                        sid=np.array([h[0].session.models_index for h in hits])), size)
        j = lambda a: jnp.asarray(np.asarray(a).astype(self.np_dtype))  # noqa: E731
        rk = _invert_batch(self.plain.racket, self.plain.ball.radius, self.plain.ball.mass, j(pad["pos"]), j(pad["v_in"]),
                           j(pad["w_in"]), j(pad["v_out"]), j(pad["spin"]), j(pad["d"]), j(pad["roll"]), j(pad["ang"]))
        models = _lane_models(self.truth_models, jnp.asarray(pad["sid"]), jnp.zeros(size, self.dtype))
        rvel, v_new, w_new, d_true = _true_contact_batch(
            models, rk["pos"], rk["rot"], rk["vel"], rk["ang_vel"], jnp.asarray(self.face, self.dtype), j(pad["pos"]),
            j(pad["v_in"]), j(pad["w_in"]), j(pad["v_out"]), jnp.asarray(2 if self.any_racket_effect else 0))
        rk["vel"] = rvel
        rk = {k: np.asarray(v)[:n].astype(np.float64) for k, v in rk.items()}
        v_new, w_new, d_true = np.asarray(v_new)[:n], np.asarray(w_new)[:n], np.asarray(d_true)[:n].astype(np.float64)
        v_aim = v_out
        for i, (lane, k, x) in enumerate(hits):
            s = lane.session
            t = lane.step * cfg.dt
            pre = _row(x[:3], x[3:6], x[6:9])
            post = _row(x[:3], v_new[i], w_new[i])
            player = PLAYERS[lane.hitter]
            racket = dict(pos=rk["pos"][i], rot=rk["rot"][i], vel=rk["vel"][i], ang_vel=rk["ang_vel"][i], d=d_true[i])
            self._event(s, t, "racket" if lane.hitter == ROBOT else "other", "serve" if shot[i] == "serve" else "hit",
                        x[:3], pre, post, player, shot[i], racket, np.concatenate([v_aim[i], spin_out[i]]))
            lane.pos, lane.vel, lane.spin = x[:3].astype(self.np_dtype), v_new[i].astype(self.np_dtype), w_new[i].astype(self.np_dtype)
            lane.mode, lane.serve, lane.bounces = "flight", shot[i] == "serve", 0
            lane.flight_start = lane.step
            lane.shots += 1


# ============================================================================ assembly
_STATE = ("x", "y", "z", "vx", "vy", "vz", "spin_x", "spin_y", "spin_z")


@dataclasses.dataclass
class Generated:
    """What :func:`generate` returns.

    Attributes:
        dataset: the measured-format :class:`~ttsim_jax.data.Dataset` (validated).
        truth: JSON-able dict (written as ``truth.json``): configuration, effects, counts.
        truth_events, truth_rackets: column tables (dicts of numpy arrays), see the module docstring.
        truth_observations: column table aligned row by row with ``dataset.observations``, or None.
        wall_time_s: how long :func:`generate` took (not written: the files depend only on the seed
            and the configuration).
    """

    dataset: Dataset
    truth: dict
    truth_events: dict
    truth_rackets: dict
    truth_observations: dict | None
    wall_time_s: float = 0.0
    _game: "_Game | None" = dataclasses.field(default=None, repr=False, compare=False)


def _record(game: _Game, name: str, sid: int):
    if name not in game.record:
        return None
    return game.effect(sid, name)


def _assemble(game: _Game, wall: float) -> Generated:
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
        notes="Synthetic data from ttsim_jax.data.generator. Sessions are games; 'racket' events are the robot's contacts "
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
    seg.update(spin_x=spin_m[:, 0], spin_y=spin_m[:, 1], spin_z=spin_m[:, 2], spin_conf=conf)
    o = dict(ds.observations)
    o.update(spin_x=spin_m[seg_id, 0], spin_y=spin_m[seg_id, 1], spin_z=spin_m[seg_id, 2], spin_conf=conf[seg_id])
    ds = ds.replace(observations=o, segments=seg)
    from .validate import validate

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
        "generator": f"ttsim_jax.data.generator v{GENERATOR_VERSION}", "seed": cfg.seed, "model": cfg.model,
        "config": cfg.to_dict(), "face_semi_axes_m": list(cfg.face), "robot_end": cfg.robot_end,
        "dt": dt, "observation_rate_hz": 1.0 / (dt * cfg.obs_every), "effects": eff_info,
        "sessions": [{"session_id": s.sid, "rallies": s.n_rallies, "first_server": PLAYERS[s.first_server],
                      "effects": {n: e.to_dict() for n, e in game.session_effects[s.sid].items()}} for s in game.sessions],
        "counts": counts,
    }
    return Generated(dataset=ds, truth=truth, truth_events=tev, truth_rackets=trk, truth_observations=tobs, wall_time_s=wall,
                     _game=game)


def generate(config: GeneratorConfig | None = None, *, progress: bool = True, **overrides) -> Generated:
    """Generates a synthetic dataset with its ground truth.

    Arguments:
        config: a :class:`GeneratorConfig` (default: the defaults); ``overrides`` change fields.
        progress: show a progress bar (rallies done).

    Returns:
        A :class:`Generated` (dataset, truth dict and truth tables). Write it with :func:`write`.
    """
    cfg = _check_config((config or GeneratorConfig()).replace(**{k: v for k, v in overrides.items() if v is not None}))
    require_memory(f"generating {cfg.games} games of {cfg.rallies_per_game[0]}-{cfg.rallies_per_game[1]} rallies",
                   memory_bytes(cfg), remedy="generate fewer games per run (several runs with different seeds)")
    t0 = time.perf_counter()
    game = _Game(cfg, progress)
    game.run()
    return _assemble(game, time.perf_counter() - t0)


def rerecord(gen: Generated, effects) -> Generated:
    """The same simulated games recorded again under other record effects, without simulating again.

    Record effects (sensor noise, missing frames, racket-state and spin-estimate errors) act only on
    what is written, so the result equals :func:`generate` with ``gen``'s configuration and these
    effects, at the cost of the writing alone: the way to study one physical truth under several
    sensors.

    Arguments:
        gen: what :func:`generate` returned in this process.
        effects: effect names (a list or a comma-separated string, ``"all"`` allowed); their
            simulator effects must be ``gen``'s.

    Returns:
        A new :class:`Generated`; ``gen`` is unchanged.
    """
    if gen._game is None:
        raise GeneratorError("rerecord: this Generated holds no simulated games (it was not made by generate "
                             "in this process)")
    old = gen._game.cfg
    cfg = _check_config(old.replace(effects=effects), "rerecord")
    physical = lambda c: [n for n in c.effects if fx.effect_class(n).WHERE == "simulator"]  # noqa: E731
    if physical(cfg) != physical(old):
        raise GeneratorError(f"rerecord: effects {list(cfg.effects)} change the simulator effects "
                             f"{physical(old)} -> {physical(cfg)}; only record effects may change")
    t0 = time.perf_counter()
    game = copy.copy(gen._game)
    game.cfg = cfg
    game._draw_effects()
    return _assemble(game, gen.wall_time_s + time.perf_counter() - t0)


def _truth_parquet(table: dict, path: Path, dataset_id: str):
    import pyarrow as pa

    from .io import write_parquet

    arrays, fields = [], []
    for k, v in table.items():
        v = np.asarray(v)
        if v.dtype == object:
            arrays.append(pa.array([str(x) for x in v], pa.string()))
        else:
            arrays.append(pa.array(v))
        fields.append(k)
    write_parquet(pa.Table.from_arrays(arrays, names=fields), path, dataset_id)


def write(gen: Generated, out: str | Path, *, overwrite: bool = False) -> Path:
    """Writes the dataset directory ``out`` and the truth files beside its tables, atomically
    (all files appear together, carrying one dataset id; see :func:`ttsim_jax.data.io.save`).

    Arguments:
        gen: from :func:`generate`.
        out: dataset directory.
        overwrite: replace an existing dataset there.

    Returns:
        The directory.
    """
    from .io import ID_KEY, save

    def truth_files(directory: Path, dataset_id: str):
        info = dict(gen.truth, **{ID_KEY: dataset_id})
        (directory / "truth.json").write_text(json.dumps(info, indent=1, sort_keys=False) + "\n")
        _truth_parquet(gen.truth_events, directory / "truth_events.parquet", dataset_id)
        _truth_parquet(gen.truth_rackets, directory / "truth_rackets.parquet", dataset_id)
        if gen.truth_observations is not None:
            _truth_parquet(gen.truth_observations, directory / "truth_observations.parquet", dataset_id)

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
    not, or a corrupted one)."""
    from .io import ID_KEY, dataset_id, read_parquet, read_truth_json

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

    return Truth(info=info, events=table("truth_events.parquet"),
                 rackets=table("truth_rackets.parquet"), observations=table("truth_observations.parquet"))
