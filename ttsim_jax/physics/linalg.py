"""Small linear-algebra helpers of the solvers (JAX, traceable)."""

from __future__ import annotations

import jax


def spd_solve(a, b):
    """a^-1 b for a symmetric positive definite ``a`` (Cholesky: far cheaper to compile than LU).

    Arguments:
        a: (n, n) symmetric positive definite matrix.
        b: (n,) or (n, k) right-hand side.

    Returns:
        The solution x of a x = b, shaped like ``b``.
    """
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b)
