"""Data-parallel training over every device of every process: JAX's multi-process runtime
(:func:`jax.distributed.initialize`) joins the processes, the environments are split along one mesh
axis over all devices, and the network's parameters are replicated.

The update is the one-device program (:func:`ttsim_jax.rl.ppo.make_update`) compiled for sharded
inputs: XLA partitions it, so the loss's mean over all environments, and with it the gradient, is
averaged across processes by the compiler's own collectives, and a run on N processes computes what
one process computes with the same total environments and seed (up to the order of float sums).
Each device holds its share of the environments; process 0 writes the files. The environment
step is partitioned by XLA as well, and its compaction gathers across devices: correct, and slow
across processes (see :func:`sharded`); a per-shard environment step is not written yet.

One command per process (on a CPU, the collectives go through gloo)::

    ttsim train ppo --config C --out DIR --coordinator HOST:PORT --num-processes 2 --process-id 0
    ttsim train ppo --config C --out DIR --coordinator HOST:PORT --num-processes 2 --process-id 1
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

#: The mesh axis the environments are split along.
AXIS = "env"


def initialize(coordinator: str, num_processes: int, process_id: int) -> None:
    """Joins this process to a run of ``num_processes`` (before any other JAX call): the coordinator
    (``HOST:PORT``, process 0 serves it) waits for all of them."""
    if not 0 <= process_id < num_processes:
        raise ValueError(f"process id {process_id} is not within 0..{num_processes - 1}")
    # CPU devices of different processes talk through gloo (the default has no cross-process collectives)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)


def sharded() -> bool:
    """Whether training splits its environments over devices: in a run of several processes.

    One process keeps to one device even where it sees several: the environment step's
    compaction of the rows that reset or touch (:class:`~ttsim_jax.env.return_ball.ReturnBall`)
    gathers across the whole batch, which partitioned over devices costs collectives every step
    (on this machine's CPU one process trains at 24,950 env-steps/s on one device, 10,755 on two
    host devices, and two processes at 545, their collectives through gloo:
    ``benchmarks/ppo_processes.py``)."""
    return jax.process_count() > 1


def mesh() -> Mesh:
    """Every device of every process along :data:`AXIS`."""
    return Mesh(np.array(jax.devices()), (AXIS,))


def check_envs(num_envs: int, where: str) -> None:
    """Refuses a number of environments the devices cannot share equally."""
    n = jax.device_count()
    if num_envs % n:
        raise ValueError(f"{where} = {num_envs}: not a multiple of the {n} devices of this run "
                         f"({jax.process_count()} processes), which share the environments equally")


def shardings(tree, num_envs: int, m: Mesh):
    """Per leaf of ``tree`` (arrays or shape structs): split along :data:`AXIS` when its leading axis
    is the environments' (``num_envs``), else replicated."""
    def one(x):
        spec = PartitionSpec(AXIS) if getattr(x, "ndim", 0) >= 1 and x.shape[0] == num_envs else PartitionSpec()
        return NamedSharding(m, spec)
    return jax.tree.map(one, tree)


def put(tree, sharding_tree):
    """``tree``'s host values (every process holds the same) as global arrays of ``sharding_tree``."""
    def one(x, s):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, s, lambda index: x[index])
    return jax.tree.map(one, tree, sharding_tree)


def replicate(tree, m: Mesh):
    """``tree``'s host values (every process holds the same) as global arrays every device holds whole."""
    whole = replicated(m)
    return put(tree, jax.tree.map(lambda _: whole, tree))


def replicated(m: Mesh):
    """The sharding of a value every device holds whole."""
    return NamedSharding(m, PartitionSpec())


def to_host(tree, m: Mesh):
    """``tree``'s global arrays gathered whole into every process, as numpy."""
    whole = jax.jit(lambda t: t, out_shardings=replicated(m))(tree)
    return jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), whole)
