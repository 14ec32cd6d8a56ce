"""Latent spin: a flight segment's spin estimated from its positions, jointly with its initial state.

Most trackers measure no spin, yet a flight carries it: the Magnus acceleration
C_M (rho_a / rho_b) w x v bends a 0.3 s flight at 8 m/s and 200 rad/s by tens of centimetres. Per
segment, theta = (p0, v0, w) is fitted to the samples under the model's own flight (its drag and
Magnus coefficient models, tables included; the spin may change in flight through the model's
effects), by the same Levenberg-Marquardt solver as the per-segment flight fit
(:func:`ttsim_jax.fit.flightfit.levenberg_marquardt`), batched and jitted the same way.

What the positions show: the two spin components across the velocity, through the Magnus force.
The component along the velocity exerts no force (w x v = 0); it acts only through C_D(Sp) and
C_M(|w|), weakly, so it is held to a prior, mean 0 and :data:`PRIOR_ALONG` rad/s wide, along the
segment's mean direction of flight, and reported as such (:attr:`LatentSpin.along`,
:attr:`LatentSpin.observed`), never as a measured 0. A weak prior on the whole spin
(:data:`PRIOR_ANY`) keeps a straight, spin-free flight finite.

Costs are in units of the position noise: the residuals are divided by ``noise`` [m], so the
inverse of the fit's curvature is the spin's covariance when the noise is right
(:attr:`LatentSpin.cov` scales it up by the reduced chi-square where the fit is worse than that).

The start: the segment's mean acceleration from a per-axis parabola, less gravity and the model's
drag at spin 0, is the Magnus acceleration, whose cross product with the velocity gives the spin
across it (:func:`initial_guess`). One start is not enough (:func:`start_spins`):

* the size: under the paper's C_M the Magnus force C_M(|w|) |w| hardly grows, and at some speeds
  falls, above a few hundred rad/s, so the guess's size can be off by a factor of three, and a fit
  from there ends in another minimum;
* the spin along the flight acts through |w| (in C_D(Sp) and C_M(|w|)) and, as the direction of
  flight turns, a little across it; a fit started at 0 there barely moves (the cost's slope is
  about 0) however large the true one is, and trades it against the size across the flight.

So every segment is fitted from the guess and three times it, and a segment whose best fit stays
well above the others' error (:data:`RESCUE`) from spins of :data:`VALLEY_ALONG` along the flight
too, their part across sized to the guess's Magnus force. On 300 flights of conti2026's physics
with spins of 30-600 rad/s about random axes, the fits' position RMSE over the floor (the noise a
fit of the initial state leaves) fell from 1.19x (the guess and three times it) to 1.03x, and
the error of the spin across the flight from 3.7 to 3.2 rad/s (median), in 1.14x the time (all six
starts on every segment: 1.04x, in 2.9x the time on 2,000 segments).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit.flightfit import COMPILER_OPTIONS, levenberg_marquardt, parabola
from ttsim_jax.fit.segment_batches import batches
from ttsim_jax.physics.aero import coefficients, flight_step

#: Prior width of the spin component along the segment's direction of flight [rad/s]: the
#: positions hardly constrain it.
PRIOR_ALONG = 50.0
#: Prior width of every spin component [rad/s] (regularises a flight whose curvature shows none).
PRIOR_ANY = 3000.0
#: Position noise the residuals are scaled by, unless given [m].
NOISE = 0.002
#: Levenberg-Marquardt iterations at most.
ITERATIONS = 20
#: Fits (a segment from one of :data:`STARTS`) per compiled call. Under vmap the solver runs until
#: every fit of a call has converged or run out of its pass's iterations (:data:`PASSES`); on 1,000
#: segments (2 CPU cores) calls of 128 took 0.76x the time of calls of 64 and the same as 256.
BATCH = 128
#: Starts per segment (:func:`start_spins`, the module docstring says why one is not enough):
#: every segment is fitted from the first BASE_STARTS, and from the others where its best fit's
#: RMSE stands above RESCUE times the median of the segments fitted together.
STARTS = 6
BASE_STARTS = 2
RESCUE = 1.15
#: Spins along the flight of the starts that hold the guess's Magnus force [rad/s] (both signs:
#: the direction of flight turns in flight, so a spin along its mean is partly across it at the
#: ends), and the grid the part across is sized on.
VALLEY_ALONG = (300.0, -300.0, 600.0, -600.0)
VALLEY_MAX, VALLEY_POINTS = 1500.0, 151
#: A fit has converged when its next step is predicted to lower the cost by less than this share of it.
TOL = 1e-6
#: The iterations are spent in passes of these shares: each pass runs the fits the passes before
#: left unconverged, in calls of their own. Most fits converge within a few iterations and a few
#: need them all (on 1,000 segments of conti2026's physics: 61 % of 2,000 fits ran past 5, 36 %
#: past 10, 13 % to 20), so one pass of 20 iterations spent most of its time on a few fits per
#: call: the passes took 0.64x its time, with the same fits (median error across the flight 7.0
#: against 6.8 rad/s).
PASSES = (5, 5, 10)
#: Two fits whose costs (chi-square) differ by less than this, with spins across the flight whose
#: sizes differ by more than :data:`AMBIGUOUS_RATIO`, leave the spin's size undecided.
AMBIGUOUS_COST = 2.0
AMBIGUOUS_RATIO = 1.25


def _unit(v):
    return v / jnp.maximum(jnp.linalg.norm(v), 1e-9)


def _parabola(tau, pos, mask):
    """(p0, v0, mean velocity, mean acceleration) of a per-axis parabola through the samples."""
    coef = parabola(tau, pos, mask)
    t_mid = jnp.sum(tau * mask) / jnp.maximum(jnp.sum(mask), 1.0)
    return coef[0], coef[1], coef[1] + 2.0 * coef[2] * t_mid, 2.0 * coef[2]


def initial_guess(model, tau, pos, mask):
    """(theta0 (9,), along (3,)): the parabola's state at tau[0] with the spin across the mean
    velocity that the mean acceleration's Magnus part implies (C_M taken at that spin, three
    passes), and the mean direction of flight."""
    p0, v0, v, acc = _parabola(tau, pos, mask)
    radius, mass, aero = model.ball.radius, model.ball.mass, model.aero
    ratio = aero.rho_air * (4.0 / 3.0) * jnp.pi * radius**3 / mass
    speed = jnp.linalg.norm(v)
    fall = (1.0 - aero.buoyancy * ratio) * aero.gravity
    w = jnp.zeros(3, pos.dtype)
    for _ in range(3):
        cd, cm = coefficients(aero, v, w, radius)
        drag = -(3.0 / (8.0 * radius)) * cd * ratio * speed * v
        # a_magnus = k w x v, so v x a_magnus = k |v|^2 w_perp
        k = jnp.maximum(cm, 0.05) * ratio
        w = jnp.cross(v, acc - drag - fall) / (k * jnp.maximum(speed**2, 1e-6))
    return jnp.concatenate([p0, v0, w]), _unit(v)


def normal_equations(model, theta, tau, pos, mask, n, noise, prior):
    """Cost, J^T J (9, 9), J^T r (9,) of the scaled position residuals plus the spin prior, and the
    velocities (T, 3) at the sample times: the state's sensitivities to (v0, w0) ride along one
    integration (forward mode, one RK4 step at a time), as in
    :func:`ttsim_jax.fit.flightfit.normal_equations`. ``prior``: (3, 3) precision of the spin."""
    dtype = theta.dtype
    eye3 = jnp.eye(3, dtype=dtype)
    directions = jnp.eye(6, dtype=dtype)  # tangents over x = (v0, w0)
    step = _flight(model, tau, n)

    def add(sums, p, dp, i):
        cost, jtj, jtr = sums
        m = mask[i] / noise**2
        r = p - pos[i]
        block = jnp.concatenate([eye3, dp.T], axis=1)  # (3, 9): d p_i / d theta
        return cost + m * (r @ r), jtj + m * (block.T @ block), jtr + m * (block.T @ r)

    def body(carry):
        i, y, dy, sums, vel = carry
        y2, dy2 = jax.vmap(lambda d: jax.jvp(lambda y_: step(y_, i), (y,), (d,)), out_axes=(None, 0))(dy)
        return i + 1, y2, dy2, add(sums, y2[0], dy2[0], i + 1), vel.at[i + 1].set(y2[1])

    p0, v0, w0 = theta[:3], theta[3:6], theta[6:9]
    dy0 = (jnp.zeros((6, 3), dtype), directions[:, :3], directions[:, 3:])
    sums = add((jnp.zeros((), dtype), jnp.zeros((9, 9), dtype), jnp.zeros(9, dtype)), p0, dy0[0], 0)
    vel = jnp.zeros((tau.shape[0], 3), dtype).at[0].set(v0)
    *_, (cost, jtj, jtr), vel = jax.lax.while_loop(lambda c: c[0] < n - 1, body,
                                                    (jnp.asarray(0), (p0, v0, w0), dy0, sums, vel))
    cost = cost + w0 @ prior @ w0
    jtj = jtj.at[6:, 6:].add(prior)
    jtr = jtr.at[6:].add(prior @ w0)
    return cost, jtj, jtr, vel


def spin_prior(along, prior_along, prior_any):
    """(..., 3, 3) precision of the spin's prior [s^2/rad^2]: ``prior_along`` wide along ``along``
    (..., 3), ``prior_any`` wide in every direction."""
    outer = along[..., :, None] * along[..., None, :]
    eye = jnp.eye(3, dtype=along.dtype) if isinstance(along, jax.Array) else np.eye(3)  # numpy on the host
    return outer / prior_along**2 + eye / prior_any**2


def spin_statistics(theta, cost, jtj, along, count, noise, prior_along, prior_any):
    """(cov (S, 3, 3), rmse (S,)) of fits of (p0, v0, w) on the host: the spin's covariance from the
    curvature, scaled by the reduced chi-square where above 1, and the position RMSE [m], both from
    the cost less the spin prior's part. ``count``: (S,) samples fitted; ``along``: (S, 3)."""
    prior = spin_prior(along, prior_along, prior_any)
    data_cost = cost - np.einsum("si,sij,sj->s", theta[:, 6:], prior, theta[:, 6:])
    chi2 = data_cost / np.maximum(3.0 * count - 9.0, 1.0)
    cov = np.linalg.pinv(jtj)[:, 6:, 6:] * np.maximum(chi2, 1.0)[:, None, None]
    return cov, noise * np.sqrt(np.maximum(data_cost, 0.0) / np.maximum(count, 1.0))


