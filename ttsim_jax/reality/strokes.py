"""A player's stroke: where on the face the ball is met, which shot, and where it is aimed.

:func:`choose_shot` picks a return shot type plausible for where the ball is met;
:func:`sample_contact_points` draws the contact point on the racket face by distance band;
:func:`aim_shots` aims a batch of shots through the flight model (with the spin a racket can give,
:func:`achievable_spin`, and over the net, :func:`clear_net`). The racket state that plays the
aimed ball comes from :mod:`ttsim_jax.reality.inversion`.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ttsim_jax.physics.dimensions import NET_HEIGHT
from ttsim_jax.shots import DRAG_AIM, MAGNUS_AIM, aim, aim_batch

from .padding import bucket, pad

#: Step [s] and horizon [s] of the light flight used to aim shots.
AIM_STEP, AIM_HORIZON = 0.02, 1.8
#: Height of the ball centre [m] that just touches the top of the net.
NET_TOP = NET_HEIGHT + 0.02


def sample_contact_points(rng: np.random.Generator, n: int, face, bands) -> np.ndarray:
    """(n, 2) contact points (d_y, d_z) inside the elliptic face, drawn by distance band.

    Band 0: 0-5 cm, band 1: 5-8 cm, band 2: beyond 8 cm (up to the outline), with probabilities
    ``bands``; uniform over the area of each band's part of the face.

    Arguments:
        rng: the random stream.
        n: number of points.
        face: (y, z) semi-axes of the face outline [m].
        bands: the three band probabilities (normalised here).

    Returns:
        (n, 2) contact points [m].
    """
    a, b = face
    p = np.asarray(bands, np.float64) / np.sum(bands)
    which = rng.choice(3, size=n, p=p)
    out = np.zeros((n, 2))
    edges = ((0.0, 0.05), (0.05, 0.08), (0.08, max(a, b)))
    for i in range(n):
        lo, hi = edges[which[i]]
        for _ in range(200):
            r = math.sqrt(rng.uniform(lo * lo, hi * hi))
            th = rng.uniform(0.0, 2.0 * math.pi)
            dy, dz = r * math.cos(th), r * math.sin(th)
            if (dy / a) ** 2 + (dz / b) ** 2 <= 0.97:
                break
        else:  # the band does not fit this face: fall back to the centre band
            r = math.sqrt(rng.uniform(0.0, 0.05**2))
            dy, dz = r * math.cos(th), r * math.sin(th)
        out[i] = dy, dz
    return out


def choose_shot(rng, weights: dict, dist: float, z: float) -> str:
    """A return shot type plausible for a ball met ``dist`` behind the net at height ``z``.

    Arguments:
        rng: the hitter's random stream.
        weights: relative frequency of each shot type of :data:`ttsim_jax.shots.SHOT_TYPES`.
        dist: distance of the ball behind the net [m].
        z: height of the ball [m].

    Returns:
        The shot type's name.
    """
    ok = {
        "topspin_drive": 1.2 <= dist <= 3.0,
        "backspin_drive": dist >= 1.7,
        "push": dist <= 1.8 and z <= 0.4,
        "block": dist <= 2.0,
        "smash": z >= 0.3 and dist <= 2.4,
        "lob": dist >= 2.3,
    }
    names = [k for k, v in ok.items() if v and weights.get(k, 0) > 0]
    if not names:
        return "topspin_drive" if weights.get("topspin_drive", 0) > 0 else max(weights, key=weights.get)
    w = np.asarray([weights[k] for k in names], np.float64)
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def clear_net(start, target, speed, top, min_speed=2.0, clearance=0.05, net=NET_TOP):
    """Lowers horizontal speeds until the closed-form arc clears the net by ``clearance``.

    Arguments:
        start, target: (n, 3) start and aimed bounce points [m].
        speed: (n,) horizontal speeds [m/s]; top: (n,) topspin [rad/s].
        min_speed: no speed is lowered below this [m/s].
        clearance: wanted height of the arc over ``net`` [m].
        net: height of the ball centre that touches the top of the net [m].

    Returns:
        (n,) the speeds, lowered where the arc was too low.
    """
    speed = speed.copy()
    for _ in range(12):
        d = target - start
        dist = np.hypot(d[:, 0], d[:, 1])
        t = dist / (DRAG_AIM * speed)
        g_eff = np.maximum(9.81 + MAGNUS_AIM * top * speed, 2.0)
        vz = d[:, 2] / t + 0.5 * g_eff * t
        frac = np.clip(-start[:, 0] / np.where(np.abs(d[:, 0]) > 1e-9, d[:, 0], 1e-9), 0.0, 1.0)
        tn = frac * t
        zn = start[:, 2] + vz * tn - 0.5 * g_eff * tn**2
        low = (zn < net + clearance) & (speed > min_speed)
        if not low.any():
            break
        speed = np.where(low, np.maximum(speed * 0.9, min_speed), speed)
    return speed


def achievable_spin(plain, v_in, w_in, v_out, w_want):
    """The spin a racket can give along with ``v_out``.

    The point contact changes only the tangential spin, by at most (kappa / r) |Dv| (see
    :func:`~ttsim_jax.reality.inversion.invert_contact`), and damps the normal spin by e_s; the
    face normal is taken along Dv here (close enough to aim).

    Arguments:
        plain: the :class:`~ttsim_jax.params.Model` the players believe.
        v_in, w_in: (n, 3) incoming velocity [m/s] and spin [rad/s].
        v_out: (n, 3) aimed outgoing velocity [m/s].
        w_want: (n, 3) wanted outgoing spin [rad/s].

    Returns:
        (n, 3) outgoing spin [rad/s] the racket can give.
    """
    p = plain.racket
    k = float(plain.ball.radius) / float(p.kappa)
    dv = v_out - v_in
    n = dv / np.maximum(np.linalg.norm(dv, axis=-1, keepdims=True), 1e-9)
    dw = w_want - w_in
    dw_t = dw - np.sum(dw * n, -1, keepdims=True) * n
    cap = np.minimum(1.0, 0.8 * np.linalg.norm(dv, axis=-1) / np.maximum(k * np.linalg.norm(dw_t, axis=-1), 1e-9))
    e_s = float(p.e_s) if p.kind == "updated" else 1.0
    return w_in + cap[:, None] * dw_t + (e_s - 1.0) * np.sum(w_in * n, -1, keepdims=True) * n


def aim_shots(plain, aim_iters: int, np_dtype, start, target, speed, top, side_spin, vz, first_x, serve, v_in, w_in):
    """Aimed outgoing velocities and spins of n shots (numpy in, numpy out).

    A shot whose aimed path would touch the net is aimed again, up to twice: slower (regular
    shots) or with both bounces farther from the net (serves), as a player clears the net.

    Arguments:
        plain: the :class:`~ttsim_jax.params.Model` the players believe (no effects).
        aim_iters: quasi-Newton iterations of :func:`ttsim_jax.shots.aim_batch`.
        np_dtype: float type of the simulation (``numpy.float32`` or ``numpy.float64``).
        start: (n, 3) ball positions at the contact [m].
        target: (n, 3) aimed bounce points [m].
        speed, top, side_spin, vz: (n,) shot speed [m/s], topspin and sidespin [rad/s], and a
            serve's vertical speed [m/s].
        first_x: (n,) x of a serve's first bounce, on the server's half [m].
        serve: (n,) bool, which shots are serves.
        v_in, w_in: (n, 3) incoming velocities [m/s] and spins [rad/s].

    Returns:
        (v_out (n, 3), spin_out (n, 3)): aimed outgoing velocities and spins (float64).
    """
    n = len(start)
    speed, first_x, target = speed.copy(), first_x.copy(), target.copy()
    regular = ~serve
    speed[regular] = clear_net(start[regular], target[regular], speed[regular], top[regular])
    v_out, spin_out = np.zeros((n, 3)), np.zeros((n, 3))
    todo = np.arange(n)
    for attempt in range(3):
        v0 = aim(start[todo], target[todo], speed[todo], top[todo])
        vz0 = np.where(serve[todo], vz[todo], v0[:, 2])
        heading = v0[:, :2] / np.linalg.norm(v0[:, :2], axis=-1, keepdims=True)
        across = np.stack([-heading[:, 1], heading[:, 0], np.zeros(len(todo))], -1)
        want = top[todo, None] * across + side_spin[todo, None] * np.array([0.0, 0.0, 1.0])
        spin_out[todo] = achievable_spin(plain, v_in[todo], w_in[todo], v0, want)
        batch = pad(dict(pos=start[todo], spin=spin_out[todo], speed=speed[todo], vz=vz0, target=target[todo, :2],
                          first_x=first_x[todo], serve=serve[todo]), bucket(len(todo)))
        j = lambda a: jnp.asarray(np.asarray(a).astype(np_dtype))  # noqa: E731
        v, _miss, net = aim_batch(plain, j(batch["pos"]), j(batch["spin"]), j(batch["speed"]), j(batch["vz"]), j(batch["target"]),
                                   j(batch["first_x"]), jnp.asarray(batch["serve"]), jnp.asarray(AIM_STEP, np_dtype),
                                   int(round(AIM_HORIZON / AIM_STEP)), jnp.asarray(aim_iters))
        v_out[todo] = np.asarray(v)[: len(todo)]
        low = np.asarray(net)[: len(todo)] < NET_TOP + 0.02
        if attempt == 2 or not low.any():
            break
        todo = todo[low]
        speed[todo] = np.where(serve[todo], speed[todo], np.maximum(0.85 * speed[todo], 2.0))
        back = np.sign(first_x[todo])
        first_x[todo] = np.where(serve[todo], back * np.minimum(np.abs(first_x[todo]) + 0.15, 1.3), first_x[todo])
        tx = target[todo, 0]
        target[todo, 0] = np.where(serve[todo], np.sign(tx) * np.minimum(np.abs(tx) + 0.15, 1.25), tx)
    return v_out, spin_out
