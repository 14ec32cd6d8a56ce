"""PPO checkpoints: one file holding the whole training state, written atomically and verified on
reading (a checkpoint container, :mod:`ttsim_jax.files.checkpoint`).

A checkpoint holds the PPO config's text, the :class:`~ttsim_jax.rl.ppo.Runner` (network,
optimiser, observation statistics, environments, key), the learning history and the training time
so far, so a run resumes exactly where it stopped and ``ttsim play`` needs nothing else.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from ttsim_jax.files.checkpoint import CHECKPOINT_MAGIC, CheckpointError, read_container, write_container

#: The container kind of a PPO checkpoint (:mod:`ttsim_jax.files.checkpoint`: a verified header
#: with the config, history and time, the runner's arrays as its payload, both under SHA-256).
KIND = "ppo-training"
#: The format of checkpoints written before they went into the container: plain msgpack, read still,
#: without any checksum.
FORMAT = "ttsim-ppo/1"
# A small policy trained on the default task (configs/ppo/return_ball_small.toml), shipped with the
# package so that ``ttsim play`` works before any training.
BUNDLED_POLICY = Path(__file__).resolve().parent / "policies" / "return_ball.msgpack"


def save_checkpoint(path, runner, config, history: list, elapsed_s: float) -> Path:
    """Writes a checkpoint atomically (a crash leaves the previous one).

    Arguments:
        path: file to write; runner: the :class:`~ttsim_jax.rl.ppo.Runner`; config: the
        :class:`~ttsim_jax.rl.config.PPOConfig`; history: list of per-chunk metric dicts;
        elapsed_s: training time so far [s].
    """
    header = {"config": config.text, "config_source": config.source, "history": history,
              "elapsed_s": float(elapsed_s)}
    write_container(path, KIND, header, serialization.to_state_dict(runner))
    return Path(path)


def read_checkpoint(path) -> dict:
    """The checkpoint's contents: ``config`` (text), ``config_source``, ``runner`` (a state dict),
    ``history`` (list) and ``elapsed_s``; raises :class:`CheckpointError` naming the file, for a
    damaged one too (any bit flipped in a checkpoint of the container: its header's or payload's
    SHA-256). A checkpoint of the earlier plain format is read without that check."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            container = f.read(len(CHECKPOINT_MAGIC)) == CHECKPOINT_MAGIC
    except OSError as e:
        raise CheckpointError(f"{path}: not a PPO checkpoint ({type(e).__name__}: {e})") from None
    if container:
        header, runner = read_container(path, KIND)
        for key in ("config", "config_source", "history", "elapsed_s"):
            if key not in header:
                raise CheckpointError(f"{path}: header lacks key {key!r} (corrupted)")
        return {"config": header["config"], "config_source": header["config_source"], "runner": runner,
                "history": header["history"], "elapsed_s": header["elapsed_s"]}
    try:
        payload = serialization.msgpack_restore(path.read_bytes())
    except (OSError, ValueError, TypeError, KeyError) as e:
        raise CheckpointError(f"{path}: not a PPO checkpoint ({type(e).__name__}: {e})") from None
    except Exception as e:  # msgpack's own errors (truncated or foreign data) are not ValueErrors
        raise CheckpointError(f"{path}: not a PPO checkpoint ({type(e).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a PPO checkpoint (format {payload.get('format') if isinstance(payload, dict) else None!r}, expected {FORMAT!r})")
    payload["history"] = json.loads(payload["history"])
    return payload


def restore_runner(template, payload: dict, path=""):
    """The runner stored in ``payload``, in the structure of ``template`` (a fresh runner of the same
    config); raises :class:`CheckpointError` when they do not match.

    A checkpoint written before the environment state carried the tracker's plan
    (:attr:`~ttsim_jax.env.return_ball.EnvState.plan`, derived from the rest of the state) gets
    zeros there; :func:`~ttsim_jax.rl.training.train` recomputes it on resuming. One written before
    each episode carried its target (:attr:`~ttsim_jax.env.return_ball.EnvState.target`; every task
    then had a fixed one) gets the template's, the task's ``target_point``."""
    stored = payload["runner"]
    state = stored.get("env_state") if isinstance(stored, dict) else None
    if isinstance(state, dict) and ("plan" not in state or "target" not in state):
        fresh = serialization.to_state_dict(template)["env_state"]
        target = fresh["target"]  # an abstract template (``ttsim play``, which reads no state): zeros
        target = np.zeros(target.shape, np.float32) if isinstance(target, jax.ShapeDtypeStruct) else np.asarray(target)
        missing = {"plan": np.zeros(fresh["plan"].shape, np.float32), "target": target}
        stored = dict(stored, env_state={**{k: v for k, v in missing.items() if k not in state}, **state})
    try:
        runner = serialization.from_state_dict(template, stored)
    except (ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{path}: the checkpoint does not match its config ({e})") from None
    # from_state_dict takes arrays of any shape: a task whose observation has changed since training
    # (another size) would otherwise fail later, inside the network, with an unclear error
    for (where, want), got in zip(jax.tree_util.tree_leaves_with_path(template), jax.tree.leaves(runner)):
        if tuple(want.shape) != tuple(jnp.shape(got)):
            raise CheckpointError(f"{path}: {jax.tree_util.keystr(where)} has shape {tuple(jnp.shape(got))} in the "
                                  f"checkpoint, {tuple(want.shape)} for its task as it is now (has the task's "
                                  "observation changed since training?)")
    return runner