def _flight(model, tau, n):
    """``step(y, i) -> y``: the model's flight from sample i to i + 1 of a padded segment (one RK4
    step per interval; padded intervals have dt = 0)."""
    dts = jnp.diff(tau)
    radius, mass, aero, effects = model.ball.radius, model.ball.mass, model.aero, model.effects

    def step(y, i):
        p, v, w = y
        return flight_step(aero, radius, mass, p, v, w, 0.0, dts[i], effects)

    return step


def start_spins(model, tau, pos, mask):
    """(theta0 (K, 9), along (3,)): the :data:`STARTS` starts of a padded segment's fits, the
    guess's position and velocity with: the guess's spin; that spin three times as large; and, for
    each of :data:`VALLEY_ALONG`, a spin of that size along the flight with the part across it sized
    so that the Magnus force C_M(|w|) |w_across| |v| stays the guess's."""
    theta0, along = initial_guess(model, tau, pos, mask)
    _, _, v, _ = _parabola(tau, pos, mask)
    w0 = theta0[6:]
    size = jnp.linalg.norm(w0)
    dtype = theta0.dtype
    cm = lambda w: coefficients(model.aero, v, w, model.ball.radius)[1]  # noqa: E731
    target = cm(w0) * size
    grid = jnp.linspace(0.0, VALLEY_MAX, VALLEY_POINTS, dtype=dtype)
    unit = w0 / jnp.maximum(size, 1e-9)
    spins = [w0, 3.0 * w0]
    for big in VALLEY_ALONG:
        product = jax.vmap(lambda a: cm(a * unit + big * along) * a)(grid)
        spins.append(grid[jnp.argmin(jnp.abs(product - target))] * unit + big * along)
    return jnp.stack([theta0.at[6:].set(w) for w in spins]), along


