"""The flight fit that filters segments: the simulator's flight stage with constant aerodynamic
coefficients, fitted per segment.

As in the paper's data filtering (and the authors' code), a segment is kept when a
constant-coefficient aerodynamic model fits it within 20 mm RMSE: the free parameters are the
initial position, the initial velocity, C_D and C_M, and the model is exactly
:func:`ttsim_jax.physics.aero.flight_step` (RK4) with constant coefficients and the spin given
(C_M has no effect when the spin is zero). The RMSE is that of the 3-D position error,
sqrt(mean_i |p_fit(t_i) - p_i|^2). The fit is the batched one of the aerodynamic identification
(:func:`ttsim_jax.fit.aero.fit_segments`). Any other ``rmse_fn(times, positions, spin) -> rmse_m``
can be given to :func:`ttsim_jax.data.segment.filter_segments`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


def ballistic_rmse_many(times: Sequence[np.ndarray], positions: Sequence[np.ndarray], spins=None) -> np.ndarray:
    """RMSE of the fitted flight model for many segments at once.

    Arguments:
        times: list of (T_i,) sample times [s] per segment (strictly increasing).
        positions: list of (T_i, 3) positions [m].
        spins: optional list/array of (3,) spins [rad/s] (default zeros).

    Returns:
        (S,) RMSE [m] per segment (NaN for segments with fewer than 3 samples).
    """
    from ttsim_jax.fit.aero import fit_segments

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
