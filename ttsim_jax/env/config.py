"""The ReturnBall task's settings (``configs/tasks/*.toml``), read and checked at load time.

A bad file is refused with a :class:`~ttsim_jax.params.ConfigError` naming the file, the key and
the value, before anything is compiled.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from ttsim_jax.files.toml import read_toml
from ttsim_jax.params import ConfigError, config_dir


@dataclass(frozen=True)
class ShotsConfig:
    types: tuple = ("serve", "topspin_drive", "backspin_drive", "push", "block")
    max_speed: float = 20.0
    max_spin: float = 600.0
    bank: int = 4096
    seed: int = 0
    aim: bool = True
    source: str = "sampled"
    measured: str = ""
    split: str = "train"


# Where ``[shots]`` come from: sampled (:mod:`ttsim_jax.shots`) or measured post-hit states
# (:mod:`ttsim_jax.data.post_hit_states`), whose shot types and splits these are.
SHOT_SOURCES = ("sampled", "measured")
MEASURED_TYPES = ("serve", "rally")
SPLITS = ("train", "test", "all")


# The action modes of ``[control] action`` (see :mod:`ttsim_jax.env.intercept`).
ACTION_MODES = ("accel", "intercept")
# How the intercept tracker predicts a bounce (``[intercept] bounce``).
BOUNCE_MODES = ("plain", "model")


@dataclass(frozen=True)
class ControlConfig:
    rate_hz: float = 100.0
    physics_dt: float = 1e-3
    max_time: float = 2.0
    action: str = "accel"


@dataclass(frozen=True)
class InterceptConfig:
    x_hit: float = 1.45
    flight_time: tuple = (0.3, 0.7)
    offset_y: float = 0.03
    offset_z: float = 0.03
    pitch: float = 0.3
    yaw: float = 0.3
    swing_time: float = 0.1
    omega: float = 40.0
    min_height: float = 0.3
    bounce: str = "plain"
    magnus: bool = False
    air: bool = False
    racket_known: bool = True  # plan with the task's racket_config; False: with the model's own racket


@dataclass(frozen=True)
class RacketConfig:
    workspace_lo: tuple = (1.4, -1.0, 0.0)
    workspace_hi: tuple = (3.0, 1.0, 1.2)
    start: tuple = (2.0, 0.0, 0.3)
    start_jitter: tuple = (0.1, 0.3, 0.1)
    max_speed: float = 8.0
    max_accel: float = 80.0
    angle_lo: tuple = (-1.0, -0.8)
    angle_hi: tuple = (1.0, 0.8)
    max_angle_rate: float = 15.0
    max_angle_accel: float = 600.0
    face: tuple = (0.0775, 0.0755)
    table_clearance: float = 0.0


@dataclass(frozen=True)
class ObservationConfig:
    """``[observation]``: what the policy sees.

    Attributes:
        spin: include the ball's spin; noise_pos, noise_vel: std of the Gaussian noise on the
            observed ball position [m] and velocity [m/s]; latency_steps: the ball is observed as it
            was this many control steps ago; plan: append the intercept tracker's prediction of the
            hit (:func:`~ttsim_jax.env.intercept.predict` of the observed ball: point, velocity,
            time to it, whether one exists), in either action mode; target: append the episode's
            target point (x, y) [m] (needed where ``[reward] target_spread`` draws one per episode).
    """

    spin: bool = True
    noise_pos: float = 0.0
    noise_vel: float = 0.0
    latency_steps: int = 0
    plan: bool = False
    target: bool = False


@dataclass(frozen=True)
class TaskResidualConfig:
    """``[residual]``: a racket residual network on the task model, and its noise as domain
    randomisation.

    Attributes:
        checkpoint: a ``.ttres`` file (``ttsim train residual``), relative to the task file; "" for
            none (the task model's own, usually none).
        sample: draw each racket contact's correction from the network's predicted standard
            deviations (a fresh draw per environment and contact), instead of its mean.
    """

    checkpoint: str = ""
    sample: bool = False


# The former name, kept for one release; the network's own configuration is
# ttsim_jax.physics.network.ResidualConfig.
ResidualConfig = TaskResidualConfig


@dataclass(frozen=True)
class RewardConfig:
    """``[reward]``: the weights of the reward's terms (see :mod:`ttsim_jax.env.return_ball`) and the
    return's target: ``target_point`` (x, y) [m], or with a nonzero ``target_spread`` (half-widths
    in x and y [m]) a point drawn uniformly in ``target_point +- target_spread`` at each reset (a
    goal-conditioned task; the policy observes it with ``[observation] target``)."""

    contact: float = 1.0
    legal: float = 2.0
    target: float = 1.0
    target_scale: float = 1.0
    target_point: tuple = (-0.9, 0.0)
    target_spread: tuple = (0.0, 0.0)
    net: float = -1.0
    out: float = -1.0
    miss: float = -1.0
    motion: float = 0.02
    approach: float = 0.5


@dataclass(frozen=True)
class TaskConfig:
    """Everything that defines a ReturnBall task (see ``configs/tasks/return_ball.toml``).

    Attributes:
        model: bundled model name or model .toml path.
        racket_config: the learning racket's configuration (blade, sponge, rubber): a bundled name
            (``ttsim_jax.params.available_rackets()``, e.g. "racket_05": long pips) or a racket file,
            whose fitted contact and residual network replace the model's; "" keeps the model's.
        shots, control, racket, observation, reward, intercept, residual: the sections of the file.
        randomisation: ((dotted model path, a, b, law), ...) per-environment draws: ``law`` "uniform"
            in [a, b], or "normal" of mean a and standard deviation b, truncated at 3 b.
        source: the file it was read from ("" for the defaults).
    """

    model: str = "conti2026"
    racket_config: str = ""
    shots: ShotsConfig = field(default_factory=ShotsConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    racket: RacketConfig = field(default_factory=RacketConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    intercept: InterceptConfig = field(default_factory=InterceptConfig)
    residual: TaskResidualConfig = field(default_factory=TaskResidualConfig)
    randomisation: tuple = ()
    source: str = ""

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return int(round(1.0 / (self.control.rate_hz * self.control.physics_dt)))

    @property
    def max_steps(self) -> int:
        """Control steps before an episode is truncated."""
        return int(math.ceil(self.control.max_time * self.control.rate_hz))


_SECTIONS = {"shots": ShotsConfig, "control": ControlConfig, "racket": RacketConfig,
             "observation": ObservationConfig, "reward": RewardConfig, "intercept": InterceptConfig,
             "residual": TaskResidualConfig}
# keys that must be positive
_POSITIVE = {"max_speed", "max_spin", "bank", "rate_hz", "physics_dt", "max_time", "max_accel", "max_angle_rate",
             "max_angle_accel", "target_scale",
             "x_hit", "swing_time", "omega", "flight_time"}
_NON_NEGATIVE = {"noise_pos", "noise_vel", "latency_steps", "motion", "approach", "offset_y", "offset_z", "pitch",
                 "yaw", "table_clearance", "target_spread"}


# Bundled tasks under their former names (the intercept mode became the default task).
RENAMED = {"return_ball_intercept": "return_ball", "return_ball_pro_intercept": "return_ball_pro"}


def default_task_path(name: str = "return_ball") -> Path:
    """The bundled task file ``configs/tasks/NAME.toml``."""
    return config_dir() / "tasks" / f"{name}.toml"


def convert_value(where: str, default, value):
    """``value`` checked against the type and length of ``default``."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} = {value!r}: expected true or false")
        return value
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{where} = {value!r}: expected a string")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} = {value!r}: expected an integer")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where} = {value!r}: expected a finite number")
        return float(value)
    if isinstance(default, tuple):
        if not isinstance(value, list) or (default and isinstance(default[0], str)) != (
                bool(value) and all(isinstance(v, str) for v in value)):
            raise ConfigError(f"{where} = {value!r}: expected a list like {list(default)!r}")
        if default and not isinstance(default[0], str):
            if len(value) != len(default):
                raise ConfigError(f"{where} = {value!r}: expected {len(default)} numbers")
            return tuple(convert_value(where, default[0], v) for v in value)
        return tuple(value)
    raise ConfigError(f"{where} = {value!r}: unexpected value")


