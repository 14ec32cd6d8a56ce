"""The fused flight path: many free-flight steps per kernel launch, contacts left to the step.

On a GPU the rally kernel's step is launch-bound: a 1 ms step is hundreds of small kernels, most
of them for the few balls that have a contact. Here one Pallas kernel (``jax.experimental.pallas``,
Triton) flies a block of balls through up to ``substeps`` RK4 steps with the state kept in
registers; on a CPU the same body runs as plain XLA over the whole batch, where a sub-step
compiles to one loop over the balls (:func:`_fly_moving`, which also gathers the few balls still
moving in a rollout's last launches). It stops each ball before the first step in which
anything *may* happen to it: a conservative version of :func:`~ttsim_jax.kernel.step.may_have_event`
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
table), no effect acting on the ball's flight or on the table's surface, ball / aero / table
parameters shared by all balls or (on a CPU) per ball, rackets as a schedule shared by all balls
or (on a CPU) one per ball (or none), and no sampled residual. The coefficient tables are passed
to the kernel as one small vector of scalars and interpolated with the same ramps as
``aero._piecewise`` (arithmetic, no gather).

Reverse mode never sees the kernel: the fused rollout is a ``jax.custom_jvp`` whose derivative is
the reference path's, so ``jax.grad`` through ``rollout(..., fused=True)`` differentiates the
reference path (with its rematerialisation).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from ttsim_jax.physics import aero as aero_stage
from ttsim_jax.physics import events as ev
from ttsim_jax.physics import table as table_stage
from ttsim_jax.kernel.step import MAX_SPEED, MAX_SPIN
from ttsim_jax.physics.numerics import component_norm

# Free-flight steps per kernel launch (a ball flies about 100-300 steps between contacts).
SUBSTEPS = 32
# Balls per kernel program (a power of two, as Triton needs): one per thread of 4 warps.
BLOCK = 128
# Margin [m] added to every stopping test, far above the rounding by which the kernel's path
# differs from the reference path's, so that the kernel never flies through a step the reference
# would flag; a ball stopped early only costs one ordinary step.
SLACK = 1e-3
# Hooks that would change the flight or the table's outline (the kernel has none of them).
_FLIGHT_HOOKS = ("ball_properties", "air_properties", "air_velocity", "spin_derivative", "table_surface")
# The kernel stops a ball whose speed or spin nears the ordinary step's validity limits.
_LIMIT_FRACTION = 0.99


# --------------------------------------------------------------------------- what it covers
def unsupported(model, axes, *, integrator: str, policy, rackets_batched: bool, sample: bool) -> str | None:
    """Why a rollout cannot take the fused path, or None if it can.

    Arguments:
        model: the model; axes: its per-ball axes (pytree prefix of 0 / None);
        integrator: the flight integrator; policy: the racket policy or None;
        rackets_batched: whether the racket schedule is per ball; sample: sampled residual.
    """
    if integrator != "rk4":
        return f"integrator {integrator!r} (the fused kernel is RK4)"
    if policy is not None:
        return "a racket policy (the fused kernel needs the rackets' schedule to bound where they go)"
    if rackets_batched and jax.default_backend() == "gpu":
        return "a per-ball racket schedule on a GPU (the Triton kernel reads the rackets' boxes as scalars)"
    if sample:
        return "a sampled residual (its draws follow the step count)"
    if type(model.aero.drag) not in _DRAG or type(model.aero.magnus) not in _MAGNUS:
        return f"coefficient models {type(model.aero.drag).__name__}/{type(model.aero.magnus).__name__}"
    hooked = [type(e).__name__ for e in model.effects if any(hasattr(e, h) for h in _FLIGHT_HOOKS)]
    if hooked:
        return f"effects acting on the flight or the table's surface: {hooked}"
    shared = axes.ball, axes.aero, axes.table
    if any(ax is not None for ax in jax.tree.leaves(shared, is_leaf=lambda x: x is None)) and \
            jax.default_backend() == "gpu":
        return "per-ball ball, aero or table parameters on a GPU (the Triton kernel reads them as scalars)"
    return None


# --------------------------------------------------------------------------- parameters as scalars
@dataclass(frozen=True)
class Layout:
    """Where each parameter sits in the kernel's parameter vector (static: the model's structure).

    Attributes:
        drag, magnus: the coefficient model types' names; n_re, n_sp: DragTable sizes;
        n_v: MagnusTable size; n_rackets: racket boxes; size: the vector's length (a power of 2).
    """

    drag: str
    magnus: str
    n_re: int
    n_sp: int
    n_v: int
    n_rackets: int
    size: int


def _drag_leaves(p):
    if isinstance(p, aero_stage.DragTable):
        return [p.re_ref, p.sp, p.cd, p.re_cap, p.cd_min]
    return [p.value]


def _magnus_leaves(p):
    if isinstance(p, aero_stage.MagnusTable):
        return [p.v_ref, p.m1, p.s, p.w_b, p.a, p.b, p.c]
    if isinstance(p, aero_stage.DurrMagnus):
        return [p.gain, p.offset, p.cap]
    return [p.value]


_DRAG = {aero_stage.ConstantCoefficient: "constant", aero_stage.DragTable: "table"}
_MAGNUS = {aero_stage.ConstantCoefficient: "constant", aero_stage.DurrMagnus: "durr", aero_stage.MagnusTable: "table"}


def leaf_axes(model, axes):
    """The model's structure with each leaf's per-ball axis (0 or None)."""
    if axes is None:
        return jax.tree.map(lambda _: None, model)
    return jax.tree.map(lambda a, sub: jax.tree.map(lambda _: a, sub), axes, model, is_leaf=lambda x: x is None)


def _any(*axes):
    """0 where any of the given leaves is per ball (a value computed from them is), else None."""
    return 0 if any(a == 0 for a in axes) else None


def pack(model, dt, racket_boxes, dtype, axes=None):
    """The kernel's parameters as one vector (or one column per ball) and its :class:`Layout`.

    Arguments:
        model: the model; dt: the step [s];
        racket_boxes: (R, 2, 3) lower and upper corners of the boxes the rackets' centres sweep,
            widened by the face, (B, R, 2, 3) one set per ball (then the result has a column per
            ball), or None; dtype: the simulation's float dtype;
        axes: the model's per-ball axes (pytree prefix of 0 / None) or None (all shared).

    Returns:
        (params, layout): params (size,) where every parameter is shared, else (size, B), one
        column per ball (the kernel then reads a row of B values where it reads a scalar; only
        :func:`_fly_xla` runs that form).
    """
    ax = leaf_axes(model, axes)
    radius, mass = model.ball.radius, model.ball.mass
    volume = (4.0 / 3.0) * jnp.pi * radius**3
    ratio = model.aero.rho_air * volume / mass
    t, a, tx, aa = model.table, model.aero, ax.table, ax.aero
    parts = [dt, radius, ratio, a.nu, a.buoyancy, a.gravity, t.length, t.width, t.floor_z]
    per_ball = [None, ax.ball.radius, _any(aa.rho_air, ax.ball.radius, ax.ball.mass), aa.nu, aa.buoyancy, aa.gravity,
                tx.length, tx.width, tx.floor_z]
    drag, magnus = a.drag, a.magnus
    parts += _drag_leaves(drag) + _magnus_leaves(magnus)
    per_ball += _drag_leaves(aa.drag) + _magnus_leaves(aa.magnus)
    if racket_boxes is not None:
        parts.append(racket_boxes)
        per_ball.append(0 if racket_boxes.ndim == 4 else None)
    batched = [p for p, b in zip(parts, per_ball) if b == 0]
    if batched:
        n = jnp.shape(batched[0])[0]
        # a per-ball leaf (B, ...) gives one row per ball; a shared one is repeated for every ball
        rows = [jnp.reshape(jnp.asarray(p, dtype), (n, -1)) if b == 0
                else jnp.broadcast_to(jnp.ravel(jnp.asarray(p, dtype)), (n, jnp.size(p))) for p, b in zip(parts, per_ball)]
        flat = jnp.concatenate(rows, axis=1).T
    else:
        flat = jnp.concatenate([jnp.ravel(jnp.asarray(p, dtype)) for p in parts])
    size = 1 << max(0, int(flat.shape[0] - 1).bit_length())
    last = lambda a: a.shape[-1]  # noqa: E731 (a per-ball table has the batch first)
    layout = Layout(drag=_DRAG[type(drag)], magnus=_MAGNUS[type(magnus)],
                    n_re=last(drag.re_ref) if isinstance(drag, aero_stage.DragTable) else 0,
                    n_sp=last(drag.sp) if isinstance(drag, aero_stage.DragTable) else 0,
                    n_v=last(magnus.v_ref) if isinstance(magnus, aero_stage.MagnusTable) else 0,
                    n_rackets=0 if racket_boxes is None else racket_boxes.shape[-3], size=size)
    return jnp.pad(flat, [(0, size - flat.shape[0])] + [(0, 0)] * (flat.ndim - 1)), layout


class _Reader:
    """Reads the parameter vector in :func:`pack`'s order, one scalar at a time (scalar loads)."""

    def __init__(self, ref):
        self.ref, self.at = ref, 0

    def scalar(self):
        self.at += 1
        return self.ref[self.at - 1]

    def many(self, n):
        return [self.scalar() for _ in range(n)]


