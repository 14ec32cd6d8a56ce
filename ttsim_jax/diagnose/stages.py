"""Per-item errors of a model plus candidate effects on each phase, in JAX (differentiable in the
effects' parameters).

Each phase uses the cheapest function that contains the physics it checks:

* *flight*: the flight stage (:func:`ttsim_jax.physics.aero.flight_step`, RK4 from sample to
  sample on absolute session time, spin integrated with the effects' ``spin_derivative``). Per
  segment the initial position and velocity are fitted (Gauss-Newton) with the effects' parameters
  held fixed; the gradient in those parameters is then taken at the fitted state, which is the
  gradient of the minimised error (envelope theorem). A segment's measured spin is the mean of its
  samples' estimates, so when an effect changes spin in flight the initial spin is set so that the
  flight's mean spin matches it (one fixed-point step).
* *table*: the kernel's contact response (:func:`ttsim_jax.kernel.ball_step.respond`) applied to the
  estimated pre-bounce state, minus the estimated post-bounce state. Where the pre-bounce spin is
  not measured (flown as 0) only the normal (z) velocity is compared: the tangential velocity
  after a bounce is driven by the incoming spin (about r |w| = 4 m/s of surface speed at 200
  rad/s), so its error would measure the unknown spin, not the contact law.
* *racket*: the racket contact in the racket frame
  (:func:`ttsim_jax.physics.racket.base_response`, plus the model's residual network's correction
  held fixed), minus the observation.

When an effect changes the spin in flight (``spin_derivative``), a contact's measured spins, its
segments' means, are the spins at the segments' mean sample times, not at the contact: both are
carried to the contact time with the effects' spin derivative (:func:`contact_spin`) before the
contact is compared (without such an effect they are the spins at the contact).

Contact errors are (v error, r * spin error) (N, 6) in m/s, the spin part 0 where the spin is not
measured on both sides; flight errors are (S, T, 3) position residuals [m].

Effects are given as ``specs`` (static, :class:`~ttsim_jax.diagnose.candidates.Spec`) and their
free values ``u`` (a tuple of dicts of arrays with a leading session axis; the actual parameter is
``start + scale * u``); every item uses the parameters of its session.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.diagnose.specs import free_order
from ttsim_jax.physics import hooks
from ttsim_jax.physics.aero import flight_step
from ttsim_jax.physics.linalg import spd_solve

#: Gauss-Newton iterations of the initial state at the start (later calls warm-start).
GN_START = 6
#: Midpoint steps of the spin between a segment's mean sample time and a contact.
SPIN_STEPS = 4


def start_of(sp, const: dict, k: str, session):
    """The start of parameter ``k`` for ``session``'s items: a per-session effect's start may carry
    a leading session axis (starts found per session, :data:`REFINE`)."""
    start = const["start"][k]
    if sp.per_session and jnp.ndim(start) > len(sp.cls.PARAMS[k].shape):
        return start[session]
    return start


def session_starts(sp, const: dict, n_sessions: int) -> dict:
    """``const`` with each start of a per-session effect given a leading session axis (the same
    values for every session), as a second descent's starts have it (:func:`second_descent`): the
    descents then share one compiled program."""
    if not sp.per_session:
        return const
    start = {k: np.broadcast_to(np.asarray(v), (n_sessions,) + sp.cls.PARAMS[k].shape).copy()
             if np.ndim(v) == len(sp.cls.PARAMS[k].shape) else v for k, v in const["start"].items()}
    return dict(const, start=start)


def second_descent(sp, start: dict, scales: dict) -> tuple:
    """(spec, consts) of a candidate's second descent (a ``REFINE`` stage): the parameters of
    ``scales`` free at those step scales, from ``start`` ({param: value}); the others held there."""
    scale = {k: np.float64(scales.get(k, 0.0)) for k in sp.cls.PARAMS}
    return dataclasses.replace(sp, free=free_order(sp.cls, scales)), dict(start=start, scale=scale)


def effects_of(specs, consts, u, session):
    """The effects of one item (its session's parameters) as a tuple of effect instances."""
    out = []
    for spec, c, uk in zip(specs, consts, u):
        i = session if spec.per_session else 0
        vals = {k: start_of(spec, c, k, i) + (c["scale"][k] * uk[k][i] if k in uk else 0.0) for k in spec.cls.PARAMS}
        out.append(spec.cls(**vals))
    return tuple(out)


def _ball(model, effects):
    return hooks.apply(effects, "ball_properties", (model.ball.radius, model.ball.mass))


# ---------------------------------------------------------------------------------------------- flight
# A jitted function is traced once per argument shapes and its derivatives and batched forms are
# cached on that one trace: a descent's program flies each segment up to four times (with an
# effect that changes the spin, twice per residual; the loss and the states' Jacobian), and JAX
# linearises a scan's body again for every pass of its fixpoint. Inlined by XLA: same program.
@jax.jit
def _path(model, effects, p0, v0, w0, t0, tau):
    """(T, 3) positions and spins along one padded segment (padding: zero steps)."""
    radius, mass = _ball(model, effects)
    dts = tau[1:] - tau[:-1]

    def step(y, k):
        y = flight_step(model.aero, radius, mass, y[0], y[1], y[2], t0 + tau[k], dts[k], effects)
        return y, (y[0], y[2])

    _, (ps, ws) = jax.lax.scan(step, (p0, v0, w0), jnp.arange(tau.shape[0] - 1))
    return jnp.concatenate([p0[None], ps]), jnp.concatenate([w0[None], ws])


def _segment_residual(model, effects, x, spin, t0, tau, pos, mask, spin_changes: bool):
    w0 = spin
    if spin_changes:
        _, ws = _path(model, effects, x[:3], x[3:], spin, t0, tau)
        mean = jnp.sum(ws * mask[:, None], 0) / jnp.maximum(jnp.sum(mask), 1.0)
        w0 = spin + (spin - mean)
    ps, _ = _path(model, effects, x[:3], x[3:], w0, t0, tau)
    return (ps - pos) * mask[:, None]


def residual_jacobian(res, z):
    """(res(z), its Jacobian (n, len(z))) by forward mode, one tangent per parameter."""
    eye = jnp.eye(z.shape[0], dtype=z.dtype)
    return jax.vmap(lambda t: jax.jvp(res, (z,), (t,)), out_axes=(None, 1))(eye)


def difference_jacobian(res, z):
    """(res(z), its Jacobian (n, len(z))) by forward differences (as MINPACK's ``lmdif`` and SciPy's
    ``least_squares`` take it by default), each step sqrt(eps) max(|z_j|, 1).

    The Gauss-Newton steps of the flight states need only an approximate Jacobian: its error slows
    their convergence to the optimum the residual defines, it does not move that optimum. Forward
    mode through a flight (:func:`residual_jacobian`) costs tens of flights on a CPU (XLA
    recomputes the primal's elementwise chains inside the tangents' loops); this costs seven.
    """
    h = jnp.sqrt(jnp.finfo(z.dtype).eps) * jnp.maximum(jnp.abs(z), 1.0)
    # z and its moved copies in one batch: one trace of the flight, not two
    rs = jax.vmap(res)(jnp.concatenate([z[None], z + jnp.diag(h)]))
    return rs[0], ((rs[1:] - rs[0]) / h[:, None]).T


def gauss_newton_update(z, r, jac):
    """``z`` after one Gauss-Newton step for the residual ``r`` with Jacobian ``jac`` (n, len(z))
    (``z`` kept where the step is not finite). ``jac`` may come from an earlier ``z`` (a chord step:
    :func:`ttsim_jax.diagnose.candidates.fit` refreshes it every few descent steps)."""
    eye = jnp.eye(z.shape[0], dtype=z.dtype)
    h = jac.T @ jac
    cand = z - spd_solve(h + 1e-9 * jnp.trace(h) * eye + 1e-30, jac.T @ r)
    return jnp.where(jnp.all(jnp.isfinite(cand)), cand, z)


def _segment_function(model, effects, spin, t0, tau, pos, mask, spin_changes):
    return lambda z: _segment_residual(model, effects, z, spin, t0, tau, pos, mask, spin_changes).ravel()


def initial_state(tau, pos, mask):
    """(S, 6) start of the Gauss-Newton fit: position and velocity at tau[0] from a parabola."""
    def one(t, p, m):
        a = jnp.stack([jnp.ones_like(t), t, t**2], -1) * m[:, None]
        coef = spd_solve(a.T @ a + 1e-9 * jnp.eye(3, dtype=a.dtype), a.T @ (p * m[:, None]))
        return jnp.concatenate([coef[0], coef[1]])

    return jax.vmap(one)(tau, pos, mask)


def changes_spin(effect) -> bool:
    """Whether an effect (class or instance) changes the spin in flight: with one attached, each
    flight is flown twice (the first flight's mean spin sets its initial spin)."""
    return callable(getattr(effect, "spin_derivative", None))


def _spin_changes(model, specs) -> bool:
    return any(changes_spin(s.cls) for s in specs) or any(changes_spin(e) for e in model.effects)


def _over_segments(model, specs, consts, u, fl: dict, x, fn, *, held: bool = False):
    """``fn(res, x_i)`` of every segment, vmapped: ``res(z)`` is the segment's (3T,) position
    residuals flown from the initial state z with its session's effects. ``held``: the effects'
    parameters held fixed, no gradient through the result."""
    if held:
        return jax.lax.stop_gradient(_over_segments(model, specs, consts, jax.lax.stop_gradient(u), fl, x, fn))
    changes = _spin_changes(model, specs)

    def one(xi, t0, tau, pos, mask, spin, s):
        fx = model.effects + effects_of(specs, consts, u, s)
        return fn(_segment_function(model, fx, spin, t0, tau, pos, mask, changes), xi)

    return jax.vmap(one)(x, fl["t0"], fl["tau"], fl["pos"], fl["mask"], fl["spin"], fl["session"])


def flight_states(model, specs, consts, u, fl: dict, x, iterations: int):
    """(S, 6) initial states of every segment after ``iterations`` Gauss-Newton steps from ``x``
    (effects' parameters held fixed; no gradient flows through the result).

    Arguments:
        model: the model (its own effects kept); specs, consts, u: the candidate effects.
        fl: dict of arrays ``t0`` (S,), ``tau`` (S, T), ``pos`` (S, T, 3), ``mask`` (S, T),
            ``spin`` (S, 3), ``session`` (S,).
        x: (S, 6) initial states to start from.
    """
    def steps(res, xi):
        return jax.lax.fori_loop(0, iterations, lambda _, z: gauss_newton_update(z, *difference_jacobian(res, z)), xi)

    return _over_segments(model, specs, consts, u, fl, x, steps, held=True)


def flight_jacobians(model, specs, consts, u, fl: dict, x):
    """Per segment the residual (S, 3T) at ``x`` and its Jacobian (S, 3T, 6) in the initial state
    (effects' parameters held fixed, no gradient; arguments as :func:`flight_states`), by forward
    differences (:func:`difference_jacobian`): seven flights, so a descent reuses one for several
    steps."""
    return _over_segments(model, specs, consts, u, fl, x, difference_jacobian, held=True)


def flight_errors(model, specs, consts, u, fl: dict, x):
    """(S, T, 3) position residuals of every segment flown from the states ``x`` (differentiable in
    ``u``; see :func:`flight_states` for the arguments)."""
    return _over_segments(model, specs, consts, u, fl, x, lambda res, xi: res(xi)).reshape(fl["pos"].shape)


# ---------------------------------------------------------------------------------------------- contacts
def contact_spin(effects, vel, spin, t, dt):
    """The spin ``dt`` seconds later (earlier for dt < 0) under the effects' ``spin_derivative``, the
    velocity held (midpoint steps, :data:`SPIN_STEPS`)."""
    h = dt / SPIN_STEPS

    def rate(w):
        return hooks.apply(effects, "spin_derivative", jnp.zeros_like(w), vel=vel, spin=w, t=t)

    def step(_, w):
        return (w + h * rate(w + 0.5 * h * rate(w))).astype(spin.dtype)

    return jax.lax.fori_loop(0, SPIN_STEPS, step, spin)


def _at_contact(fx, c_row, x_spin, y_spin):
    """The racket-/world-frame pre- and post-contact spins carried from the segments' mean sample
    times to the contact (:func:`contact_spin`)."""
    w_in, w_out, rot, t, dt = c_row
    d_in = contact_spin(fx, w_in[:3], w_in[3:], t, dt[0]) - w_in[3:]
    d_out = contact_spin(fx, w_out[:3], w_out[3:], t, -dt[1]) - w_out[3:]
    return x_spin + rot.T @ d_in, y_spin + rot.T @ d_out


def _spin_rows(c: dict):
    return (c["world_in"], c["world_out"], c["rot"], c["t"], c["spin_dt"])


def table_errors(model, specs, consts, u, c: dict):
    """(N, 6) table-contact errors (see the module docstring) of the contacts in ``c``
    (``pos``, ``x``, ``y_obs``, ``known``, ``known_in``, ``session`` and the spin times' arrays)."""
    from ttsim_jax.kernel.ball_step import respond
    from ttsim_jax.physics.events import TABLE
    from ttsim_jax.state import Ball

    r = model.ball.radius
    changes = _spin_changes(model, specs)

    def one(p, x, y, known, known_in, s, rows):
        fx = effects_of(specs, consts, u, s)
        m = model.replace(effects=model.effects + fx)
        w_in, w_out = _at_contact(m.effects, rows, x[3:6], y[3:]) if changes else (x[3:6], y[3:])
        post, _, _ = respond(m, Ball(p, x[:3], w_in), TABLE, None)
        tangential = jnp.stack([known_in, known_in, jnp.ones_like(known_in)])
        return jnp.concatenate([(post.vel - y[:3]) * tangential, r * (post.spin - w_out) * known])

    return jax.vmap(one)(c["pos"], c["x"], c["y_obs"], c["known"], c["known_in"], c["session"], _spin_rows(c))


def racket_errors(model, specs, consts, u, c: dict):
    """(N, 6) racket-contact errors in the racket frame (see the module docstring) of the contacts
    in ``c`` (``x``, ``y_obs``, ``correction``, ``known``, ``session`` and the spin times' arrays)."""
    from ttsim_jax.physics.racket import base_response

    r = model.ball.radius
    changes = _spin_changes(model, specs)

    def one(x, y, corr, known, s, rows):
        fx = model.effects + effects_of(specs, consts, u, s)
        radius, mass = _ball(model, fx)
        w_in, w_out = _at_contact(fx, rows, x[3:6], y[3:]) if changes else (x[3:6], y[3:])
        v, w = base_response(model.racket, x[:3], w_in, x[6:8], radius, mass, fx)
        e = jnp.concatenate([v - y[:3], w - w_out]) + corr
        return jnp.concatenate([e[:3], r * e[3:] * known])

    return jax.vmap(one)(c["x"], c["y_obs"], c["correction"], c["known"], c["session"], _spin_rows(c))


ERRORS = {"table": table_errors, "racket": racket_errors}
