"""The ball axis sharded over devices: each device runs the kernel on its own balls.

Balls never interact, so a rollout shards without communication: every device flies, detects and
gathers contacts among its own balls only (its own contact buffer, its own event log), and shared
parameters are replicated. Random draws depend on each ball's id and the step, not on its shard,
so sharded and unsharded rollouts agree.

Multi-host: call ``jax.distributed.initialize()`` on every host first; ``jax.devices()`` then
lists every host's devices and a 1-D mesh over them shards the batch across hosts the same way.
Each host must hold the same program and feed the same global arrays (e.g. via
``jax.make_array_from_process_local_data``); the rollout itself needs no cross-host traffic.
"""

from __future__ import annotations

import functools

import jax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from ttsim_jax.kernel.axes import StaticAxes, check_per_ball, resolve_axes
from ttsim_jax.kernel.rollout import RolloutOutput, default_capacity, rollout
from ttsim_jax.kernel.execution import Execution
from ttsim_jax.kernel.plans import RacketPolicy, normalise_schedule
from ttsim_jax.kernel.record import Record
from ttsim_jax.kernel.state import RallyState

AXIS = "balls"


def ball_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``"balls"`` over ``devices`` (default: every device)."""
    devices = jax.devices() if devices is None else devices
    return jax.make_mesh((len(devices),), (AXIS,), devices=devices)


def _state_specs(state: RallyState):
    per_ball = P(AXIS)
    return state.replace(ball=jax.tree.map(lambda _: per_ball, state.ball), alive=per_ball, status=per_ball,
                         ball_id=per_ball, step=P(), t0=P(), dt=P())


@functools.lru_cache(maxsize=64)
def _compiled(mesh, axes, n_steps, has_plan, plan_per_ball, static_kw):
    """The jitted shard_map of a rollout, cached on everything static so repeated calls reuse it."""
    kw = dict(static_kw)
    axes_tree = axes.tree()
    record = kw["record"]

    def local_rollout(model, state, plan, dt, key):
        return rollout(model, state, n_steps, dt, plan, model_axes=axes_tree, sample_key=key, **kw)

    def specs(model, state, plan):
        model_specs = jax.tree.map(lambda ax, sub: jax.tree.map(lambda _: P() if ax is None else P(AXIS), sub),
                                   axes_tree, model, is_leaf=lambda x: x is None)
        plan_specs = None if plan is None else jax.tree.map(lambda _: P(AXIS) if plan_per_ball else P(), plan)
        return model_specs, _state_specs(state), plan_specs

    def run(model, state, plan, dt, key):
        model_specs, state_specs, plan_specs = specs(model, state, plan)
        out_specs = (state_specs, RolloutOutput(
            events=None if not record.max_events else P(AXIS), trajectory=None if not record.every else P(AXIS),
            times=None if not record.every else P()))
        fn = jax.shard_map(local_rollout, mesh=mesh, in_specs=(model_specs, state_specs, plan_specs, P(), P()),
                           out_specs=out_specs, check_vma=False)
        return fn(model, state, plan, dt, key)

    return jax.jit(run), specs


def sharded_rollout(model, state: RallyState, n_steps: int, dt: float = 1e-3, racket=None, *, mesh: Mesh | None = None,
                    model_axes=None, sample_key=None, execution: Execution = Execution(), **options):
    """:func:`~ttsim_jax.kernel.rollout.rollout` with the ball axis split over the devices of ``mesh``.

    Arguments:
        model, state, n_steps, dt, racket, model_axes, sample_key, execution: as for ``rollout``
            (its ``contact_capacity`` counts rows per device; default: the default for the local batch).
        mesh: a 1-D mesh with axis ``"balls"`` (default :func:`ball_mesh`); the batch must divide
            evenly over it.
        options: ``rollout``'s other keyword arguments (``integrator``, ``record``).

    Returns:
        (state, outputs) as ``rollout``, sharded along the ball axis.
    """
    unknown = sorted(set(options) - {"integrator", "record"})
    if unknown:
        raise TypeError(f"sharded_rollout() got an unexpected keyword argument {unknown[0]!r}")
    mesh = ball_mesh() if mesh is None else mesh
    n_dev = mesh.shape[AXIS]
    batch = state.batch
    if batch % n_dev:
        raise ValueError(f"the batch of {batch} balls does not divide over {n_dev} devices")
    axes = resolve_axes(model, model_axes)
    check_per_ball(model, axes, batch)
    per_ball_plan = False
    if racket is not None and not isinstance(racket, RacketPolicy):
        per_ball_plan = normalise_schedule(racket, n_steps, batch)[1]
    execution = execution.replace(contact_capacity=execution.contact_capacity or default_capacity(batch // n_dev))
    static_kw = (("integrator", options.get("integrator", "rk4")), ("record", options.get("record", Record())),
                 ("execution", execution))
    fn, specs = _compiled(mesh, StaticAxes(axes), n_steps, racket is not None, per_ball_plan, static_kw)
    model_specs, state_specs, plan_specs = specs(model, state, racket)
    place = lambda tree, sp: jax.tree.map(lambda a, s: jax.device_put(a, NamedSharding(mesh, s)), tree, sp)  # noqa: E731
    return fn(place(model, model_specs), place(state, state_specs),
              None if racket is None else place(racket, plan_specs), jax.numpy.asarray(dt, state.ball.pos.dtype),
              sample_key)
