"""Starting values of the gusts of the ``air_flow`` candidate, from the flights' own wind estimates.

A gust is a sinusoid in session time, ``amp sin(2 pi freq t + phase)``. Its frequency cannot be
found by gradient descent from a guess: the loss is a comb of local minima in the frequency,
about 1 / (session duration) apart. So, once the steady wind is fitted, each training segment's
own constant wind offset is estimated (:func:`segment_winds`: one Gauss-Newton step of the
segment's initial state and the offset together, with the offset's information matrix), and per
session a weighted least-squares periodogram of those offsets against the segments' mean times
picks the gust components one at a time (:func:`periodogram_gusts`). A component is kept only
when it lowers the offsets' chi-square by more than :data:`MIN_CHI2` (noise alone, over the
frequency grid, stays below it), the offsets' information first scaled down by their
overdispersion about their mean (other unmodelled effects scatter them too); the others start at
zero amplitude. The descent then refines
wind, amplitudes, phases and frequencies together from those starts
(:func:`ttsim_jax.diagnose.candidates.fit`).

Only the training segments enter, so the held-out score stays a fair test of the gusts.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.diagnose import stages
from ttsim_jax.files.programs import stored_jit
from ttsim_jax.physics.linalg import spd_solve

#: Least fall of the per-segment offsets' chi-square for a gust component to be kept: its 6
#: degrees of freedom (a sine and a cosine vector) at the best frequency of the grid reach a median
#: of 20 and a 99th percentile of 31 on pure noise (200 sessions of 85 segments over 100 s).
MIN_CHI2 = 40.0
#: Segments left out of the periodogram: residual RMS after the offset above OUTLIER times the
#: median segment's. (A wild offset along a direction the segment hardly resolves needs no
#: filter: its information there is small, and so is its weight.)
OUTLIER = 3.0
#: Frequency band searched [Hz] (the catalogue draws 0.05-1 Hz) and grid points per 1 / duration.
BAND = (0.02, 1.2)
OVERSAMPLE = 6


@struct.dataclass
class _Offset:
    """An extra constant air velocity (the per-segment wind offset being estimated); a pytree, as
    every effect that a flight (:func:`~ttsim_jax.diagnose.stages.flight_errors`) is flown with."""

    w: jax.Array

    def air_velocity(self, value, **_):
        return value + self.w


def _segment_wind(model, effects, x, spin, t0, tau, pos, mask, changes):
    def res(z):
        fx = effects + (_Offset(z[6:]),)
        return stages._segment_residual(model, fx, z[:6], spin, t0, tau, pos, mask, changes).ravel()

    z = jnp.concatenate([x, jnp.zeros(3, x.dtype)])
    eye = jnp.eye(9, dtype=x.dtype)
    r, jac = stages.residual_jacobian(res, z)
    h = jac.T @ jac
    hr = h + 1e-9 * jnp.trace(h) * eye + 1e-30
    step = -spd_solve(hr, jac.T @ r)
    # information of the offset with the state free: the Schur complement of the state block
    info = h[6:, 6:] - h[6:, :6] @ spd_solve(hr[:6, :6], h[:6, 6:])
    sse = jnp.sum((r + jac @ step) ** 2)
    ok = jnp.all(jnp.isfinite(step)) & jnp.all(jnp.isfinite(info))
    return jnp.where(ok, step[6:], 0.0), jnp.where(ok, info, 0.0), jnp.where(ok, sse, 0.0)


def _winds_impl(model, consts, u, fl, x, specs):
    changes = stages._spin_changes(model, specs)

    def one(xi, t0, tau, pos, mask, spin, s):
        fx = model.effects + stages.effects_of(specs, consts, u, s)
        return _segment_wind(model, fx, xi, spin, t0, tau, pos, mask, changes)

    return jax.vmap(one)(x, fl["t0"], fl["tau"], fl["pos"], fl["mask"], fl["spin"], fl["session"])


_winds = stored_jit(_winds_impl, static_argnames=("specs",))


def segment_winds(model, specs, consts, u, fl: dict, x):
    """Per flight segment, its constant wind offset on top of the effects at ``u``.

    Arguments:
        model, specs, consts, u: the model and the fitted candidate effects (as in
            :func:`ttsim_jax.diagnose.stages.flight_errors`).
        fl: the flight data dict; x: (S, 6) the segments' initial states fitted at ``u``.

    Returns:
        (offset (S, 3) [m/s], information (S, 3, 3) [s^2/m^2 per m^2 of residual], sse (S,) [m^2]
        residual sum of squares after the step): multiply the information by 1 / sigma^2, sigma the
        position noise, to get the inverse covariance of the offset. Zero for a failed segment.
    """
    consts = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), consts)
    w, info, sse = _winds(model.replace(name=""), consts, u, fl, x, tuple(specs))
    return np.asarray(w, np.float64), np.asarray(info, np.float64), np.asarray(sse, np.float64)


def _fit_sinusoid(t, w, info, freqs):
    """Per frequency, the chi-square fall of w ~ c + a sin(2 pi f t) + b cos(2 pi f t) against w ~ c
    (weights ``info``), and the coefficients (a, b) (F, 2, 3)."""
    arg = 2.0 * np.pi * freqs[:, None] * t[None, :]
    g = np.stack([np.ones_like(arg), np.sin(arg), np.cos(arg)], -1)  # (F, n, 3)
    # normal equations of the 9 unknowns (c, a, b: 3 vectors): sum_i (g g^T) kron info_i
    lhs = np.einsum("fip,fiq,ijk->fpjqk", g, g, info).reshape(len(freqs), 9, 9)
    rhs = np.einsum("fip,ijk,ik->fpj", g, info, w).reshape(len(freqs), 9)
    lhs += 1e-9 * np.trace(lhs, axis1=1, axis2=2)[:, None, None] * np.eye(9) + 1e-30 * np.eye(9)
    coef = np.linalg.solve(lhs, rhs[..., None])[..., 0]
    fall = np.einsum("fp,fp->f", coef, rhs)  # chi^2(c, a, b) fall from zero
    c_only = np.linalg.solve(info.sum(0) + 1e-30 * np.eye(3), np.einsum("ijk,ik->j", info, w))
    fall0 = c_only @ np.einsum("ijk,ik->j", info, w)
    return fall - fall0, coef.reshape(len(freqs), 3, 3)[:, 1:]


def periodogram_gusts(t, w, info, components: int = 3, min_chi2: float = MIN_CHI2):
    """Gust components of one session's per-segment wind offsets, strongest first.

    Arguments:
        t: (n,) the segments' mean sample times [s]; w: (n, 3) their offsets [m/s]; info: (n, 3, 3)
            their inverse covariances.
        components: number of components (the effect's); min_chi2: :data:`MIN_CHI2`.

    Returns:
        (amp (K, 3), freq (K,), phase (K,), chi2 (K,)): amplitude vectors, frequencies [Hz], phases
        [rad] such that amp sin(2 pi freq t + phase) fits the offsets; a component whose chi-square
        fall is below ``min_chi2`` has amplitude 0 (frequency and phase then mean nothing).
    """
    t, w, info = np.asarray(t, np.float64), np.array(w, np.float64), np.asarray(info, np.float64)
    amp, freq, phase, chi2 = np.zeros((components, 3)), np.zeros(components), np.zeros(components), np.zeros(components)
    if len(t) < 8:
        return amp, freq, phase, chi2
    # the offsets scatter more than the noise alone predicts wherever the model misses something
    # else segment by segment (other effects, estimated spins): scale the information down by that
    # overdispersion, so that such scatter is not taken for gusts
    c = np.linalg.solve(info.sum(0) + 1e-30 * np.eye(3), np.einsum("ijk,ik->j", info, w))
    r = w - c
    phi = max(float(np.einsum("ij,ijk,ik->", r, info, r)) / (3.0 * (len(t) - 1)), 1.0)
    info = info / phi
    span = max(float(t.max() - t.min()), 1.0)
    freqs = np.arange(BAND[0], BAND[1], 1.0 / (OVERSAMPLE * span))
    for k in range(components):
        fall, ab = _fit_sinusoid(t, w, info, freqs)
        best = int(np.argmax(fall))
        chi2[k], freq[k] = fall[best], freqs[best]
        # one phase per component: the best rank-1 form of [a b] = amp (cos phase, sin phase)
        u_, s_, vt = np.linalg.svd(ab[best].T)
        vec, (cos, sin) = u_[:, 0] * s_[0], vt[0]
        phase[k] = np.arctan2(sin, cos)
        if fall[best] < min_chi2:
            break
        amp[k] = vec
        w = w - vec[None, :] * np.sin(2.0 * np.pi * freq[k] * t + phase[k])[:, None]
    return amp, freq, phase, chi2


#: Scales of the second descent's parameters (units of Adam's step): the wind and the gusts near
#: their starts, the frequency within a fraction of the periodogram's resolution.
SCALES = {"wind": 0.05, "gust_amp": 0.05, "gust_phase": 0.3, "gust_freq": 0.002}


def typical_segments(reduced, rows) -> tuple[np.ndarray, float]:
    """(rows kept, sigma^2): the noise variance from the median of the segments' reduced residuals
    after their wind offset, and ``rows`` without the segments above :data:`OUTLIER`^2 times it (a
    flight the segmentation cut wrongly, a contact inside: its wild offset would pull the
    periodogram)."""
    reduced, rows = np.asarray(reduced, np.float64), np.asarray(rows, bool)
    sigma2 = max(float(np.median(reduced[rows])) if rows.any() else 0.0, 1e-12)
    return rows & (reduced < OUTLIER**2 * sigma2), sigma2


def mean_times(fl: dict) -> np.ndarray:
    """(S,) each flight segment's mean sample time [s] (session time)."""
    tau, mask = np.asarray(fl["tau"], np.float64), np.asarray(fl["mask"], np.float64)
    return np.asarray(fl["t0"], np.float64) + (tau * mask).sum(1) / np.maximum(mask.sum(1), 1.0)


def gust_stage(pb, model, specs, consts, u, x, i):
    """The second descent of the ``air_flow`` candidate ``specs[i]`` after its steady wind was fitted
    (``u``, flight states ``x``): (spec with wind and gusts free, consts whose starts carry a session
    axis), or None when no session shows a gust (then the first descent's result stands).

    Used by :func:`ttsim_jax.diagnose.candidates.fit` through its ``REFINE`` table."""
    sp, const = specs[i], consts[i]
    if "flight" not in pb.data or not sp.per_session or not {"wind", "gust_amp", "gust_freq", "gust_phase"} <= set(
            sp.cls.PARAMS):
        return None
    fl = pb.data["flight"]
    w, info, sse = segment_winds(model, specs, consts, u, fl, x)
    mask = np.asarray(fl["mask"], np.float64)
    dof = np.maximum(3.0 * mask.sum(1) - 9.0, 0.0)
    reduced = sse / np.maximum(dof, 1.0)
    train = (np.asarray(fl["train"]) > 0) & (mask.sum(1) >= 6)
    train, sigma2 = typical_segments(reduced, train)
    t, session = mean_times(fl), np.asarray(fl["session"])
    n = pb.n_sessions
    start = {k: np.broadcast_to(np.asarray(stages.start_of(sp, const, k, 0), np.float64), (n,) + p.shape).copy()
             for k, p in sp.cls.PARAMS.items()}
    u_wind = np.asarray(u[i]["wind"], np.float64) if "wind" in u[i] else np.zeros((n, 3))
    start["wind"] = start["wind"] + const["scale"]["wind"] * u_wind
    found = False
    for s in range(n):
        rows = train & (session == s)
        amp, freq, phase, _ = periodogram_gusts(t[rows], w[rows], info[rows] / sigma2, components=len(start["gust_freq"][s]))
        kept = np.linalg.norm(amp, axis=1) > 0
        found |= bool(kept.any())
        start["gust_amp"][s] = amp
        start["gust_freq"][s] = np.where(kept, freq, start["gust_freq"][s])
        start["gust_phase"][s] = np.where(kept, phase, start["gust_phase"][s])
    if not found:
        return None
    return stages.second_descent(sp, start, SCALES)