def _ramps(xp, last=1.0):
    """(start, 1 / width, upper clip) of each ramp of ``aero._ramps`` over breakpoints ``xp`` (a list
    of scalars), computed once per launch so that the steps multiply instead of divide."""
    return [(xp[k - 1], 1.0 / (xp[k] - xp[k - 1]), last if k == len(xp) - 1 else 1.0) for k in range(1, len(xp))]


def _weights(x, ramps):
    """The ramp weights s_k(x) of ``aero._ramps`` over :func:`_ramps`."""
    return [jnp.clip((x - start) * inv, 0.0, upper) for start, inv, upper in ramps]


def _ramp_sum(weights, fp):
    """fp[0] + sum_k (fp[k] - fp[k-1]) s_k: ``aero._piecewise`` unrolled."""
    out = fp[0]
    for k, s in enumerate(weights, start=1):
        out = out + (fp[k] - fp[k - 1]) * s
    return out


def _coefficient_fns(rd: _Reader, layout: Layout, radius, nu):
    """(drag(speed, spin_rate), magnus(speed, spin_rate)) read from the parameter vector."""
    if layout.drag == "table":
        re_ref = rd.many(layout.n_re)
        sp = [rd.many(layout.n_sp) for _ in range(layout.n_re)]
        cd = [rd.many(layout.n_sp) for _ in range(layout.n_re)]
        re_cap, cd_min = rd.scalar(), rd.scalar()
        re_ramps = _ramps(re_ref, (re_cap - re_ref[-2]) / (re_ref[-1] - re_ref[-2]))
        sp_ramps = [_ramps(row) for row in sp]
        re_per_speed = 2.0 * radius / nu

        def drag(speed, spin_rate):
            ratio = spin_rate * radius / jnp.maximum(speed, 1e-6)
            curves = [_ramp_sum(_weights(ratio, sp_ramps[k]), cd[k]) for k in range(layout.n_re)]
            return jnp.maximum(_ramp_sum(_weights(speed * re_per_speed, re_ramps), curves), cd_min)
    else:
        value = rd.scalar()

        def drag(speed, spin_rate):
            return value

    if layout.magnus == "table":
        v_ramps = _ramps(rd.many(layout.n_v))
        coef = [rd.many(layout.n_v) for _ in range(6)]  # m1, s, w_b, a, b, c

        def magnus(speed, spin_rate):
            weights = _weights(speed, v_ramps)
            m1, s, w_b, a, b, c = (_ramp_sum(weights, col) for col in coef)
            w = spin_rate
            return jnp.maximum(jnp.where(w <= w_b, m1 * w + s, (a * w + b) * w + c), 0.0)
    elif layout.magnus == "durr":
        gain, offset, cap = rd.many(3)

        def magnus(speed, spin_rate):
            return jnp.minimum(gain * speed / jnp.maximum(spin_rate * radius, 1e-9) - offset, cap)
    else:
        value = rd.scalar()

        def magnus(speed, spin_rate):
            return value

    return drag, magnus