def fit_start(model, tau, pos, mask, n, noise, prior_along, prior_any, start, along, iterations):
    """The latent-spin fit of one padded segment from ``start`` (9,) (one of :func:`start_spins`, or
    a fit that ran out of iterations before), with the spin's prior along ``along`` (3,) (the
    unobserved axis :func:`start_spins` gives), for at most ``iterations`` (traced)
    Levenberg-Marquardt iterations. Returns a dict of ``theta`` (9,), ``cost``, ``jtj`` and
    ``converged`` (it stopped before ``iterations``)."""
    prior = spin_prior(along, prior_along, prior_any)

    def normal(theta):
        return normal_equations(model, theta, tau, pos, mask, n, noise, prior)

    theta, cost, h, _, k = levenberg_marquardt(normal, start, iterations, tol=TOL, stop_on_failure=False)
    return dict(theta=theta, cost=jnp.where(jnp.isfinite(cost), cost, jnp.inf), jtj=h, converged=k < iterations)


def _starts_impl(model, tau, pos, mask, rank):
    def one(a, b, c, r):
        theta, along = start_spins(model, a, b, c)
        return theta[r], along

    return jax.vmap(one)(tau, pos, mask, rank)


def _fit_batch_impl(model, tau, pos, mask, n_max, noise, prior_along, prior_any, start, along, iterations):
    return jax.vmap(lambda a, b, c, d, e: fit_start(model, a, b, c, n_max, noise, prior_along, prior_any, d, e,
                                                    iterations))(tau, pos, mask, start, along)


