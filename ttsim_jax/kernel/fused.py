"""The fused flight path: many free-flight steps per kernel launch, contacts left to the step.

On a GPU the rally kernel's step is launch-bound: a 1 ms step is hundreds of small kernels, most
of them for the few balls that have a contact. Here one Pallas kernel (``jax.experimental.pallas``,
Triton) flies a block of balls through up to ``substeps`` RK4 steps with the state kept in
registers; on a CPU the same body runs as plain XLA over the whole batch, where a sub-step
compiles to one loop over the balls (:func:`_fly_moving`, which also gathers the few balls still
moving in a rollout's last launches). It stops each ball before the first step in which
anything *may* happen to it: a conservative version of :func:`~ttsim_jax.kernel.ball_step.may_have_event`
(the swept box of the step meeting the table or the box a racket sweeps over the rollout, the
floor, the net plane, leaving play, a state near the invalid range), each with a margin
(``SLACK``) so that rounding can only stop a ball earlier. The ordinary step
(:func:`~ttsim_jax.kernel.step.step`) then runs once at each ball's own time, and handles contacts
exactly as in the reference path. Stopping early is harmless: that step is a step of free flight.

So each ball carries its own step count while the rollout runs (:func:`advance`): kernel, one step,
kernel, ... until every ball has reached the end (or the next recorded step). The results equal
the reference path's within float32 rounding of the flight (``tests/kernel/test_fused.py``).

What the kernel covers (:func:`unsupported` says why anything else runs the reference path): RK4,
the drag and Magnus coefficient models of ``physics.aero`` (constant, C_D(Re, Sp) table, Dürr, C_M
table), ball / aero / table parameters shared by all balls or per ball (the shared ones read as
scalars, the per-ball ones as rows: on a GPU each program reads its block of them), rackets as a
schedule shared by all balls or one per ball (or none), a racket policy with a reach
(:attr:`~ttsim_jax.kernel.plans.RacketPolicy.reach`: the kernel stops a ball before its path meets
the boxes the policy's rackets stay in, and the ordinary step evaluates the policy for each ball at
its own time; a ball whose rackets are found outside those boxes ends ``INVALID``), the sampled
residual (a ball's step k draws with the key the reference path's step k has), and effects acting
in flight: the ball's and the air's properties (hooks without context, read as constants), and on
a CPU the air's velocity and the spin's decay, evaluated at every RK4 stage for each ball at its
own time (:class:`Hooks`). Not an effect that moves the table's surface (the stopping test uses
the flat table's box). The coefficient tables are passed to the kernel as one small vector of
scalars and interpolated with the same ramps as ``aero._piecewise`` (arithmetic, no gather).

Reverse mode never sees the kernel: the fused rollout is a ``jax.custom_jvp`` whose derivative is
the reference path's, so ``jax.grad`` through ``rollout(..., execution=Execution(fused=True))``
differentiates the reference path (with its rematerialisation).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.kernel.fused_params import (DRAG_KINDS, FLIGHT_HOOKS, MAGNUS_KINDS, STATE_HOOKS, Layout, Reader,
                                           coefficient_fns, hooked_properties, in_flight, pack)
from ttsim_jax.kernel.plans import face_boxes, within_reach
from ttsim_jax.kernel.ball_step import MAX_SPEED, MAX_SPIN
from ttsim_jax.kernel.step import StepState, take_rows
from ttsim_jax.physics import events as ev
from ttsim_jax.physics import hooks
from ttsim_jax.physics import table as table_stage
from ttsim_jax.physics.numerics import component_norm

# Free-flight steps per kernel launch (a ball flies about 100-300 steps between contacts).
SUBSTEPS = 32
# Balls per kernel program (a power of two, as Triton needs): one per thread of 4 warps.
BLOCK = 128
# Margin [m] added to every stopping test, far above the rounding by which the kernel's path
# differs from the reference path's, so that the kernel never flies through a step the reference
# would flag; a ball stopped early only costs one ordinary step.
SLACK = 1e-3
# The kernel stops a ball whose speed or spin nears the ordinary step's validity limits.
_LIMIT_FRACTION = 0.99


# --------------------------------------------------------------------------- what it covers
def unsupported(model, axes, *, integrator: str, policy, rackets_batched: bool) -> str | None:
    """Why a rollout cannot take the fused path, or None if it can.

    Arguments:
        model: the model; axes: its per-ball axes (pytree prefix of 0 / None);
        integrator: the flight integrator; policy: the racket policy or None;
        rackets_batched: whether the racket schedule is per ball.
    """
    gpu = jax.default_backend() == "gpu"
    if integrator != "rk4":
        return f"integrator {integrator!r} (the fused kernel is RK4)"
    if policy is not None and policy.reach is None:
        return ("a racket policy without a reach (RacketPolicy.reach: the boxes its rackets stay in, which the "
                "fused kernel stops balls at)")
    if type(model.aero.drag) not in DRAG_KINDS or type(model.aero.magnus) not in MAGNUS_KINDS:
        return f"coefficient models {type(model.aero.drag).__name__}/{type(model.aero.magnus).__name__}"
    surface = [type(e).__name__ for e in model.effects if hasattr(e, "table_surface")]
    if surface:
        return f"effects moving the table's surface: {surface} (the kernel stops balls at the flat table's box)"
    if gpu and in_flight(model):
        hooked = [type(e).__name__ for e in model.effects if any(hasattr(e, h) for h in FLIGHT_HOOKS)]
        return f"effects acting in flight on a GPU: {hooked} (the Triton kernel has no hooks)"
    return None


def per_ball_physics(axes) -> bool:
    """Whether any ball, aero, table or effect parameter is per ball (``axes``: the model's per-ball
    axes, a pytree prefix of 0 / None): the kernel then reads rows of per-ball values."""
    shared = axes.ball, axes.aero, axes.table, axes.effects
    return any(ax is not None for ax in jax.tree.leaves(shared, is_leaf=lambda x: x is None))


# --------------------------------------------------------------------------- the kernel
def _spin_within(w):
    """Whether the spin (components w) is within the kernel's share of the ordinary step's limit."""
    return (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) < (_LIMIT_FRACTION * MAX_SPIN) ** 2


def _stop_reach(radius):
    """How far beyond a step's chord the stop test looks for the table and the rackets' boxes [m]."""
    return radius + ev.SWEEP_MARGIN + SLACK


def _stop_test(radius, length, width, floor_z, boxes):
    """flagged(p0, p1, v1, w1=None): a superset of the reference step's flags (table, floor, net,
    rackets, leaving play, validity) for the step that takes a ball from p0 to (p1, v1) (and spin
    w1, when it changes in flight), each a tuple of x, y, z components (scalars or rows).

    Arguments:
        radius, length, width, floor_z: the ball's radius and the table's size and floor height;
        boxes: [(lower corner, upper corner)] of the rackets' swept boxes (:func:`racket_boxes`),
            each corner a tuple of 3 components.
    """
    def meets(p0, p1, lo, hi, reach):
        """The box swept by the chord p0 -> p1, widened by ``reach``, meets the box [lo, hi]."""
        out = None
        for i in range(3):
            m = (jnp.minimum(p0[i], p1[i]) - reach <= hi[i]) & (jnp.maximum(p0[i], p1[i]) + reach >= lo[i])
            out = m if out is None else out & m
        return out

    table_lo = (-0.5 * length, -0.5 * width, -table_stage.THICKNESS)
    table_hi = (0.5 * length, 0.5 * width, 0.0)
    reach = _stop_reach(radius)
    box = [b - SLACK for b in ev.PLAY_BOX]
    max_v2 = (_LIMIT_FRACTION * MAX_SPEED) ** 2

    def flagged(p0, p1, v1, w1=None):
        flag = meets(p0, p1, table_lo, table_hi, reach)
        flag |= p1[2] - radius - floor_z < SLACK
        flag |= (p0[0] * p1[0] <= 0.0) | (jnp.abs(p1[0]) < SLACK)
        for lo, hi in boxes:
            flag |= meets(p0, p1, lo, hi, reach)
        for i in range(3):
            flag |= jnp.abs(p1[i]) > box[i]
        finite = None
        for c in (*p1, *v1, *(w1 or ())):
            f = jnp.isfinite(c)
            finite = f if finite is None else finite & f
        ok = finite & ((v1[0] * v1[0] + v1[1] * v1[1] + v1[2] * v1[2]) < max_v2)
        if w1 is not None:
            ok &= _spin_within(w1)
        return flag | ~ok

    return flagged


class Hooks:
    """The effects' hooks that follow a ball's state and time in flight (``air_velocity``,
    ``spin_derivative``), for the kernel's body on a CPU: each evaluated for every ball at once on
    the kernel's (B,) columns, with the effects' per-ball parameters.

    Arguments:
        effects: the model's effects; axes: their per-ball axes (pytree prefix of 0 / None);
        k: (B,) each ball's step count at the launch, t0, dt: the clock (a ball that has taken n
            sub-steps is at t0 + (k + n) dt, the reference path's time of that step).
    """

    def __init__(self, effects, axes, k, t0, dt):
        self.effects, self.axes, self.k, self.t0, self.dt = effects, axes, k, t0, dt
        self.air = any(hasattr(e, "air_velocity") for e in effects)
        self.spin = any(hasattr(e, "spin_derivative") for e in effects)

    def rows(self, idx):
        """The hooks of the balls ``idx`` (rows past the end read the last ball's)."""
        rows = jnp.minimum(idx, self.k.shape[0] - 1)
        return Hooks(take_rows(self.effects, self.axes, rows), self.axes, self.k[rows], self.t0, self.dt)

    def time(self, n):
        """(B,) the time of each ball after n (B,) sub-steps."""
        return self.t0 + (self.k + n).astype(jnp.result_type(self.dt)) * self.dt

    def _columns(self, hook, t, **state):
        def one(effects, t, **state):  # every hook here has a 3-vector's neutral value
            return hooks.apply(effects, hook, jnp.zeros_like(next(iter(state.values()))), t=t, **state)

        # components as rows (3, B), in and out: (B, 3) made every use a strided pass of its own
        stacked = {name: jnp.stack(cols) for name, cols in state.items()}
        out = jax.vmap(lambda fx, t, st: one(fx, t, **st), in_axes=(self.axes, 0, 1), out_axes=1)(
            self.effects, t, stacked)
        return out[0], out[1], out[2]

    def air_velocity(self, p, t):
        return self._columns("air_velocity", t, pos=p)

    def spin_derivative(self, v, w, t):
        return self._columns("spin_derivative", t, vel=v, spin=w)


def _kernel(layout: Layout, substeps: int, p_ref, *refs, hooks: Hooks | None = None):
    """One block of balls: up to ``substeps`` RK4 steps each, stopping before a flagged step.

    Refs: 9 state components (pos, vel, spin x, y, z) and the steps each ball may take, then
    the same 9 components out and the steps taken. ``hooks``: the effects acting on the moving
    ball (:class:`Hooks`; only where the body runs as plain XLA), or None.
    """
    ins, outs = refs[:10], refs[10:]
    rd = Reader(p_ref, layout)
    dt, radius, ratio, nu, buoyancy = rd.many(5)
    gx, gy, gz = rd.many(3)
    length, width, floor_z = rd.many(3)
    drag, magnus = coefficient_fns(rd, layout, radius, nu)
    boxes = [(rd.many(3), rd.many(3)) for _ in range(layout.n_rackets)]
    kd = -(3.0 / (8.0 * radius)) * ratio
    buoy = 1.0 - buoyancy * ratio
    grav = (buoy * gx, buoy * gy, buoy * gz)
    dtype = dt.dtype

    state = tuple(r[...] for r in ins[:9])
    budget = ins[9][...]
    air = hooks is not None and hooks.air
    turning = hooks is not None and hooks.spin  # else the spin is constant in flight
    fixed_rate = None if turning else component_norm(*state[6:9])

    def accel(p, v, w, t):
        if air:  # drag and Magnus act on the velocity relative to the air
            wind = hooks.air_velocity(p, t)
            v = tuple(v[i] - wind[i] for i in range(3))
        speed = component_norm(*v)
        spin_rate = component_norm(*w) if turning else fixed_rate
        cd, cm = drag(speed, spin_rate), magnus(speed, spin_rate)
        c = kd * cd * speed
        cross = (w[1] * v[2] - w[2] * v[1], w[2] * v[0] - w[0] * v[2], w[0] * v[1] - w[1] * v[0])
        return tuple(c * v[i] + cm * ratio * cross[i] + grav[i] for i in range(3))

    def deriv(p, v, w, t):
        """(acceleration, d(spin)/dt or None) at one RK4 stage."""
        return accel(p, v, w, t), (hooks.spin_derivative(v, w, t) if turning else None)

    def rk4(p, v, w, n):
        t = hooks.time(n) if hooks is not None else None
        th, t1 = (None, None) if t is None else (t + 0.5 * dt, t + dt)
        axpy = lambda h, x, y: tuple(y[i] + h * x[i] for i in range(3))  # noqa: E731
        a1, d1 = deriv(p, v, w, t)
        # the stages' positions matter to the air's velocity only; the spin's to a turning ball only
        stage = lambda h, k, y: axpy(h, k, y) if k is not None else y  # noqa: E731
        p2, v2, w2 = stage(0.5 * dt, v if air else None, p), axpy(0.5 * dt, a1, v), stage(0.5 * dt, d1, w)
        a2, d2 = deriv(p2, v2, w2, th)
        p3, v3, w3 = stage(0.5 * dt, v2 if air else None, p), axpy(0.5 * dt, a2, v), stage(0.5 * dt, d2, w)
        a3, d3 = deriv(p3, v3, w3, th)
        p4, v4, w4 = stage(dt, v3 if air else None, p), axpy(dt, a3, v), stage(dt, d3, w)
        a4, d4 = deriv(p4, v4, w4, t1)
        avg = lambda y, k1, k2, k3, k4: tuple(y[i] + dt / 6.0 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i])  # noqa: E731
                                              for i in range(3))
        return avg(p, v, v2, v3, v4), avg(v, a1, a2, a3, a4), (avg(w, d1, d2, d3, d4) if turning else w)

    w0 = state[6:9]
    # a constant spin near the limit: the ball takes no step at all (a turning one is tested each step)
    spin_ok = True if turning else _spin_within(w0)
    flagged = _stop_test(radius, length, width, floor_z, boxes)

    def cond(carry):
        j, active = carry[0], carry[2]
        return (j < substeps) & (jnp.max(active.astype(jnp.int32)) > 0)

    def body(carry):
        j, n, active, p, v, w = carry
        p1, v1, w1 = rk4(p, v, w, n)
        go = active & ~flagged(p, p1, v1, w1 if turning else None)
        keep = lambda new, old: tuple(jnp.where(go, a, b) for a, b in zip(new, old))  # noqa: E731
        p, v = keep(p1, p), keep(v1, v)
        w = keep(w1, w) if turning else w
        n = n + go.astype(jnp.int32)
        return j + 1, n, go & (n < budget), p, v, w

    zero = jnp.zeros_like(budget)
    init = (jnp.int32(0), zero, (budget > 0) & spin_ok, state[0:3], state[3:6], w0)
    _, n, _, p, v, w = jax.lax.while_loop(cond, body, init)
    for ref, val in zip(outs, (*p, *v, *w)):
        ref[...] = val.astype(dtype)
    outs[9][...] = n


