"""The shots a sensitivity study differentiates: a ball meeting a racket, then flying to its landing.

A shot is the ball a few steps before it meets the racket and the racket's state at the meeting;
the racket is in play for :data:`WINDOW` steps around it (moving with its velocity), so the rally
kernel finds the contact, its time of impact and the racket response itself, and a racket moved
by a few centimetres along its normal still meets the ball inside the window. Shots come from two places:

* :func:`sampled_shots`: realistic returns by shot type (``ttsim_jax.shots``): for each, an incoming
  ball and a contact position on the face are drawn, and the racket pose and velocity that send
  the ball off as the shot type asks are solved for through the model's racket contact
  (Gauss-Newton), so the racket state is a real input of the shot.
* :func:`dataset_shots`: a dataset's racket contacts with a racket state, with the ball state before
  the contact fitted from the observations (``ttsim_jax.data.contact_states``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.physics import racket as racket_stage
from ttsim_jax.physics.numerics import safe_norm
from ttsim_jax.state import Ball, Racket

FACE = (0.0775, 0.0755)  # ITTF-sized face semi-axes [m], as Racket.create
# Steps the racket is in play; the nominal contact is in the middle of the window, so a racket
# moved along its normal by up to (WINDOW / 2 - 0.5) dt times the relative normal speed (17 mm at
# 1 ms and 5 m/s) is still met in it.
WINDOW = 8


def contact_time(dt):
    """Time from a shot's start to its nominal contact: the middle of step WINDOW / 2 - 1."""
    return (WINDOW // 2 - 0.5) * dt


@dataclass
class ShotSet:
    """Shots with the labels a report groups them by.

    Attributes:
        ball: :class:`Ball` (B, 3) numpy fields at the start (:func:`contact_time` before the contact).
        racket: :class:`Racket` (B, ...) numpy fields at the contact.
        label: (B,) shot type (or dataset session) names.
        speed: (B,) speed of the ball leaving the racket as aimed [m/s].
        spin: (B,) signed topspin of the ball leaving the racket as aimed [rad/s] (negative: backspin).
        contact: (B, 2) contact position (d_y, d_z) on the face [m].
        source: where the shots came from ("sampled" or the dataset path).
    """

    ball: Ball
    racket: Racket
    label: np.ndarray
    speed: np.ndarray
    spin: np.ndarray
    contact: np.ndarray
    source: str = "sampled"
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.label)

    def take(self, index) -> "ShotSet":
        """The shots at ``index`` (any numpy index)."""
        pick = lambda a: np.asarray(a)[index]  # noqa: E731
        return ShotSet(jax.tree.map(pick, self.ball), jax.tree.map(pick, self.racket), pick(self.label),
                       pick(self.speed), pick(self.spin), pick(self.contact), self.source, dict(self.meta))


def face_frame(normal):
    """(..., 3, 3) racket rotation whose x-axis is ``normal`` and whose z-axis (handle to tip) is as
    close to world up as the normal allows."""
    n = normal / safe_norm(normal, keepdims=True)
    up = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], n.dtype), n.shape)
    z = up - jnp.sum(up * n, -1, keepdims=True) * n
    z = z / safe_norm(z, keepdims=True)
    y = jnp.cross(z, n)
    return jnp.stack([n, y, z], axis=-1)


def contact_racket(normal, vel, ang_vel, ball_pos, d, radius):
    """The racket (single, (…) fields) whose face touches the ball at ``ball_pos`` at position ``d``."""
    rot = face_frame(normal)
    pos = ball_pos - radius * rot[:, 0] - rot[:, 1] * d[0] - rot[:, 2] * d[1]
    return Racket(pos=pos, rot=rot, vel=vel, ang_vel=ang_vel, face=jnp.asarray(FACE, pos.dtype))


