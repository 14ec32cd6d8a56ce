"""Table contact identification: restitution (e0, e1) and the local residual matrices.

The model (:func:`ttsim_jax.physics.table.local_contact`, surface frame, normal = z):

    v+ = base_v(e0, e1) - R^T (dA_vv R v + dA_vw R w),   w+ = base_w(e0, e1) - R^T (dA_wv R v + dA_ww R w)

with R the residual frame of the incoming velocity (:func:`~ttsim_jax.physics.table.residual_frame`)
and the base the Nakashima point contact with e_n = e0 + e1 v_z (mu, kappa, alpha_roll are the base
model's). In the local frame the residual is linear in (R v, R w), so with the base computed for
the current (e0, e1) each bounce gives six linear equations

    R (base - observed) = dA (R v, R w) + de0 v_z + de1 v_z^2   (the last two in the v_z row only).

The de0 / de1 columns correct e0, e1 (a first estimate comes from ordinary least squares on
v_z+ = -(e0 + e1 v_z) v_z); the residual entry dA_vv[2, 2] multiplies the same column as de0 and
cannot be told apart from it, so it is fixed at zero (e0 takes it); and (R v)_y = 0 by the
frame's construction, so dA_vv[:, 1] and dA_wv[:, 1] act on nothing and stay zero. Features and targets are
standardised, the residual entries L1-penalised (e0, e1 not), and the problem solved on a
geometric path of penalties with ``jaxopt.ProximalGradient`` and ``prox_lasso`` (FISTA on the
Gram matrices, one jitted call vmapped over folds and penalties). K-fold cross-validation picks
the penalty (``rule="1se"``: the largest within one standard error of the best, which favours the
sparse pattern; ``"min"``: the best). The base depends on e_n through the sliding grip, so the
fit is repeated ``outer`` times with the updated (e0, e1). The lasso selects the entries; their
values are then refitted by ordinary least squares on that selection (the relaxed lasso: the
penalty's shrinkage would otherwise leak into e0, e1 through the uncentred features), and
entries below ``min_t`` standard errors in that refit are dropped. The refit keeps e_n within
the base model's [e_min, e_max] (a bounce gains no energy) at v_z = 0 and at the fastest bounce:
where the free fit leaves that range, the restitution is the least-squares fit on the bound
(:attr:`TableFit.bounds` says which).

The simulator fades the residual below ``RESIDUAL_FADE_SPEED`` of horizontal speed and scales it
down where it would create energy (:func:`~ttsim_jax.physics.table.residual_bound`);
the fit uses only bounces where both are 1: slower bounces are skipped (``slow_horizontal``), and
bounces where the fitted matrices would be bounded are dropped and the fit repeated once
(``residual_bounded``).

Standard errors are those of the least-squares refit (conditional on the selection).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit.racket_arrays import model_and_name
from ttsim_jax.fit.table_bounces import SKIP_REASONS, Bounces, table_bounces  # noqa: F401 (public here too)
from ttsim_jax.physics import table as table_stage

MATRICES = ("dA_vv", "dA_vw", "dA_wv", "dA_ww")
UNITS = {"dA_vv": "1", "dA_vw": "m", "dA_wv": "1/m", "dA_ww": "1"}


@dataclasses.dataclass(frozen=True)
class LassoSettings:
    """Penalty path and cross-validation of the residual fit.

    Attributes:
        n_lambdas: penalties on the path (geometric, from the one that zeroes every entry).
        lambda_ratio: smallest / largest penalty.
        folds: K of the K-fold cross-validation.
        rule: ``"1se"`` or ``"min"`` (see the module docstring).
        seed: seed of the fold assignment.
        maxiter, tol: proximal-gradient iterations and tolerance (standardised units).
        outer: refits with the base recomputed for the updated (e0, e1).
        min_t: entries selected by the lasso whose refit value is below min_t standard errors are
            set to zero (0: keep every selected entry).
    """

    n_lambdas: int = 20
    lambda_ratio: float = 1e-3
    folds: int = 5
    rule: str = "1se"
    seed: int = 0
    maxiter: int = 1000
    tol: float = 1e-5
    outer: int = 3
    min_t: float = 3.0

    def __post_init__(self):
        if self.rule not in ("1se", "min"):
            raise ValueError(f"LassoSettings.rule = {self.rule!r}: must be '1se' or 'min'")
        if self.folds < 2:
            raise ValueError(f"LassoSettings.folds = {self.folds!r}: must be >= 2")
        if self.n_lambdas < 2 or not 0.0 < self.lambda_ratio < 1.0:
            raise ValueError(f"LassoSettings: n_lambdas = {self.n_lambdas!r} (>= 2), lambda_ratio = "
                             f"{self.lambda_ratio!r} (in (0, 1))")


# ----------------------------------------------------------------------------------------------
# Jitted pieces


@jax.jit
def predicted_bounces(table, radius, vel, spin):
    """(v+, w+, residual weight) of the full table model for (N, 3) surface-frame states (pad them
    to :func:`padded_size` rows with :func:`pad_rows`, so that sizes share a compilation)."""

    def one(v, w):
        bv, bw, dv, dw = table_stage.residual_terms(table, radius, v, w)
        lam = table_stage.residual_bound(table.kappa, radius, v, w, bv, bw, dv, dw)
        return bv + lam * dv, bw + lam * dw, table_stage.residual_fade(v) * lam

    return jax.vmap(one)(vel, spin)


@jax.jit
def _regression(table, radius, vel, spin, vel_out, spin_out):
    """Features (N, 7) = (R v, R w, v_z^2) and targets (N, 6) = R (base - observed)."""

    def one(v, w, vo, wo):
        zero = table.replace(residual=jnp.zeros_like(table.residual))
        bv, bw = table_stage.local_contact(zero, radius, v, w)
        rot = table_stage.residual_frame(v)
        x = jnp.concatenate([rot @ v, rot @ w, v[2:3] ** 2])
        return x, jnp.concatenate([rot @ (bv - vo), rot @ (bw - wo)])

    return jax.vmap(one)(vel, spin, vel_out, spin_out)


def _proximal_solve(gram, cross, lam, penalty, mask, maxiter, tol):
    """argmin_B 1/2 tr(B G B^T) - tr(B C) + lam sum(penalty |B|), entries outside ``mask`` zero."""
    from jaxopt import ProximalGradient
    from jaxopt.prox import prox_lasso

    step = 1.0 / jnp.maximum(jnp.linalg.eigvalsh(gram)[-1], 1e-12)

    def fun(b, gram, cross):
        return 0.5 * jnp.sum((b @ gram) * b) - jnp.sum(b * cross.T)

    def prox(b, l1reg, scaling):
        return mask * prox_lasso(b, l1reg, scaling)

    solver = ProximalGradient(fun=fun, prox=prox, stepsize=lambda _: step, maxiter=maxiter, tol=tol,
                              acceleration=True, implicit_diff=False)
    return solver.run(jnp.zeros(mask.shape, gram.dtype), lam * penalty, gram=gram, cross=cross).params


@functools.partial(jax.jit, static_argnames=("maxiter", "tol"))
def _lasso_path(grams, crosses, lambdas, penalty, mask, maxiter, tol):
    """Coefficients (F, P, 6, 7) for F Gram pairs (folds) and P penalties."""
    solve = lambda g, c, lam: _proximal_solve(g, c, lam, penalty, mask, maxiter, tol)  # noqa: E731
    over_lambdas = jax.vmap(solve, in_axes=(None, None, 0))
    return jax.vmap(over_lambdas, in_axes=(0, 0, None))(grams, crosses, lambdas)


# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class TableFit:
    """What :func:`fit_table` found.

    Attributes:
        e0, e1: fitted restitution law; stderr_e0, stderr_e1: their standard errors.
        residual: (4, 3, 3) fitted dA_vv, dA_vw, dA_wv, dA_ww; stderr: (4, 3, 3), nan where zero.
        pattern: (4, 3, 3) bool, the non-zero entries.
        lambdas: (P,) penalty path (standardised units); cv_mean, cv_se: (P,) cross-validation error
            (mean over folds of the standardised squared error per bounce) and its standard error.
        lambda_index: the chosen penalty; lambda_min_index: the one of least CV error.
        n_used: bounces in the final fit; n_bounded: bounces dropped by the residual bound.
        used: (N,) bool over the input bounces.
        errors: 'base' / 'fitted' -> component -> median absolute error of the model given to
            :func:`fit_table` and of the fitted one on the used bounces.
        settings: the :class:`LassoSettings` as a dict.
        bounds: the physical bounds the fit holds (e_n within [e_min, e_max] over the bounces'
            normal speeds), one description each; empty when the free fit is within them.
        unconstrained: ``{"e0": ..., "e1": ...}`` of the free fit where a bound holds.
    """

    e0: float
    e1: float
    stderr_e0: float
    stderr_e1: float
    residual: np.ndarray
    stderr: np.ndarray
    pattern: np.ndarray
    lambdas: np.ndarray
    cv_mean: np.ndarray
    cv_se: np.ndarray
    lambda_index: int
    lambda_min_index: int
    n_used: int
    n_bounded: int
    used: np.ndarray
    errors: dict
    settings: dict
    bounds: list = dataclasses.field(default_factory=list)
    unconstrained: dict = dataclasses.field(default_factory=dict)

    def params(self, table):
        """``table`` (TableParams) with the fitted e0, e1 and residual matrices."""
        dt = table.residual.dtype
        return table.replace(e0=jnp.asarray(self.e0, dt), e1=jnp.asarray(self.e1, dt),
                             residual=jnp.asarray(self.residual, dt))

    def pattern_text(self) -> list[str]:
        """One line per matrix: rows of 'x' (non-zero) and '.' (zero); '-' for the entries that are
        not identifiable (dA_vv[2, 2], in e0; the (R v)_y columns)."""
        out = []
        for k, name in enumerate(MATRICES):
            rows = []
            for i in range(3):
                rows.append("".join("-" if (k == 0 and i == 2 and j == 2) or (k in (0, 2) and j == 1)
                                    else ("x" if self.pattern[k, i, j] else ".") for j in range(3)))
            out.append(f"{name}: {' '.join(rows)}")
        return out

    def summary(self) -> str:
        lines = [f"e0 = {self.e0:.4f} +- {self.stderr_e0:.4f}, e1 = {self.e1:.4f} +- {self.stderr_e1:.4f} s/m "
                 f"({self.n_used} bounces; {self.n_bounded} dropped by the residual bound)",
                 f"lasso: lambda {self.lambdas[self.lambda_index]:.3g} ({self.settings['rule']}; least CV error at "
                 f"{self.lambdas[self.lambda_min_index]:.3g}), {int(self.pattern.sum())} of the 29 identifiable "
                 "entries non-zero (x; - not identifiable):"]
        lines += ["  " + t for t in self.pattern_text()]
        if self.bounds:
            lines.append(f"held at a physical bound: {'; '.join(self.bounds)} (the free fit: e0 = "
                         f"{self.unconstrained['e0']:.4f}, e1 = {self.unconstrained['e1']:.4f} s/m)")
        comps = list(self.errors["fitted"])
        lines.append("median |error| base -> fitted: " + ", ".join(
            f"{c} {self.errors['base'][c]:.3g} -> {self.errors['fitted'][c]:.3g}" for c in comps))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        clean = lambda a: [None if not np.isfinite(v) else float(v) for v in np.ravel(a)]  # noqa: E731
        return dict(e0=self.e0, e1=self.e1, stderr_e0=self.stderr_e0, stderr_e1=self.stderr_e1,
                    residual={n: np.asarray(self.residual[k]).tolist() for k, n in enumerate(MATRICES)},
                    stderr={n: np.reshape(clean(self.stderr[k]), (3, 3)).tolist() for k, n in enumerate(MATRICES)},
                    pattern={n: np.asarray(self.pattern[k]).astype(int).tolist() for k, n in enumerate(MATRICES)},
                    pattern_text=self.pattern_text(), cv_lambda=float(self.lambdas[self.lambda_index]),
                    cv_lambda_min=float(self.lambdas[self.lambda_min_index]), lambdas=clean(self.lambdas),
                    cv_mean=clean(self.cv_mean), cv_se=clean(self.cv_se), n_used=self.n_used,
                    n_bounded=self.n_bounded, errors=self.errors, settings=self.settings, bounds=self.bounds,
                    unconstrained=self.unconstrained)


_COMPONENTS = ("v_x", "v_y", "v_z", "w_x", "w_y", "w_z")


def _errors(table, radius, vel, spin, vel_out, spin_out, rows) -> dict:
    """Component -> median |model - observed| over ``rows`` (all bounces go through the model:
    one compiled shape)."""
    vp, wp, _ = predicted_bounces(table, radius, vel, spin)
    err = np.abs(np.concatenate([np.asarray(vp), np.asarray(wp)], 1) - np.concatenate([vel_out, spin_out], 1))[rows]
    return {c: float(np.median(err[:, k])) if len(err) else float("nan") for k, c in enumerate(_COMPONENTS)}


def bounce_errors(table, radius, vel_in, spin_in, vel_out, spin_out) -> dict:
    """Component -> median |model - observed| of the table model ``table`` over bounces.

    Arguments:
        table: TableParams; radius: the ball's radius [m].
        vel_in, spin_in, vel_out, spin_out: (N, 3) states before / after each bounce.

    Returns:
        ``{"v_x": ..., ..., "w_z": ...}`` [m/s, rad/s] (NaN with no bounce).
    """
    n = len(vel_in)
    size = padded_size(n)
    vin, win = (jnp.asarray(pad_rows(np.asarray(a, np.float64).reshape(-1, 3), size) if n else np.zeros((size, 3)),
                            jnp.float32) for a in (vel_in, spin_in))
    out = [np.asarray(a, np.float64).reshape(-1, 3) for a in (vel_out, spin_out)]
    out = [pad_rows(a, size) if n else np.zeros((size, 3)) for a in out]
    return _errors(table, jnp.asarray(radius, jnp.float32), vin, win, out[0], out[1], np.arange(size) < n)


def _bounded_lstsq(a, y, cons_a, cons_b):
    """Least squares ``a x ~ y`` subject to ``cons_a x <= cons_b`` (a few constraints).

    The optimum of a convex quadratic over a polyhedron solves the equality-constrained problem of
    its active constraints, so every set of at most ``len(x)`` constraints is solved that way and
    the feasible solution with the least residual kept.

    Returns:
        (x, standard errors (0 along what the active constraints fix), active (bool per constraint)).
    """
    n, p = a.shape
    m = len(cons_b)
    best = None
    for k in range(min(p, m) + 1):
        for act in itertools.combinations(range(m), k):
            c, d = cons_a[list(act)], cons_b[list(act)]
            kkt = np.block([[a.T @ a, c.T], [c, np.zeros((k, k))]])
            x = np.linalg.lstsq(kkt, np.concatenate([a.T @ y, d]), rcond=None)[0][:p]
            if k and not np.allclose(c @ x, d, atol=1e-9):
                continue  # dependent constraints that cannot hold together
            if np.any(cons_a @ x > cons_b + 1e-9):
                continue
            sse = float(np.sum((a @ x - y) ** 2))
            if best is None or sse < best[0] - 1e-12:
                best = (sse, x, act)
        if best is not None and k == 0:
            break  # the free fit is feasible: no bound is active
    sse, x, act = best
    free = np.linalg.svd(cons_a[list(act)])[2][len(act):].T if act else np.eye(p)  # null space of the active rows
    s2 = sse / max(n - free.shape[1], 1)
    cov = free @ np.linalg.pinv(free.T @ a.T @ a @ free) @ free.T * s2
    return x, np.sqrt(np.maximum(np.diag(cov), 0.0)), np.isin(np.arange(m), act)


def _restitution_bounds(e0, e1, vz_min, e_min, e_max):
    """Constraints ``c (de0, de1) <= d`` keeping e_n = (e0 + de0) + (e1 + de1) v_z within
    [e_min, e_max] at v_z = 0 and at the fastest bounce's ``vz_min`` (e_n is linear in v_z, so the
    two ends bound it over the bounces' range), and their descriptions."""
    c, d, what = [], [], []
    for v in (0.0, vz_min):
        here = e0 + e1 * v
        c += [[1.0, v], [-1.0, -v]]
        d += [e_max - here, here - e_min]
        at = "e0" if v == 0.0 else f"e_n at v_z = {v:.2f} m/s"
        what += [f"{at} <= e_max = {e_max:g}", f"{at} >= e_min = {e_min:g}"]
    return np.asarray(c), np.asarray(d), what