def fly(params, layout: Layout, ball, budget, *, substeps: int = SUBSTEPS, block: int = BLOCK,
        interpret: bool | None = None, hooks: Hooks | None = None):
    """Flies every ball up to ``min(substeps, budget)`` free-flight steps, stopping before a step in
    which something may happen to it.

    Arguments:
        params, layout: from :func:`pack`; ball: :class:`~ttsim_jax.state.Ball` (B, 3) fields;
        budget: (B,) int32 steps each ball may take (0: it stays where it is).
        substeps: most steps per launch; block: balls per Pallas program (a power of two);
        interpret: None (default): the Triton kernel on a GPU, elsewhere the kernel's body as plain
            XLA over the balls that move (:func:`_fly_moving`); True: Pallas in interpret mode
            (a check of the kernel as Pallas runs it, slow); False: the Pallas kernel compiled.
        hooks: the effects acting on the moving ball (:class:`Hooks`), or None; only without Pallas.

    Returns:
        (ball after the steps, (B,) int32 steps taken).
    """
    if interpret is None and jax.default_backend() != "gpu":
        return _fly_moving(params, layout, ball, budget, substeps=substeps, hooks=hooks)
    if hooks is not None:
        raise ValueError("fly: the Pallas kernel has no hooks (effects acting in flight run the body as plain XLA)")
    from jax.experimental import pallas as pl

    b = budget.shape[0]
    interpret = bool(interpret)
    block = min(block, 1 << max(0, (b - 1).bit_length()))
    n_blocks = -(-b // block)
    pad = n_blocks * block - b
    cols = _columns(ball, budget)
    cols = [jnp.pad(c, (0, pad), mode="edge") for c in cols[:9]] + [jnp.pad(cols[9], (0, pad))]
    dtype = ball.pos.dtype
    lanes = pl.BlockSpec((block,), lambda i: (i,))
    whole = pl.BlockSpec((layout.size,), lambda i: (0,))
    inputs, specs = [params], [whole]
    if layout.rows:  # per-ball parameters: the shared vector, then a block of their rows per program
        vector, matrix = params
        inputs = [vector, jnp.pad(matrix, ((0, 0), (0, pad)), mode="edge")]
        specs = [whole, pl.BlockSpec((matrix.shape[0], block), lambda i: (0, i))]
    out_shape = [jax.ShapeDtypeStruct((b + pad,), dtype)] * 9 + [jax.ShapeDtypeStruct((b + pad,), jnp.int32)]
    extra = {}
    if not interpret:  # Triton (the GPU default may be another Pallas backend)
        from jax.experimental.pallas import triton as plt
        params_cls = getattr(plt, "CompilerParams", None) or getattr(plt, "TritonCompilerParams")
        extra["compiler_params"] = params_cls(num_warps=4)

    def body(*refs):
        n = len(specs)  # with per-ball rows, (vector, rows) as pack gives them: fused_params.Reader indexes it
        return _kernel(layout, substeps, refs[0] if n == 1 else refs[:n], *refs[n:])

    out = pl.pallas_call(
        body, out_shape=out_shape, grid=(n_blocks,), in_specs=specs + [lanes] * 10, out_specs=[lanes] * 10,
        interpret=interpret, name="fused_flight", **extra)(*inputs, *cols)
    return _from_columns(ball, [a[:b] for a in out])


def _columns(ball, budget) -> list:
    """The kernel's 10 inputs: pos, vel, spin x, y, z as (B,) columns, then the int32 budget."""
    return [a[:, i] for a in (ball.pos, ball.vel, ball.spin) for i in range(3)] + [budget.astype(jnp.int32)]


def _from_columns(ball, out):
    """(ball of ``ball``'s type, steps taken) from the kernel's 10 output columns."""
    stack = lambda cs: jnp.stack(cs, axis=-1)  # noqa: E731
    return type(ball)(stack(out[0:3]), stack(out[3:6]), stack(out[6:9])), out[9]


class _Slot:
    """A stand-in for a Pallas ref that holds one whole array (the kernel's body run as plain XLA)."""

    def __init__(self, value=None):
        self.value = value

    def __getitem__(self, index):
        return self.value if index is Ellipsis else self.value[index]

    def __setitem__(self, index, value):
        self.value = value


def _fly_xla(params, layout: Layout, ball, budget, *, substeps: int, hooks: Hooks | None = None):
    """:func:`fly` without Pallas: the kernel's body over all the given balls at once. XLA compiles
    a sub-step into one loop over the balls (measured on a CPU at 65,536 balls: as fast as the
    lean hand-written loop on one core; blocks of 256-4,096 balls ran 1.5-2.4x slower)."""
    outs = [_Slot() for _ in range(10)]
    _kernel(layout, substeps, _Slot(params), *[_Slot(c) for c in _columns(ball, budget)], *outs, hooks=hooks)
    return _from_columns(ball, [o.value for o in outs])


#: Fractions of the batch into which :func:`_fly_moving` gathers the balls that move.
GATHER_FRACTIONS = (64, 8)


def _fly_moving(params, layout: Layout, ball, budget, *, substeps: int, hooks: Hooks | None = None):
    """:func:`_fly_xla` over the balls that move only, gathered into the smallest of B / 64, B / 8
    and B rows that holds them. A ball stopped for an event falls behind the others by the rest of
    that launch, so the last launches of a rollout move few balls; without the gather each costs
    a whole batch's sub-steps."""
    b = budget.shape[0]
    sizes = [b // f for f in GATHER_FRACTIONS if b // f >= 8]  # (the equality tests' 64 balls gather into 8)
    moving = budget > 0

    def gathered(size):
        def run():
            (idx,) = jnp.nonzero(moving, size=size, fill_value=b)  # b: past the end, dropped below
            sub = jax.tree.map(lambda a: a.at[idx].get(mode="fill", fill_value=0), ball)
            # per-ball parameters follow their balls (the padding rows, which do not fly, read the last ball's)
            p = params if layout.rows == () else (params[0], params[1].at[:, idx].get(mode="clip"))
            out, n = _fly_xla(p, layout, sub, budget.at[idx].get(mode="fill", fill_value=0), substeps=substeps,
                              hooks=None if hooks is None else hooks.rows(idx))
            put = lambda a, v: a.at[idx].set(v, mode="drop")  # noqa: E731
            return jax.tree.map(put, ball, out), put(jnp.zeros_like(budget), n)
        return run

    branches = [gathered(s) for s in sizes] + [
        lambda: _fly_xla(params, layout, ball, budget, substeps=substeps, hooks=hooks)]
    if len(branches) == 1:
        return branches[0]()
    count = jnp.sum(moving.astype(jnp.int32))
    return jax.lax.switch(sum((count > s).astype(jnp.int32) for s in sizes), branches)


# --------------------------------------------------------------------------- the rollout's loop
def racket_boxes(pos, vel, face, rows, dt, radius):
    """(R, 2, 3) boxes that hold the centre of every ball touching a racket in the schedule's rows;
    (B, R, 2, 3) for a schedule per ball.

    Arguments:
        pos, vel, face: a :class:`~ttsim_jax.state.Racket` schedule's fields, (T, R, ...), or
            (T, B, R, ...) per ball; rows: (T,) bool, the steps the kernel may fly through, or
            (T, B) per ball; dt: step [s]; radius: ball radius [m].

    Returns:
        Per racket, the corners of the box its face spans over those steps
        (:func:`~ttsim_jax.kernel.plans.face_boxes`) widened by :func:`_widen`; an empty box (lower
        corner +inf) when no row is selected.
    """
    inf = jnp.asarray(jnp.inf, pos.dtype)
    faces = face_boxes(pos, vel, face, dt)
    sel = rows[..., None, None]
    lo = jnp.min(jnp.where(sel, faces[..., 0, :], inf), axis=0)
    hi = jnp.max(jnp.where(sel, faces[..., 1, :], -inf), axis=0)
    return _widen(jnp.stack([lo, hi], axis=-2), radius)


def _widen(boxes, radius):
    """Boxes that hold a racket's face widened to hold the centre of every ball touching it (a
    radius, and ``SWEEP_MARGIN`` for the path's bow off its chord)."""
    reach = radius + ev.SWEEP_MARGIN
    return boxes + jnp.stack([-reach, reach]).astype(boxes.dtype)[:, None]


def _in_boxes(pos, boxes, reach):
    """(B,) whether each ball's centre ``pos`` (B, 3) lies within ``reach`` of a box of ``boxes``
    ((R, 2, 3) shared or (B, R, 2, 3) per ball): where the kernel's stop test flags its next step
    whatever that step is."""
    lo, hi = boxes[..., 0, :] - reach, boxes[..., 1, :] + reach
    if boxes.ndim == 3:
        lo, hi = lo[None], hi[None]
    p = pos[:, None, :]
    return jnp.any(jnp.all((p >= lo) & (p <= hi), axis=-1), axis=-1)


def _own_rows(schedule, kb, end, step0, substeps: int):
    """Each ball's next ``substeps`` rows of a per-ball (T, B, R, ...) schedule: (pos, vel, face) as
    (substeps, B, R, ...) and which rows come before ``end``, :func:`racket_boxes`'s arguments.
    O(B substeps) per launch, where selecting them among all T rows cost O(B T) (a 300-step
    rollout ran 17x slower)."""
    steps = kb[None] + jnp.arange(substeps)[:, None]  # (substeps, B)
    row = jnp.clip(steps - step0, 0, schedule.pos.shape[0] - 1)
    col = jnp.arange(kb.shape[0])[None]
    return schedule.pos[row, col], schedule.vel[row, col], schedule.face[row, col], steps < end


@struct.dataclass
class Drive:
    """What moves the balls of a fused advance beside the model: the rackets and the clock.

    Attributes:
        schedule: the rackets' (T, R, ...) schedule from step ``step0`` on ((T, B, R, ...) with
            ``rackets_batched``: one per ball, each ball's kernel stop tested against its own
            rackets' boxes), or None.
        policy: a :class:`~ttsim_jax.kernel.plans.RacketPolicy` with a ``reach`` (in place of a
            schedule), or None: the kernel stops a ball before its path meets a box of the reach;
            the ordinary step evaluates the policy for each ball at its own time, and a ball whose
            rackets lie outside the reach there ends ``INVALID``.
        t0, dt, step0: the clock: the time of step k is t0 + k dt, the schedule's first row is step ``step0``.
        key: the rollout's PRNG key when the residual is sampled, else None: a ball's step k draws
            with ``fold_in(key, k)``, the key the reference path's step k has, so its draws are
            the same whatever the other balls do.
        rackets_batched: (static) the schedule holds one set of rackets per ball.
    """

    schedule: Any = None
    policy: Any = None
    t0: Any = 0.0
    dt: Any = 1e-3
    step0: Any = 0
    key: Any = None
    rackets_batched: bool = struct.field(pytree_node=False, default=False)


@dataclasses.dataclass(frozen=True)
class Launch:
    """How the kernel is launched (same results): ``substeps`` steps flown per launch at most,
    ``block`` balls per program, ``interpret`` (None: on a CPU) Pallas's interpreter."""

    substeps: int = SUBSTEPS
    block: int = BLOCK
    interpret: bool | None = None


def advance(model, axes, state: StepState, ball_id, k, length: int, drive: Drive, stepper, *,
            launch: Launch = Launch()) -> StepState:
    """Advances every ball from step ``k`` to ``k + length`` on the fused path.

    Each ball keeps its own step count: the kernel (:func:`fly`) flies it up to its next possible
    event, then ``stepper`` (the ordinary step, with per-ball times and rackets) takes that step,
    until every ball has arrived.

    Arguments:
        model, axes: the model and its per-ball axes; state, ball_id: the batch as in
            :func:`~ttsim_jax.kernel.step.step`; k: () step count of every ball;
            length: steps to take (static); drive: the rackets and the clock (:class:`Drive`);
            stepper: ``step`` with its static options bound; launch: :class:`Launch`.

    Returns:
        The :class:`~ttsim_jax.kernel.step.StepState` at step ``k + length``.
    """
    ball, alive, status, log = state.ball, state.alive, state.status, state.log
    schedule, policy, rackets_batched, key = drive.schedule, drive.policy, drive.rackets_batched, drive.key
    t0, dt, step0 = drive.t0, drive.dt, drive.step0
    substeps, block, interpret = launch.substeps, launch.block, launch.interpret
    dtype = ball.pos.dtype
    end = k + length
    phys_axes = axes.replace(residual=None)
    # per ball or not, after effects: the largest widens the racket boxes most
    radius = jnp.max(hooked_properties(model, axes)[0][0])
    moving_hooks = in_flight(model, STATE_HOOKS)
    last_row = None if schedule is None else schedule.pos.shape[0] - 1
    reach = None
    if policy is not None:
        reach = jnp.asarray(policy.reach(policy.params, dt), dtype)
        policy_boxes = _widen(reach, radius)

    def body(carry):
        ball, alive, status, log, kb = carry
        boxes = None if policy is None else policy_boxes
        if schedule is not None:
            if rackets_batched:  # each ball's own next rows, its own boxes
                boxes = racket_boxes(*_own_rows(schedule, kb, end, step0, substeps), dt, radius)
            else:
                rows = jnp.arange(schedule.pos.shape[0]) + step0
                moving = kb < end
                lo = jnp.min(kb)
                hi = jnp.minimum(jnp.max(jnp.where(moving, kb, lo)) + substeps, end)
                boxes = racket_boxes(schedule.pos, schedule.vel, schedule.face, (rows >= lo) & (rows < hi), dt,
                                     radius)
        params, layout = pack(model, dt, boxes, dtype, axes)
        hooks = Hooks(model.effects, phys_axes.effects, kb, t0, dt) if moving_hooks else None
        budget = end - kb
        if boxes is not None:  # a ball already by a racket would stop at once: it joins no launch
            budget = jnp.where(_in_boxes(ball.pos, boxes, _stop_reach(radius)), 0, budget)
        ball, n = fly(params, layout, ball, budget, substeps=substeps, block=block, interpret=interpret, hooks=hooks)
        kb = kb + n
        on = kb < end
        t = t0 + kb.astype(dtype) * dt
        rackets, ok = None, jnp.ones_like(alive)
        if policy is not None:  # each ball's rackets at its own time, as the reference step k has them
            rackets = jax.vmap(policy.fn, in_axes=(None, 0, 0))(policy.params, ball, t)
            rackets = jax.tree.map(lambda a: a.astype(dtype), rackets)
            # the promise the kernel flew by; SLACK: the stop test's margin beyond the boxes
            ok = within_reach(rackets, reach, dt, tol=SLACK)
        elif schedule is not None:
            row = jnp.clip(kb - step0, 0, last_row)
            if rackets_batched:
                rackets = jax.tree.map(lambda a: a[row, jnp.arange(row.shape[0])], schedule)
            else:
                rackets = jax.tree.map(lambda a: a[row], schedule)
        keys = None if key is None else jax.vmap(lambda kk: jax.random.fold_in(key, kk))(kb)
        new = stepper(model, axes, StepState(ball, alive & on & ok, status, log), ball_id, rackets, t, dt,
                      rackets_batched=rackets is not None, key=keys)
        ball, alive_new, status, log = new.ball, new.alive, new.status, new.log
        broken = alive & on & ~ok
        alive = jnp.where(on, alive_new, alive) & ~broken
        status = jnp.where(broken, ev.INVALID, status)
        return ball, alive, status, log, jnp.where(on & alive, kb + 1, end)

    kb = jnp.where(alive, k, end)
    carry = jax.lax.while_loop(lambda c: jnp.any(c[4] < end), body, (ball, alive, status, log, kb))
    return StepState(*carry[:4])