# parameters whose fitted value and standard error `ttsim fit` writes to OUT.fit.json:
# model path -> (stage, value key, standard error key) inside summary[stage]["fit"]
FITTED = {"table.e0": ("table", "e0", "stderr_e0"), "table.e1": ("table", "e1", "stderr_e1"),
          **{f"racket.{k}": ("racket", f"values.{k}", f"stderr.{k}") for k in ("e0", "e1", "et0", "et1", "e_s")}}


def _beside(source: str, value: str) -> Path:
    """``value`` as a path: ``~`` expanded, a relative one taken from the folder of the task file
    ``source`` (the working directory for a task without a file)."""
    path = Path(value).expanduser()
    return path if path.is_absolute() else (Path(source).parent if source else Path.cwd()) / path


def _normal_law(where: str, key: str, value: dict, source: str) -> tuple[float, float]:
    """(mean, std) of a ``[randomisation]`` entry given as ``{mean = M, std = S}`` or as
    ``{fit = "OUT.fit.json", scale = K}`` (the fitted value and K times its standard error)."""
    import json

    if "fit" in value:
        bad = set(value) - {"fit", "scale"}
        if bad:
            raise ConfigError(f"{where}: unknown key(s) {sorted(bad)} beside fit; known: fit, scale")
        scale = convert_value(f"{where}.scale", 1.0, value.get("scale", 1.0))
        fit = convert_value(f"{where}.fit", "", value["fit"])
        if key not in FITTED:
            raise ConfigError(f"{where}: `ttsim fit` gives no standard error for {key!r}; fitted ones: {sorted(FITTED)}")
        path = _beside(source, fit)
        try:
            summary = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise ConfigError(f"{where}.fit = {fit!r}: cannot read a fit summary at {path} ({e})") from None
        stage, mean_key, std_key = FITTED[key]
        found = []
        for k in (mean_key, std_key):
            node = summary.get(stage, {}).get("fit", {}) if isinstance(summary, dict) else {}
            for part in k.split("."):
                node = node.get(part) if isinstance(node, dict) else None
            if not isinstance(node, (int, float)) or isinstance(node, bool) or not math.isfinite(node):
                raise ConfigError(f"{where}.fit = {fit!r}: {path} has no finite {stage}.fit.{k} (got {node!r}); "
                                  f"was the {stage} stage fitted?")
            found.append(float(node))
        mean, std = found[0], found[1] * scale
    else:
        bad = set(value) - {"mean", "std"}
        if bad or len(value) != 2:
            raise ConfigError(f"{where} = {value!r}: expected [low, high], {{mean = M, std = S}} or {{fit = FILE}}")
        mean, std = convert_value(f"{where}.mean", 0.0, value["mean"]), convert_value(f"{where}.std", 0.0, value["std"])
    if std < 0:
        raise ConfigError(f"{where}: std = {std!r} must not be negative")
    return mean, std


