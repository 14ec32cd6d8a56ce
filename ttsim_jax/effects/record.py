"""Effects that act outside the simulator: errors in what the dataset records.

The reality generator simulates with the true states and applies these to what it writes: the
recorded racket states (racket-state error) and the ball observations (sensor effects). They
never change the simulated truth. Their methods work on numpy arrays with a numpy Generator.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from .base import Effect, Param, register


def rotation_matrix(rotvec) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 3) rotation vectors (Rodrigues)."""
    v = np.asarray(rotvec, np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    axis = np.where(angle > 1e-15, v / np.where(angle > 1e-15, angle, 1.0), 0.0)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], -2)
    a = angle[..., None]
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + np.sin(a) * k + (1.0 - np.cos(a)) * (k @ k)


def _np(x):
    return np.asarray(x, np.float64)


@register
@struct.dataclass
class RacketStateError(Effect):
    """Error of the recorded racket state (forward kinematics of a vibrating robot, clock offsets).

    The simulator uses the true racket; the dataset records the racket at t + dt_err (moved along
    its velocity and angular velocity), then offset by a constant bias plus per-contact vibration:
    pos += pos_bias + N(0, pos_std), vel += vel_bias + N(0, vel_std), ang_vel += N(0, ang_vel_std),
    orientation turned by the rotation vector rot_bias + N(0, rot_std); dt_err = time_bias +
    N(0, time_std). The stds are per axis.
    """

    pos_bias: jnp.ndarray
    pos_std: jnp.ndarray
    vel_bias: jnp.ndarray
    vel_std: jnp.ndarray
    rot_bias: jnp.ndarray
    rot_std: jnp.ndarray
    ang_vel_std: jnp.ndarray
    time_bias: jnp.ndarray
    time_std: jnp.ndarray

    NAME = "racket_state_error"
    DESCRIPTION = "recorded robot racket state off by a bias and vibration (~8 mm, 0.2 m/s, 0.7 deg) and a timing offset"
    WHERE = "record"
    SCOPE = "dataset"
    PARAMS = {
        "pos_bias": Param("m", 0.0, (0.005, -0.004, 0.005), "constant position offset (|.| ~ 8 mm)", (3,), plausible=(-0.03, 0.03)),
        "pos_std": Param("m", 0.0, 0.0046, "per-axis std of the position vibration (8 mm rms in 3-D)", plausible=(0.0, 0.02)),
        "vel_bias": Param("m/s", 0.0, (0.12, -0.1, 0.12), "constant velocity offset (|.| ~ 0.2 m/s)", (3,), plausible=(-0.5, 0.5)),
        "vel_std": Param("m/s", 0.0, 0.115, "per-axis std of the velocity vibration (0.2 m/s rms)", plausible=(0.0, 0.5)),
        "rot_bias": Param("rad", 0.0, (0.007, -0.007, 0.007), "constant orientation error, rotation vector (0.7 deg)", (3,), plausible=(-0.05, 0.05)),
        "rot_std": Param("rad", 0.0, 0.0071, "per-axis std of the orientation vibration (0.7 deg rms)", plausible=(0.0, 0.05)),
        "ang_vel_std": Param("rad/s", 0.0, 1.0, "per-axis std of the angular-velocity error", plausible=(0.0, 5.0)),
        "time_bias": Param("s", 0.0, 0.001, "constant timing offset of the racket record", plausible=(-0.01, 0.01)),
        "time_std": Param("s", 0.0, 0.001, "std of the timing offset per contact", plausible=(0.0, 0.01)),
    }

    @classmethod
    def _draw(cls, rng):
        def vec(mag):
            u = rng.normal(size=3)
            return u / np.linalg.norm(u) * mag * rng.uniform(0.5, 1.5)

        return {"pos_bias": vec(0.008), "pos_std": 0.0046 * rng.uniform(0.5, 1.5),
                "vel_bias": vec(0.2), "vel_std": 0.115 * rng.uniform(0.5, 1.5),
                "rot_bias": vec(np.deg2rad(0.7)), "rot_std": np.deg2rad(0.7) / np.sqrt(3) * rng.uniform(0.5, 1.5),
                "ang_vel_std": rng.uniform(0.5, 2.0), "time_bias": rng.uniform(-0.002, 0.002),
                "time_std": rng.uniform(0.0005, 0.002)}

    def record_racket(self, pos, rot, vel, ang_vel, rng: np.random.Generator):
        """The recorded (pos, rot, vel, ang_vel) of true racket states ((N, 3), (N, 3, 3), ...)."""
        pos, rot, vel, ang_vel = _np(pos), _np(rot), _np(vel), _np(ang_vel)
        n = len(pos)
        dt = _np(self.time_bias) + _np(self.time_std) * rng.normal(size=n)
        pos = pos + vel * dt[:, None]
        rot = rotation_matrix(ang_vel * dt[:, None]) @ rot
        pos = pos + _np(self.pos_bias) + _np(self.pos_std) * rng.normal(size=(n, 3))
        vel = vel + _np(self.vel_bias) + _np(self.vel_std) * rng.normal(size=(n, 3))
        ang_vel = ang_vel + _np(self.ang_vel_std) * rng.normal(size=(n, 3))
        rot = rotation_matrix(_np(self.rot_bias) + _np(self.rot_std) * rng.normal(size=(n, 3))) @ rot
        return pos, rot, vel, ang_vel