# --------------------------------------------------------------------------- the kernel
def _kernel(layout: Layout, substeps: int, p_ref, *refs):
    """One block of balls: up to ``substeps`` RK4 steps each, stopping before a flagged step.

    Refs: 9 state components (pos, vel, spin x, y, z) and the steps each ball may take, then
    the same 9 components out and the steps taken.
    """
    ins, outs = refs[:10], refs[10:]
    rd = _Reader(p_ref)
    dt, radius, ratio, nu, buoyancy = rd.many(5)
    gx, gy, gz = rd.many(3)
    length, width, floor_z = rd.many(3)
    drag, magnus = _coefficient_fns(rd, layout, radius, nu)
    boxes = [(rd.many(3), rd.many(3)) for _ in range(layout.n_rackets)]
    kd = -(3.0 / (8.0 * radius)) * ratio
    buoy = 1.0 - buoyancy * ratio
    grav = (buoy * gx, buoy * gy, buoy * gz)
    dtype = dt.dtype

    state = tuple(r[...] for r in ins[:9])
    budget = ins[9][...]
    w = state[6:9]
    spin_rate = component_norm(*w)

    def accel(v):
        speed = component_norm(*v)
        cd, cm = drag(speed, spin_rate), magnus(speed, spin_rate)
        c = kd * cd * speed
        cross = (w[1] * v[2] - w[2] * v[1], w[2] * v[0] - w[0] * v[2], w[0] * v[1] - w[1] * v[0])
        return tuple(c * v[i] + cm * ratio * cross[i] + grav[i] for i in range(3))

    def rk4(p, v):
        # spin is constant in flight here (no effect defines spin_derivative)
        a1 = accel(v)
        v2 = tuple(v[i] + 0.5 * dt * a1[i] for i in range(3))
        a2 = accel(v2)
        v3 = tuple(v[i] + 0.5 * dt * a2[i] for i in range(3))
        a3 = accel(v3)
        v4 = tuple(v[i] + dt * a3[i] for i in range(3))
        a4 = accel(v4)
        p1 = tuple(p[i] + dt / 6.0 * (v[i] + 2 * v2[i] + 2 * v3[i] + v4[i]) for i in range(3))
        v1 = tuple(v[i] + dt / 6.0 * (a1[i] + 2 * a2[i] + 2 * a3[i] + a4[i]) for i in range(3))
        return p1, v1

    def meets(p0, p1, lo, hi, reach):
        """The box swept by the chord p0 -> p1, widened by ``reach``, meets the box [lo, hi]."""
        out = None
        for i in range(3):
            m = (jnp.minimum(p0[i], p1[i]) - reach <= hi[i]) & (jnp.maximum(p0[i], p1[i]) + reach >= lo[i])
            out = m if out is None else out & m
        return out

    table_lo = (-0.5 * length, -0.5 * width, -table_stage.THICKNESS)
    table_hi = (0.5 * length, 0.5 * width, 0.0)
    reach = radius + ev.SWEEP_MARGIN + SLACK
    box = [b - SLACK for b in ev.PLAY_BOX]
    max_v2 = (_LIMIT_FRACTION * MAX_SPEED) ** 2
    max_w2 = (_LIMIT_FRACTION * MAX_SPIN) ** 2
    spin_ok = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) < max_w2

    def flagged(p0, p1, v1):
        """A superset of the reference step's flags (table, floor, net, rackets, play, validity)."""
        flag = meets(p0, p1, table_lo, table_hi, reach)
        flag |= p1[2] - radius - floor_z < SLACK
        flag |= (p0[0] * p1[0] <= 0.0) | (jnp.abs(p1[0]) < SLACK)
        for lo, hi in boxes:
            flag |= meets(p0, p1, lo, hi, reach)
        for i in range(3):
            flag |= jnp.abs(p1[i]) > box[i]
        finite = None
        for c in (*p1, *v1):
            f = jnp.isfinite(c)
            finite = f if finite is None else finite & f
        speed_ok = (v1[0] * v1[0] + v1[1] * v1[1] + v1[2] * v1[2]) < max_v2
        return flag | ~(finite & speed_ok & spin_ok)

    def cond(carry):
        j, active = carry[0], carry[2]
        return (j < substeps) & (jnp.max(active.astype(jnp.int32)) > 0)

    def body(carry):
        j, n, active, p, v = carry
        p1, v1 = rk4(p, v)
        go = active & ~flagged(p, p1, v1)
        p = tuple(jnp.where(go, a, b) for a, b in zip(p1, p))
        v = tuple(jnp.where(go, a, b) for a, b in zip(v1, v))
        n = n + go.astype(jnp.int32)
        return j + 1, n, go & (n < budget), p, v

    zero = jnp.zeros_like(budget)
    _, n, _, p, v = jax.lax.while_loop(cond, body, (jnp.int32(0), zero, budget > 0, state[0:3], state[3:6]))
    for ref, val in zip(outs, (*p, *v, *w)):
        ref[...] = val.astype(dtype)
    outs[9][...] = n


