"""Numerical helpers that keep values and gradients finite at singular points."""

from __future__ import annotations

import jax.numpy as jnp

TINY = 1e-12


def safe_norm(x, axis=-1, keepdims=False):
    """Euclidean norm whose value and gradient are 0 (not NaN) at x = 0."""
    if x.ndim and x.shape[axis] == 3 and axis in (-1, x.ndim - 1):
        # the components' sum, not a reduction: a reduction over a short axis ends an elementwise
        # loop on a CPU (under vmap, every norm in a flight step was a pass over the batch of its own)
        n2 = dot3(x, x)
        if keepdims:
            n2 = n2[..., None]
    else:
        n2 = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    ok = n2 > TINY
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def safe_sqrt(x):
    """sqrt(max(x, 0)) whose gradient is 0 (not NaN) where x <= 0: ``jnp.sqrt(jnp.maximum(x, 0))``
    multiplies sqrt's infinite slope at 0 by max's zero one there, which is NaN."""
    ok = x > 0.0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def component_norm(*components):
    """:func:`safe_norm` of a vector given by its components (elementwise arithmetic only, no
    reduction: in a batched kernel a reduction over a short axis is an operation of its own)."""
    n2 = components[0] * components[0]
    for c in components[1:]:
        n2 = n2 + c * c
    ok = n2 > TINY
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def dot3(a, b):
    """The dot product of (..., 3) vectors, as elementwise arithmetic (see :func:`matvec`; a batch of
    3-term dot products became a reduction of its own, which XLA's CPU backend ran 10-100x slower
    than the arithmetic around it)."""
    # one unstack, not six indexings: the same arithmetic in a third of the traced operations
    a0, a1, a2 = jnp.unstack(a, axis=-1)
    b0, b1, b2 = jnp.unstack(b, axis=-1)
    return a0 * b0 + a1 * b1 + a2 * b2


def triple(a, b, c):
    """The triple product a . (b x c) of (..., 3) vectors, as elementwise arithmetic (a batched
    cross product is a concatenation, an operation of its own on a CPU; see :func:`dot3`)."""
    a0, a1, a2 = jnp.unstack(a, axis=-1)
    b0, b1, b2 = jnp.unstack(b, axis=-1)
    c0, c1, c2 = jnp.unstack(c, axis=-1)
    return a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0)

def matvec(m, v):
    """``m @ v`` for (..., 3, 3) and (..., 3), as elementwise arithmetic: under vmap a 3 x 3
    product is a batched dot, an operation of its own on a CPU (slow for a batch of tiny ones)
    that no elementwise loop fuses with; the sum over three terms fuses with its neighbours."""
    return m[..., :, 0] * v[..., 0:1] + m[..., :, 1] * v[..., 1:2] + m[..., :, 2] * v[..., 2:3]


def matmul(a, b):
    """``a @ b`` for (..., 3, 3) matrices, as elementwise arithmetic (see :func:`matvec`)."""
    return (a[..., :, 0:1] * b[..., None, 0, :] + a[..., :, 1:2] * b[..., None, 1, :]
            + a[..., :, 2:3] * b[..., None, 2, :])


def transpose(m):
    """(..., 3, 3) ``m`` transposed."""
    return jnp.swapaxes(m, -1, -2)


def safe_divide(num, den, fallback=0.0):
    """num / den where |den| > TINY, else ``fallback``; gradients stay finite."""
    ok = jnp.abs(den) > TINY
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fallback)


def safe_unit(x, fallback):
    """x / |x|, or ``fallback`` where |x| is (numerically) zero."""
    n = safe_norm(x, keepdims=True)
    ok = n > 1e-9
    return jnp.where(ok, x / jnp.where(ok, n, 1.0), fallback)


def rotate(rotvec, v):
    """``v`` (..., 3) turned by the rotation vector ``rotvec`` (..., 3) (Rodrigues), smooth (and
    differentiable) at 0, where it is ``v`` exactly."""
    th2 = (rotvec[..., 0] ** 2 + rotvec[..., 1] ** 2 + rotvec[..., 2] ** 2)[..., None]
    small = th2 < 1e-8
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / jnp.where(small, 1.0, th2))
    turn = jnp.cross(rotvec, v)
    return v + a * turn + b * jnp.cross(rotvec, turn)


def rotation_matrix(rotvec):
    """(..., 3, 3) rotation matrix of a rotation vector (:func:`rotate`; the identity exactly at 0)."""
    eye = jnp.eye(3, dtype=rotvec.dtype)
    return jnp.swapaxes(rotate(rotvec[..., None, :], eye), -1, -2)
