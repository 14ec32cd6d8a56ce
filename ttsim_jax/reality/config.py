"""What the reality generator makes: :class:`GeneratorConfig`, its presets, its TOML file and checks.

:func:`make_config` builds a checked configuration from the defaults, a preset (:data:`PRESETS`), a
TOML file (:func:`config_from_toml`) and keyword overrides; every bad value raises
:class:`GeneratorError` naming the file, the key and the value. :func:`memory_bytes` estimates
what :func:`ttsim_jax.reality.generate` will hold for a configuration.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

from ttsim_jax import effects as fx
from ttsim_jax.errors import UserError
from ttsim_jax.files.toml import read_toml
from ttsim_jax.shots import SHOT_TYPES


class GeneratorError(UserError, ValueError):
    """A bad generator configuration; the message names the file, the key and the value."""


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
    effects: tuple = tuple(fx.parse_names("all"))
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


def check_config(cfg: GeneratorConfig, where: str = "generator config") -> GeneratorConfig:
    """Checks every field of a configuration and normalises its effect names.

    Arguments:
        cfg: the configuration (its ``effects`` are replaced by the parsed names).
        where: what the messages name (a file, or the caller).

    Returns:
        ``cfg``, checked.

    Raises:
        GeneratorError: naming ``where``, the key and the value of the first bad field.
    """

    def bad(key, why):
        raise GeneratorError(f"{where}: key '{key}' = {getattr(cfg, key)!r}: {why}")

    if not isinstance(cfg.games, int) or cfg.games < 1:
        bad("games", "must be a positive integer")
    if not isinstance(cfg.seed, int) or cfg.seed < 0:
        bad("seed", "must be a non-negative integer")
    def pair(key, least, integer=False):
        """A (low, high) range: two numbers, ``least`` <= low <= high."""
        v = getattr(cfg, key)
        kind = int if integer else (int, float)
        if not (isinstance(v, (tuple, list)) and len(v) == 2 and all(isinstance(x, kind) and not isinstance(x, bool)
                                                                      and math.isfinite(x) for x in v)):
            bad(key, f"must be [low, high]: two {'integers' if integer else 'numbers'}")
        if not least <= v[0] <= v[1]:
            bad(key, f"must be [low, high] with {least:g} <= low <= high")

    pair("rallies_per_game", 1, integer=True)
    pair("rally_gap", 0.0)
    pair("hit_distance", 0.1)
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
    if not (isinstance(cfg.face, (tuple, list)) and len(cfg.face) == 2 and 0.05 < cfg.face[0] < 0.2
            and 0.05 < cfg.face[1] < 0.2):
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
    return check_config(cfg)


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
    data = read_toml(path, "generator config file", GeneratorError)
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
    return check_config(cfg, where=str(path))