@register
@struct.dataclass
class PositionNoise(Effect):
    """Triangulation noise of the ball positions (and of the event positions derived from them)."""

    std: jnp.ndarray

    NAME = "position_noise"
    DESCRIPTION = "Gaussian noise on observed ball positions"
    WHERE = "record"
    SCOPE = "dataset"
    PARAMS = {"std": Param("m", 0.0, (0.0015, 0.0015, 0.001), "per-axis standard deviation", (3,), plausible=(0.0, 0.02))}

    @classmethod
    def _draw(cls, rng):
        return {"std": rng.uniform(0.0008, 0.0025) * np.array([1.0, 1.0, 0.7])}

    def observe_positions(self, pos, rng: np.random.Generator):
        """Noisy copies of (N, 3) true positions."""
        pos = _np(pos)
        return pos + _np(self.std) * rng.normal(size=pos.shape)


@register
@struct.dataclass
class SpinNoise(Effect):
    """Errors of the per-segment spin estimate, with confidences.

    A normal estimate is true * (1 + N(0, rel_std)) + N(0, abs_std) per axis, with confidence
    U(conf_min, 1); segments shorter than ``short_duration`` get twice the noise and their
    confidence times ``short_factor``. With probability ``outlier_prob`` the estimate is wrong
    (a random spin of similar size) and its confidence U(0, outlier_conf).
    """

    rel_std: jnp.ndarray
    abs_std: jnp.ndarray
    conf_min: jnp.ndarray
    outlier_prob: jnp.ndarray
    outlier_conf: jnp.ndarray
    short_duration: jnp.ndarray
    short_factor: jnp.ndarray

    NAME = "spin_noise"
    DESCRIPTION = "noisy spin estimates with confidences; occasional outliers with low confidence"
    WHERE = "record"
    SCOPE = "dataset"
    PARAMS = {
        "rel_std": Param("1", 0.0, 0.05, "relative noise of the spin estimate", plausible=(0.0, 0.5)),
        "abs_std": Param("rad/s", 0.0, 10.0, "absolute noise per axis", plausible=(0.0, 100.0)),
        "conf_min": Param("1", 1.0, 0.6, "lowest confidence of a normal estimate", plausible=(0.0, 1.0)),
        "outlier_prob": Param("1", 0.0, 0.04, "probability that an estimate is an outlier", plausible=(0.0, 0.5)),
        "outlier_conf": Param("1", 0.0, 0.4, "highest confidence of an outlier", plausible=(0.0, 1.0)),
        "short_duration": Param("s", 0.0, 0.15, "segments shorter than this are estimated worse", plausible=(0.0, 1.0)),
        "short_factor": Param("1", 1.0, 0.6, "confidence factor of short segments", plausible=(0.0, 1.0)),
    }

    @classmethod
    def _draw(cls, rng):
        return {"rel_std": rng.uniform(0.02, 0.08), "abs_std": rng.uniform(5.0, 20.0), "conf_min": rng.uniform(0.5, 0.8),
                "outlier_prob": rng.uniform(0.02, 0.06), "outlier_conf": rng.uniform(0.2, 0.45),
                "short_duration": 0.15, "short_factor": rng.uniform(0.4, 0.8)}

    def measure_spin(self, spin, duration, rng: np.random.Generator):
        """(spin (S, 3), conf (S,)) estimates of segments with true mean spin (S, 3) and durations (S,)."""
        spin, duration = _np(spin), _np(duration)
        s = len(spin)
        short = duration < _np(self.short_duration)
        noise = np.where(short, 2.0, 1.0)[:, None]
        est = spin * (1.0 + noise * _np(self.rel_std) * rng.normal(size=(s, 1))) + noise * _np(self.abs_std) * rng.normal(size=(s, 3))
        lo = _np(self.conf_min)
        conf = lo + (1.0 - lo) * rng.random(s)
        conf = np.where(short, conf * _np(self.short_factor), conf)
        out = rng.random(s) < _np(self.outlier_prob)
        mag = np.linalg.norm(spin, axis=-1, keepdims=True) * rng.uniform(0.3, 1.5, (s, 1)) + 50.0
        u = rng.normal(size=(s, 3))
        wrong = u / np.linalg.norm(u, axis=-1, keepdims=True) * mag
        est = np.where(out[:, None], wrong, est)
        conf = np.where(out, _np(self.outlier_conf) * rng.random(s), conf)
        return est, np.clip(conf, 0.0, 1.0)


