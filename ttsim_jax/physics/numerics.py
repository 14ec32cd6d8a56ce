"""Numerical helpers that keep values and gradients finite at singular points."""

from __future__ import annotations

import jax.numpy as jnp

TINY = 1e-12


def safe_norm(x, axis=-1, keepdims=False):
    """Euclidean norm whose value and gradient are 0 (not NaN) at x = 0."""
    n2 = jnp.sum(x * x, axis=axis, keepdims=keepdims)
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