def load_task_config(path=None, overrides: dict | None = None) -> TaskConfig:
    """Reads and checks a task file.

    Arguments:
        path: a task .toml file, a bundled task name (``"return_ball"``, ``"return_ball_pro"``, their
            "accel" forms ``"return_ball_accel"``, ``"return_ball_pro_accel"``, the goal-conditioned
            ``"return_ball_goal"``), or
            None for ``return_ball``.
        overrides: ``{"section.key": value}`` applied on top of the file (``{"shots.bank": 64}``).

    Returns:
        A :class:`TaskConfig`; raises :class:`ConfigError` naming the file, key and value.
    """
    path = default_task_path() if path is None else Path(path)
    if path.suffix != ".toml" and not path.exists():
        name, path = str(path), default_task_path(str(path))
        if not path.is_file():
            bundled = sorted(p.stem for p in path.parent.glob("*.toml"))
            hint = f"; {name} is now {RENAMED[name]}" if name in RENAMED else ""
            raise ConfigError(f"{path}: no such task file (bundled tasks: {', '.join(bundled)}{hint})")
    if not path.is_file():
        raise ConfigError(f"{path}: no such task file")
    raw = read_toml(path, "task file", ConfigError)
    for key, value in (overrides or {}).items():
        section, _, name = key.partition(".")
        if name:
            raw.setdefault(section, {})[name] = value
        else:
            raw[section] = value
    return parse_task_config(raw, str(path))