def _solve_racket(params, radius, mass, pos, vel_in, spin_in, vel_out, spin_out, d, iters=12):
    """Gauss-Newton (damped) for the face normal (two angles) and racket velocity (3) that send a
    ball arriving with (vel_in, spin_in) off with (vel_out, spin_out); the spin error is weighted by
    the radius (surface speed), the racket does not spin. Returns (normal, racket velocity)."""
    n0 = (vel_out - vel_in) / safe_norm(vel_out - vel_in)
    e = 0.85
    vn = (jnp.dot(vel_out, n0) + e * jnp.dot(vel_in, n0)) / (1 + e)
    u0 = jnp.concatenate([jnp.zeros(2, pos.dtype), vn * n0 + (vel_out - jnp.dot(vel_out, n0) * n0)])
    t1 = jnp.cross(n0, jnp.array([0.0, 0.0, 1.0], pos.dtype))
    t1 = t1 / safe_norm(t1)
    t2 = jnp.cross(n0, t1)
    zero = jnp.zeros(3, pos.dtype)

    def residual(u):
        n = n0 + u[0] * t1 + u[1] * t2
        rk = contact_racket(n, u[2:], zero, pos, d, radius)
        v, w, _ = racket_stage.racket_contact(params, rk, radius, mass, pos, vel_in, spin_in)
        return jnp.concatenate([v - vel_out, radius * (w - spin_out)])

    def body(_, u):
        r = residual(u)
        j = jax.jacfwd(residual)(u)
        h = j.T @ j
        du = jnp.linalg.solve(h + 1e-3 * jnp.diag(jnp.diag(h)) + 1e-9 * jnp.eye(5, dtype=u.dtype), j.T @ r)
        return u - jnp.clip(du, -2.0, 2.0)

    u = jax.lax.fori_loop(0, iters, body, u0)
    n = n0 + u[0] * t1 + u[1] * t2
    return n / safe_norm(n), u[2:]


@jax.jit
def _solve_batch(params, radius, mass, pos, vel_in, spin_in, vel_out, spin_out, d):
    return jax.vmap(_solve_racket, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0))(
        params, radius, mass, pos, vel_in, spin_in, vel_out, spin_out, d)


def start_state(ball_pos, vel_in, spin_in, dt):
    """The ball :func:`contact_time` before it is at ``ball_pos``, backed off along a straight line
    (gravity would move it by g t^2 / 2, 0.06 mm at 1 ms steps: the contact point moves by that)."""
    return Ball(pos=ball_pos - contact_time(dt) * vel_in, vel=vel_in, spin=spin_in)


def sampled_shots(model, n: int, seed: int = 0, types=None, dt: float = 1e-3, aim: bool = True) -> ShotSet:
    """``n`` returns sampled by shot type, each a ball arriving at a racket that plays the shot.

    The outgoing ball (where it leaves, its aimed velocity and spin) is drawn and aimed through the
    model by :func:`ttsim_jax.shots.sample_shots`; the incoming ball (4-9 m/s from the far side,
    -300 to 300 rad/s of top- or backspin) and the contact position on the face (within half the
    face) are drawn here; the racket is solved for (:func:`_solve_racket`). Where the racket model
    cannot give the exact aimed spin, the shot is the one the solved racket plays.

    Arguments:
        model: the model (its racket parameters and flight aim the shots).
        n: number of shots. seed: numpy seed. types: shot type names (default all).
        dt: the step the shots will be simulated with (the ball starts :func:`contact_time` before the contact).
        aim: aim each outgoing ball through the model (else the closed-form aim only: faster,
            more shots miss).

    Returns:
        A :class:`ShotSet` in the model's float dtype.
    """
    from ttsim_jax.shots import sample_shots

    out, labels = sample_shots(n, seed=seed, types=types, model=model if aim else None)
    rng = np.random.default_rng(seed + 1)
    heading = out.vel[:, :2] / np.linalg.norm(out.vel[:, :2], axis=-1, keepdims=True)
    across = np.concatenate([-heading[:, 1:2], heading[:, 0:1], np.zeros((n, 1))], -1)
    speed_in = rng.uniform(4.0, 9.0, n)
    vel_in = np.stack([-speed_in, rng.uniform(-1.0, 1.0, n), rng.uniform(-1.0, 2.0, n)], -1)
    spin_in = rng.uniform(-300.0, 300.0, (n, 1)) * across  # about the across axis: top- or backspin
    r = np.sqrt(rng.uniform(0.0, 0.25, n)) * np.asarray(FACE).min()
    phi = rng.uniform(0.0, 2 * np.pi, n)
    d = np.stack([r * np.cos(phi), r * np.sin(phi)], -1)
    topspin = np.sum(np.asarray(out.spin) * across, -1)
    return shots_from_states(model, out.pos, vel_in, spin_in, out.vel, out.spin, d, dt=dt, label=labels,
                             topspin=topspin)


