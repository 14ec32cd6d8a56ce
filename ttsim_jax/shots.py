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

from ttsim_jax.state import Ball

G = 9.81


@dataclass(frozen=True)
class ShotType:
    """Ranges (low, high) of one kind of shot.

    Attributes:
        start_x, start_y, start_z: where the ball leaves the racket [m] (x behind the end line at
            -1.37 for shots from the -x end).
        speed: horizontal speed [m/s].
        target_x, target_y: aimed first bounce [m].
        topspin: spin about the horizontal axis perpendicular to the path [rad/s]; negative is
            backspin.
        sidespin: spin about z [rad/s].
        bounce: which bounce the target is for (the serve aims its second bounce, on the far half).
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


SHOT_TYPES: dict[str, ShotType] = {
    # the serve bounces on the server's own half first
    "serve": ShotType((-1.6, -1.4), (-0.6, 0.6), (0.2, 0.35), (2.5, 5.0), (0.3, 1.1), (-0.6, 0.6),
                      (-500.0, 400.0), (-400.0, 400.0), bounce=1, max_up=2.0),
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


def _heading_velocity(speed, u):
    import jax.numpy as jnp

    return jnp.stack([speed * jnp.cos(u[:, 0]), speed * jnp.sin(u[:, 0]), u[:, 1]], -1)


def _newton_step(model, pos, spin, speed, bounce, max_up, u, target, dt, n_steps):
    """One damped Newton step on (heading, v_z) of every ball towards its target bounce."""
    import jax
    import jax.numpy as jnp

    from ttsim_jax.rally import simulate

    def landing(u):
        r = simulate(model, Ball(pos, _heading_velocity(speed, u), spin), n_steps, dt)
        return jnp.take_along_axis(r.events.pre.pos[:, :, :2], bounce[:, None, None], axis=1)[:, 0]

    f0, j0 = jax.jvp(landing, (u,), (jnp.zeros_like(u).at[:, 0].set(1.0),))
    _, j1 = jax.jvp(landing, (u,), (jnp.zeros_like(u).at[:, 1].set(1.0),))
    jac = jnp.stack([j0, j1], -1)  # (N, 2, 2)
    ok = jnp.abs(jnp.linalg.det(jac)) > 1e-9
    step = jnp.linalg.solve(jnp.where(ok[:, None, None], jac, jnp.eye(2)), (f0 - target)[..., None])[..., 0]
    step = jnp.clip(step, jnp.array([-0.3, -3.0]), jnp.array([0.3, 3.0]))  # damp wild steps
    u = u - jnp.where(ok[:, None], step, 0.0)
    return u.at[:, 1].set(jnp.minimum(u[:, 1], max_up))


_newton_jit = None


def refine_aim(model, ball: Ball, target_xy, bounce=None, max_up=None, iters: int = 3, dt: float = 4e-3,
               t_max: float = 1.6):
    """Newton iterations through the simulator so each shot's target bounce lands on its target.

    The unknowns are each ball's heading and vertical speed (its horizontal speed and spin are
    kept). The landing point is where the ball comes down to the table plane (a table widened to
    be unmissable; the net is not modelled), and its Jacobian comes from two forward-mode passes
    through the batched simulation.

    Arguments:
        model: the model to aim with. ball: (N, 3) initial states. target_xy: (N, 2) targets.
        bounce: (N,) which bounce each target is for (default: the first).
        max_up: (N,) largest initial upward speed [m/s] (default: unbounded).
        iters: Newton iterations. dt, t_max: step and horizon of the aiming simulations.

    Returns:
        The ball with adjusted velocities (numpy fields).
    """
    global _newton_jit
    import jax
    import jax.numpy as jnp

    if _newton_jit is None:
        _newton_jit = jax.jit(_newton_step, static_argnames=("n_steps",))
    big = model.table.length * 0 + 1e3
    wide = model.replace(table=model.table.replace(length=big, width=big), effects=())
    pos, spin, vel = jnp.asarray(ball.pos), jnp.asarray(ball.spin), jnp.asarray(ball.vel)
    speed = jnp.linalg.norm(vel[:, :2], axis=-1)
    bounce = jnp.zeros(pos.shape[0], jnp.int32) if bounce is None else jnp.asarray(bounce, jnp.int32)
    u = jnp.stack([jnp.arctan2(vel[:, 1], vel[:, 0]), vel[:, 2]], -1)
    target = jnp.asarray(target_xy, u.dtype)
    max_up = jnp.full(pos.shape[0], jnp.inf, u.dtype) if max_up is None else jnp.asarray(max_up, u.dtype)
    for _ in range(iters):
        u = _newton_jit(wide, pos, spin, speed, bounce, max_up, u, target, jnp.asarray(dt, u.dtype),
                        n_steps=int(round(t_max / dt)))
    return Ball(pos=np.asarray(ball.pos), vel=np.asarray(_heading_velocity(speed, u), dtype=np.asarray(ball.vel).dtype),
                spin=np.asarray(ball.spin))


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
    bounce, max_up = np.zeros(n, np.int32), np.zeros(n)
    for name in names:
        k = labels == name
        m = int(k.sum())
        s = SHOT_TYPES[name]
        u = lambda r: rng.uniform(r[0], r[1], m)  # noqa: E731
        start[k] = np.stack([u(s.start_x), u(s.start_y), u(s.start_z)], -1)
        target[k] = np.stack([u(s.target_x), u(s.target_y), np.full(m, radius)], -1)
        speed[k], top[k], side[k] = u(s.speed), u(s.topspin), u(s.sidespin)
        bounce[k], max_up[k] = s.bounce, s.max_up
    vel = aim(start, target, speed, top)
    heading = vel[:, :2] / np.linalg.norm(vel[:, :2], axis=-1, keepdims=True)
    across = np.stack([-heading[:, 1], heading[:, 0], np.zeros(n)], -1)  # z x heading: topspin axis
    spin = top[:, None] * across + side[:, None] * np.array([0.0, 0.0, 1.0])
    ball = Ball(pos=start, vel=vel, spin=spin)
    if model is not None:
        ball = refine_aim(model, ball, target[:, :2], bounce, max_up)
    start, vel = np.asarray(ball.pos), np.asarray(ball.vel)
    flip = rng.random(n) < mirror
    # turning the scene 180 degrees about z maps x, y -> -x, -y for positions, velocities and spins
    turn = np.where(flip[:, None], np.array([-1.0, -1.0, 1.0]), 1.0)
    ball = Ball(pos=(start * turn).astype(np.float32), vel=(vel * turn).astype(np.float32),
                spin=(spin * turn).astype(np.float32))
    return ball, labels