def _restitution_ols(vz_in, vz_out, w, e_min, e_max):
    """(e0, e1) of v_z+ = -(e0 + e1 v_z) v_z by weighted least squares, e_n within [e_min, e_max]."""
    a = np.stack([-vz_in, -vz_in**2], 1) * np.sqrt(w)[:, None]
    c, d, _ = _restitution_bounds(0.0, 0.0, float(np.min(vz_in[w > 0])), e_min, e_max)
    return _bounded_lstsq(a, vz_out * np.sqrt(w), c, d)[0]


def _masks():
    """(penalty, mask) of the (6, 7) coefficient matrix: e0 / e1 columns unpenalised; the v_z^2
    column exists only in the v_z row; the (R v)_y column is identically zero."""
    penalty = np.ones((6, 7))
    penalty[2, 2] = penalty[2, 6] = 0.0
    mask = np.ones((6, 7))
    mask[:, 6] = 0.0
    mask[2, 6] = 1.0
    mask[:, 1] = 0.0  # (R v)_y = 0 by construction of R: dA_vv[:, 1], dA_wv[:, 1] act on nothing
    return penalty, mask


def _grams(z, u, w):
    """Gram G = Z^T W Z / sum W (7, 7) and C = Z^T W U / sum W (7, 6)."""
    s = max(float(np.sum(w)), 1e-30)
    return (z * w[:, None]).T @ z / s, (z * w[:, None]).T @ u / s