def fly(params, layout: Layout, ball, budget, *, substeps: int = SUBSTEPS, block: int = BLOCK,
        interpret: bool | None = None):
    """Flies every ball up to ``min(substeps, budget)`` free-flight steps, stopping before a step in
    which something may happen to it.

    Arguments:
        params, layout: from :func:`pack`; ball: :class:`~ttsim_jax.state.Ball` (B, 3) fields;
        budget: (B,) int32 steps each ball may take (0: it stays where it is).
        substeps: most steps per launch; block: balls per Pallas program (a power of two);
        interpret: None (default): the Triton kernel on a GPU, elsewhere the kernel's body as plain
            XLA over the balls that move (:func:`_fly_moving`); True: Pallas in interpret mode
            (a check of the kernel as Pallas runs it, slow); False: the Pallas kernel compiled.

    Returns:
        (ball after the steps, (B,) int32 steps taken).
    """
    if interpret is None and jax.default_backend() != "gpu":
        return _fly_moving(params, layout, ball, budget, substeps=substeps)
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
    out_shape = [jax.ShapeDtypeStruct((b + pad,), dtype)] * 9 + [jax.ShapeDtypeStruct((b + pad,), jnp.int32)]
    extra = {}
    if not interpret:  # Triton (the GPU default may be another Pallas backend)
        from jax.experimental.pallas import triton as plt
        params_cls = getattr(plt, "CompilerParams", None) or getattr(plt, "TritonCompilerParams")
        extra["compiler_params"] = params_cls(num_warps=4)
    out = pl.pallas_call(
        lambda *refs: _kernel(layout, substeps, *refs), out_shape=out_shape, grid=(n_blocks,),
        in_specs=[whole] + [lanes] * 10, out_specs=[lanes] * 10, interpret=interpret, name="fused_flight",
        **extra)(params, *cols)
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


