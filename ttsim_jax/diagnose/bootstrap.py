"""Seeded group (cluster) bootstrap of ratios of sums, the one resampling the diagnosis uses.

Items of one group (the observations of a flight segment) are not independent, so whole groups are
drawn with replacement: a draw is a vector of group counts (multinomial), and a statistic that is a
ratio of sums over items is a ratio of count-weighted sums over groups.
"""

from __future__ import annotations

import math

import numpy as np

#: Bootstrap draws.
DRAWS = 1000


def group_weights(n_groups: int, n_boot: int = DRAWS, seed: int = 0) -> np.ndarray:
    """(n_boot, n_groups) counts of each group in each bootstrap draw (seeded)."""
    rng = np.random.default_rng(seed)
    if n_groups == 0:
        return np.zeros((n_boot, 0))
    return rng.multinomial(n_groups, np.full(n_groups, 1.0 / n_groups), size=n_boot).astype(np.float64)


def ratio_ci(num, den, weights: np.ndarray) -> tuple[float, list]:
    """sum(num) / sum(den) and its 95 % bootstrap interval.

    Arguments:
        num, den: (G,) per-group sums; weights: (n_boot, G) from :func:`group_weights`.

    Returns:
        (value, [low, high]); NaN where the denominator is 0.
    """
    num, den = np.asarray(num, np.float64), np.asarray(den, np.float64)
    if not den.sum() > 0:
        return math.nan, [math.nan, math.nan]
    value = float(num.sum() / den.sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        draws = (weights @ num) / (weights @ den)
    draws = draws[np.isfinite(draws)]
    if len(draws) < 2:
        return value, [math.nan, math.nan]
    return value, [float(np.percentile(draws, 2.5)), float(np.percentile(draws, 97.5))]


def rms_reduction(before, after, counts, weights: np.ndarray) -> tuple[float, list]:
    """Reduction [%] of the RMS error, 100 (1 - sqrt(sum after / sum before)), with its paired
    95 % bootstrap interval.

    Arguments:
        before, after: (G,) per-group sums of squared errors; counts: (G,) items per group (only
        to drop empty groups); weights: (n_boot, G).
    """
    b, a = np.asarray(before, np.float64), np.asarray(after, np.float64)
    if not b.sum() > 0 or not np.asarray(counts).sum() > 0:
        return math.nan, [math.nan, math.nan]
    value = float(100.0 * (1.0 - math.sqrt(a.sum() / b.sum())))
    with np.errstate(invalid="ignore", divide="ignore"):
        draws = 100.0 * (1.0 - np.sqrt((weights @ a) / (weights @ b)))
    draws = draws[np.isfinite(draws)]
    if len(draws) < 2:
        return value, [math.nan, math.nan]
    return value, [float(np.percentile(draws, 2.5)), float(np.percentile(draws, 97.5))]
