"""Ridge regression with a cross-validated weight, and the exact split of a held-out gain among
the parts of a linear correction: the fitting of the diagnosis's model-free bound
(:mod:`ttsim_jax.diagnose.bound`)."""

from __future__ import annotations

import itertools
import math

import numpy as np

#: Folds of the cross-validation of the regularisation.
FOLDS = 5
#: Ridge weights tried, relative to the mean diagonal of the weighted Gram matrix of the
#: scaled features (so that a weight means the same for any number of rows).
LAMBDAS = np.logspace(-6, 2, 17)
#: Ridge weights tried for a group of columns relative to the other columns' (:func:`ridge_cv_groups`);
#: the last, 10^8, leaves the group out in effect.
GROUP_FACTORS = (1.0, 10.0, 100.0, 1e8)


def ridge_cv(x, y, w, fold, penalty, lambdas=LAMBDAS, one_se: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Ridge regression of each column of ``y`` on ``x`` with row weights, the weight chosen by
    cross-validation: with ``one_se``, the largest whose cross-validated error is within one
    standard error of the smallest (on a few dozen contacts the plain minimum of a noisy
    cross-validation curve picks a fit that does worse on new data than none); else the smallest.

    Arguments:
        x: (R, K) features; y: (R, J) targets; w: (R, J) row weights per target (0: not fitted);
        fold: (R,) fold of each row (0 .. F-1, rows of one item in one fold; -1: not used);
        penalty: (K,) 1 for penalised features, 0 for unpenalised ones (a constant); lambdas:
        relative ridge weights tried, increasing (units: the mean diagonal of the weighted Gram
        matrix of the penalised features).

    Returns:
        (beta (K, J), chosen relative weight (J,)); a target whose rows all weigh 0 gets beta 0.
    """
    beta, chosen, _ = _fit(_moments(x, y, w, fold), penalty, np.ones(len(penalty)), lambdas, one_se)
    return beta, chosen


def ridge_cv_groups(x, y, w, fold, penalty, groups, factors=GROUP_FACTORS, lambdas=LAMBDAS,
                    one_se: bool = False) -> tuple[np.ndarray, np.ndarray, tuple]:
    """:func:`ridge_cv` where some groups of penalised columns may need a stronger ridge weight than
    the others (many columns that few items inform, e.g. terms per session): each group's weight is
    a factor of :data:`GROUP_FACTORS` times the others', the factors chosen with the weight by the
    same cross-validation (the smallest held-fold error summed over the targets); the largest factor
    leaves the group out in effect.

    Arguments:
        as :func:`ridge_cv`; groups: boolean (K,) masks of the columns of each group; factors: the
            factors tried per group.

    Returns:
        (beta (K, J), chosen relative weight (J,), chosen factor per group).
    """
    mom = _moments(x, y, w, fold)
    best = None
    for combo in itertools.product(factors, repeat=len(groups)):
        factor = np.ones(len(penalty))
        for g, f in zip(groups, combo):
            factor[np.asarray(g, bool)] = f
        beta, chosen, err = _fit(mom, penalty, factor, lambdas, one_se)
        if best is None or err.sum() < best[0]:
            best = (float(err.sum()), beta, chosen, combo)
    return best[1], best[2], best[3]


def _moments(x, y, w, fold) -> tuple:
    """Per fold and target: weighted Gram matrix, moment and sum of squares (a fold's training sums
    are the totals minus its own)."""
    x, y, w = np.asarray(x, np.float64), np.asarray(y, np.float64), np.asarray(w, np.float64)
    k, j = x.shape[1], y.shape[1]
    folds = int(fold.max()) + 1 if len(fold) else 0
    gram, mom, sq = np.zeros((folds, j, k, k)), np.zeros((folds, j, k)), np.zeros((folds, j))
    for f in range(folds):
        rows = fold == f
        xf, yf, wf = x[rows], y[rows], w[rows]
        gram[f] = np.einsum("rk,rj,rl->jkl", xf, wf, xf)
        mom[f] = np.einsum("rk,rj->jk", xf, wf * yf)
        sq[f] = np.sum(wf * yf**2, 0)
    return gram, mom, sq


def _fit(moments, penalty, factor, lambdas, one_se: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(beta (K, J), chosen relative weight (J,), cross-validated error at it (J,)) of the ridge fit
    whose penalty on column k is ``lambda * scale * penalty[k] * factor[k]`` (scale: the mean
    diagonal of the Gram matrix over the penalised columns, so a weight means the same for any
    number of rows)."""
    gram, mom, sq = moments
    folds, j, k = gram.shape[0], gram.shape[1], gram.shape[2]
    total_g, total_m = gram.sum(0), mom.sum(0)
    mask = np.asarray(penalty, np.float64)
    pen = np.diag(mask * np.asarray(factor, np.float64))
    beta, chosen, error = np.zeros((k, j)), np.zeros(j), np.zeros(j)
    for t in range(j):
        scale = np.trace(total_g[t] * mask) / max(np.sum(mask), 1.0)
        if not scale > 0 or folds < 2:
            continue
        # tiny floor on every diagonal entry keeps an unused unpenalised column solvable
        floor = 1e-12 * scale * np.eye(k)
        cv = np.zeros((len(lambdas), folds))
        for i, lam in enumerate(lambdas):
            a = lam * scale * pen + floor
            for f in range(folds):
                b = np.linalg.solve(total_g[t] - gram[f, t] + a, total_m[t] - mom[f, t])
                cv[i, f] = sq[f, t] - 2.0 * b @ mom[f, t] + b @ gram[f, t] @ b  # held fold's weighted SSE
        total = cv.sum(1)
        best = int(np.argmin(total))
        se = math.sqrt(folds) * float(np.std(cv[best], ddof=1))
        pick = max(i for i in range(len(lambdas)) if total[i] <= total[best] + se) if one_se else best
        chosen[t], error[t] = lambdas[pick], total[pick]
        beta[:, t] = np.linalg.solve(total_g[t] + lambdas[pick] * scale * pen + floor, total_m[t])
    return beta, chosen, error


def folds(n: int, train: np.ndarray, seed: int) -> np.ndarray:
    """(n,) fold of each training item (seeded, balanced), -1 elsewhere."""
    out = np.full(n, -1)
    idx = np.flatnonzero(train)
    rng = np.random.default_rng(seed)
    out[rng.permutation(idx)] = np.arange(len(idx)) % FOLDS
    return out


def scaled(x, w) -> tuple[np.ndarray, np.ndarray]:
    """(x / scale, scale): each feature over its root mean square on the rows of weight w, not
    centred, so that a term proportional to a feature is attributed to that feature and not partly
    to the constant (a feature 0 on those rows gets scale inf and stays 0: it cannot be fitted)."""
    w = np.asarray(w, np.float64)
    rms = np.sqrt(np.sum(w[:, None] * x**2, 0) / max(float(w.sum()), 1e-300))
    scale = np.where(rms > 0, rms, np.inf)
    return x / scale, scale


def attribute(x, beta_parts, y, w) -> np.ndarray:
    """Parts of the held-out fall of the squared error, sum w [y^2 - (y - c)^2], one per named part
    of the correction c = x sum_m beta_m (they sum to the whole fall; see the module docstring).

    Arguments:
        x: (R, K) features; beta_parts: (M, K, J) the correction's parts; y: (R, J) the errors it
        removes; w: (R, J) held-out weights.

    Returns:
        (M,) parts.
    """
    c = x @ beta_parts.sum(0)
    lever = w * (2.0 * y - c)
    return np.einsum("rk,mkj,rj->m", x, beta_parts, lever)