def read_section(raw: dict, name: str, cls, source: str, positive=(), non_negative=()):
    """An instance of the dataclass ``cls`` from the TOML table ``raw[name]`` (missing keys keep their
    defaults), every value checked against its default's type; raises :class:`ConfigError` naming
    the file, the table, the key and the value."""
    section = raw.get(name, {})
    if not isinstance(section, dict):
        raise ConfigError(f"{source}: [{name}] must be a table")
    defaults = cls()
    known = {f.name for f in dataclasses.fields(cls)}
    bad = set(section) - known
    if bad:
        raise ConfigError(f"{source}: [{name}] unknown key(s) {sorted(bad)}; known: {sorted(known)}")
    values = {}
    for key, value in section.items():
        where = f"{source}: [{name}] {key}"
        v = convert_value(where, getattr(defaults, key), value)
        if key in positive and (v <= 0 if not isinstance(v, tuple) else any(x <= 0 for x in v)):
            raise ConfigError(f"{where} = {value!r}: must be positive")
        if key in non_negative and (v < 0 if not isinstance(v, tuple) else any(x < 0 for x in v)):
            raise ConfigError(f"{where} = {value!r}: must not be negative")
        values[key] = v
    return cls(**values)


def parse_task_config(raw: dict, source: str = "") -> TaskConfig:
    """A :class:`TaskConfig` from the parsed TOML ``raw`` (see :func:`load_task_config`)."""
    unknown = set(raw) - set(_SECTIONS) - {"model", "racket_config", "randomisation"}
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)}; known: model, racket_config, randomisation, "
                          f"{', '.join(_SECTIONS)}")
    out = {name: read_section(raw, name, cls, source, _POSITIVE, _NON_NEGATIVE) for name, cls in _SECTIONS.items()}
    racket = out["racket"]
    for lo, hi, what in (("workspace_lo", "workspace_hi", "workspace"), ("angle_lo", "angle_hi", "angle")):
        if any(a >= b for a, b in zip(getattr(racket, lo), getattr(racket, hi))):
            raise ConfigError(f"{source}: [racket] {lo} = {list(getattr(racket, lo))} must be below "
                              f"{hi} = {list(getattr(racket, hi))} in every coordinate ({what})")
    if racket.workspace_lo[0] <= 0.0:
        raise ConfigError(f"{source}: [racket] workspace_lo = {list(racket.workspace_lo)}: x must be positive "
                          "(the racket stays on the agent's half, x > 0)")
    if any(not a <= s <= b for a, s, b in zip(racket.workspace_lo, racket.start, racket.workspace_hi)):
        raise ConfigError(f"{source}: [racket] start = {list(racket.start)} lies outside the workspace")
    from ttsim_jax.shots import SHOT_TYPES

    shots = out["shots"]
    if shots.source not in SHOT_SOURCES:
        raise ConfigError(f"{source}: [shots] source = {shots.source!r}: expected one of {list(SHOT_SOURCES)}")
    if shots.split not in SPLITS:
        raise ConfigError(f"{source}: [shots] split = {shots.split!r}: expected one of {list(SPLITS)}")
    known = SHOT_TYPES if shots.source == "sampled" else MEASURED_TYPES
    if shots.source == "measured":
        if "types" not in raw.get("shots", {}):
            shots = dataclasses.replace(shots, types=MEASURED_TYPES)
        if not shots.measured:
            raise ConfigError(f"{source}: [shots] source = \"measured\" needs measured = \"FOLDER\" (a folder of "
                              "DeepMind's serves.json and rallies.json)")
        expanded = os.path.expandvars(shots.measured)
        if "$" in expanded:
            raise ConfigError(f"{source}: [shots] measured = {shots.measured!r}: set the environment variable it "
                              "names (the folder of the public measured data)")
        folder = _beside(source, expanded)
        if not folder.is_dir():
            raise ConfigError(f"{source}: [shots] measured = {shots.measured!r}: no such folder ({folder})")
        out["shots"] = shots = dataclasses.replace(shots, measured=str(folder))
    if not shots.types or set(shots.types) - set(known):
        raise ConfigError(f"{source}: [shots] types = {list(shots.types)}: unknown or none; known for source = "
                          f"{shots.source!r}: {list(known)}")
    control = out["control"]
    ratio = 1.0 / (control.rate_hz * control.physics_dt)
    if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
        raise ConfigError(f"{source}: [control] rate_hz = {control.rate_hz} and physics_dt = {control.physics_dt}: "
                          "a control period must be a whole number of physics steps")
    if control.action not in ACTION_MODES:
        raise ConfigError(f"{source}: [control] action = {control.action!r}: expected one of {list(ACTION_MODES)}")
    if out["intercept"].bounce not in BOUNCE_MODES:
        raise ConfigError(f"{source}: [intercept] bounce = {out['intercept'].bounce!r}: expected one of "
                          f"{list(BOUNCE_MODES)}")
    flight = out["intercept"].flight_time
    if flight[0] > flight[1]:
        raise ConfigError(f"{source}: [intercept] flight_time = {list(flight)}: low must not exceed high")
    reward = out["reward"]
    if any(reward.target_spread) and not out["observation"].target:
        raise ConfigError(f"{source}: [reward] target_spread = {list(reward.target_spread)} draws a target per "
                          "episode that the policy would not see: set [observation] target = true")
    residual = out["residual"]
    if residual.checkpoint:
        path = _beside(source, residual.checkpoint)
        if not path.is_file():
            raise ConfigError(f"{source}: [residual] checkpoint = {residual.checkpoint!r}: no such file ({path})")
        out["residual"] = residual = TaskResidualConfig(checkpoint=str(path), sample=residual.sample)
    if residual.sample and not residual.checkpoint:
        raise ConfigError(f"{source}: [residual] sample = true needs a network: set [residual] checkpoint")
    ranges = []
    rand = raw.get("randomisation", {})
    if not isinstance(rand, dict):
        raise ConfigError(f"{source}: [randomisation] must be a table")
    for key, value in rand.items():
        where = f"{source}: [randomisation] {key!r}"
        if isinstance(value, dict):
            ranges.append((key, *_normal_law(where, key, value, source), "normal"))
            continue
        lo, hi = convert_value(where, (0.0, 0.0), value)
        if lo > hi:
            raise ConfigError(f"{where} = {value!r}: low must not exceed high")
        ranges.append((key, lo, hi, "uniform"))
    model = raw.get("model", "conti2026")
    if not isinstance(model, str):
        raise ConfigError(f"{source}: model = {model!r}: expected a model name or path")
    racket_config = raw.get("racket_config", "")
    if not isinstance(racket_config, str):
        raise ConfigError(f"{source}: racket_config = {racket_config!r}: expected a racket name or path")
    if racket_config:
        from ttsim_jax.params import resolve_racket_path

        resolve_racket_path(racket_config)  # an unknown name is refused here, naming the bundled ones
    return TaskConfig(model=model, racket_config=racket_config, randomisation=tuple(ranges), source=source, **out)
