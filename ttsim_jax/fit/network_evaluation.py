"""How well a residual network corrects its base model on held-out contacts, and its sigma calibration.

:func:`predict` gives base + attenuated residual and the predicted sigmas; :func:`evaluate_residual`
compares base and corrected errors and the fraction of errors inside one sigma;
:func:`evaluate_by_band` does so per contact-distance band, as the paper's racket figure;
:func:`calibrate_sigma` fits the network's ``sigma_scale`` on the validation split.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit.network_stats import CALIBRATION_MODES, ONE_SIGMA_COVERAGE, calibration_scale
from ttsim_jax.physics.network import ResidualModel, residual_outputs

COMPONENTS = ("v_x", "v_y", "v_z", "w_x", "w_y", "w_z")


def predict(model: ResidualModel, x, y_base):
    """(prediction (M, 6), sigma (M, 6)) in float64: base + attenuated residual, predicted sigmas."""
    out = jax.jit(residual_outputs)(model, jnp.asarray(x, jnp.float32))
    corr = np.concatenate([np.asarray(out["dv"]), np.asarray(out["dw"])], 1).astype(np.float64)
    sigma = np.concatenate([np.asarray(out["sigma_v"]), np.asarray(out["sigma_w"])], 1).astype(np.float64)
    return np.asarray(y_base, np.float64) + corr, sigma, np.asarray(out["beta"])


def calibrate_sigma(model: ResidualModel, x, y_base, y_obs, mode: str = "component",
                    target: float = ONE_SIGMA_COVERAGE) -> tuple[ResidualModel, dict]:
    """Fits ``model.sigma_scale`` on held-out (validation) contacts.

    The error is that of the corrected prediction (base + attenuated residual) against the
    observation, the quantity :func:`evaluate_residual` checks against sigma. For each group of
    components (``mode``: "component" = six factors, "group" = velocity and spin, "none" = keep
    1) the factor is the ``target`` quantile of |error| / sigma, so that fraction of validation
    errors lies inside one calibrated sigma.

    Arguments:
        model: the trained model (its current ``sigma_scale`` is replaced, not compounded).
        x, y_base, y_obs: validation contacts, (M, n_inputs), (M, 6), (M, 6).
        mode: "component", "group" or "none".
        target: wanted one-sigma coverage.

    Returns:
        (calibrated model, info dict: mode, factors, validation coverage before and after per
        component and overall).
    """
    if mode not in CALIBRATION_MODES:
        raise ValueError(f"calibrate_sigma: mode = {mode!r}, must be one of {list(CALIBRATION_MODES)}")
    model = model.replace(sigma_scale=jnp.ones((6,), jnp.float32))
    pred, sigma, _ = predict(model, x, y_base)
    err = np.abs(pred - np.asarray(y_obs, np.float64))
    groups = CALIBRATION_MODES[mode]
    factors = np.ones(6) if groups is None else calibration_scale(err, sigma, groups, target)
    inside_before = err <= sigma
    inside_after = err <= sigma * factors
    info = dict(mode=mode, target=float(target), n=int(len(err)),
                factors=dict(zip(COMPONENTS, factors.tolist())),
                val_within_one_sigma_before=dict(zip(COMPONENTS, inside_before.mean(0).tolist())),
                val_within_one_sigma_after=dict(zip(COMPONENTS, inside_after.mean(0).tolist())),
                val_within_one_sigma_overall_before=float(inside_before.mean()),
                val_within_one_sigma_overall_after=float(inside_after.mean()))
    return model.replace(sigma_scale=jnp.asarray(factors, jnp.float32)), info


def evaluate_residual(model: ResidualModel, x, y_base, y_obs) -> dict:
    """Held-out errors of the base model against base + attenuated residual.

    Arguments:
        model: the residual model.
        x: (M, n_inputs) inputs; y_base, y_obs: (M, 6).

    Returns:
        dict (JSON-friendly): per-component median absolute and RMS errors (base, corrected);
        median |error vector| of velocity and spin (base, corrected, % drop); median errors of
        the speed and spin magnitudes, as the paper plots them; the fraction of errors within
        one predicted sigma per component and overall (0.683 if calibrated Gaussian), also
        with the uncalibrated sigmas (``sigma_scale`` removed); beta statistics.
    """
    y_base, y_obs = np.asarray(y_base, np.float64), np.asarray(y_obs, np.float64)
    pred, sigma, beta = predict(model, x, y_base)
    err_b, err_c = y_base - y_obs, pred - y_obs
    names = list(COMPONENTS)
    med = lambda a: float(np.median(a))  # noqa: E731
    rep = dict(n=len(x))
    rep["median_abs_error_base"] = dict(zip(names, np.median(np.abs(err_b), 0).tolist()))
    rep["median_abs_error_residual"] = dict(zip(names, np.median(np.abs(err_c), 0).tolist()))
    rep["rmse_base"] = dict(zip(names, np.sqrt(np.mean(err_b**2, 0)).tolist()))
    rep["rmse_residual"] = dict(zip(names, np.sqrt(np.mean(err_c**2, 0)).tolist()))
    for part, sl in (("vel", slice(0, 3)), ("spin", slice(3, 6))):
        b = med(np.linalg.norm(err_b[:, sl], axis=1))
        c = med(np.linalg.norm(err_c[:, sl], axis=1))
        rep[f"median_{part}_error_base"], rep[f"median_{part}_error_residual"] = b, c
        rep[f"median_{part}_error_drop_pct"] = 100.0 * (1.0 - c / b) if b > 0 else 0.0
        mag_b = med(np.abs(np.linalg.norm(y_base[:, sl], axis=1) - np.linalg.norm(y_obs[:, sl], axis=1)))
        mag_c = med(np.abs(np.linalg.norm(pred[:, sl], axis=1) - np.linalg.norm(y_obs[:, sl], axis=1)))
        rep[f"median_{part}_magnitude_error_base"], rep[f"median_{part}_magnitude_error_residual"] = mag_b, mag_c
    inside = np.abs(err_c) <= sigma
    rep["within_one_sigma"] = dict(zip(names, inside.mean(0).tolist()))
    rep["within_one_sigma_overall"] = float(inside.mean())
    raw = np.abs(err_c) <= sigma / np.maximum(np.asarray(model.sigma_scale, np.float64), 1e-30)
    rep["within_one_sigma_uncalibrated"] = dict(zip(names, raw.mean(0).tolist()))
    rep["within_one_sigma_uncalibrated_overall"] = float(raw.mean())
    rep["beta_mean"], rep["beta_fraction_one"] = float(beta.mean()), float((beta >= 1.0).mean())
    return rep


DISTANCE_BANDS = (0.05, 0.08)  # the paper's contact-distance bands: 0-5, 5-8 and > 8 cm


def band_label(lo: float, hi: float) -> str:
    """'0-5 cm', '5-8 cm', '> 8 cm' style label of a distance band [m]."""
    cm = lambda v: f"{100 * v:g}"  # noqa: E731
    return f"> {cm(lo)} cm" if math.isinf(hi) else f"{cm(lo)}-{cm(hi)} cm"


def evaluate_by_band(model: ResidualModel, x, y_base, y_obs, distance, edges=DISTANCE_BANDS) -> list[dict]:
    """Errors of the base model and of base + residual, grouped by contact distance |d|.

    As in the paper's racket figure: bands 0-5, 5-8 and > 8 cm from the face centre by default.

    Arguments:
        model: the residual model.
        x, y_base, y_obs: contacts, (M, n_inputs), (M, 6), (M, 6), racket frame.
        distance: (M,) contact distance from the face centre [m].
        edges: inner band edges [m].

    Returns:
        One dict per band (also for empty ones, with ``n`` = 0): ``band`` (label), ``lo``,
        ``hi`` [m], ``n``, and for the base model (``base``) and the corrected one
        (``residual``) the median absolute error of each component (v_x .. w_z) and of the
        speed and spin magnitudes (``|v|``, ``|w|``, as the paper plots them), plus the
        fraction inside one sigma (``within_one_sigma``).
    """
    y_base, y_obs = np.asarray(y_base, np.float64), np.asarray(y_obs, np.float64)
    distance = np.asarray(distance, np.float64)
    if distance.shape != (len(y_obs),):
        raise ValueError(f"evaluate_by_band: distance has shape {distance.shape}, expected ({len(y_obs)},)")
    pred, sigma, _ = predict(model, x, y_base) if len(y_obs) else (y_base, y_base, None)
    e_base, e_res = np.abs(contact_errors(y_base, y_obs)), np.abs(contact_errors(pred, y_obs))
    out = []
    for label, lo, hi, sel in distance_bands(distance, edges):
        row = dict(band=label, lo=lo, hi=hi, n=int(sel.sum()))
        for key, e in (("base", e_base), ("residual", e_res)):
            med = np.median(e[sel], 0) if sel.any() else np.full(len(ERROR_NAMES), math.nan)
            row[key] = dict(zip(ERROR_NAMES, med.tolist()))
        inside = np.abs(pred[sel] - y_obs[sel]) <= sigma[sel]
        row["within_one_sigma"] = float(np.mean(inside)) if sel.any() else math.nan
        out.append(row)
    return out


#: Columns of :func:`contact_errors`: the six components and the speed and spin magnitudes.
ERROR_NAMES = COMPONENTS + ("|v|", "|w|")


def contact_errors(y, y_obs) -> np.ndarray:
    """Signed errors of predicted post-contact states, as the paper plots them.

    Arguments:
        y, y_obs: (M, 6) predicted and observed (v, w).

    Returns:
        (M, 8) float64: y - y_obs per component, then |v| - |v_obs| and |w| - |w_obs|
        (:data:`ERROR_NAMES`).
    """
    y, y_obs = np.asarray(y, np.float64), np.asarray(y_obs, np.float64)
    mags = [np.linalg.norm(y[:, sl], axis=1) - np.linalg.norm(y_obs[:, sl], axis=1)
            for sl in (slice(0, 3), slice(3, 6))]
    return np.concatenate([y - y_obs, np.stack(mags, 1)], 1)


def distance_bands(distance, edges=DISTANCE_BANDS):
    """The contact-distance bands: a list of (label, lo, hi, mask (M,)) from 0 to infinity.

    Arguments:
        distance: (M,) contact distances from the face centre [m].
        edges: inner band edges [m] (the paper's 5 and 8 cm by default).
    """
    distance = np.asarray(distance, np.float64)
    bounds = [0.0, *edges, math.inf]
    return [(band_label(lo, hi), lo, hi, (distance >= lo) & (distance < hi)) for lo, hi in zip(bounds[:-1], bounds[1:])]
