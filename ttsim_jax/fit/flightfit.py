"""The flight fit of a segment: initial state and constant (C_D, C_M), by least squares.

Each segment's observed positions p_i at times t_i are fitted by the flight stage
(:func:`ttsim_jax.physics.aero.flight_step`, RK4, one step per observation interval by default)
with constant coefficients and the segment's measured spin, over eight free parameters
theta = (p0 (3), v0 (3), C_D, C_M): minimise sum_i |p(t_i; theta) - p_i|^2. The fit serves twice:
it filters segments, as in the paper's data filtering (and the authors' code: a segment is kept
when the fit's 3-D position RMSE, sqrt(mean_i |p_fit(t_i) - p_i|^2), is within 20 mm;
:func:`ballistic_rmse`, the default ``rmse_fn`` of :func:`ttsim_jax.data.segment.filter_segments`),
and its per-segment coefficients are what the aerodynamic identification
(:mod:`ttsim_jax.fit.identify`, :mod:`ttsim_jax.fit.aero_forms`) regresses into the paper's forms.

The solver is a Levenberg-Marquardt loop written in ``jax.lax`` and vmapped over segments, so a
whole batch is one compiled call:

* the Jacobian comes from forward mode through the integration, for the five parameters that act
  on the acceleration (the initial position's columns are the identity), and J^T J, J^T r are
  summed sample by sample during that one integration (:func:`normal_equations`), so nothing of
  the segment's length is carried through the loop;
* the damped normal equations are solved (Cholesky) after scaling the columns to unit norm, which
  keeps float32 usable although the columns differ by orders of magnitude (metres, m/s,
  coefficients); standard errors and effective speeds are computed on the host afterwards;
* a step is kept only if it lowers the cost, with the damping divided by 3 on success and
  multiplied by 10 on failure. A segment has converged when the next step is predicted (by the
  linearised model, from the normal equations in hand) to lower the cost by less than ``TOL`` of
  it, or when a step gained less than that; deciding on the prediction saves the integration
  that would only confirm convergence. Every iteration is one forward pass with tangents and no
  branch; a group's loop ends when all its segments have converged, or after ``ITERATIONS``.

Segments are padded and grouped for the compiled calls by :mod:`ttsim_jax.fit.segment_batches`.

After the fit, each segment's effective speeds (the paper's force-averaged velocities) are computed
along the fitted trajectory at the observation times:

    drag:   v_eff = sum |v_i|^3 / sum |v_i|^2
    Magnus: v_eff = sum |v_i|^2 sin(theta_i) / sum |v_i| sin(theta_i),  sin(theta_i) = |v_i x w| / (|v_i| |w|)

The identification regresses the fitted coefficients at these speeds into the paper's functional
forms.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.physics.aero import AeroParams, ConstantCoefficient, flight_step
from ttsim_jax.physics.linalg import spd_solve

from .segment_batches import BATCH, GROUP, grouped_batches

#: Where every fit starts: Nakashima's coefficients.
CD_0, CM_0 = 0.54, 0.069
#: Convergence: the fit stops once the next step is predicted to lower the cost by less than this fraction.
TOL = 1e-6
#: Most Levenberg-Marquardt iterations (a batch stops earlier once every segment has converged).
ITERATIONS = 8
#: Names of the fitted parameters, in order.
PARAMS = ("x0", "y0", "z0", "vx0", "vy0", "vz0", "C_D", "C_M")


@struct.dataclass
class Air:
    """Ball and air of the flight model (arrays, so that changing them does not recompile).

    Attributes:
        radius, mass: ball radius [m] and mass [kg].
        rho_air: air density [kg/m^3]; nu: kinematic viscosity [m^2/s].
        gravity: (3,) gravitational acceleration [m/s^2]; buoyancy: 1.0 with buoyancy, 0.0 without.
    """

    radius: jnp.ndarray
    mass: jnp.ndarray
    rho_air: jnp.ndarray
    nu: jnp.ndarray
    gravity: jnp.ndarray
    buoyancy: jnp.ndarray

    @classmethod
    def from_model(cls, model, dtype=jnp.float32) -> "Air":
        """The ball and air of a loaded :class:`~ttsim_jax.params.Model`."""
        arr = lambda x: jnp.asarray(x, dtype)  # noqa: E731
        a = model.aero
        return cls(arr(model.ball.radius), arr(model.ball.mass), arr(a.rho_air), arr(a.nu), arr(a.gravity),
                   arr(a.buoyancy))

    def aero(self, cd, cm) -> AeroParams:
        """Flight parameters with constant coefficients ``cd``, ``cm``."""
        return AeroParams(rho_air=self.rho_air, nu=self.nu, gravity=self.gravity, buoyancy=self.buoyancy,
                          drag=ConstantCoefficient(cd), magnus=ConstantCoefficient(cm))


@functools.lru_cache(maxsize=4)
def default_air(dtype: str = "float32") -> Air:
    """The ball and air of the bundled conti2026 model (loaded once per dtype: parsing the model
    costs more than fitting a small batch)."""
    from ttsim_jax.params import load_model

    return Air.from_model(load_model("conti2026"), jnp.dtype(dtype))


# --------------------------------------------------------------------------- one segment
def integrate(aero: AeroParams, p0, v0, tau, spin, n, air: Air, substeps: int = 1):
    """Positions and velocities of a flight under any flight parameters at the sample times.

    Arguments:
        aero: flight parameters (any coefficient models).
        p0, v0: (3,) state at tau[0].
        tau: (T,) sample times from the first [s]; padding repeats the last time.
        spin: (3,) constant spin [rad/s].
        n: number of samples to integrate to (the rest keep their initial zeros); may be larger
            than the segment's own length (padded steps have dt = 0).
        air: the ball's radius and mass (its air is not used: ``aero`` has its own).
        substeps: RK4 steps per observation interval (static).

    Returns:
        (P, V): (T, 3) positions [m] and velocities [m/s].
    """
    dts = jnp.diff(tau)
    buf = jnp.zeros((tau.shape[0], 3), p0.dtype)

    def body(carry):
        i, p, v, ps, vs = carry
        h = dts[i] / substeps
        for _ in range(substeps):
            p, v, _ = flight_step(aero, air.radius, air.mass, p, v, spin, 0.0, h)
        return i + 1, p, v, ps.at[i + 1].set(p), vs.at[i + 1].set(v)

    init = (jnp.asarray(0), p0, v0, buf.at[0].set(p0), buf.at[0].set(v0))
    *_, ps, vs = jax.lax.while_loop(lambda c: c[0] < n - 1, body, init)
    return ps, vs


def trajectory(theta, tau, spin, n, air: Air, substeps: int = 1):
    """:func:`integrate` with constant coefficients: theta = ``[p0, v0, C_D, C_M]`` (8,)."""
    return integrate(air.aero(theta[6], theta[7]), theta[:3], theta[3:6], tau, spin, n, air, substeps)


def residual(theta, tau, pos, mask, spin, n, air: Air, substeps: int = 1):
    """Masked position residuals (3T,) of one segment: ``(p(t_i; theta) - p_i) * mask_i``."""
    ps, _ = trajectory(theta, tau, spin, n, air, substeps)
    return ((ps - pos) * mask[:, None]).ravel()


def jacobian(theta, tau, pos, mask, spin, n, air: Air, substeps: int = 1):
    """(3T, 8) Jacobian of :func:`residual`, and the residual and velocities at theta.

    The initial position does not act on the acceleration (no position-dependent forces in this
    model), so its columns are the mask times the identity and only the other five parameters need
    forward-mode tangents.

    Returns:
        (jac (3T, 8), residual (3T,), velocities (T, 3)).
    """

    def rest(x):
        ps, vs = trajectory(jnp.concatenate([theta[:3], x]), tau, spin, n, air, substeps)
        return ((ps - pos) * mask[:, None]).ravel(), vs

    x = theta[3:]
    # One integration carries the primal and the five tangents (jacfwd would integrate twice).
    tangents = jnp.eye(x.shape[0], dtype=x.dtype)
    (r, vel), (jac5, _) = jax.vmap(lambda t: jax.jvp(rest, (x,), (t,)), out_axes=((None, None), 1))(tangents)
    jac_p0 = (mask[:, None, None] * jnp.eye(3, dtype=theta.dtype)).reshape(-1, 3)
    return jnp.concatenate([jac_p0, jac5], axis=1), r, vel


def normal_equations(theta, tau, pos, mask, spin, n, air: Air, substeps: int = 1):
    """Cost, J^T J and J^T r of :func:`residual`, accumulated sample by sample in one integration.

    Equal to forming them from :func:`jacobian`, but nothing of length T is carried through the
    loop: the state's sensitivities to (v0, C_D, C_M) ride along the integration (forward mode
    through one RK4 step at a time) and each sample adds its 3 x 8 Jacobian block [I, D_i] to the
    sums. Carrying (T, 3, 5) tangent buffers through a loop costs far more than the arithmetic.

    Returns:
        (cost, jtj (8, 8), jtr (8,), velocities (T, 3) at the sample times).
    """
    dtype = theta.dtype
    dts = jnp.diff(tau)
    eye3 = jnp.eye(3, dtype=dtype)
    # Tangent directions over x = (v0, C_D, C_M): (dv0, dC_D, dC_M) per direction.
    dv0 = jnp.concatenate([eye3, jnp.zeros((2, 3), dtype)])
    dcoef = jnp.concatenate([jnp.zeros((3, 2), dtype), jnp.eye(2, dtype=dtype)])

    def step(p, v, cd, cm, h):
        aero = air.aero(cd, cm)
        for _ in range(substeps):
            p, v, _ = flight_step(aero, air.radius, air.mass, p, v, spin, 0.0, h)
        return p, v

    def add(sums, p, dp, i):
        cost, jtj, jtr = sums
        m = mask[i]
        r = p - pos[i]
        d = dp.T  # (3, 5): d p_i / d x
        block = jnp.concatenate([eye3, d], axis=1)  # (3, 8)
        return cost + m * (r @ r), jtj + m * (block.T @ block), jtr + m * (block.T @ r)

    def body(carry):
        i, p, v, dp, dv, sums, vel = carry
        h = dts[i] / substeps
        cd, cm = theta[6], theta[7]
        tangent = lambda dp_, dv_, dc: jax.jvp(lambda p_, v_, c_: step(p_, v_, c_[0], c_[1], h),  # noqa: E731
                                               (p, v, jnp.stack([cd, cm])), (dp_, dv_, dc))
        (p2, v2), (dp2, dv2) = jax.vmap(tangent, out_axes=((None, None), 0))(dp, dv, dcoef)
        return i + 1, p2, v2, dp2, dv2, add(sums, p2, dp2, i + 1), vel.at[i + 1].set(v2)

    p0, v0 = theta[:3], theta[3:6]
    dp0 = jnp.zeros((5, 3), dtype)
    sums = add((jnp.zeros((), dtype), jnp.zeros((8, 8), dtype), jnp.zeros(8, dtype)), p0, dp0, 0)
    vel = jnp.zeros((tau.shape[0], 3), dtype).at[0].set(v0)
    *_, sums, vel = jax.lax.while_loop(lambda c: c[0] < n - 1, body, (jnp.asarray(0), p0, v0, dp0, dv0, sums, vel))
    return (*sums, vel)


def parabola(tau, pos, mask):
    """(3, 3) coefficients (constant, linear, quadratic) of a per-axis least-squares parabola in
    tau through the masked samples."""
    a = jnp.stack([jnp.ones_like(tau), tau, tau**2], axis=-1) * mask[:, None]
    return spd_solve(a.T @ a + 1e-9 * jnp.eye(3, dtype=a.dtype), a.T @ (pos * mask[:, None]))


def initial_guess(tau, pos, mask, cd0=CD_0, cm0=CM_0):
    """(8,) start of the fit: position and velocity at tau[0] from a per-axis parabola."""
    coef = parabola(tau, pos, mask)
    return jnp.concatenate([coef[0], coef[1], jnp.array([cd0, cm0], pos.dtype)])


def _scaled(h):
    """Column scales d and the scaled matrix H / (d d^T); d is never zero."""
    diag = jnp.diagonal(h)
    d = jnp.sqrt(diag + 1e-12 * jnp.max(diag) + jnp.finfo(h.dtype).tiny)
    return d, h / (d[:, None] * d[None, :])


def _lm_step(h, g, lam):
    """Levenberg-Marquardt step of the normal equations (h, g) with damping ``lam`` on the scaled
    columns, and the cost reduction the linearised model predicts for it."""
    d, hs = _scaled(h)
    step = -spd_solve(hs + (lam + 1e-6) * jnp.eye(h.shape[0], dtype=h.dtype), g / d) / d
    return step, -(2.0 * g @ step + step @ h @ step)


def levenberg_marquardt(normal: Callable, theta0, iterations: int = ITERATIONS, tol: float = TOL,
                        stop_on_failure: bool = True):
    """Levenberg-Marquardt from ``theta0`` over normal equations ``normal(theta) -> (cost, J^T J,
    J^T r, aux)`` (jit- and vmap-able; under vmap the loop runs until every problem has converged).

    ``stop_on_failure`` (static): a step that does not lower the cost ends the fit (right for a
    smooth cost near its minimum, and it saves iterations); False retries with ten times the
    damping instead, for costs with kinks (a bounce's friction regimes), until the predicted gain
    falls below ``tol`` or the iterations run out.

    Returns:
        (theta, cost, J^T J, aux at theta, iterations taken).
    """

    def body(carry):
        k, theta, step, lam, cost, h, g, aux, _ = carry
        # The first pass has step = 0 and cost = inf: it evaluates the start and always keeps it,
        # so the Jacobian code is traced once.
        cand = theta + step
        c_new, h_new, g_new, a_new = normal(cand)
        ok = jnp.isfinite(c_new) & (c_new < cost) & jnp.all(jnp.isfinite(cand))
        stalled = (c_new >= cost * (1.0 - tol)) & (k > 0) & stop_on_failure
        pick = lambda a, b: jnp.where(ok, a, b)  # noqa: E731
        theta, lam, cost, h, g = pick(cand, theta), pick(lam / 3.0, lam * 10.0), pick(c_new, cost), pick(h_new, h), \
            pick(g_new, g)
        aux = jax.tree.map(pick, a_new, aux)
        nxt, predicted = _lm_step(h, g, lam)
        # Converged: the next step is predicted to gain less than tol of the cost (deciding on the
        # prediction, from normal equations already in hand, saves the integration that would
        # confirm it), or a step failed to gain that much (a problem that cannot be fitted stops
        # too: its cost tells).
        done = (predicted < tol * cost) | stalled
        return k + 1, theta, nxt, lam, cost, h, g, aux, done

    aux0 = jax.tree.map(jnp.zeros_like, jax.eval_shape(normal, theta0)[3])
    init = (jnp.asarray(0), theta0, jnp.zeros_like(theta0), jnp.asarray(1e-3, theta0.dtype),
            jnp.asarray(jnp.inf, theta0.dtype), jnp.eye(theta0.shape[0], dtype=theta0.dtype), jnp.zeros_like(theta0),
            aux0, jnp.asarray(False))
    k, theta, _, _, cost, h, _, aux, _ = jax.lax.while_loop(lambda c: (c[0] <= iterations) & ~c[-1], body, init)
    return theta, cost, h, aux, k - 1


def fit_one(tau, pos, mask, spin, n, air: Air, iterations: int = ITERATIONS, substeps: int = 1, tol: float = TOL):
    """Levenberg-Marquardt fit of one padded segment; see :func:`fit_batch`."""

    def normal(theta):
        return normal_equations(theta, tau, pos, mask, spin, n, air, substeps)

    theta, cost, h, vel, k = levenberg_marquardt(normal, initial_guess(tau, pos, mask), iterations, tol)
    return dict(theta=theta, cost=cost, jtj=h, velocity=vel, iterations=k)


def summarize(raw: dict, mask, spin) -> dict:
    """Per-segment statistics of a batch's fits, on the host (numpy; kept out of the compiled fit).

    Arguments:
        raw: what the compiled fit returned (``theta``, ``cost``, ``jtj``, ``velocity``, ``iterations``).
        mask: (S, T) sample mask; spin: (S, 3) spins.

    Returns:
        The dict described in :func:`fit_batch`.
    """
    theta, cost, h, vel = (np.asarray(raw[k], np.float64) for k in ("theta", "cost", "jtj", "velocity"))
    mask, spin = np.asarray(mask, np.float64), np.asarray(spin, np.float64)
    count = mask.sum(1)
    dof = np.maximum(3.0 * count - theta.shape[1], 1.0)
    d = np.sqrt(np.diagonal(h, axis1=1, axis2=2) + 1e-12)
    hs = h / (d[:, :, None] * d[:, None, :]) + 1e-6 * np.eye(theta.shape[1])
    cov = np.linalg.inv(hs) / (d[:, :, None] * d[:, None, :])
    stderr = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0) * (cost / dof)[:, None])
    speed = np.linalg.norm(vel, axis=-1)
    w = np.linalg.norm(spin, axis=-1)[:, None]
    sin = np.linalg.norm(np.cross(vel, spin[:, None, :]), axis=-1) / np.maximum(speed * w, 1e-9)

    def ratio(num, den):
        return (mask * num).sum(1) / np.maximum((mask * den).sum(1), 1e-12)

    rmse = np.sqrt(cost / np.maximum(count, 1.0))
    ok = np.all(np.isfinite(theta), axis=1) & np.isfinite(rmse) & (count >= 3)
    return dict(theta=np.where(ok[:, None], theta, np.nan), stderr=stderr, rmse=np.where(ok, rmse, np.nan),
                v_eff_drag=ratio(speed**3, speed**2), v_eff_magnus=ratio(speed**2 * sin, speed * sin),
                mean_sin=ratio(sin, np.ones_like(sin)), velocity=vel, iterations=np.asarray(raw["iterations"]), ok=ok)


def fit_batch(tau, pos, mask, spin, n_max, air: Air, iterations: int = ITERATIONS, substeps: int = 1):
    """Fits a padded batch of segments, group by group; compiled once per (rows, capacity,
    iterations, substeps).

    Arguments:
        tau: (G, R, T) times from each segment's first sample [s], G groups of R segments;
            padding repeats the last time.
        pos: (G, R, T, 3) observed positions [m]; mask: (G, R, T) 1 for samples, 0 for padding.
        spin: (G, R, 3) spins [rad/s] (zeros when unknown: C_M then stays at its start value and
            its standard error is huge).
        n_max: (G,) longest segment of each group (samples); a group's integration stops there.
        air: ball and air (:class:`Air`).
        iterations, substeps: Levenberg-Marquardt iterations, RK4 steps per interval (static).

    Returns:
        dict of arrays over the G * R rows (group by group): ``theta`` (G R, 8) ``[p0, v0, C_D,
        C_M]`` (NaN where the fit failed), ``stderr`` (G R, 8) standard errors, ``rmse`` (G R,)
        [m], ``v_eff_drag`` and ``v_eff_magnus`` (G R,) effective speeds [m/s], ``mean_sin``
        (G R,) mean sine between velocity and spin, ``velocity`` (G R, max(n_max), 3) fitted
        velocities at the sample times, ``iterations`` (G R,) taken (a group's loop runs until its slowest
        segment converges), ``ok``.
    """
    # One call per group, all dispatched before any result is awaited; one call over all groups
    # (lax.map) would cost more to compile than the calls cost to dispatch.
    pending = [_fit_batch_jit(tau[g], pos[g], mask[g], spin[g], jnp.asarray(n_max[g]), air, iterations, substeps)
               for g in range(len(n_max))]
    used = max(int(np.max(n_max)), 1)  # samples beyond every segment's end are padding
    raws = jax.device_get(pending)
    raw = {k: np.concatenate([r[k][:, :used] if k == "velocity" else r[k] for r in raws]) for k in raws[0]}
    flat = lambda a: np.reshape(a, (-1, *np.shape(a)[2:]))  # noqa: E731
    return summarize(raw, flat(np.asarray(mask)[:, :, :used]), flat(spin))


def _fit_batch_impl(tau, pos, mask, spin, n_max, air, iterations, substeps):
    return jax.vmap(lambda a, b, c, d: fit_one(a, b, c, d, n_max, air, iterations, substeps))(tau, pos, mask, spin)


#: XLA options of the fit's compilation: the legacy (elemental) CPU emitters compile this graph of
#: many small fusions in about half the time of the fusion emitters, and run it as fast.
COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

_fit_batch_jit = jax.jit(_fit_batch_impl, static_argnames=("iterations", "substeps"), compiler_options=COMPILER_OPTIONS)


# --------------------------------------------------------------------------- many segments
@dataclasses.dataclass
class SegmentFits:
    """Fits of many segments (numpy, in the order the segments were given).

    Attributes:
        theta: (S, 8) fitted ``[p0, v0, C_D, C_M]`` (NaN where a fit failed or was not run).
        stderr: (S, 8) standard errors of theta.
        rmse: (S,) 3-D position RMSE of the fit [m].
        v_eff_drag, v_eff_magnus: (S,) effective speeds [m/s].
        spin: (S, 3) the spins used [rad/s].
        n: (S,) samples per segment.
        mean_sin: (S,) mean sine of the angle between velocity and spin.
        velocities: per segment, (T_i, 3) fitted velocities at the sample times [m/s] (None if
            not fitted).
    """

    theta: np.ndarray
    stderr: np.ndarray
    rmse: np.ndarray
    v_eff_drag: np.ndarray
    v_eff_magnus: np.ndarray
    spin: np.ndarray
    n: np.ndarray
    mean_sin: np.ndarray
    velocities: list

    @property
    def cd(self) -> np.ndarray:
        return self.theta[:, 6]

    @property
    def cm(self) -> np.ndarray:
        return self.theta[:, 7]

    def __len__(self) -> int:
        return len(self.rmse)


def fit_segments(times: Sequence[np.ndarray], positions: Sequence[np.ndarray], spins=None, *, air: Air | None = None,
                 batch: int = BATCH, group: int = GROUP, iterations: int = ITERATIONS, substeps: int = 1,
                 dtype=np.float32, progress: Callable | None = None) -> SegmentFits:
    """Fits every segment: sorted by length, padded to its capacity, in groups of similar length
    (at most ``group``), one compiled call per group, ``batch // rows`` groups dispatched before
    their results are awaited (:func:`grouped_batches`, :func:`fit_batch`).

    Arguments:
        times: list of (T_i,) increasing sample times [s].
        positions: list of (T_i, 3) observed positions [m].
        spins: (S, 3) spins [rad/s] (default zeros).
        air: ball and air (default: those of the bundled conti2026 model).
        batch: segments dispatched together (and between ``progress`` calls); group: segments
            integrated side by side (see :func:`grouped_batches`); iterations, substeps: see
            :func:`fit_batch`.
        dtype: float type of the fit (float32 by default; float64 needs ``jax_enable_x64``).
        progress: optional callable ``progress(n_done)`` called after each batch.

    Returns:
        :class:`SegmentFits`; segments with fewer than 3 samples are left NaN.
    """
    n_seg = len(times)
    spins = np.zeros((n_seg, 3)) if spins is None else np.asarray(spins, np.float64).reshape(n_seg, 3)
    air = default_air(np.dtype(dtype).name) if air is None else jax.tree.map(lambda x: jnp.asarray(x, dtype), air)
    lengths = np.array([len(t) for t in times], int)
    out = SegmentFits(theta=np.full((n_seg, 8), np.nan), stderr=np.full((n_seg, 8), np.nan),
                      rmse=np.full(n_seg, np.nan), v_eff_drag=np.full(n_seg, np.nan),
                      v_eff_magnus=np.full(n_seg, np.nan), spin=spins, n=lengths, mean_sin=np.full(n_seg, np.nan),
                      velocities=[None] * n_seg)
    done = 0
    for idx, rows, arrays, n_max in grouped_batches(times, positions, spins, batch, group, dtype):
        res = fit_batch(*arrays, n_max, air, iterations, substeps)
        out.theta[idx] = res["theta"][rows]
        out.stderr[idx] = res["stderr"][rows]
        out.rmse[idx] = res["rmse"][rows]
        out.v_eff_drag[idx] = res["v_eff_drag"][rows]
        out.v_eff_magnus[idx] = res["v_eff_magnus"][rows]
        out.mean_sin[idx] = res["mean_sin"][rows]
        for row, i in zip(rows, idx):
            out.velocities[i] = res["velocity"][row, : lengths[i]]
        done += len(idx)
        if progress is not None:
            progress(done)
    return out


def ballistic_rmse_many(times: Sequence[np.ndarray], positions: Sequence[np.ndarray], spins=None) -> np.ndarray:
    """RMSE of the fitted flight model for many segments at once.

    Arguments:
        times: list of (T_i,) sample times [s] per segment (strictly increasing).
        positions: list of (T_i, 3) positions [m].
        spins: optional list/array of (3,) spins [rad/s] (default zeros).

    Returns:
        (S,) RMSE [m] per segment (NaN for segments with fewer than 3 samples).
    """
    return fit_segments(list(times), list(positions), spins).rmse


def ballistic_rmse(times, positions, spin=None) -> float:
    """RMSE [m] of the flight model fitted to one segment; the default ``rmse_fn``.

    Arguments:
        times: (T,) sample times [s].
        positions: (T, 3) positions [m].
        spin: optional (3,) spin [rad/s].

    Returns:
        sqrt(mean |p_fit - p|^2) over the samples [m].
    """
    spins = None if spin is None else np.asarray(spin, np.float64)[None]
    return float(ballistic_rmse_many([np.asarray(times)], [np.asarray(positions)], spins)[0])
