"""Aerodynamic flight: drag, Magnus, gravity with buoyancy; coefficient models; integrators.

Acceleration of a ball of radius r and mass m (density rho_b = m / V):

    a = -(3 / (8 r)) C_D (rho_a / rho_b) |v_r| v_r + C_M (rho_a / rho_b) (w x v_r) + (1 - b rho_a / rho_b) g

with v_r = v - v_air the velocity relative to the air and b = 1 with buoyancy, 0 without. This is
the paper's force equation divided by m; C_M uses the sign convention of PAPER_NOTES (Magnus force
along w x v).

Coefficient models are small pytrees; the stage dispatches on their type, so a new family is a new
dataclass plus one function in :data:`DRAG_MODELS` / :data:`MAGNUS_MODELS`.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.physics import hooks
from ttsim_jax.physics.numerics import safe_norm


# --------------------------------------------------------------------------- coefficient models
@struct.dataclass
class ConstantCoefficient:
    """A constant coefficient (Nakashima 2011)."""

    value: jnp.ndarray


@struct.dataclass
class DurrMagnus:
    """C_M = min(gain |v| / (|w| r) - offset, cap) (Dürr 2026): the Magnus force hardly depends on |w|."""

    gain: jnp.ndarray
    offset: jnp.ndarray
    cap: jnp.ndarray


@struct.dataclass
class DragTable:
    """The paper's C_D(Re, Sp) (Table I).

    Each reference Reynolds number has a piecewise-linear curve in the spin ratio Sp, flat outside
    its first and last breakpoints. C_D(Re, Sp) evaluates each reference curve at Sp and
    interpolates linearly in Re between the two bracketing curves. Below the first reference it is
    held; above the last it extrapolates linearly with the last two curves up to ``re_cap``, then is
    held; the result is clamped to at least ``cd_min``.

    Evaluating the curves at the same Sp (rather than blending their breakpoints, as the authors'
    code does) keeps the breakpoints ordered under extrapolation: blended breakpoints cross above
    about 22 m/s.

    Attributes:
        re_ref: (K,) reference Reynolds numbers, increasing.
        sp: (K, P) spin-ratio breakpoints of each reference curve, increasing along P.
        cd: (K, P) drag coefficients at those breakpoints.
        re_cap: Reynolds number beyond which the extrapolation is held.
        cd_min: lower clamp of the result.
    """

    re_ref: jnp.ndarray
    sp: jnp.ndarray
    cd: jnp.ndarray
    re_cap: jnp.ndarray
    cd_min: jnp.ndarray


@struct.dataclass
class MagnusTable:
    """The paper's C_M(v, w) (Tables II and III).

    C_M = m1 w + s for w <= w_b, a w^2 + b w + c above, clamped at 0. The six coefficients are
    interpolated linearly in |v| between the reference speeds and held outside them.

    Attributes:
        v_ref: (K,) reference speeds [m/s], increasing.
        m1, s, w_b, a, b, c: (K,) coefficients at those speeds (w in rad/s).
    """

    v_ref: jnp.ndarray
    m1: jnp.ndarray
    s: jnp.ndarray
    w_b: jnp.ndarray
    a: jnp.ndarray
    b: jnp.ndarray
    c: jnp.ndarray


def _ramps(x, xp, last=1.0):
    """Weights s_k = clip((x - xp[k-1]) / (xp[k] - xp[k-1]), 0, 1), k = 1..K-1.

    A piecewise-linear f through (xp, fp) is fp[0] + sum_k (fp[k] - fp[k-1]) s_k: the same as
    interpolation held outside [xp[0], xp[-1]], but as plain arithmetic with no search, which is
    several times faster under vmap on CPU. ``last`` is the upper clip of the last ramp
    (> 1 extrapolates beyond xp[-1]).
    """
    s = (x - xp[:-1]) / (xp[1:] - xp[:-1])
    upper = jnp.ones_like(s).at[-1].set(last)
    return jnp.clip(s, 0.0, upper)


def _piecewise(x, xp, fp, last=1.0):
    """Piecewise-linear interpolation of fp (K, ...) at x over xp (K,); see :func:`_ramps`."""
    s = _ramps(x, xp, last)
    # an unrolled sum, not a dot product: under vmap a dot is an operation of its own that no
    # elementwise loop fuses with (a pass over the batch per dot in every RK4 stage)
    # (the steps and weights unstacked at once: indexing each is two traced operations, and a
    # flight step's trace, repeated by every program that flies, was half indexing)
    out = fp[0]
    for s_k, step in zip(jnp.unstack(s, axis=0), jnp.unstack(fp[1:] - fp[:-1], axis=0)):
        out = out + s_k * step
    return out


def drag_constant(p: ConstantCoefficient, speed, spin_rate, radius, nu):
    return p.value


def drag_table(p: DragTable, speed, spin_rate, radius, nu):
    re = 2.0 * speed * radius / nu
    sp = spin_rate * radius / jnp.maximum(speed, 1e-6)
    curves = jax.vmap(_piecewise, in_axes=(None, 0, 0))(sp, p.sp, p.cd)  # (K,) each curve at Sp
    last = (p.re_cap - p.re_ref[-2]) / (p.re_ref[-1] - p.re_ref[-2])  # extrapolate up to the cap
    cd = _piecewise(re, p.re_ref, curves, last)
    return jnp.maximum(cd, p.cd_min)


@struct.dataclass
class BlendedDragTable(DragTable):
    """C_D(Re, Sp) read as the authors' code reads Table I (model config ``kind = "table_blended"``).

    Between two reference Reynolds numbers the Sp breakpoints *and* the C_D values of the two
    bracketing rows are blended linearly in Re, and that one curve is evaluated at Sp (the
    project's :class:`DragTable` evaluates both rows at the same Sp, then blends the values).
    Above the last reference the values extrapolate as in :class:`DragTable` (up to ``re_cap``)
    but the breakpoints are held at the last row's: extrapolated breakpoints cross above about
    22 m/s. Same fields as :class:`DragTable`.
    """


@struct.dataclass
class MagnusValueTable(MagnusTable):
    """C_M(v, w) with the *values* interpolated in |v| (model config ``kind = "table_values"``).

    C_M is evaluated with each reference speed's coefficients (clamped at 0) and those values are
    interpolated linearly in |v|, held outside the references; :class:`MagnusTable` (the
    authors' reading) interpolates the six coefficients instead. Same fields as :class:`MagnusTable`.
    """


def drag_table_blended(p: BlendedDragTable, speed, spin_rate, radius, nu):
    re = 2.0 * speed * radius / nu
    sp = spin_rate * radius / jnp.maximum(speed, 1e-6)
    last = (p.re_cap - p.re_ref[-2]) / (p.re_ref[-1] - p.re_ref[-2])
    breakpoints = _piecewise(re, p.re_ref, p.sp)  # (P,) held beyond the references
    values = _piecewise(re, p.re_ref, p.cd, last)  # (P,)
    return jnp.maximum(_piecewise(sp, breakpoints, values), p.cd_min)


def magnus_table_values(p: MagnusValueTable, speed, spin_rate, radius, nu):
    w = spin_rate
    per_ref = jnp.maximum(jnp.where(w <= p.w_b, p.m1 * w + p.s, (p.a * w + p.b) * w + p.c), 0.0)  # (K,)
    return _piecewise(speed, p.v_ref, per_ref)


def magnus_constant(p: ConstantCoefficient, speed, spin_rate, radius, nu):
    return p.value


def magnus_durr(p: DurrMagnus, speed, spin_rate, radius, nu):
    # At w -> 0 the ratio diverges but the cap takes over, and the force (C_M w x v) vanishes.
    ratio = p.gain * speed / jnp.maximum(spin_rate * radius, 1e-9)
    return jnp.minimum(ratio - p.offset, p.cap)


def magnus_table(p: MagnusTable, speed, spin_rate, radius, nu):
    coef = jnp.stack([p.m1, p.s, p.w_b, p.a, p.b, p.c], axis=-1)  # (K, 6)
    m1, s, w_b, a, b, c = _piecewise(speed, p.v_ref, coef)
    w = spin_rate
    cm = jnp.where(w <= w_b, m1 * w + s, (a * w + b) * w + c)
    return jnp.maximum(cm, 0.0)


DRAG_MODELS: dict[type, Callable] = {ConstantCoefficient: drag_constant, DragTable: drag_table,
                                     BlendedDragTable: drag_table_blended}
MAGNUS_MODELS: dict[type, Callable] = {
    ConstantCoefficient: magnus_constant,
    DurrMagnus: magnus_durr,
    MagnusTable: magnus_table,
    MagnusValueTable: magnus_table_values,
}


def _zeros_like(x):
    """A zero tangent of ``x`` (float0 for an integer)."""
    x = jnp.asarray(x)
    return jnp.zeros_like(x) if jnp.issubdtype(x.dtype, jnp.inexact) else np.zeros(x.shape, jax.dtypes.float0)


def _through_partials(fn: Callable) -> Callable:
    """``fn(p, speed, spin_rate, radius, nu)`` (a coefficient model's function) with a JVP that
    carries the tangents of speed and spin rate through the two partial derivatives.

    A fit's tangents ride along the flight, six directions at once in the latent-spin fit, three in
    evaluate's flight fit; JAX's own JVP pushes every direction through every operation of a table
    (a drag table is a few dozen ramps). Here the table is differentiated once along speed and once
    along spin rate, and each direction costs two multiply-adds. The partials are JAX's own
    derivatives of ``fn`` (the same values). Where a tangent of the model's parameters, the radius
    or the viscosity is not zero (``jax.grad`` of a table entry, a sensitivity study), the whole JVP
    is ``fn``'s own, as without this. Under conti2026 on 2 CPU cores, runs interleaved: the
    latent-spin fit of 1,000 segments in 0.74x its time with the same fits, ``jax.grad`` of 1,024
    flights' landing points by their initial velocities in 0.5x; evaluate's flight fit (three
    directions) and the gradient by the model's parameters unchanged within the runs' scatter.
    """
    from jax.custom_derivatives import SymbolicZero

    zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731

    @jax.custom_jvp
    def f(p, speed, spin_rate, radius, nu):
        return fn(p, speed, spin_rate, radius, nu)

    def jvp(primals, tangents):
        p, speed, spin_rate, radius, nu = primals
        if not all(zero(t) for t in jax.tree.leaves((tangents[0], *tangents[3:]), is_leaf=zero)):
            # a parameter moves (jax.grad of a rollout by its model, a sensitivity study): fn's own
            # JVP, in one pass over the table
            dense = jax.tree.map(lambda t, x: _zeros_like(x) if zero(t) else t, tangents, primals, is_leaf=zero)
            return jax.jvp(fn, primals, dense)
        t_speed, t_spin = tangents[1:3]
        # both partials from one JVP over the two unit directions (the primal traced once: 0.9x the
        # latent fit's time of two JVPs)
        one, nil = jnp.ones_like(speed), jnp.zeros_like(speed)
        out, (d_speed, d_spin) = jax.vmap(
            lambda a, b: jax.jvp(lambda v, w: fn(p, v, w, radius, nu), (speed, spin_rate), (a, b)),
            out_axes=(None, 0))(jnp.stack([one, nil]), jnp.stack([nil, one]).astype(spin_rate.dtype))
        tangent = jnp.zeros_like(out)
        if not zero(t_speed):
            tangent = tangent + d_speed * t_speed
        if not zero(t_spin):
            tangent = tangent + d_spin * t_spin
        return out, tangent

    f.defjvp(jvp, symbolic_zeros=True)
    return f


#: The coefficient functions whose JVP goes through their two partials (:func:`_through_partials`);
#: the closed forms (a few operations) keep their own JVP, as cheap.
TABLE_FUNCTIONS = frozenset({drag_table, drag_table_blended, magnus_table, magnus_table_values})
_PARTIALS = {fn: _through_partials(fn) for fn in TABLE_FUNCTIONS}


def _lookup(models: dict, p, what: str) -> Callable:
    try:
        fn = models[type(p)]
    except KeyError:
        raise TypeError(f"no {what} coefficient function for {type(p).__name__}; known: "
                        f"{[t.__name__ for t in models]}") from None
    return _PARTIALS.get(fn, fn)


# --------------------------------------------------------------------------- parameters
@struct.dataclass
class AeroParams:
    """Air and coefficient models of the flight stage.

    Attributes:
        rho_air: air density [kg/m^3].
        nu: kinematic viscosity of air [m^2/s] (for the Reynolds number).
        gravity: (3,) gravitational acceleration [m/s^2].
        buoyancy: 1.0 to include buoyancy, 0.0 to leave it out.
        drag: a drag coefficient model (:class:`ConstantCoefficient` or :class:`DragTable`).
        magnus: a Magnus coefficient model (:class:`ConstantCoefficient`, :class:`DurrMagnus`,
            :class:`MagnusTable`).
    """

    rho_air: jnp.ndarray
    nu: jnp.ndarray
    gravity: jnp.ndarray
    buoyancy: jnp.ndarray
    drag: object
    magnus: object


def coefficients(aero: AeroParams, vel_rel, spin, radius, nu=None):
    """(C_D, C_M) for air-relative velocity ``vel_rel`` (3,) and spin (3,); ``nu``: the air's
    kinematic viscosity (default the model's)."""
    nu = aero.nu if nu is None else nu
    speed = safe_norm(vel_rel)
    spin_rate = safe_norm(spin)
    cd = _lookup(DRAG_MODELS, aero.drag, "drag")(aero.drag, speed, spin_rate, radius, nu)
    cm = _lookup(MAGNUS_MODELS, aero.magnus, "Magnus")(aero.magnus, speed, spin_rate, radius, nu)
    return cd, cm


def acceleration(aero: AeroParams, radius, mass, pos, vel, spin, t, effects=()):
    """Linear acceleration (3,) of a ball in flight.

    Arguments:
        aero: flight parameters.
        radius, mass: ball radius [m] and mass [kg].
        pos, vel, spin: (3,) ball state.
        t: time [s] (for time-varying effects such as gusts).
        effects: tuple of effects (hooks ``air_properties``: the air's density and viscosity,
            ``air_velocity``).

    Returns:
        (3,) acceleration [m/s^2].
    """
    volume = (4.0 / 3.0) * jnp.pi * radius**3
    rho_air, nu = hooks.apply(effects, "air_properties", (aero.rho_air, aero.nu))
    ratio = rho_air * volume / mass  # rho_air / rho_ball
    air = hooks.apply(effects, "air_velocity", jnp.zeros_like(vel), pos=pos, t=t)
    v_rel = vel - air
    cd, cm = coefficients(aero, v_rel, spin, radius, nu)
    # over the components, as three columns under vmap: with (B, 3) arrays (and the cross
    # product's concatenation), XLA's loop over a batch recomputed the shared terms per component
    c = -(3.0 / (8.0 * radius)) * cd * ratio * safe_norm(v_rel)
    m = cm * ratio
    fall = 1.0 - aero.buoyancy * ratio
    (v0, v1, v2), (w0, w1, w2) = jnp.unstack(v_rel, axis=-1), jnp.unstack(spin, axis=-1)
    g0, g1, g2 = jnp.unstack(jnp.asarray(aero.gravity, v_rel.dtype), axis=-1)
    return jnp.stack([c * v0 + m * (w1 * v2 - w2 * v1) + fall * g0, c * v1 + m * (w2 * v0 - w0 * v2) + fall * g1,
                      c * v2 + m * (w0 * v1 - w1 * v0) + fall * g2], -1)


# --------------------------------------------------------------------------- integrators
def derivative(aero: AeroParams, radius, mass, effects=()):
    """f(y, t) -> dy/dt for the flight state y = (pos, vel, spin)."""

    def f(y, t):
        pos, vel, spin = y
        acc = acceleration(aero, radius, mass, pos, vel, spin, t, effects)
        dspin = hooks.apply(effects, "spin_derivative", jnp.zeros_like(spin), vel=vel, spin=spin, t=t)
        return (vel, acc, dspin)
    return f


def _axpy(a, x, y):
    return jax.tree.map(lambda xi, yi: yi + a * xi, x, y)


def step_rk4(f, y, t, dt):
    k1 = f(y, t)
    k2 = f(_axpy(0.5 * dt, k1, y), t + 0.5 * dt)
    k3 = f(_axpy(0.5 * dt, k2, y), t + 0.5 * dt)
    k4 = f(_axpy(dt, k3, y), t + dt)
    return jax.tree.map(lambda yi, a, b, c, d: yi + dt / 6.0 * (a + 2 * b + 2 * c + d), y, k1, k2, k3, k4)


def step_rk2(f, y, t, dt):
    """Heun's method (explicit trapezoid), second order, two evaluations."""
    k1 = f(y, t)
    k2 = f(_axpy(dt, k1, y), t + dt)
    return jax.tree.map(lambda yi, a, b: yi + 0.5 * dt * (a + b), y, k1, k2)


def step_euler(f, y, t, dt):
    """Semi-implicit (symplectic) Euler, first order, one evaluation."""
    _, acc, dspin = f(y, t)
    pos, vel, spin = y
    vel = vel + dt * acc
    return (pos + dt * vel, vel, spin + dt * dspin)


INTEGRATORS: dict[str, Callable] = {"rk4": step_rk4, "rk2": step_rk2, "euler": step_euler}


def flight_step(aero: AeroParams, radius, mass, pos, vel, spin, t, dt, effects=(), integrator: str = "rk4"):
    """Advances one ball in free flight by ``dt``.

    Arguments:
        aero: flight parameters; radius, mass: ball radius and mass.
        pos, vel, spin: (3,) ball state at time t.
        t, dt: time and step [s].
        effects: tuple of effects (hooks ``air_velocity``, ``spin_derivative``).
        integrator: ``"rk4"`` (default), ``"rk2"`` or ``"euler"``; static.

    Returns:
        (pos, vel, spin) at t + dt.
    """
    try:
        stepper = INTEGRATORS[integrator]
    except KeyError:
        raise ValueError(f"unknown integrator {integrator!r}; known: {list(INTEGRATORS)}") from None
    return stepper(derivative(aero, radius, mass, effects), (pos, vel, spin), t, dt)