def _fly_xla(params, layout: Layout, ball, budget, *, substeps: int):
    """:func:`fly` without Pallas: the kernel's body over all the given balls at once. XLA compiles
    a sub-step into one loop over the balls (measured on a CPU at 65,536 balls: as fast as the
    lean hand-written loop on one core; blocks of 256-4,096 balls ran 1.5-2.4x slower)."""
    outs = [_Slot() for _ in range(10)]
    _kernel(layout, substeps, _Slot(params), *[_Slot(c) for c in _columns(ball, budget)], *outs)
    return _from_columns(ball, [o.value for o in outs])


#: Fractions of the batch into which :func:`_fly_moving` gathers the balls that move.
GATHER_FRACTIONS = (64, 8)


def _fly_moving(params, layout: Layout, ball, budget, *, substeps: int):
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
            p = params if params.ndim == 1 else params.at[:, idx].get(mode="clip")
            out, n = _fly_xla(p, layout, sub, budget.at[idx].get(mode="fill", fill_value=0), substeps=substeps)
            put = lambda a, v: a.at[idx].set(v, mode="drop")  # noqa: E731
            return jax.tree.map(put, ball, out), put(jnp.zeros_like(budget), n)
        return run

    branches = [gathered(s) for s in sizes] + [lambda: _fly_xla(params, layout, ball, budget, substeps=substeps)]
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
        Per racket, the corners of the box its centre spans over those steps (start and end of
        each step), widened by its largest face semi-axis, a radius and ``SWEEP_MARGIN``; an empty
        box (lower corner +inf) when no row is selected.
    """
    inf = jnp.asarray(jnp.inf, pos.dtype)
    start, end = pos, pos + dt * vel
    sel = rows[..., None, None]
    lo = jnp.min(jnp.where(sel, jnp.minimum(start, end), inf), axis=0)
    hi = jnp.max(jnp.where(sel, jnp.maximum(start, end), -inf), axis=0)
    reach = (jnp.max(jnp.where(sel, face, 0.0), axis=(0, -1)) + radius + ev.SWEEP_MARGIN)[..., None]
    return jnp.stack([lo - reach, hi + reach], axis=-2)


def _own_rows(schedule, kb, end, step0, substeps: int):
    """Each ball's next ``substeps`` rows of a per-ball (T, B, R, ...) schedule: (pos, vel, face) as
    (substeps, B, R, ...) and which rows come before ``end``, :func:`racket_boxes`'s arguments.
    O(B substeps) per launch, where selecting them among all T rows cost O(B T) (a 300-step
    rollout ran 17x slower)."""
    steps = kb[None] + jnp.arange(substeps)[:, None]  # (substeps, B)
    row = jnp.clip(steps - step0, 0, schedule.pos.shape[0] - 1)
    col = jnp.arange(kb.shape[0])[None]
    return schedule.pos[row, col], schedule.vel[row, col], schedule.face[row, col], steps < end


def advance(model, axes, ball, alive, status, ball_id, log, k, length: int, schedule, step0, t0, dt, stepper, *,
            rackets_batched: bool = False, substeps: int = SUBSTEPS, block: int = BLOCK,
            interpret: bool | None = None):
    """Advances every ball from step ``k`` to ``k + length`` on the fused path.

    Each ball keeps its own step count: the kernel (:func:`fly`) flies it up to its next possible
    event, then ``stepper`` (the ordinary step, with per-ball times and rackets) takes that step,
    until every ball has arrived.

    Arguments:
        model, axes: the model and its per-ball axes; ball, alive, status, ball_id, log: the
            batch as in :func:`~ttsim_jax.kernel.step.step`; k: () step count of every ball;
            length: steps to take (static); schedule: the rackets' (T, R, ...) schedule from step
            ``step0`` on ((T, B, R, ...) with ``rackets_batched``: one per ball, each ball's
            kernel stop tested against its own rackets' boxes), or None; t0, dt: the clock (time of
            step k is t0 + k dt); stepper: ``step`` with its static options bound.

    Returns:
        (ball, alive, status, log) at step ``k + length``.
    """
    dtype = ball.pos.dtype
    end = k + length
    radius = jnp.max(model.ball.radius)  # per ball or not: the largest widens the racket boxes most
    last_row = None if schedule is None else schedule.pos.shape[0] - 1

    def body(carry):
        ball, alive, status, log, kb = carry
        boxes = None
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
        ball, n = fly(params, layout, ball, end - kb, substeps=substeps, block=block, interpret=interpret)
        kb = kb + n
        on = kb < end
        t = t0 + kb.astype(dtype) * dt
        rackets = None
        if schedule is not None:
            row = jnp.clip(kb - step0, 0, last_row)
            if rackets_batched:
                rackets = jax.tree.map(lambda a: a[row, jnp.arange(row.shape[0])], schedule)
            else:
                rackets = jax.tree.map(lambda a: a[row], schedule)
        ball, alive_new, status, log = stepper(model, axes, ball, alive & on, status, ball_id, log, rackets, t, dt,
                                               rackets_batched=schedule is not None, key=None)
        alive = jnp.where(on, alive_new, alive)
        return ball, alive, status, log, jnp.where(on & alive, kb + 1, end)

    kb = jnp.where(alive, k, end)
    carry = jax.lax.while_loop(lambda c: jnp.any(c[4] < end), body, (ball, alive, status, log, kb))
    return carry[:4]