@register
@struct.dataclass
class MissingFrames(Effect):
    """Frames lost to occlusion or dropped by the tracker: single frames and bursts."""

    drop_prob: jnp.ndarray
    burst_rate: jnp.ndarray
    burst_frames: jnp.ndarray

    NAME = "missing_frames"
    DESCRIPTION = "missing observations: isolated dropped frames and occlusion bursts"
    WHERE = "record"
    SCOPE = "dataset"
    PARAMS = {
        "drop_prob": Param("1", 0.0, 0.02, "probability that a single frame is missing", plausible=(0.0, 0.5)),
        "burst_rate": Param("1/s", 0.0, 0.3, "occlusion bursts per second of play", plausible=(0.0, 5.0)),
        "burst_frames": Param("1", 0.0, 6.0, "mean length of a burst in frames", plausible=(0.0, 50.0)),
    }

    @classmethod
    def _draw(cls, rng):
        return {"drop_prob": rng.uniform(0.005, 0.04), "burst_rate": rng.uniform(0.1, 0.5), "burst_frames": rng.uniform(3.0, 10.0)}

    def drop_frames(self, t, rng: np.random.Generator):
        """(N,) bool mask of the frames kept, for one session's frame times ``t`` (sorted)."""
        t = _np(t)
        keep = rng.random(len(t)) >= _np(self.drop_prob)
        if len(t) and float(self.burst_rate) > 0 and float(self.burst_frames) > 0:
            frame = float(np.median(np.diff(t))) if len(t) > 1 else 0.005
            # bursts per second of observed play (gaps between rallies hold no frames)
            n_bursts = rng.poisson(float(self.burst_rate) * len(t) * frame)
            starts = rng.integers(0, len(t), n_bursts)
            lengths = rng.geometric(1.0 / max(float(self.burst_frames), 1.0), n_bursts)
            for a, n in zip(starts, lengths):
                keep[a : a + n] = False
        return keep