def _refit(x, y, rows, support, bounds):
    """Least squares of each target column on its selected features (the relaxed lasso: the L1
    penalty selects, this fit removes its shrinkage); the v_z row's de0, de1 (columns 2 and 6)
    under ``bounds`` = (c, d) of :func:`_restitution_bounds`. Returns (coefficients, standard
    errors, both (6, 7), zero / nan off the support; active (bool per bound))."""
    b, se = np.zeros(support.shape), np.full(support.shape, np.nan)
    active = np.zeros(len(bounds[1]), bool)
    for i in range(support.shape[0]):
        cols = np.flatnonzero(support[i])
        if len(cols) == 0:
            continue
        a = x[rows][:, cols]
        cons = np.zeros((len(bounds[1]), len(cols)))
        if i == 2:  # columns 2 and 6 are always in the v_z row's support (fit_table)
            cons[:, np.searchsorted(cols, 2)], cons[:, np.searchsorted(cols, 6)] = bounds[0][:, 0], bounds[0][:, 1]
        sol, err, act = _bounded_lstsq(a, y[rows, i], cons, bounds[1] if i == 2 else np.ones(len(bounds[1])))
        b[i, cols], se[i, cols] = sol, err
        if i == 2:
            active = act
    return b, se, active


# Bounces are padded (with weight 0) to a multiple of this, so that datasets of different sizes
# share the compiled per-bounce functions.
PAD = 2048