_starts = jax.jit(_starts_impl)
_fit_batch = jax.jit(_fit_batch_impl, compiler_options=COMPILER_OPTIONS)


def best_starts(theta, cost, along):
    """Per segment, of its :data:`STARTS` fits ((S, K, 9), (S, K), (S, 3)): the index
    of the best and whether another fits as well (:data:`AMBIGUOUS_COST`) with a spin across the
    flight of another size (:data:`AMBIGUOUS_RATIO`). Numpy, on the host."""
    cost = np.where(np.isfinite(cost), cost, np.inf)
    best = np.argmin(cost, axis=1)
    w = theta[:, :, 6:]
    across = w - np.sum(w * along[:, None], axis=2, keepdims=True) * along[:, None]
    size = np.maximum(np.linalg.norm(across, axis=2), 1e-9)
    rows = np.arange(len(best))
    other = (cost <= cost[rows, best][:, None] + AMBIGUOUS_COST) & (
        np.abs(np.log(size / size[rows, best][:, None])) > np.log(AMBIGUOUS_RATIO))
    return best, other.any(axis=1)


@dataclasses.dataclass
class LatentSpin:
    """Latent spins of many segments (numpy, in the order the segments were given).

    Attributes:
        p0, v0: (S, 3) fitted state at each segment's first sample; spin: (S, 3) [rad/s];
        cov: (S, 3, 3) the spin's covariance [rad^2/s^2] (from the fit's curvature, scaled by the
            reduced chi-square where above 1);
        along: (S, 3) unit vector of the unobserved spin axis (the direction of flight), where the
            spin is its prior's (mean 0, :data:`PRIOR_ALONG`) plus what C_D and C_M's dependence
            on the spin shows;
        rmse: (S,) position RMSE of the fit [m]; n: (S,) samples; ok: (S,) the fit ran and is
            finite (the others' values are NaN);
        ambiguous: (S,) a spin of another size across the flight fits as well (:data:`STARTS`):
            the positions show its direction, not its size.
    """

    p0: np.ndarray
    v0: np.ndarray
    spin: np.ndarray
    cov: np.ndarray
    along: np.ndarray
    rmse: np.ndarray
    n: np.ndarray
    ok: np.ndarray
    ambiguous: np.ndarray

    def __len__(self) -> int:
        return len(self.rmse)

    @property
    def observed(self) -> np.ndarray:
        """(S, 3) the spin's part across the direction of flight: what the positions show."""
        return self.spin - np.sum(self.spin * self.along, 1, keepdims=True) * self.along

    @property
    def stderr_observed(self) -> np.ndarray:
        """(S,) standard error of the observed part's size [rad/s] (the root of the covariance's
        trace across the direction of flight)."""
        p = np.eye(3)[None] - self.along[:, :, None] * self.along[:, None, :]
        return np.sqrt(np.maximum(np.einsum("sij,sjk,ski->s", p, self.cov, p), 0.0))


