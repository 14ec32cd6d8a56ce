"""Flight-segment position error of a model, as the paper evaluates it.

:func:`segment_rmse` scores models on a dataset's flight segments (what ``ttsim evaluate``'s
flight stage and ``ttsim fit``'s comparison with the base model report); :func:`flight_rmse` on
given samples. Per segment: the initial position is the first observation (or, with
``fit_position``, fitted too), the spin the measured one, the initial velocity is fitted
(Gauss-Newton on the positions, through the model's own flight stage and coefficient models), and
the error is the 3-D position RMSE over the segment's samples, sqrt(mean_i |p_model(t_i) - p_i|^2).
Segments are batched like the identification's fits (:func:`ttsim_jax.fit.segment_batches.batches`);
one compilation per model family.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit.flightfit import Air, initial_guess, integrate
from ttsim_jax.fit.segment_batches import BATCH, batches, dataset_segments
from ttsim_jax.fit.choices import LATENT_MIN_SAMPLES, SPIN_SOURCES  # noqa: F401 (re-exported)
from ttsim_jax.fit.latent_spin import fit_latent_spin
from ttsim_jax.physics.linalg import spd_solve
from ttsim_jax.results import ItemArrays, Skipped

ITERATIONS = 6
#: Where a flown segment's spin came from (:func:`segment_rmse`'s ``spin_source``).
FLOWN = ("measured", "latent", "zero")


@dataclasses.dataclass(frozen=True)
class FlightStage(ItemArrays):
    """Models scored on flight segments (:func:`segment_rmse`; ``ttsim evaluate``'s flight stage).

    Attributes:
        segment_id: (S,) the segments scored.
        spin_measured: whether they have a measured spin.
        n_without_spin: segments left out for want of one.
        rmse: {model name: (S,) 3-D position RMSE [m]}, NaN where the model's flight gave no finite
            position.
        spin: (S, 3) the measured spins [rad/s] (zeros where none).
        spin_source: (S,) where each segment's spin came from (:data:`FLOWN`).
        latent_spin: {model name: (S, 3) the spins it flew [rad/s]} of the models that fitted a
            latent spin.
    """

    segment_id: np.ndarray
    spin_measured: bool
    n_without_spin: int
    rmse: dict
    spin: np.ndarray
    spin_source: np.ndarray
    latent_spin: dict


def spin_source_counts(source) -> dict:
    """{kind of :data:`FLOWN`: number of segments} of an array of spin sources."""
    source = np.asarray(source).astype(str)
    return {k: int(np.sum(source == k)) for k in FLOWN}



def _rmse_one(aero, air, tau, pos, mask, spin, n, iterations, fit_position):
    guess = initial_guess(tau, pos, mask)

    def res(x):
        p0 = x[:3] if fit_position else pos[0]
        ps, _ = integrate(aero, p0, x[-3:], tau, spin, n, air)
        return ((ps - pos) * mask[:, None]).ravel()

    def body(_, x):
        # One integration carries the residual and the tangents.
        eye = jnp.eye(x.shape[0], dtype=x.dtype)
        r, jac = jax.vmap(lambda t: jax.jvp(res, (x,), (t,)), out_axes=(None, 1))(eye)
        h = jac.T @ jac
        cand = x - spd_solve(h + 1e-9 * jnp.trace(h) * eye + 1e-30, jac.T @ r)
        return jnp.where(jnp.all(jnp.isfinite(cand)), cand, x)

    x = jax.lax.fori_loop(0, iterations, body, guess[:6] if fit_position else guess[3:6])
    r = res(x)
    return jnp.sqrt(jnp.sum(r**2) / jnp.maximum(jnp.sum(mask), 1.0)), x


_rmse_batch = jax.jit(jax.vmap(_rmse_one, in_axes=(None, None, 0, 0, 0, 0, None, None, None)),
                      static_argnames=("iterations", "fit_position"))


def flight_rmse(model, times: Sequence[np.ndarray], positions: Sequence[np.ndarray], spins, *,
                fit_position: bool = False, iterations: int = ITERATIONS, batch: int = BATCH) -> np.ndarray:
    """3-D position RMSE [m] of ``model``'s flight per segment (initial velocity fitted).

    Arguments:
        model: a loaded :class:`~ttsim_jax.params.Model` (its ball, air and coefficient models).
        times: list of (T_i,) sample times [s]; positions: list of (T_i, 3) positions [m].
        spins: (S, 3) measured spins [rad/s].
        fit_position: also fit the initial position (the identification's protocol) instead of
            taking the first observation (the paper's evaluation).
        iterations: Gauss-Newton iterations on the initial velocity.
        batch: segments per compiled call.

    Returns:
        (S,) RMSE [m] (NaN for segments with fewer than 3 samples).
    """
    dtype = np.float32
    air = Air.from_model(model, dtype)
    aero = jax.tree.map(lambda x: jnp.asarray(x, dtype), model.aero)
    spins = np.asarray(spins, np.float64).reshape(len(times), 3)
    out = np.full(len(times), np.nan)
    for idx, (tau, pos, mask, spin), n_max in batches(times, positions, spins, batch, dtype):
        rmse, _ = _rmse_batch(aero, air, tau, pos, mask, spin, jnp.asarray(n_max), iterations, fit_position)
        out[idx] = np.asarray(rmse)[: len(idx)]
    return out




def segment_rmse(ds, models: list, *, min_samples: int = 5, min_spin_conf: float = 0.5, sessions=None,
                 spin: str = "measured", tick: Callable = lambda: None) -> dict:
    """Flight-segment 3-D position RMSE per model on a dataset (:func:`flight_rmse` per segment).

    Arguments:
        ds: a :class:`~ttsim_jax.data.Dataset`.
        models: [(name, Model)].
        min_samples: segments with fewer observations are left out.
        min_spin_conf: least spin confidence of a measured spin.
        sessions: score only the segments of these session ids (None: all).
        spin: where a segment's spin comes from: ``"measured"`` (the segments with a measured spin
            when the data has any, the others left out; else every segment, with spin 0),
            ``"auto"`` (the measured spin where there is one, elsewhere the latent spin of
            :mod:`ttsim_jax.fit.latent_spin`, fitted under each model from the segment's own
            samples; spin 0 for a segment too short to fit one), ``"latent"`` (the latent spin for
            every segment) or ``"zero"``.
        tick: called once per model when it is scored.

    Returns:
        A :class:`FlightStage`, or :class:`~ttsim_jax.results.Skipped` without a segment of
        ``min_samples`` observations.
    """
    if spin not in SPIN_SOURCES:
        raise ValueError(f"spin = {spin!r}: must be one of {SPIN_SOURCES}")
    ids, times, positions, spins, conf = dataset_segments(ds, min_samples)
    session_of = dict(zip(np.asarray(ds.segments["segment_id"]).tolist(), np.asarray(ds.segments["session_id"]).tolist()))
    segment_sessions = np.asarray([session_of[i] for i in ids.tolist()], np.int64)
    keep = np.ones(len(ids), bool) if sessions is None else np.isin(segment_sessions, np.asarray(sessions))
    n_keep = int(keep.sum())
    if not n_keep:
        for _ in models:
            tick()
        return Skipped(f"no flight segment with at least {min_samples} observations")
    spin_known = conf >= min_spin_conf
    with_spin = bool((keep & spin_known).any())
    if spin == "measured" and with_spin:  # a flight flown with spin 0 for want of a measurement says little
        keep &= spin_known
    times = [t for t, k in zip(times, keep) if k]
    positions = [p for p, k in zip(positions, keep) if k]
    measured = np.where(spin_known[keep, None], spins[keep], 0.0)
    fittable = np.array([len(t) >= LATENT_MIN_SAMPLES for t in times], bool)
    if spin in ("measured", "zero"):
        latent_rows = np.zeros(len(times), bool)
    else:
        latent_rows = fittable & (~spin_known[keep] if spin == "auto" else True)
    source = np.where(latent_rows, "latent", np.where(spin_known[keep] & (spin in ("auto", "measured")), "measured",
                                                       "zero")).astype("U8")
    flown = measured if spin in ("auto", "measured") else np.zeros_like(measured)
    rmse, latent = {}, {}
    for name, model in models:
        spins_m = flown.copy()
        if latent_rows.any():
            rows = np.flatnonzero(latent_rows)
            ls = fit_latent_spin([times[i] for i in rows], [positions[i] for i in rows], model,
                                 min_samples=LATENT_MIN_SAMPLES)
            spins_m[rows] = np.where(ls.ok[:, None], ls.spin, 0.0)
            source[rows[~ls.ok]] = "zero"
            latent[name] = spins_m
        rmse[name] = flight_rmse(model, times, positions, spins_m)
        tick()
    return FlightStage(segment_id=ids[keep], spin_measured=with_spin, n_without_spin=int(n_keep - keep.sum()), rmse=rmse,
                       spin=measured, spin_source=source, latent_spin=latent)