def shots_from_states(model, pos, vel_in, spin_in, vel_out, spin_out, d, *, dt: float = 1e-3, label=None,
                      topspin=None) -> ShotSet:
    """Shots whose racket is solved (:func:`_solve_racket`) to turn the incoming ball into the outgoing one.

    Arguments:
        model: the model (racket parameters, ball, float dtype).
        pos: (B, 3) ball centre at the contact. vel_in, spin_in: (B, 3) the ball arriving.
        vel_out, spin_out: (B, 3) the ball leaving as wanted. d: (B, 2) contact position on the face.
        dt: the step the shots will be simulated with. label: (B,) names (default "shot").
        topspin: (B,) signed topspin for the report (default: the spin about the horizontal axis
            across the outgoing path).

    Returns:
        A :class:`ShotSet`.
    """
    dtype = np.dtype(model.ball.radius.dtype)
    n = len(pos)
    j = lambda a: jnp.asarray(np.asarray(a, dtype))  # noqa: E731
    radius, mass = model.ball.radius, model.ball.mass
    normal, vel_r = _solve_batch(model.racket, radius, mass, j(pos), j(vel_in), j(spin_in), j(vel_out),
                                 j(spin_out), j(d))
    zero = jnp.zeros_like(normal)
    rk = jax.vmap(contact_racket, in_axes=(0, 0, 0, 0, 0, None))(normal, vel_r, zero, j(pos), j(d), radius)
    ball = start_state(j(pos), j(vel_in), j(spin_in), dt)
    if topspin is None:
        v = np.asarray(vel_out, np.float64)
        h = v[:, :2] / np.maximum(np.linalg.norm(v[:, :2], axis=-1, keepdims=True), 1e-9)
        topspin = np.asarray(spin_out)[:, 0] * -h[:, 1] + np.asarray(spin_out)[:, 1] * h[:, 0]
    return ShotSet(ball=jax.tree.map(np.asarray, ball), racket=jax.tree.map(np.asarray, rk),
                   label=np.asarray(["shot"] * n if label is None else label),
                   speed=np.linalg.norm(np.asarray(vel_out), axis=-1).astype(dtype),
                   spin=np.asarray(topspin).astype(dtype), contact=np.asarray(d).astype(dtype))


def dataset_shots(model, path, dt: float = 1e-3, limit: int | None = None) -> ShotSet:
    """The racket contacts of the dataset at ``path`` that have a racket state and fitted ball states.

    The ball before the contact is the fitted incoming state (``ttsim_jax.data.contact_states``:
    velocity from a polynomial fit, spin from the segment); the racket is the dataset's. Speed,
    spin and label are those of the fitted outgoing ball and the contact's session.

    Arguments:
        model: the model (its float dtype is used). path: dataset directory. dt: simulation step.
        limit: keep at most this many contacts (the first ones).

    Returns:
        A :class:`ShotSet`; empty datasets raise ``DataError``.
    """
    from ttsim_jax.data import errors
    from ttsim_jax.data.batch import racket_contact_batch
    from ttsim_jax.data.io import load as load_dataset
    from ttsim_jax.fit.racket_arrays import contact_arrays
    from ttsim_jax.physics.rotations import quat_to_matrix

    ds = load_dataset(path)
    arrays = contact_arrays(ds, model=model)
    if len(arrays) == 0:
        raise errors.DataError(f"{path}: no racket contact with a racket state and fitted ball states "
                               f"(skipped: {arrays.counts()})")
    batch = racket_contact_batch(ds, dtype=np.float64)
    ids = np.asarray(batch.event_id)
    row = {int(e): i for i, e in enumerate(ids) if bool(batch.mask[i])}
    idx = np.asarray([row[int(e)] for e in arrays.event_id])
    if limit is not None:
        idx, keep = idx[:limit], slice(0, limit)
    else:
        keep = slice(None)
    dtype = np.dtype(model.ball.radius.dtype)
    j = lambda a: jnp.asarray(np.asarray(a, dtype))  # noqa: E731
    rk = Racket(pos=j(np.asarray(batch.racket_position)[idx]), rot=j(quat_to_matrix(np.asarray(batch.racket_quat)[idx])),
                vel=j(np.asarray(batch.racket_velocity)[idx]), ang_vel=j(np.asarray(batch.racket_ang_vel)[idx]),
                face=j(np.broadcast_to(FACE, (len(idx), 2))))
    w_in, w_out = arrays.world_in[keep], arrays.world_out[keep]
    ball = start_state(j(np.asarray(batch.ball_position)[idx]), j(w_in[:, :3]), j(w_in[:, 3:]), dt)
    vel_out, spin_out = w_out[:, :3], w_out[:, 3:]
    heading = vel_out[:, :2] / np.maximum(np.linalg.norm(vel_out[:, :2], axis=-1, keepdims=True), 1e-9)
    across = np.concatenate([-heading[:, 1:2], heading[:, 0:1], np.zeros((len(idx), 1))], -1)
    session = np.asarray(arrays.session_id[keep])
    return ShotSet(ball=jax.tree.map(np.asarray, ball), racket=jax.tree.map(np.asarray, rk),
                   label=np.asarray([f"session {s}" for s in session]),
                   speed=np.linalg.norm(vel_out, axis=-1).astype(dtype),
                   spin=np.sum(spin_out * across, -1).astype(dtype),
                   contact=np.asarray(batch.contact_point)[idx].astype(dtype), source=str(path))
