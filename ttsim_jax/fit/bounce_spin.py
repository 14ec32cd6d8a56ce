"""Latent spin across a table bounce: the segments before and after it fitted as one flight.

A flight alone shows its spin's direction across the velocity far better than its size: under the
paper's C_M the Magnus force C_M(|w|) |w| hardly grows above a few hundred rad/s, and under
Dürr's it falls, so a spin and one several times its size bend a segment alike
(:mod:`ttsim_jax.fit.latent_spin`). A bounce tells them apart: the table's friction turns the
spin into velocity (a topspin of 400 rad/s leaves the table metres per second faster than one of
40), and the outgoing spin follows from the incoming one through the table law.

So, per bounce, theta = (p0, v0, w) of the incoming segment is fitted to the samples of both
segments under the model: its flight to the last incoming sample and on to the bounce, the time
of impact found where the flight meets the table plane (z = one radius; two Newton steps from
the contact time the data give, so the fit's own trajectory decides it), the model's table
contact (:func:`ttsim_jax.physics.table.table_contact`, the playing surface), and its flight
through the outgoing samples. Costs are in units of the position noise, with the spin prior of
the single-segment fit (:func:`ttsim_jax.fit.latent_spin.spin_prior`: weak overall, narrow
along the incoming direction of flight), by the same Levenberg-Marquardt solver. The cost has
several minima (a spin of the wrong size with the flight's start adjusted to it), so the start is
chosen first: the single-segment latent spin scaled by each of :data:`SCREEN`, its cost
evaluated (one flight each), and the fit run from the :data:`FITTED` best, the best fit kept;
failed steps retry with more damping rather than end the fit (the table's friction regimes make
the cost kinked).

What it assumes: the model's table law. The fitted spin is the one that law needs to reproduce
the outgoing flight, so a bounce scored against the model's own table law from this spin is
partly circular; the evaluation's table stage therefore scores bounces from the single-segment
latent spin, and this fit serves where the spin leaving a bounce is wanted (the ball a racket
meets after the bounce) and to check a measured spin's size.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit.flightfit import COMPILER_OPTIONS, levenberg_marquardt
from ttsim_jax.fit.latent_spin import NOISE, PRIOR_ALONG, PRIOR_ANY, fit_latent_spin, spin_prior, spin_statistics
from ttsim_jax.fit.segment_batches import capacity, pack
from ttsim_jax.physics import table as table_stage
from ttsim_jax.physics.aero import flight_step

#: The single-segment latent spin is scaled by each of these, and the cost of each evaluated, to
#: choose where the fit starts: the sizes a flight cannot tell apart (a spin and several times it,
#: or a fraction), log-spaced.
SCREEN = tuple(float(x) for x in np.geomspace(0.2, 5.0, 15))
#: The fit runs from this many of the best screened starts.
FITTED = 3
#: Levenberg-Marquardt iterations at most.
ITERATIONS = 20
#: Pairs per compiled call.
BATCH = 64
#: Newton steps onto the table plane from the data's contact time.
NEWTON = 2
#: Shortest segment on either side [samples].
MIN_SAMPLES = 8


def _flight(model, y, h):
    return flight_step(model.aero, model.ball.radius, model.ball.mass, *y, 0.0, h, model.effects)


def predict(model, theta, tau_a, tau_b, t_c):
    """Positions of one bounce pair's flight at its samples, and the spin leaving the bounce.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model`; theta: (9,) (p0, v0, w) at ``tau_a[0]`` = 0.
        tau_a: (T,) incoming sample times from the first one (padding repeats the last);
        tau_b: (T,) outgoing sample times on the same clock (padding repeats the last);
        t_c: the data's contact time on that clock.

    Returns:
        (positions (T, 3) incoming, positions (T, 3) outgoing, spin (3,) after the bounce, time of
        impact).
    """
    radius = model.ball.radius

    def along(y, dts):
        def body(y_, h):
            y2 = _flight(model, y_, h)
            return y2, y2[0]
        y_end, ps = jax.lax.scan(body, y, dts)
        return y_end, jnp.concatenate([y[0][None], ps])

    y0 = (theta[:3], theta[3:6], theta[6:9])
    y, pa = along(y0, jnp.diff(tau_a))
    t = t_c
    y = _flight(model, y, t_c - tau_a[-1])
    for _ in range(NEWTON):  # onto the plane z = radius along the fitted flight
        h = (radius - y[0][2]) / jnp.minimum(y[1][2], -0.1)
        y, t = _flight(model, y, h), t + h
    post = table_stage.table_contact(model.table, radius, *y, model.effects, edges=False)
    y = _flight(model, post, tau_b[0] - t)
    _, pb = along(y, jnp.diff(tau_b))
    return pa, pb, post[2], t


def _residuals(model, theta, tau_a, pos_a, mask_a, tau_b, pos_b, mask_b, t_c, noise):
    """(the pair's position residuals in units of the noise (6T,), the spin after the bounce)."""
    pa, pb, w_out, _ = predict(model, theta, tau_a, tau_b, t_c)
    r = jnp.concatenate([((pa - pos_a) * mask_a[:, None]).ravel(), ((pb - pos_b) * mask_b[:, None]).ravel()])
    return r / noise, w_out


def _normal(model, theta, data, noise, prior):
    """Cost, J^T J, J^T r with the spin prior, and the spin after the bounce; ``data`` the pair's
    (tau_a, pos_a, mask_a, tau_b, pos_b, mask_b, t_c). The nine tangents ride one flight (forward
    mode), the residuals computed once beside them."""
    def f(th):
        return _residuals(model, th, *data, noise)

    eye = jnp.eye(theta.shape[0], dtype=theta.dtype)
    (r, w_out), (jac, _) = jax.vmap(lambda d: jax.jvp(f, (theta,), (d,)), out_axes=((None, None), (1, 1)))(eye)
    w = theta[6:]
    cost = r @ r + w @ prior @ w
    jtj = (jac.T @ jac).at[6:, 6:].add(prior)
    jtr = (jac.T @ r).at[6:].add(prior @ w)
    return cost, jtj, jtr, w_out


def _fit_pair(model, tau_a, pos_a, mask_a, tau_b, pos_b, mask_b, t_c, start, along, noise, prior_along, prior_any,
              iterations):
    prior = spin_prior(along, prior_along, prior_any)
    data = (tau_a, pos_a, mask_a, tau_b, pos_b, mask_b, t_c)

    def screen(scale):
        th = start.at[6:].multiply(scale)
        r, _ = _residuals(model, th, *data, noise)
        cost = r @ r + th[6:] @ prior @ th[6:]
        return jnp.where(jnp.isfinite(cost), cost, jnp.inf)

    scales = jnp.asarray(SCREEN, start.dtype)
    best_scales = scales[jnp.argsort(jax.vmap(screen)(scales))[:FITTED]]

    def one(scale):
        return levenberg_marquardt(lambda th: _normal(model, th, data, noise, prior), start.at[6:].multiply(scale),
                                   iterations, stop_on_failure=False)

    theta, cost, h, w_out, _ = jax.vmap(one)(best_scales)
    cost = jnp.where(jnp.isfinite(cost), cost, jnp.inf)
    best = jnp.argmin(cost)
    return dict(theta=theta[best], cost=cost[best], jtj=h[best], spin_out=w_out[best])


def _fit_batch_impl(model, tau_a, pos_a, mask_a, tau_b, pos_b, mask_b, t_c, start, along, noise, prior_along,
                    prior_any, iterations):
    return jax.vmap(lambda *a: _fit_pair(model, *a, noise, prior_along, prior_any, iterations))(
        tau_a, pos_a, mask_a, tau_b, pos_b, mask_b, t_c, start, along)


_fit_batch = jax.jit(_fit_batch_impl, static_argnames=("iterations",), compiler_options=COMPILER_OPTIONS)


@dataclasses.dataclass
class BounceSpin:
    """Latent spins across bounces (numpy, in the order the pairs were given).

    Attributes:
        spin_in: (N, 3) spin before the bounce [rad/s]; spin_out: (N, 3) after it, through the
            model's table law; cov: (N, 3, 3) ``spin_in``'s covariance (curvature, scaled by the
            reduced chi-square where above 1);
        p0, v0: (N, 3) fitted state at the incoming segment's first sample;
        rmse: (N,) position RMSE over both segments [m]; single: (N, 3) the incoming segment's own
            latent spin (the start); ok: (N,) fitted and finite (the others NaN).
    """

    spin_in: np.ndarray
    spin_out: np.ndarray
    cov: np.ndarray
    p0: np.ndarray
    v0: np.ndarray
    rmse: np.ndarray
    single: np.ndarray
    ok: np.ndarray

    def __len__(self) -> int:
        return len(self.rmse)


def fit_bounce_spin(times_in: Sequence[np.ndarray], positions_in: Sequence[np.ndarray],
                    times_out: Sequence[np.ndarray], positions_out: Sequence[np.ndarray], t_contact, model, *,
                    noise: float = NOISE, prior_along: float = PRIOR_ALONG, prior_any: float = PRIOR_ANY,
                    batch: int = BATCH, iterations: int = ITERATIONS, dtype=None) -> BounceSpin:
    """The latent spin of every bounce from the segments on both sides (module docstring).

    Arguments:
        times_in, positions_in: per bounce, the incoming segment's (T_i,) times [s] and (T_i, 3)
            positions [m]; times_out, positions_out: the outgoing segment's; t_contact: (N,) the
            data's contact times [s].
        model: a :class:`~ttsim_jax.params.Model`.
        noise, prior_along, prior_any: as for :func:`ttsim_jax.fit.latent_spin.fit_latent_spin`.
        batch: pairs per compiled call; iterations: Levenberg-Marquardt iterations at most;
        dtype: the fit's float type (default JAX's).

    Returns:
        :class:`BounceSpin`. A pair with fewer than :data:`MIN_SAMPLES` samples on a side is not
        fitted (NaN, ``ok`` False).
    """
    n = len(times_in)
    if not (len(positions_in) == len(times_out) == len(positions_out) == len(t_contact) == n):
        raise ValueError(f"fit_bounce_spin: {n} incoming segments, {len(times_out)} outgoing, "
                         f"{len(t_contact)} contact times: one of each per bounce")
    dtype = jnp.zeros(()).dtype if dtype is None else np.dtype(dtype)
    nan = lambda *s: np.full((n, *s), np.nan)  # noqa: E731
    out = BounceSpin(spin_in=nan(3), spin_out=nan(3), cov=nan(3, 3), p0=nan(3), v0=nan(3), rmse=nan(), single=nan(3),
                     ok=np.zeros(n, bool))
    usable = [i for i in range(n) if min(len(times_in[i]), len(times_out[i])) >= MIN_SAMPLES]
    if not usable:
        return out
    single = fit_latent_spin([times_in[i] for i in usable], [positions_in[i] for i in usable], model,
                             noise=noise, prior_along=prior_along, prior_any=prior_any, dtype=dtype)
    m = jax.tree.map(lambda x: jnp.asarray(x, dtype) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) else x,
                     model.replace(residual=None))
    scalar = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    starts = np.concatenate([single.p0, single.v0, single.spin], 1)
    starts = np.where(np.isfinite(starts), starts, 0.0)
    out.single[usable] = single.spin
    lengths = np.array([max(len(times_in[i]), len(times_out[i])) for i in usable])
    groups: dict[int, list[int]] = {}
    for j in np.argsort(lengths, kind="stable"):
        groups.setdefault(capacity(int(lengths[j])), []).append(int(j))
    zeros = np.zeros((n, 3))  # pack's spins, unused here
    for size, members in sorted(groups.items()):
        for lo in range(0, len(members), batch):
            part = members[lo:lo + batch]
            rows = -(-len(part) // 8) * 8
            idx = [usable[j] for j in part]
            ta, pa, ma, _ = pack(times_in, positions_in, zeros, idx, size, rows, dtype)
            tb, pb, mb, _ = pack(times_out, positions_out, zeros, idx, size, rows, dtype)
            t0 = np.array([times_in[i][0] for i in idx], np.float64)
            off = np.zeros(rows)
            off[:len(idx)] = np.array([times_out[i][0] for i in idx]) - t0
            tb = (tb + off[:, None]).astype(dtype)
            tc = np.zeros(rows, dtype)
            tc[:len(idx)] = np.asarray(t_contact, np.float64)[idx] - t0
            st = np.zeros((rows, 9), dtype)
            st[:len(idx)] = starts[part]
            al = np.tile(np.array([1.0, 0.0, 0.0], dtype), (rows, 1))
            al[:len(idx)] = np.where(np.isfinite(single.along[part]), single.along[part], al[:len(idx)])
            # padding rows: a copy of the first pair, so that they fit something finite
            for arr in (ta, pa, ma, tb, pb, mb, tc, st, al):
                arr[len(idx):] = arr[0]
            raw = jax.device_get(_fit_batch(m, *(jnp.asarray(a) for a in (ta, pa, ma, tb, pb, mb, tc, st, al)),
                                            scalar(noise), scalar(prior_along), scalar(prior_any), iterations))
            k = len(idx)
            theta, cost, h = (np.asarray(raw[key][:k], np.float64) for key in ("theta", "cost", "jtj"))
            count = np.asarray(ma[:k], np.float64).sum(1) + np.asarray(mb[:k], np.float64).sum(1)
            cov, rmse = spin_statistics(theta, cost, h, al[:k].astype(np.float64), count, noise, prior_along,
                                        prior_any)
            w_out = np.asarray(raw["spin_out"][:k], np.float64)
            ok = np.isfinite(theta).all(1) & np.isfinite(cost) & np.isfinite(w_out).all(1) & np.isfinite(cov).all((1, 2))
            sel = np.asarray(idx)
            for name, value in (("p0", theta[:, :3]), ("v0", theta[:, 3:6]), ("spin_in", theta[:, 6:]),
                                ("spin_out", w_out), ("cov", cov), ("rmse", rmse)):
                getattr(out, name)[sel] = np.where(ok.reshape((-1,) + (1,) * (value.ndim - 1)), value, np.nan)
            out.ok[sel] = ok
    return out


def bounce_pairs(ds, event_ids=None, *, min_samples: int = MIN_SAMPLES) -> dict:
    """The table bounces of a dataset with a flight segment on each side, as :func:`fit_bounce_spin` takes them.

    Arguments:
        ds: a :class:`~ttsim_jax.data.Dataset`; event_ids: the bounces to take (default: every
            table event); min_samples: shortest segment on either side.

    Returns:
        dict: ``event_id``, ``in_row``, ``out_row`` (N,) (rows of the segments table),
        ``t_contact`` (N,), ``times_in``, ``positions_in``, ``times_out``, ``positions_out``
        (lists): the bounces among ``event_ids`` that have both segments, in their order.
    """
    ev = ds.events
    kinds = np.asarray(ev["kind"]).astype(str)
    ids = np.asarray(ev["event_id"], np.int64)[kinds == "table"] if event_ids is None else np.asarray(event_ids, np.int64)
    rows = ds.event_rows(ids) if len(ids) else np.zeros(0, np.int64)
    ids = ids[(rows >= 0) & (kinds[np.maximum(rows, 0)] == "table")] if len(ids) else ids
    in_rows, out_rows = ds.segments_around(ids) if len(ids) else (np.zeros(0, np.int64),) * 2
    both = (in_rows >= 0) & (out_rows >= 0)
    ids, in_rows, out_rows = ids[both], in_rows[both], out_rows[both]
    seg_ids = np.asarray(ds.segments["segment_id"])
    obs_in = ds.segment_rows(seg_ids[in_rows]) if len(ids) else []
    obs_out = ds.segment_rows(seg_ids[out_rows]) if len(ids) else []
    keep = np.array([min(len(obs_in[k]), len(obs_out[k])) >= min_samples for k in range(len(ids))], bool)
    keep_list = np.flatnonzero(keep)
    t_all = np.asarray(ev["t"], np.float64)
    t_obs = np.asarray(ds.observations["t"], np.float64)
    return dict(event_id=ids[keep], in_row=in_rows[keep], out_row=out_rows[keep],
                t_contact=t_all[ds.event_rows(ids[keep])] if keep.any() else np.zeros(0),
                times_in=[t_obs[obs_in[k]] for k in keep_list], positions_in=[ds.positions[obs_in[k]] for k in keep_list],
                times_out=[t_obs[obs_out[k]] for k in keep_list],
                positions_out=[ds.positions[obs_out[k]] for k in keep_list])


def dataset_bounce_spin(ds, model, event_ids=None, *, noise: float = NOISE) -> tuple[dict, BounceSpin]:
    """(:func:`bounce_pairs` of ``ds``, their :class:`BounceSpin`), ``noise`` as for :func:`fit_bounce_spin`."""
    pairs = bounce_pairs(ds, event_ids)
    return pairs, fit_bounce_spin(pairs["times_in"], pairs["positions_in"], pairs["times_out"], pairs["positions_out"],
                                  pairs["t_contact"], model, noise=noise)
