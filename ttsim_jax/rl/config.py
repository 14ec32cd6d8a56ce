"""PPO settings (``configs/ppo/*.toml``), read and checked at load time."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ttsim_jax.env.config import read_section
from ttsim_jax.params import ConfigError, config_dir


@dataclass(frozen=True)
class PPOSettings:
    num_envs: int = 512
    num_steps: int = 32
    update_epochs: int = 3
    num_minibatches: int = 4
    learning_rate: float = 3e-4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    ent_coef: float = 1e-3
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    init_log_std: float = -0.5
    anneal_lr: bool = False


@dataclass(frozen=True)
class TrainSettings:
    total_env_steps: int = 20_000_000
    time_limit_s: float = 1200.0
    seed: int = 0
    updates_per_chunk: int = 10
    eval_every_chunks: int = 10
    eval_envs: int = 512
    checkpoint_every_chunks: int = 5


@dataclass(frozen=True)
class PPOConfig:
    """Attributes: task (bundled task name or task .toml path), hidden (layer widths), ppo, train,
    source (the file read, "" for defaults), text (its contents, stored in checkpoints)."""

    task: str = "return_ball"
    hidden: tuple = (64, 64)
    ppo: PPOSettings = field(default_factory=PPOSettings)
    train: TrainSettings = field(default_factory=TrainSettings)
    source: str = ""
    text: str = ""

    @property
    def batch_size(self) -> int:
        """Transitions per update."""
        return self.ppo.num_envs * self.ppo.num_steps


_POSITIVE = {"num_envs", "num_steps", "update_epochs", "num_minibatches", "learning_rate", "gamma", "gae_lambda",
             "clip_eps", "max_grad_norm", "total_env_steps", "time_limit_s", "updates_per_chunk",
             "checkpoint_every_chunks"}
_NON_NEGATIVE = {"ent_coef", "vf_coef", "seed", "eval_every_chunks", "eval_envs"}


def default_ppo_path() -> Path:
    """The bundled ``configs/ppo/return_ball.toml``."""
    return config_dir() / "ppo" / "return_ball.toml"


def parse_ppo_config(text: str, source: str = "") -> PPOConfig:
    """A :class:`PPOConfig` from TOML text; raises :class:`ConfigError` naming the file, key and value."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{source}: not a valid TOML file ({e})") from None
    unknown = set(raw) - {"task", "network", "ppo", "train"}
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)}; known: task, network, ppo, train")
    task = raw.get("task", "return_ball")
    if not isinstance(task, str):
        raise ConfigError(f"{source}: task = {task!r}: expected a task name or path")
    hidden = raw.get("network", {}).get("hidden", list(PPOConfig.hidden))
    if (not isinstance(hidden, list) or not hidden
            or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in hidden)):
        raise ConfigError(f"{source}: [network] hidden = {hidden!r}: expected a list of positive integers")
    if set(raw.get("network", {})) - {"hidden"}:
        raise ConfigError(f"{source}: [network] unknown key(s) {sorted(set(raw['network']) - {'hidden'})}")
    ppo = read_section(raw, "ppo", PPOSettings, source, _POSITIVE, _NON_NEGATIVE)
    train = read_section(raw, "train", TrainSettings, source, _POSITIVE, _NON_NEGATIVE)
    if (ppo.num_envs * ppo.num_steps) % ppo.num_minibatches:
        raise ConfigError(f"{source}: [ppo] num_minibatches = {ppo.num_minibatches} must divide num_envs x "
                          f"num_steps = {ppo.num_envs * ppo.num_steps}")
    for key in ("gamma", "gae_lambda"):
        if getattr(ppo, key) > 1.0:
            raise ConfigError(f"{source}: [ppo] {key} = {getattr(ppo, key)}: must not exceed 1")
    return PPOConfig(task=task, hidden=tuple(hidden), ppo=ppo, train=train, source=source, text=text)


def load_ppo_config(path=None, overrides: dict | None = None) -> PPOConfig:
    """Reads a PPO file (default: the bundled one); ``overrides`` ``{"section.key": value}`` apply on top."""
    path = default_ppo_path() if path is None else Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such PPO config file")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file") from None
    config = parse_ppo_config(text, str(path))
    if overrides:
        import dataclasses

        for key, value in overrides.items():
            section, _, name = key.partition(".")
            sub = getattr(config, section)
            config = dataclasses.replace(config, **{section: dataclasses.replace(sub, **{name: value})})
    return config
