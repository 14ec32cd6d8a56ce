"""Data-parallel training over every device of every process: JAX's multi-process runtime
(:func:`jax.distributed.initialize`) joins the processes, the environments are split along one mesh
axis over all devices, and the network's parameters are replicated.

The update is the one-device program (:func:`ttsim_jax.rl.ppo.make_update`) compiled for sharded
inputs: XLA partitions it, so the loss's mean over all environments, and with it the gradient, is
averaged across processes by the compiler's own collectives, and a run on N devices computes the
same in one process or spread over several (up to the order of float sums).
Each device holds its share of the environments and steps them itself (:func:`per_shard`);
process 0 writes the files.

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
    """Whether training splits its environments over devices: where the run has several (one
    process's, or those of several processes)."""
    return jax.device_count() > 1


def per_shard(env, mesh: Mesh):
    """``step(key, state, action, params)`` of ``env`` (one device's share of the environments,
    :meth:`~ttsim_jax.env.return_ball.ReturnBall.resized`) run on each device over its own
    environments (``shard_map``), for states and actions split along :data:`AXIS`.

    The environment step compacts the rows that reset or touch a racket; partitioned by XLA over
    devices that compaction gathers across the whole batch every step (two processes trained at
    545 env-steps/s that way, 44,281 this way: ``benchmarks/ppo_processes.py``). Each device
    compacts its own rows instead, and draws
    its own random numbers (the key folded with its index): a run is then the same for the same
    seed and number of devices, however many processes hold them."""
    spec = PartitionSpec(AXIS)

    def local(key, state, action, params):
        return env.step(jax.random.fold_in(key, jax.lax.axis_index(AXIS)), state, action, params)

    def step(key, state, action, params):
        # the kernel's batch-wide clock (scalars) is the same on every device
        state_spec = jax.tree.map(lambda x: spec if x.ndim else PartitionSpec(), state)
        run = jax.shard_map(local, mesh=mesh, in_specs=(PartitionSpec(), state_spec, spec, PartitionSpec()),
                            out_specs=(spec, state_spec, spec, spec, spec, spec), check_vma=False)
        return run(key, state, action, params)

    return step


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
