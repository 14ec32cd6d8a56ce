"""Sampling realistic table tennis shots (host-side, numpy, seeded).

Each shot type has ranges for where the ball leaves the racket, how fast it travels horizontally,
where it is aimed, and its spin. The initial velocity is aimed with the vacuum ballistic solution
(drag and Magnus then bend the real path, as they would a player's aim), which keeps every shot
type in its realistic regime: smashes up to 35 m/s, loops up to 1000 rad/s of topspin, lobs high,
pushes short and low with backspin. Shots travel along +x; ``mirror`` sends a fraction along -x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from functools import partial

import jax
import jax.numpy as jnp

from ttsim_jax.physics import aero as aero_stage
from ttsim_jax.physics import table as table_stage
from ttsim_jax.physics.numerics import safe_divide, safe_norm
from ttsim_jax.state import Ball

G = 9.81


@dataclass(frozen=True)
class ShotType:
    """Ranges (low, high) of one kind of shot.

    Attributes:
        start_x, start_y, start_z: where the ball leaves the racket [m] (x behind the end line at
            -:data:`~ttsim_jax.physics.dimensions.TABLE_HALF_LENGTH` for shots from the -x end).
        speed: horizontal speed [m/s].
        target_x, target_y: aimed first bounce [m].
        topspin: spin about the horizontal axis perpendicular to the path [rad/s]; negative is
            backspin.
        sidespin: spin about z [rad/s].
        bounce: which bounce the target is for (the serve aims its second bounce, on the far half).
        first_x: for serves, where the first bounce lands (on the server's half) [m].
        max_up: largest initial upward speed [m/s]: keeps the aim on the low arc of the two that
            reach a target (a push is never a lob).
    """

    start_x: tuple
    start_y: tuple
    start_z: tuple
    speed: tuple
    target_x: tuple
    target_y: tuple
    topspin: tuple
    sidespin: tuple
    bounce: int = 0
    max_up: float = 3.0
    first_x: tuple = (0.0, 0.0)


SHOT_TYPES: dict[str, ShotType] = {
    # the serve bounces on the server's own half first
    "serve": ShotType((-1.6, -1.4), (-0.6, 0.6), (0.2, 0.35), (2.5, 5.0), (0.3, 1.1), (-0.6, 0.6),
                      (-500.0, 400.0), (-400.0, 400.0), bounce=1, max_up=2.0, first_x=(-1.15, -0.7)),
    "topspin_drive": ShotType((-2.4, -1.5), (-0.7, 0.7), (0.15, 0.5), (10.0, 22.0), (0.5, 1.3), (-0.65, 0.65),
                              (200.0, 1000.0), (-200.0, 200.0)),
    "backspin_drive": ShotType((-2.8, -1.8), (-0.7, 0.7), (0.2, 0.6), (5.0, 9.0), (0.5, 1.3), (-0.65, 0.65),
                               (-600.0, -150.0), (-150.0, 150.0)),
    "push": ShotType((-1.6, -1.3), (-0.6, 0.6), (0.12, 0.28), (2.5, 4.5), (0.3, 1.0), (-0.6, 0.6),
                     (-400.0, -80.0), (-100.0, 100.0), max_up=2.0),
    "block": ShotType((-1.8, -1.4), (-0.7, 0.7), (0.15, 0.4), (6.0, 12.0), (0.4, 1.3), (-0.65, 0.65),
                      (0.0, 250.0), (-100.0, 100.0)),
    "smash": ShotType((-2.0, -1.4), (-0.6, 0.6), (0.5, 1.1), (20.0, 35.0), (0.6, 1.3), (-0.65, 0.65),
                      (0.0, 300.0), (-100.0, 100.0)),
    "lob": ShotType((-4.0, -2.5), (-1.0, 1.0), (-0.2, 0.5), (7.0, 13.0), (0.6, 1.3), (-0.65, 0.65),
                    (300.0, 900.0), (-300.0, 300.0), max_up=9.0),
}


# Magnus acceleration per unit of (topspin x horizontal speed), C_M rho_air / rho_ball ~ 0.2 * 0.0148,
# and the share of the horizontal speed that drag takes over a typical flight: used only to aim.
MAGNUS_AIM = 0.2 * 0.0148
DRAG_AIM = 0.85


def aim(start, target, speed, topspin=0.0):
    """Initial velocity (N, 3) reaching ``target`` from ``start`` at horizontal ``speed``.

    A parabola under an effective gravity g + (Magnus pull of the topspin), flown at the mean
    horizontal speed that drag leaves: enough for the shot to land near its target.
    """
    d = target - start
    dist = np.hypot(d[:, 0], d[:, 1])
    t = dist / (DRAG_AIM * speed)
    g_eff = np.maximum(G + MAGNUS_AIM * topspin * speed, 2.0)
    vz = d[:, 2] / t + 0.5 * g_eff * t
    return np.stack([speed * d[:, 0] / dist, speed * d[:, 1] / dist, vz], axis=-1)


def landing_points(model, pos, vel, spin, h, n_steps):
    """Where the ball comes down to the table plane the first and second time, for aiming.

    A light flight (RK4 of step ``h``, no events but the table plane, taken as unbounded),
    differentiable in the initial velocity.

    Returns:
        (first (2,), second (2,), twice: whether it came down twice, net (2,): the ball's height
        where it crosses the net plane x = 0 before the first and before the second landing, +inf
        if it does not).
    """
    radius, mass = model.ball.radius, model.ball.mass

    def body(c, _):
        p, v, w, n, first, second, net = c
        p1, v1, w1 = aero_stage.flight_step(model.aero, radius, mass, p, v, w, 0.0, h)
        crosses_net = (p[0] * p1[0] <= 0.0) & (p[0] != p1[0])
        z_net = p[2] + safe_divide(-p[0], p1[0] - p[0], 0.0) * (p1[2] - p[2])
        net = jnp.where(crosses_net & (jnp.arange(2) == n), jnp.minimum(net, z_net), net)
        cross = (n < 2) & (p1[2] < radius) & (v1[2] < 0.0)
        frac = jnp.clip(safe_divide(p[2] - radius, p[2] - p1[2], 0.0), 0.0, 1.0)
        pc, vc, wc = p + frac * (p1 - p), v + frac * (v1 - v), w + frac * (w1 - w)
        bp, bv, bw = table_stage.table_contact(model.table, radius, pc, vc, wc, edges=False)
        # the rest of the step after the bounce: a second-order Taylor step (as the rally kernel)
        rest = (1.0 - frac) * h
        acc = aero_stage.acceleration(model.aero, radius, mass, bp, bv, bw, 0.0)
        bp, bv = bp + rest * bv + 0.5 * rest * rest * acc, bv + rest * acc
        p1 = jnp.where(cross, bp, p1)
        v1 = jnp.where(cross, bv, v1)
        w1 = jnp.where(cross, bw, w1)
        first = jnp.where(cross & (n == 0), pc[:2], first)
        second = jnp.where(cross & (n == 1), pc[:2], second)
        return (p1, v1, w1, n + cross.astype(n.dtype), first, second, net), None

    init = (pos, vel, spin, jnp.zeros((), jnp.int32), pos[:2], pos[:2], jnp.full(2, jnp.inf, pos.dtype))
    (_, _, _, n, first, second, net), _ = jax.lax.scan(body, init, None, length=n_steps)
    return first, second, n >= 2, net


def aim_one(model, pos, spin, speed, vz, target, first_x, serve, h, n_steps, iters):
    """Newton iterations on (heading, horizontal speed, v_z) of one shot.

    A regular shot keeps its horizontal speed and lands its first bounce on ``target``; a serve
    (``serve`` True) lands its first bounce at x = ``first_x`` (its own half) and its second on
    ``target``: three conditions, three unknowns.

    Returns:
        (velocity (3,), distance [m] of the aimed bounce from its target (inf if it never lands),
        height [m] of the ball where it crosses the net before the aimed bounce).
    """

    def vel(u):
        return jnp.stack([u[1] * jnp.cos(u[0]), u[1] * jnp.sin(u[0]), u[2]])

    def f(u):
        first, second, _, _ = landing_points(model, pos, vel(u), spin, h, n_steps)
        reg = jnp.concatenate([first - target, (u[1] - speed)[None]])
        srv = jnp.concatenate([second - target, (first[0] - first_x)[None]])
        return jnp.where(serve, srv, reg)

    d = target - pos[:2]
    u = jnp.stack([jnp.arctan2(d[1], d[0]), speed, vz])
    lim = jnp.array([0.3, 2.0, 3.0], pos.dtype)
    eye = jnp.eye(3, dtype=pos.dtype)

    def step(u, val, jac):
        ok = jnp.abs(jnp.linalg.det(jac)) > 1e-12
        du = jnp.clip(jnp.linalg.solve(jnp.where(ok, jac, eye), val), -lim, lim)
        u_new = u - jnp.where(ok, du, 0.0)
        return u_new.at[1].set(jnp.clip(u_new[1], 1.0, 40.0))

    # one Newton step with the exact Jacobian (forward mode), then Broyden updates of it: each
    # further iteration costs one flight instead of four
    val, lin = jax.linearize(f, u)
    jac = jax.vmap(lin, out_axes=1)(eye)

    def broyden(_, c):
        u, val, jac = c
        u_new = step(u, val, jac)
        val_new = f(u_new)
        du, df = u_new - u, val_new - val
        jac = jac + jnp.outer(df - jac @ du, du) / jnp.maximum(jnp.dot(du, du), 1e-12)
        return u_new, val_new, jac

    u, val, jac = jax.lax.fori_loop(0, iters, broyden, (u, val, jac))
    first, second, twice, net = landing_points(model, pos, vel(u), spin, h, n_steps)
    miss = jnp.where(serve, safe_norm(second - target) + jnp.abs(first[0] - first_x), safe_norm(first - target))
    return vel(u), jnp.where(twice | ~serve, miss, jnp.inf), jnp.where(serve, net[1], net[0])


@partial(jax.jit, static_argnames=("n_steps",))
def aim_batch(model, pos, spin, speed, vz, target, first_x, serve, h, n_steps, iters):
    return jax.vmap(aim_one, in_axes=(None, 0, 0, 0, 0, 0, 0, 0, None, None, None))(
        model, pos, spin, speed, vz, target, first_x, serve, h, n_steps, iters)


def refine_aim(model, ball: Ball, target_xy, bounce=None, first_x=None, max_up=None, iters: int = 4,
               dt: float = 0.02, t_max: float = 1.8):
    """Aims each shot through the flight model (:func:`aim_batch`) so its bounce lands on target.

    Arguments:
        model: the model to aim with. ball: (N, 3) initial states (velocity: the first guess; its
            horizontal speed is kept for regular shots). target_xy: (N, 2) targets.
        bounce: (N,) 1 for serves (first bounce at x = ``first_x``, second on the target), 0 for
            the others (first bounce on the target); default all 0.
        first_x: (N,) where serves bounce first [m].
        max_up: (N,) largest initial upward speed [m/s]: a shot whose aim would need more keeps
            its first guess (a push is never turned into a lob).
        iters, dt, t_max: Broyden iterations, step and horizon of the aiming flights.

    Returns:
        The ball with aimed velocities (numpy fields).
    """
    import jax.numpy as jnp

    n = len(ball.pos)
    vel0 = np.asarray(ball.vel)
    dtype = np.asarray(ball.pos).dtype
    serve = np.zeros(n, bool) if bounce is None else np.asarray(bounce) == 1
    first_x = np.zeros(n) if first_x is None else np.asarray(first_x)
    j = lambda a: jnp.asarray(np.asarray(a, dtype))  # noqa: E731
    vel, _, _ = aim_batch(model, j(ball.pos), j(ball.spin), j(np.linalg.norm(vel0[:, :2], axis=-1)), j(vel0[:, 2]),
                          j(target_xy), j(first_x), jnp.asarray(serve), j(dt),
                          int(round(t_max / dt)), jnp.asarray(iters))
    vel = np.asarray(vel)
    keep = ~np.isfinite(vel).all(-1)
    if max_up is not None:
        keep |= vel[:, 2] > np.asarray(max_up)
    vel = np.where(keep[:, None], vel0, vel).astype(vel0.dtype)
    return Ball(pos=np.asarray(ball.pos), vel=vel, spin=np.asarray(ball.spin))


def sample_shots(n: int, seed: int = 0, types=None, mirror: float = 0.0, radius: float = 0.02, model=None):
    """Samples ``n`` shots.

    Arguments:
        n: number of shots.
        seed: seed of the numpy generator.
        types: shot type names to draw from (uniformly); default all of :data:`SHOT_TYPES`.
        mirror: fraction of shots sent along -x instead (from the other end).
        radius: ball radius [m] (the aimed bounce is at z = radius).
        model: if given, each shot is aimed through this model (:func:`refine_aim`), so its first
            bounce lands near its target; otherwise only the closed-form aim is used.

    Returns:
        (ball, labels): a :class:`~ttsim_jax.state.Ball` with (n, 3) float32 numpy fields and an
        (n,) array of shot type names.
    """
    rng = np.random.default_rng(seed)
    names = list(types or SHOT_TYPES)
    unknown = set(names) - set(SHOT_TYPES)
    if unknown:
        raise ValueError(f"unknown shot types {sorted(unknown)}; known: {list(SHOT_TYPES)}")
    labels = np.asarray(names)[rng.integers(0, len(names), n)]
    start, target, speed, top, side = (np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n), np.zeros(n), np.zeros(n))
    bounce, max_up, first_x = np.zeros(n, np.int32), np.zeros(n), np.zeros(n)
    for name in names:
        k = labels == name
        m = int(k.sum())
        s = SHOT_TYPES[name]
        u = lambda r: rng.uniform(r[0], r[1], m)  # noqa: E731
        start[k] = np.stack([u(s.start_x), u(s.start_y), u(s.start_z)], -1)
        target[k] = np.stack([u(s.target_x), u(s.target_y), np.full(m, radius)], -1)
        speed[k], top[k], side[k] = u(s.speed), u(s.topspin), u(s.sidespin)
        bounce[k], max_up[k], first_x[k] = s.bounce, s.max_up, u(s.first_x)
    vel = aim(start, target, speed, top)
    heading = vel[:, :2] / np.linalg.norm(vel[:, :2], axis=-1, keepdims=True)
    across = np.stack([-heading[:, 1], heading[:, 0], np.zeros(n)], -1)  # z x heading: topspin axis
    spin = top[:, None] * across + side[:, None] * np.array([0.0, 0.0, 1.0])
    ball = Ball(pos=start, vel=vel, spin=spin)
    if model is not None:
        ball = refine_aim(model, ball, target[:, :2], bounce, first_x, max_up)
    start, vel = np.asarray(ball.pos), np.asarray(ball.vel)
    flip = rng.random(n) < mirror
    # turning the scene 180 degrees about z maps x, y -> -x, -y for positions, velocities and spins
    turn = np.where(flip[:, None], np.array([-1.0, -1.0, 1.0]), 1.0)
    ball = Ball(pos=(start * turn).astype(np.float32), vel=(vel * turn).astype(np.float32),
                spin=(spin * turn).astype(np.float32))
    return ball, labels
