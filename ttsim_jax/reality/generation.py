"""Generating synthetic measured data with a known truth, and recording the same games again.

:func:`generate` checks a configuration, runs its games (:class:`~ttsim_jax.reality.game.Game`) and
assembles the dataset and truth (:func:`~ttsim_jax.reality.assembly.assemble`);
:func:`rerecord` assembles the same simulated games under other record effects.
"""

from __future__ import annotations

import copy
import time

from ttsim_jax import effects as fx
from ttsim_jax.sizes import require as require_memory

from .assembly import Generated, assemble
from .config import GeneratorConfig, GeneratorError, check_config, memory_bytes
from .game import Game


def generate(config: GeneratorConfig | None = None, *, progress: bool = True, **overrides) -> Generated:
    """Generates a synthetic dataset with its ground truth.

    Arguments:
        config: a :class:`GeneratorConfig` (default: the defaults); ``overrides`` change fields.
        progress: show a progress bar (rallies done).

    Returns:
        A :class:`Generated` (dataset, truth dict and truth tables). Write it with :func:`~ttsim_jax.reality.write`.
    """
    cfg = check_config((config or GeneratorConfig()).replace(**{k: v for k, v in overrides.items() if v is not None}))
    require_memory(f"generating {cfg.games} games of {cfg.rallies_per_game[0]}-{cfg.rallies_per_game[1]} rallies",
                   memory_bytes(cfg), remedy="generate fewer games per run (several runs with different seeds)")
    t0 = time.perf_counter()
    game = Game(cfg, progress)
    game.run()
    return assemble(game, time.perf_counter() - t0)


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
    cfg = check_config(old.replace(effects=effects), "rerecord")
    physical = lambda c: [n for n in c.effects if fx.effect_class(n).WHERE == "simulator"]  # noqa: E731
    if physical(cfg) != physical(old):
        raise GeneratorError(f"rerecord: effects {list(cfg.effects)} change the simulator effects "
                             f"{physical(old)} -> {physical(cfg)}; only record effects may change")
    t0 = time.perf_counter()
    game = copy.copy(gen._game)
    game.cfg = cfg
    game.draw_effects()
    return assemble(game, gen.wall_time_s + time.perf_counter() - t0)