def padded_size(n: int) -> int:
    """``n`` rounded up to a multiple of :data:`PAD`."""
    return max(-(-n // PAD), 1) * PAD


def pad_rows(a, size: int):
    """``a`` with its first row repeated up to ``size`` rows (finite values for the padding)."""
    a = np.asarray(a)
    return np.concatenate([a, np.repeat(a[:1], size - len(a), axis=0)]) if size > len(a) else a


def fit_table(vel_in, spin_in, vel_out, spin_out, model="conti2026", settings: LassoSettings = LassoSettings(),
              progress: Callable | None = None) -> TableFit:
    """Fits e0, e1 and the residual matrices to bounces (surface-frame states).

    Arguments:
        vel_in, spin_in, vel_out, spin_out: (N, 3) states before / after each bounce.
        model: bundled name, TOML path or Model: ball radius and the fixed table parameters (mu,
            kappa, alpha_roll, e_min, e_max); its e0, e1 and residual give the "base" errors.
        settings: :class:`LassoSettings`.
        progress: optional ``progress(done, total)`` over the solver passes.

    Returns:
        :class:`TableFit`.
    """
    from ttsim_jax.kernel.ball_step import ball_properties

    m, _ = model_and_name(model)
    radius = ball_properties(m)[0]
    vin, win, vout, wout = (np.asarray(a, np.float64) for a in (vel_in, spin_in, vel_out, spin_out))
    n = len(vin)
    for name, a in zip(("vel_in", "spin_in", "vel_out", "spin_out"), (vin, win, vout, wout)):
        if a.shape != (n, 3) or not np.all(np.isfinite(a)):
            bad = np.flatnonzero(~np.all(np.isfinite(a), axis=-1)) if a.shape == (n, 3) else []
            raise ValueError(f"fit_table: {name} must be a finite ({n}, 3) array; shape {a.shape}, non-finite rows "
                             f"{np.asarray(bad[:5]).tolist()}")
    if n < 2 * settings.folds:
        raise ValueError(f"fit_table: {n} bounces; at least {2 * settings.folds} are needed for "
                         f"{settings.folds}-fold cross-validation")
    real = np.arange(padded_size(n)) < n
    vin, win, vout, wout = (pad_rows(a, len(real)) for a in (vin, win, vout, wout))
    jv, jw, jvo, jwo = (jnp.asarray(a, jnp.float32) for a in (vin, win, vout, wout))
    weights = real.astype(np.float64)
    folds = pad_rows(np.random.default_rng(settings.seed).permutation(n) % settings.folds, len(real))
    penalty, mask = _masks()
    e_min, e_max = float(m.table.e_min), float(m.table.e_max)
    e0, e1 = _restitution_ols(vin[:, 2], vout[:, 2], weights, e_min, e_max)
    passes = settings.outer + 1
    n_bounded = 0
    table = m.table
    for k in range(passes):
        table = table.replace(e0=jnp.asarray(e0, table.e0.dtype), e1=jnp.asarray(e1, table.e1.dtype))
        x, y = (np.asarray(a, np.float64) for a in _regression(table, radius, jv, jw, jvo, jwo))
        act = weights > 0
        sx = np.sqrt(np.mean(x[act] ** 2, axis=0)) + 1e-12
        sy = np.sqrt(np.mean(y[act] ** 2, axis=0)) + 1e-12
        z, u = x / sx, y / sy
        train = [weights * (folds != f) for f in range(settings.folds)] + [weights]
        grams, crosses = zip(*(_grams(z, u, w) for w in train))
        lam_max = float(np.max(np.abs(crosses[-1].T) * penalty * mask))
        lambdas = lam_max * np.geomspace(1.0, settings.lambda_ratio, settings.n_lambdas)
        coef = np.asarray(_lasso_path(jnp.asarray(np.stack(grams), jnp.float32),
                                      jnp.asarray(np.stack(crosses), jnp.float32), jnp.asarray(lambdas, jnp.float32),
                                      jnp.asarray(penalty, jnp.float32), jnp.asarray(mask, jnp.float32),
                                      maxiter=settings.maxiter, tol=settings.tol), np.float64)
        cv = np.zeros((settings.folds, settings.n_lambdas))
        for f in range(settings.folds):
            held = weights * (folds == f)
            g, c = _grams(z, u, held)
            q = np.sum(held[:, None] * u**2) / max(np.sum(held), 1e-30)
            b = coef[f]
            cv[f] = np.einsum("pij,jk,pik->p", b, g, b) - 2.0 * np.einsum("pij,ji->p", b, c) + q
        cv_mean, cv_se = cv.mean(0), cv.std(0, ddof=1) / np.sqrt(settings.folds)
        best = int(np.argmin(cv_mean))
        chosen = best if settings.rule == "min" else int(np.flatnonzero(cv_mean <= cv_mean[best] + cv_se[best])[0])
        support = (coef[-1, chosen] != 0.0) & (mask > 0)
        support[2, 2] = support[2, 6] = True
        # a restitution above 1 (a bounce that gains energy) or below 0 is held at the bound
        cons, lim, what = _restitution_bounds(e0, e1, float(np.min(vin[weights > 0, 2])), e_min, e_max)
        b, se, active = _refit(x, y, weights > 0, support, (cons, lim))
        if settings.min_t > 0:  # prune entries the refit cannot tell from zero, refit the rest
            weak = np.abs(b) < settings.min_t * np.nan_to_num(se, nan=np.inf)
            weak[2, 2] = weak[2, 6] = False
            support = support & ~weak
            b, se, active = _refit(x, y, weights > 0, support, (cons, lim))
        free = _refit(x, y, weights > 0, support, (cons, np.full(len(lim), np.inf)))[0]
        unconstrained = dict(e0=float(e0 + free[2, 2]), e1=float(e1 + free[2, 6]))
        bounds = [w for w, a in zip(what, active) if a]
        e0, e1 = e0 + b[2, 2], e1 + b[2, 6]
        b[2, 2] = 0.0
        residual = np.stack([b[:3, :3], b[:3, 3:6], b[3:, :3], b[3:, 3:6]])
        if progress is not None:
            progress(k + 1, passes)
        if k < passes - 1:  # the next pass leaves out the bounces the fitted residual is bounded on
            fitted = table.replace(e0=jnp.asarray(e0, table.e0.dtype), e1=jnp.asarray(e1, table.e1.dtype),
                                   residual=jnp.asarray(residual, table.residual.dtype))
            bounded = np.asarray(predicted_bounces(fitted, radius, jv, jw)[2]) < 0.999
            n_bounded = int((bounded & real).sum())
            weights = np.where(bounded | ~real, 0.0, 1.0)
    act = weights > 0
    stderr = np.stack([se[:3, :3], se[:3, 3:6], se[3:, :3], se[3:, 3:6]])
    stderr_e0, stderr_e1 = float(se[2, 2]), float(se[2, 6])
    stderr[0, 2, 2] = np.nan
    pattern = residual != 0.0
    stderr = np.where(pattern, stderr, np.nan)
    result = TableFit(e0=float(e0), e1=float(e1), stderr_e0=stderr_e0, stderr_e1=stderr_e1, residual=residual,
                      stderr=stderr, pattern=pattern, lambdas=lambdas, cv_mean=cv_mean, cv_se=cv_se,
                      lambda_index=chosen, lambda_min_index=best, n_used=int(act.sum()), n_bounded=n_bounded,
                      used=act[:n], errors={}, settings=dataclasses.asdict(settings), bounds=bounds,
                      unconstrained=unconstrained if bounds else {})
    result.errors = dict(base=_errors(m.table, radius, jv, jw, vout, wout, act),
                         fitted=_errors(result.params(m.table), radius, jv, jw, vout, wout, act))
    return result


def table_sections(table, result: TableFit) -> dict:
    """{section: TOML text} of ``[table]`` and ``[table.residual]`` with the fitted values (the
    other table parameters from ``table``, the base model's TableParams)."""
    from ttsim_jax.fit.aero_forms import toml_array

    f = lambda v: f"{float(v):.6g}"  # noqa: E731
    head = (f"[table]                                         # fitted: e_n = e0 + e1 v_z (ttsim fit)\n"
            f'e0 = {{ value = {f(result.e0)}, unit = "1" }}\n'
            f'e1 = {{ value = {f(result.e1)}, unit = "s/m" }}\n'
            f'e_min = {{ value = {f(table.e_min)}, unit = "1" }}\n'
            f'e_max = {{ value = {f(table.e_max)}, unit = "1" }}\n'
            f'mu = {{ value = {f(table.mu)}, unit = "1" }}\n'
            f'kappa = {{ value = {f(table.kappa)}, unit = "1" }}\n'
            f'alpha_roll = {{ value = {f(table.alpha_roll)}, unit = "1" }}\n')
    res = "[table.residual]                                # fitted: Lasso residual matrices, local frame of v_xy\n"
    res += "".join(f'{name} = {{ value = {toml_array(result.residual[k])}, unit = "{UNITS[name]}" }}\n'
                   for k, name in enumerate(MATRICES))
    return {"table": head, "table.residual": res}
