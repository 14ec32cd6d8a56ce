"""Rotation matrices <-> unit quaternions (w, x, y, z), in NumPy.

The measured-data format stores racket orientations as quaternions (``qw, qx, qy, qz``, racket
frame -> world frame) and the simulator works with rotation matrices (columns: face normal, y, z);
these two functions convert between them for every layer that reads or writes racket states.
"""

from __future__ import annotations

import numpy as np


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrices of unit quaternions.

    Arguments:
        q: (..., 4) quaternions (w, x, y, z); normalised first.

    Returns:
        (..., 3, 3) rotation matrices (float64).
    """
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quat(m) -> np.ndarray:
    """Unit quaternions of rotation matrices, by Shepperd's method.

    Arguments:
        m: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) unit quaternions (w, x, y, z) with w >= 0 (float64).
    """
    m = np.asarray(m, np.float64)
    r = m.reshape(-1, 3, 3)
    tr = np.trace(r, axis1=1, axis2=2)
    # dividing by the largest of the four terms keeps the square root away from zero (rotations
    # by about 180 degrees, where the trace alone loses every digit)
    k = np.argmax(np.stack([tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], -1), -1)
    q = np.zeros((len(r), 4))
    for case in range(4):
        i = k == case
        if not i.any():
            continue
        rr = r[i]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[i])
            q[i] = np.stack([0.25 * s, (rr[:, 2, 1] - rr[:, 1, 2]) / s, (rr[:, 0, 2] - rr[:, 2, 0]) / s,
                             (rr[:, 1, 0] - rr[:, 0, 1]) / s], -1)
        elif case == 1:
            s = 2.0 * np.sqrt(np.maximum(1.0 + rr[:, 0, 0] - rr[:, 1, 1] - rr[:, 2, 2], 1e-300))
            q[i] = np.stack([(rr[:, 2, 1] - rr[:, 1, 2]) / s, 0.25 * s, (rr[:, 0, 1] + rr[:, 1, 0]) / s,
                             (rr[:, 0, 2] + rr[:, 2, 0]) / s], -1)
        elif case == 2:
            s = 2.0 * np.sqrt(np.maximum(1.0 + rr[:, 1, 1] - rr[:, 0, 0] - rr[:, 2, 2], 1e-300))
            q[i] = np.stack([(rr[:, 0, 2] - rr[:, 2, 0]) / s, (rr[:, 0, 1] + rr[:, 1, 0]) / s, 0.25 * s,
                             (rr[:, 1, 2] + rr[:, 2, 1]) / s], -1)
        else:
            s = 2.0 * np.sqrt(np.maximum(1.0 + rr[:, 2, 2] - rr[:, 0, 0] - rr[:, 1, 1], 1e-300))
            q[i] = np.stack([(rr[:, 1, 0] - rr[:, 0, 1]) / s, (rr[:, 0, 2] + rr[:, 2, 0]) / s,
                             (rr[:, 1, 2] + rr[:, 2, 1]) / s, 0.25 * s], -1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(m.shape[:-2] + (4,))
