"""Batches padded to a few sizes, so that the generator's compiled programs are few."""

from __future__ import annotations

import numpy as np


def bucket(n: int) -> int:
    """Padded batch size for ``n`` items: powers of two from 16.

    Arguments:
        n: number of items.

    Returns:
        The smallest power of two >= ``n``, at least 16.
    """
    return max(16, 1 << (max(n, 1) - 1).bit_length())


def pad(arrays: dict, size: int) -> dict:
    """Arrays lengthened to ``size`` rows by repeating their first row.

    Arguments:
        arrays: ``{name: array}`` with equal leading lengths of at least 1.
        size: the padded length (>= the arrays' length).

    Returns:
        ``{name: numpy array of length size}``; the first rows are the inputs'.
    """
    out = {}
    for k, a in arrays.items():
        a = np.asarray(a)
        reps = size - len(a)
        out[k] = np.concatenate([a, np.repeat(a[:1], reps, axis=0)]) if reps > 0 else a
    return out
