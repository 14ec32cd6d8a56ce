"""Rigid transforms from a source's coordinate frame to the canonical table frame, and the
measurement of where a source's table surface lies (from its bounces)."""

from __future__ import annotations

import dataclasses

import numpy as np

from . import schema


@dataclasses.dataclass(frozen=True)
class FrameTransform:
    """``p_canonical = rotation @ p_source + translation`` (a proper rotation: det = +1).

    Attributes:
        rotation: (3, 3) rotation matrix.
        translation: (3,) translation [m].
    """

    rotation: np.ndarray
    translation: np.ndarray

    def points(self, p) -> np.ndarray:
        """Maps (..., 3) positions."""
        return np.asarray(p, np.float64) @ self.rotation.T + self.translation

    def vectors(self, v) -> np.ndarray:
        """Maps (..., 3) free vectors (velocities, angular velocities)."""
        return np.asarray(v, np.float64) @ self.rotation.T


def rotation_between(a, b) -> np.ndarray:
    """The smallest rotation taking direction ``a`` to direction ``b`` (Rodrigues)."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-15:
        if c > 0:
            return np.eye(3)
        raise ValueError("opposite directions: rotation axis undefined")
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def table_frame(axes, plane=(0.0, 0.0, 0.0), shift_xy=(0.0, 0.0), radius: float = schema.BALL_RADIUS) -> FrameTransform:
    """Builds the transform source -> canonical from measured table facts.

    Arguments:
        axes: (3, 3) proper rotation taking source axes to table-aligned axes (x along the table).
        plane: ``(a, b, c)`` of the plane ``z = a x + b y + c`` on which the ball centres sit at
            table bounces, measured in the table-aligned axes.
        shift_xy: translation along x and y [m] applied last (moves the table centre to the origin).
        radius: ball radius [m]: the bounce plane is moved to z = radius.

    Returns:
        The :class:`FrameTransform`.
    """
    axes = np.asarray(axes, np.float64)
    if abs(np.linalg.det(axes) - 1.0) > 1e-9:
        raise ValueError("axes must be a proper rotation (det +1) so that spin vectors keep their sense")
    a, b, c = plane
    tilt = rotation_between([-a, -b, 1.0], [0.0, 0.0, 1.0])
    rot = tilt @ axes
    on_plane = tilt @ np.array([0.0, 0.0, c])
    translation = np.array([shift_xy[0], shift_xy[1], radius - on_plane[2]])
    return FrameTransform(rot, translation)


def fit_bounce_plane(points, *, tilt: bool = True, outlier: float = 0.03) -> dict:
    """Fits the plane of bounce contact points (ball centres at table contacts).

    Arguments:
        points: (N, 3) contact points [m].
        tilt: fit ``z = a x + b y + c`` (True) or only a height ``z = c``.
        outlier: points farther than this from the median height are ignored [m].

    Returns:
        dict with ``a``, ``b``, ``c``, ``median`` (median height), ``n`` (points used), ``std``
        (residual standard deviation) and ``max_abs`` (largest residual).
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    keep = np.abs(p[:, 2] - np.median(p[:, 2])) <= outlier
    q = p[keep]
    if tilt:
        design = np.c_[q[:, 0], q[:, 1], np.ones(len(q))]
        (a, b, c), *_ = np.linalg.lstsq(design, q[:, 2], rcond=None)
    else:
        a, b, c = 0.0, 0.0, float(np.median(q[:, 2]))
    r = q[:, 2] - (a * q[:, 0] + b * q[:, 1] + c)
    return {
        "a": float(a),
        "b": float(b),
        "c": float(c),
        "median": float(np.median(q[:, 2])),
        "n": int(len(q)),
        "std": float(np.std(r)),
        "max_abs": float(np.max(np.abs(r))) if len(r) else float("nan"),
    }