def fit_latent_spin(times: Sequence[np.ndarray], positions: Sequence[np.ndarray], model, *, noise: float = NOISE,
                    prior_along: float = PRIOR_ALONG, prior_any: float = PRIOR_ANY, batch: int = BATCH,
                    iterations: int = ITERATIONS, min_samples: int = 8, dtype=None,
                    progress: Callable | None = None) -> LatentSpin:
    """The latent spin of every segment (see the module docstring).

    Arguments:
        times: list of (T_i,) increasing sample times [s]; positions: list of (T_i, 3) [m].
        model: a :class:`~ttsim_jax.params.Model` (its ball, air, coefficient models and effects).
        noise: position noise [m] the residuals are scaled by; prior_along, prior_any: prior widths
            [rad/s] (:data:`PRIOR_ALONG`, :data:`PRIOR_ANY`).
        batch: segments per compiled call; iterations: Levenberg-Marquardt iterations at most;
        min_samples: shorter segments are not fitted (NaN); dtype: the fit's float type (default
            JAX's: float32, float64 with ``jax_enable_x64``);
        progress: optional ``progress(n_done)`` after each batch.

    Returns:
        :class:`LatentSpin`.
    """
    if not noise > 0 or not prior_along > 0 or not prior_any > 0:
        raise ValueError(f"noise, prior_along and prior_any must be > 0, got {noise}, {prior_along}, {prior_any}")
    dtype = jnp.zeros(()).dtype if dtype is None else np.dtype(dtype)
    n_seg = len(times)
    lengths = np.array([len(t) for t in times], int)
    nan = lambda *s: np.full((n_seg, *s), np.nan)  # noqa: E731
    out = LatentSpin(p0=nan(3), v0=nan(3), spin=nan(3), cov=nan(3, 3), along=nan(3), rmse=nan(), n=lengths,
                     ok=np.zeros(n_seg, bool), ambiguous=np.zeros(n_seg, bool))
    m = jax.tree.map(lambda x: jnp.asarray(x, dtype) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) else x,
                     model.replace(residual=None))
    scalar = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    # Every (segment, start) is a fit of its own (start_spins), run in passes (PASSES): each runs
    # the fits the one before left unconverged, for its share of the iterations, in calls of their
    # own. The starts along the flight are run only for the segments the first two leave well above
    # the others' error (RESCUE).
    seg = np.repeat(np.arange(n_seg), STARTS)
    rank = np.tile(np.arange(STARTS), n_seg)
    theta = np.full((len(seg), 9), np.nan)
    cost = np.full(len(seg), np.inf)
    jtj = np.full((len(seg), 9, 9), np.nan)
    along = np.full((n_seg, 3), np.nan)
    args = (scalar(noise), scalar(prior_along), scalar(prior_any))
    shares = np.cumsum(PASSES) / np.sum(PASSES)
    budget = np.diff(np.concatenate([[0], np.round(shares * iterations).astype(int)]))
    done = np.zeros(n_seg, int)

    def calls(rows_of):
        for idx, (tau, pos, mask, _), n_max in batches([times[i] for i in seg[rows_of]],
                                                       [positions[i] for i in seg[rows_of]], np.zeros((len(rows_of), 3)),
                                                       batch, dtype, min_samples=min_samples, pow2_rows=True):
            pad = lambda a: np.concatenate([a, np.repeat(a[:1], len(tau) - len(a), 0)])  # noqa: E731
            yield rows_of[np.asarray(idx)], pad, (jnp.asarray(tau), jnp.asarray(pos), jnp.asarray(mask),
                                                  jnp.asarray(n_max))

    def run(todo):
        for rows, pad, arrays in calls(todo):
            start, ax = jax.device_get(_starts(m, *arrays[:3], jnp.asarray(pad(rank[rows]))))
            theta[rows] = np.asarray(start[:len(rows)], np.float64)
            along[seg[rows]] = np.asarray(ax[:len(rows)], np.float64)
        for n_iter in budget:
            if not len(todo) or n_iter <= 0:
                continue
            left = []
            for rows, pad, arrays in calls(todo):
                start = np.where(np.isfinite(theta[rows]), theta[rows], 0.0)
                raw = jax.device_get(_fit_batch(m, *arrays, *args, jnp.asarray(pad(start), dtype),
                                                jnp.asarray(pad(along[seg[rows]]), dtype), jnp.asarray(int(n_iter))))
                k = len(rows)
                theta[rows] = np.asarray(raw["theta"][:k], np.float64)
                cost[rows] = np.asarray(raw["cost"][:k], np.float64)
                jtj[rows] = np.asarray(raw["jtj"][:k], np.float64)
                going = ~np.asarray(raw["converged"][:k], bool) & np.isfinite(theta[rows]).all(1)
                left.append(rows[going])
                np.add.at(done, seg[rows[~going]], 1)
                if progress is not None:
                    progress(int(np.count_nonzero(done >= BASE_STARTS)))
            todo = np.concatenate(left) if left else np.zeros(0, int)

    fits = np.flatnonzero((lengths[seg] >= min_samples) & (rank < BASE_STARTS))
    run(fits)
    best = cost.reshape(n_seg, STARTS).min(1)
    rmse = np.sqrt(np.maximum(best, 0.0) / np.maximum(lengths, 1))
    usable = np.isfinite(rmse) & (lengths >= min_samples)
    if usable.any():
        rescue = (lengths >= min_samples) & ~(rmse <= RESCUE * np.median(rmse[usable]))
        run(np.flatnonzero(rescue[seg] & (rank >= BASE_STARTS)))
    fitted = np.flatnonzero(lengths >= min_samples)
    if len(fitted):
        th = theta.reshape(n_seg, STARTS, 9)[fitted]
        best, ambiguous = best_starts(th, cost.reshape(n_seg, STARTS)[fitted], along[fitted])
        pick = fitted * STARTS + best
        count = np.array([len(times[i]) for i in fitted], np.float64)
        cov, rmse = spin_statistics(theta[pick], cost[pick], jtj[pick], along[fitted], count, noise, prior_along,
                                    prior_any)
        ok = np.isfinite(theta[pick]).all(1) & np.isfinite(cost[pick]) & np.isfinite(cov).all((1, 2))
        for name, value in (("p0", theta[pick, :3]), ("v0", theta[pick, 3:6]), ("spin", theta[pick, 6:]),
                            ("cov", cov), ("along", along[fitted]), ("rmse", rmse)):
            getattr(out, name)[fitted] = np.where(ok.reshape((-1,) + (1,) * (value.ndim - 1)), value, np.nan)
        out.ok[fitted] = ok
        out.ambiguous[fitted] = ambiguous & ok
    if progress is not None:
        progress(n_seg)
    return out


def dataset_latent_spin(ds, model, *, min_samples: int = 8, noise: float = NOISE,
                        progress: Callable | None = None) -> tuple[np.ndarray, LatentSpin]:
    """(segment_ids (S,), :class:`LatentSpin`) of every segment of a dataset with at least
    ``min_samples`` observations; ``noise`` and ``progress`` as for :func:`fit_latent_spin`."""
    from ttsim_jax.fit.segment_batches import dataset_segments

    ids, times, positions, _, _ = dataset_segments(ds, min_samples)
    return ids, fit_latent_spin(times, positions, model, noise=noise, min_samples=min_samples, progress=progress)
