"""The fused flight kernel's parameters: the model read as one small vector of scalars.

The kernel (:mod:`ttsim_jax.kernel.fused`) reads every parameter it needs from one vector
(:func:`pack`), one scalar at a time (:class:`Reader`): the ball, the air, gravity, the table's
outline, the drag and Magnus coefficient models (their tables interpolated with the same ramps as
``aero._piecewise``, arithmetic only) and the boxes the rackets sweep. A parameter that is per ball
is read from a matrix with one row per scalar and one column per ball, the others stay scalars (a
per-ball air density made every coefficient table a row per ball too, and the kernel 6.6x
slower). Effects whose hooks take no state (the ball's and the air's properties) enter here as the
constants they give.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from ttsim_jax.kernel.ball_step import ball_properties
from ttsim_jax.physics import aero as aero_stage
from ttsim_jax.physics import hooks


# Hooks that change the flight: those without context give constants the kernel reads from its
# parameters (:func:`pack`); those that follow the ball's state and time are evaluated in the kernel
# (:class:`ttsim_jax.kernel.fused.Hooks`, on a CPU).
CONSTANT_HOOKS = ("ball_properties", "air_properties")
STATE_HOOKS = ("air_velocity", "spin_derivative")
FLIGHT_HOOKS = CONSTANT_HOOKS + STATE_HOOKS


def in_flight(model, points=FLIGHT_HOOKS) -> bool:
    """Whether an effect of ``model`` defines one of the hook ``points`` (by default: acts in flight)."""
    return any(hasattr(e, h) for e in model.effects for h in points)


# --------------------------------------------------------------------------- parameters as scalars
@dataclass(frozen=True)
class Layout:
    """Where each parameter sits in the kernel's parameter vector (static: the model's structure).

    Attributes:
        drag, magnus: the coefficient model types' names; n_re, n_sp: DragTable sizes;
        n_v: MagnusTable size; n_rackets: racket boxes; size: the vector's length (a power of 2);
        rows: where the parameters are per ball, for each scalar of the vector its row in the
        per-ball matrix, or -1 where it is shared (read from the vector); () when none is.
    """

    drag: str
    magnus: str
    n_re: int
    n_sp: int
    n_v: int
    n_rackets: int
    size: int
    rows: tuple[int, ...] = ()


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


DRAG_KINDS = {aero_stage.ConstantCoefficient: "constant", aero_stage.DragTable: "table"}
MAGNUS_KINDS = {aero_stage.ConstantCoefficient: "constant", aero_stage.DurrMagnus: "durr", aero_stage.MagnusTable: "table"}


def leaf_axes(model, axes):
    """The model's structure with each leaf's per-ball axis (0 or None)."""
    if axes is None:
        return jax.tree.map(lambda _: None, model)
    return jax.tree.map(lambda a, sub: jax.tree.map(lambda _: a, sub), axes, model, is_leaf=lambda x: x is None)


def _any(*axes):
    """0 where any of the given leaves is per ball (a value computed from them is), else None."""
    return 0 if any(a == 0 for a in axes) else None


def hooked_properties(model, axes):
    """((radius, mass, rho_air, nu), axis): the ball's and the air's properties after the effects'
    ``ball_properties`` and ``air_properties`` hooks (constant in flight: they take no state), (B,)
    each with axis 0 where any leaf they may read is per ball, else scalars and None."""
    def after(m):
        radius, mass = ball_properties(m)
        rho_air, nu = hooks.apply(m.effects, "air_properties", (m.aero.rho_air, m.aero.nu))
        return radius, mass, rho_air, nu

    if axes is None:
        return after(model), None
    phys, phys_axes = model.replace(residual=None), axes.replace(residual=None)
    ax = leaf_axes(phys, phys_axes)
    read = (ax.ball, ax.aero.rho_air, ax.aero.nu, ax.effects)
    if all(a is None for a in jax.tree.leaves(read, is_leaf=lambda x: x is None)):
        return after(phys), None
    return jax.vmap(after, in_axes=(phys_axes,))(phys), 0


def pack(model, dt, racket_boxes, dtype, axes=None):
    """The kernel's parameters as one vector (or one column per ball) and its :class:`Layout`.

    Arguments:
        model: the model; dt: the step [s];
        racket_boxes: (R, 2, 3) lower and upper corners of the boxes the rackets' centres sweep,
            widened by the face, (B, R, 2, 3) one set per ball (then the result has a column per
            ball), or None; dtype: the simulation's float dtype;
        axes: the model's per-ball axes (pytree prefix of 0 / None) or None (all shared).

    Returns:
        (params, layout): params (size,) where every parameter is shared, else a pair of that vector
        (zeros in the per-ball parameters' places) and an (n, B) matrix, a row per per-ball scalar
        and a column per ball (the kernel reads a row of values there: the batch's in
        ``fused._fly_xla``, a block's in the Triton kernel).
    """
    ax = leaf_axes(model, axes)
    t, a, tx, aa = model.table, model.aero, ax.table, ax.aero
    radius, mass, rho_air, nu = model.ball.radius, model.ball.mass, a.rho_air, a.nu
    radius_ax, ratio_ax, nu_ax = ax.ball.radius, _any(aa.rho_air, ax.ball.radius, ax.ball.mass), aa.nu
    if in_flight(model, CONSTANT_HOOKS):
        (radius, mass, rho_air, nu), each = hooked_properties(model, axes)
        radius_ax = ratio_ax = nu_ax = each
    volume = (4.0 / 3.0) * jnp.pi * radius**3
    ratio = rho_air * volume / mass
    parts = [dt, radius, ratio, nu, a.buoyancy, a.gravity, t.length, t.width, t.floor_z]
    per_ball = [None, radius_ax, ratio_ax, nu_ax, aa.buoyancy, aa.gravity, tx.length, tx.width, tx.floor_z]
    drag, magnus = a.drag, a.magnus
    parts += _drag_leaves(drag) + _magnus_leaves(magnus)
    per_ball += _drag_leaves(aa.drag) + _magnus_leaves(aa.magnus)
    if racket_boxes is not None:
        parts.append(racket_boxes)
        per_ball.append(0 if racket_boxes.ndim == 4 else None)
    shared, matrix, rows = [], [], []
    for p, b in zip(parts, per_ball):
        p = jnp.asarray(p, dtype)
        if b == 0:  # (B, ...): one row per scalar, one column per ball; its places in the vector unused
            cols = jnp.reshape(p, (p.shape[0], -1)).T
            first = sum(m.shape[0] for m in matrix)
            rows += list(range(first, first + cols.shape[0]))
            matrix.append(cols)
            shared.append(jnp.zeros(cols.shape[0], dtype))
        else:
            shared.append(jnp.ravel(p))
            rows += [-1] * shared[-1].shape[0]
    flat = jnp.concatenate(shared)
    size = 1 << max(0, int(flat.shape[0] - 1).bit_length())
    last = lambda a: a.shape[-1]  # noqa: E731 (a per-ball table has the batch first)
    layout = Layout(drag=DRAG_KINDS[type(drag)], magnus=MAGNUS_KINDS[type(magnus)],
                    n_re=last(drag.re_ref) if isinstance(drag, aero_stage.DragTable) else 0,
                    n_sp=last(drag.sp) if isinstance(drag, aero_stage.DragTable) else 0,
                    n_v=last(magnus.v_ref) if isinstance(magnus, aero_stage.MagnusTable) else 0,
                    n_rackets=0 if racket_boxes is None else racket_boxes.shape[-3], size=size,
                    rows=tuple(rows) if matrix else ())
    flat = jnp.pad(flat, (0, size - flat.shape[0]))
    return (flat, jnp.concatenate(matrix)) if matrix else flat, layout


class Reader:
    """Reads the parameters in :func:`pack`'s order, one scalar at a time (scalar loads), or a row
    of B values where the layout has it per ball."""

    def __init__(self, ref, layout: Layout):
        self.ref, self.rows, self.at = ref, layout.rows, 0

    def scalar(self):
        self.at += 1
        if not self.rows:
            return self.ref[self.at - 1]
        row = self.rows[self.at - 1]
        return self.ref[0][self.at - 1] if row < 0 else self.ref[1][row]

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


def coefficient_fns(rd: Reader, layout: Layout, radius, nu):
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
        # a name of its own: the Magnus branch below binds its constant too, and a closure reads
        # the name when called (one shared name gave the drag Magnus's constant)
        cd_value = rd.scalar()

        def drag(speed, spin_rate):
            return cd_value

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
        cm_value = rd.scalar()

        def magnus(speed, spin_rate):
            return cm_value

    return drag, magnus
