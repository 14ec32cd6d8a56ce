"""Statistics the residual network's training computes from data, never used in inference.

* :func:`kmeans`: the attenuation centres of the scaled training (v~, w~).
* :func:`calibrate_beta`: validates the attenuation on held-out contacts, widening it if needed.
* :func:`population_batch_stats`: the exact batch-norm statistics of the whole training split,
  replacing the running averages (which reflect the last few mini-batches and their order).
* :func:`calibration_scale`: the factors of the predicted sigmas that make ~68.3 % of held-out
  errors fall inside one sigma (:data:`ONE_SIGMA_COVERAGE`).

The network itself is :mod:`ttsim_jax.physics.network`.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.physics.network import PAPER_BETA, ResidualConfig

# The fraction of a Gaussian inside one standard deviation, erf(1 / sqrt(2)).
ONE_SIGMA_COVERAGE = 0.6826894921370859

# calibration mode -> group label of each of the six output components
CALIBRATION_MODES = {"component": (0, 1, 2, 3, 4, 5), "group": (0, 0, 0, 1, 1, 1), "none": None}


# ----------------------------------------------------------------------------------------------
# Batch-norm statistics and sigma calibration (after training)


@partial(jax.jit, static_argnames=("config",))
def _population_stats(params, x_scaled, weights, config: ResidualConfig):
    h = x_scaled
    stats = {}
    total = jnp.sum(weights)
    for i, _ in enumerate(config.trunk):
        dense = params[f"trunk_{i}"]
        h = h @ dense["kernel"] + dense["bias"]
        # Two-pass (centred) moments: no cancellation when |mean| >> std.
        mean = jnp.sum(weights[:, None] * h, axis=0) / total
        var = jnp.sum(weights[:, None] * (h - mean) ** 2, axis=0) / total
        stats[f"bn_{i}"] = {"mean": mean, "var": var}
        bn = params[f"bn_{i}"]
        h = (h - mean) * jax.lax.rsqrt(var + 1e-5) * bn["scale"] + bn["bias"]  # as flax.linen.BatchNorm
        h = jax.nn.relu(h)
        # dropout is the identity in inference mode
    return stats


def population_batch_stats(variables, config: ResidualConfig, x_scaled, weights=None) -> dict:
    """Exact batch-norm statistics of a data set, replacing the running averages.

    Training keeps an exponential moving average of mini-batch statistics, which reflects the
    last few batches (and their order). This recomputes, layer by layer in inference mode (no
    dropout, earlier layers already normalised with their recomputed statistics), the mean and
    the (biased, as Flax's) variance of every batch-norm input over the whole of ``x_scaled``:
    one pass over the data, independent of any order. With them, inference mode on a data set
    reproduces training mode with the whole set as one batch (dropout off).

    Arguments:
        variables: {'params', 'batch_stats'} of :class:`~ttsim_jax.physics.network.ResidualNet`
            (batch_stats is replaced).
        config: the architecture.
        x_scaled: (N, n_inputs) min-max scaled inputs (normally the whole training split).
        weights: optional (N,) non-negative row weights (e.g. 0 for padding rows).

    Returns:
        New variables {'params', 'batch_stats'} with the population statistics (dtype of the
        old statistics).
    """
    x_scaled = jnp.asarray(x_scaled)
    if x_scaled.ndim != 2 or x_scaled.shape[1] != config.n_inputs or x_scaled.shape[0] < 1:
        raise ValueError(f"population_batch_stats: x_scaled has shape {tuple(x_scaled.shape)}, "
                         f"expected (N >= 1, {config.n_inputs})")
    w = jnp.ones((x_scaled.shape[0],), x_scaled.dtype) if weights is None else jnp.asarray(weights, x_scaled.dtype)
    params = variables["params"]
    stats = _population_stats(params, x_scaled, w, config)
    old = variables["batch_stats"]
    stats = {k: {n: v.astype(jnp.asarray(old[k][n]).dtype) for n, v in d.items()} for k, d in stats.items()}
    return {"params": params, "batch_stats": stats}


def calibration_scale(abs_error, sigma, groups=None, target=ONE_SIGMA_COVERAGE, floor=1e-6):
    """Factors that make a fraction ``target`` of the errors fall inside one scaled sigma.

    For each group of components, the factor s is the ``target`` quantile of |error| / sigma
    over all rows and components of the group, so that |error| <= s sigma for that fraction of
    them (the empirical coverage; it does not assume Gaussian errors).

    Arguments:
        abs_error: (M, 6) absolute errors of the (corrected) prediction on held-out data.
        sigma: (M, 6) the predicted sigmas (uncalibrated).
        groups: (6,) group label of each component (default: each its own group); e.g.
            (0, 0, 0, 1, 1, 1) for one factor for velocity and one for spin.
        target: wanted coverage (default: a Gaussian's one-sigma mass, 0.6827).
        floor: lower bound of a factor (keeps sigmas positive).

    Returns:
        (6,) float64 factors.
    """
    ratio = np.asarray(abs_error, np.float64) / np.maximum(np.asarray(sigma, np.float64), 1e-30)
    if ratio.ndim != 2 or ratio.shape[1] != 6 or ratio.shape[0] < 1:
        raise ValueError(f"calibration_scale: need (M >= 1, 6) errors and sigmas, got {ratio.shape}")
    groups = np.arange(6) if groups is None else np.asarray(groups)
    out = np.ones(6)
    for g in np.unique(groups):
        cols = groups == g
        out[cols] = max(float(np.quantile(ratio[:, cols], target)), floor)
    return out


# ----------------------------------------------------------------------------------------------
# k-means


@partial(jax.jit, static_argnames=("k", "iters"))
def kmeans(points, k: int, key, iters: int = 50):
    """k-means clustering: k-means++ initialisation, then Lloyd iterations.

    Arguments:
        points: (N, D) points, N >= k.
        k: number of centres (static).
        key: PRNG key for the initialisation.
        iters: Lloyd iterations (static).

    Returns:
        (k, D) centres. A centre that loses all its points keeps its position.
    """
    points = jnp.asarray(points)
    n = points.shape[0]
    if n < k:
        raise ValueError(f"kmeans: {n} points cannot make {k} clusters")
    k0, kseq = jax.random.split(key)

    def sqdist(c):
        return jnp.sum((points - c) ** 2, axis=1)

    first = points[jax.random.randint(k0, (), 0, n)]
    centres = jnp.zeros((k, points.shape[1]), points.dtype).at[0].set(first)

    def pp_step(i, carry):
        centres, d2 = carry
        # k-means++: the next centre is drawn with probability proportional to the squared
        # distance to the nearest chosen centre; the tiny floor keeps duplicates drawable.
        j = jax.random.categorical(jax.random.fold_in(kseq, i), jnp.log(d2 + 1e-20))
        c = points[j]
        return centres.at[i].set(c), jnp.minimum(d2, sqdist(c))

    centres, _ = jax.lax.fori_loop(1, k, pp_step, (centres, sqdist(first)))

    def lloyd(_, centres):
        d2 = (jnp.sum(points * points, axis=1, keepdims=True) - 2.0 * points @ centres.T
              + jnp.sum(centres * centres, axis=1)[None, :])
        assign = jnp.argmin(d2, axis=1)
        sums = jax.ops.segment_sum(points, assign, num_segments=k)
        counts = jax.ops.segment_sum(jnp.ones((n,), points.dtype), assign, num_segments=k)
        return jnp.where(counts[:, None] > 0, sums / jnp.maximum(counts, 1.0)[:, None], centres)

    return jax.lax.fori_loop(0, iters, lloyd, centres)


def calibrate_beta(dist_heldout, a=PAPER_BETA[0], b=PAPER_BETA[1], c=PAPER_BETA[2], quantile=0.99):
    """Validates the attenuation on held-out data and rescales its distance if needed.

    The paper's curve gives full trust (beta = 1) up to dist_1 = ln(a / (1 + c)) / b (0.150 for
    the authors' numbers), tuned to their data with 1000 centres. Distances to the nearest centre
    grow with fewer centres or sparser data, so a held-out contact from the training distribution
    could then be attenuated. Held-out data are in-distribution, so the residual should be fully
    trusted on (nearly) all of them: if the ``quantile`` of held-out distances exceeds dist_1, b
    is lowered so that dist_1 equals that quantile (the curve's shape, i.e. the ratio of its zero
    to its full-trust distance, is kept). Otherwise the coefficients pass unchanged.

    Arguments:
        dist_heldout: (M,) distances of held-out (validation) inputs to the nearest centre.
        a, b, c: the coefficients to validate.
        quantile: the fraction of held-out contacts that must get beta = 1.

    Returns:
        (coefficients (a, b', c) as floats, info dict with the distance quantile, the full-trust
        and zero distances before and after, and whether b was changed).
    """
    dist = np.asarray(dist_heldout, np.float64)
    dq = float(np.quantile(dist, quantile))
    d_one = math.log(a / (1.0 + c)) / b
    new_b = b if dq <= d_one else math.log(a / (1.0 + c)) / dq
    beta_old = np.clip(a * np.exp(-b * dist) - c, 0.0, 1.0)
    info = dict(distance_quantile=dq, quantile=quantile, full_trust_distance_before=d_one,
                full_trust_distance=math.log(a / (1.0 + c)) / new_b,
                zero_distance=math.log(a / c) / new_b if c > 0 else math.inf,
                rescaled=bool(new_b != b), mean_beta_heldout_before=float(beta_old.mean()))
    return (float(a), float(new_b), float(c)), info
