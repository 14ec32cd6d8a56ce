"""The bank of incoming shots a ReturnBall task draws its episodes from (``[shots]`` of the task
file), drawn once and kept in the user's cache when aimed through the model."""

from __future__ import annotations

import jax
import numpy as np

from ttsim_jax.env.config import TaskConfig
from ttsim_jax.params import ConfigError, Model
from ttsim_jax.sizes import require as require_memory
from ttsim_jax.state import Ball

#: Memory that drawing a bank holds per shot of the bank, aimed through the model [bytes]: the
#: sampler draws twice the bank and flies every draw to its bounce. Measured
#: (benchmarks/bank_memory.py): a bank of 4,096 peaked 2,043 MiB (ru_maxrss) above one of 512
#: (conti2026, CPU, after compiling), 0.57 MiB a shot.
AIM_BYTES_PER_SHOT = 600_000
#: The same unaimed: two draws of 9 float64 values and a label a shot, and their temporaries (4x).
DRAW_BYTES_PER_SHOT = 2 * (9 * 8 + 8) * 4


def bank_bytes(config: TaskConfig) -> int:
    """What drawing the task's shot bank holds at once [bytes] (nothing for a measured bank, whose
    size is the file's, nor for an aimed bank already in the cache: this is the drawing's)."""
    c = config.shots
    if c.source == "measured":
        return 0
    return int(c.bank) * (AIM_BYTES_PER_SHOT if c.aim else DRAW_BYTES_PER_SHOT)


def require_bank(config: TaskConfig) -> None:
    """Refuses a task whose shot bank's drawing (:func:`bank_bytes`) is above the memory budget."""
    c = config.shots
    require_memory(f"{config.source}: [shots] bank = {c.bank}" + (" (aimed through the model)" if c.aim else ""),
                   bank_bytes(config), remedy="give a smaller bank" + (", or aim = false" if c.aim else ""))


def shot_bank(model: Model, config: TaskConfig, cache: bool = True):
    """The incoming shots: ``sample_shots`` of the configured types, redrawing any faster or spinning
    faster than the configured maxima.

    Aiming thousands of shots through the model takes a minute on a CPU, so an aimed bank is kept in
    ``$XDG_CACHE_HOME/ttsim_jax`` (default ``~/.cache``), named by a hash of the ``[shots]`` settings,
    the model's parameters and the sampler's source; ``cache=False`` always draws afresh.

    With ``[shots] source = "measured"`` the bank holds measured states instead
    (:func:`measured_bank`).

    Returns:
        (:class:`Ball` (S, 3) float32 numpy fields, (S,) int shot type index into ``config.shots.types``).
    """
    if config.shots.source == "measured":
        return measured_bank(model, config)
    import hashlib
    import inspect

    from ttsim_jax import shots as shots_module
    from ttsim_jax.files.cache import cache_root

    c = config.shots
    path = None
    if cache and c.aim:
        digest = hashlib.sha256(repr(c).encode())
        for leaf in jax.tree.leaves(model):
            digest.update(np.asarray(leaf).tobytes())
        digest.update(inspect.getsource(shots_module).encode())
        path = cache_root() / f"shots-{digest.hexdigest()[:20]}.npz"
        if path.is_file():
            with np.load(path) as f:
                return Ball(pos=f["pos"], vel=f["vel"], spin=f["spin"]), f["types"]
    require_bank(config)
    kept, labels, seed = [], [], c.seed
    while sum(len(k) for k in kept) < c.bank:
        ball, lab = shots_module.sample_shots(2 * c.bank, seed=seed, types=list(c.types),
                                              radius=float(model.ball.radius), model=model if c.aim else None)
        ok = ((np.linalg.norm(ball.vel, axis=-1) <= c.max_speed) & (np.linalg.norm(ball.spin, axis=-1) <= c.max_spin)
              & np.isfinite(ball.vel).all(-1))
        if not ok.any():
            raise ConfigError(f"{config.source}: [shots] no shot of types {list(c.types)} is within max_speed = "
                              f"{c.max_speed} and max_spin = {c.max_spin}")
        kept.append(np.concatenate([ball.pos, ball.vel, ball.spin], -1)[ok])
        labels.append(lab[ok])
        seed += 1_000_003
    arr = np.concatenate(kept)[:c.bank].astype(np.float32)
    lab = np.concatenate(labels)[:c.bank]
    index = {name: i for i, name in enumerate(c.types)}
    bank = Ball(pos=arr[:, 0:3], vel=arr[:, 3:6], spin=arr[:, 6:9])
    types = np.array([index[s] for s in lab], np.int32)
    if path is not None:
        import io

        from ttsim_jax.files.atomic import atomic_write

        buf = io.BytesIO()
        np.savez(buf, pos=bank.pos, vel=bank.vel, spin=bank.spin, types=types)
        try:
            atomic_write(path, buf.getvalue())
        except OSError:  # a read-only home: no cache, same bank
            pass
    return bank, types


def measured_bank(model: Model, config: TaskConfig):
    """The bank of measured post-hit states (:mod:`ttsim_jax.data.post_hit_states`): the
    ``[shots] split`` of the ``types`` in the folder ``measured``, those within ``max_speed`` and
    ``max_spin`` and clear of the table (centre above it by more than a radius), in a seeded random
    order, repeated or cut to ``bank`` shots.

    Returns:
        what :func:`shot_bank` returns; raises :class:`ConfigError` when no state is left.
    """
    from ttsim_jax.data.post_hit_states import read_post_hit_states

    c = config.shots
    s = read_post_hit_states(c.measured, kinds=c.types)
    keep = {"train": ~s.test, "test": s.test, "all": np.ones(len(s), bool)}[c.split]
    keep &= (np.linalg.norm(s.vel, axis=-1) <= c.max_speed) & (np.linalg.norm(s.spin, axis=-1) <= c.max_spin)
    keep &= s.pos[:, 2] > float(model.ball.radius)
    if not keep.any():
        raise ConfigError(f"{config.source}: [shots] no measured state of types {list(c.types)} in the {c.split!r} "
                          f"split of {c.measured} is within max_speed = {c.max_speed} and max_spin = {c.max_spin}")
    s = s.select(keep)
    order = np.resize(np.random.default_rng(c.seed).permutation(len(s)), c.bank)
    index = {name: i for i, name in enumerate(c.types)}
    f32 = lambda a: np.asarray(a[order], np.float32)  # noqa: E731
    return Ball(pos=f32(s.pos), vel=f32(s.vel), spin=f32(s.spin)), np.array([index[k] for k in s.kind[order]], np.int32)
