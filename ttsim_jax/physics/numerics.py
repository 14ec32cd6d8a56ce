"""Numerical helpers that keep values and gradients finite at singular points."""

from __future__ import annotations

import jax.numpy as jnp

TINY = 1e-12


def safe_norm(x, axis=-1, keepdims=False):
    """Euclidean norm whose value and gradient are 0 (not NaN) at x = 0."""
    n2 = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    ok = n2 > TINY
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def component_norm(*components):
    """:func:`safe_norm` of a vector given by its components (elementwise arithmetic only, no
    reduction: in a batched kernel a reduction over a short axis is an operation of its own)."""
    n2 = components[0] * components[0]
    for c in components[1:]:
        n2 = n2 + c * c
    ok = n2 > TINY
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


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
