"""Model-free residual analysis and the size of effects on the record.

:func:`dependence`: which measured quantities a phase's errors depend on, whatever the cause: the
Spearman rank correlation, over groups (segment or contact means, so that a segment's many
observations count once), of the error magnitude and of each signed error component with every
numeric regime quantity. A flight error's magnitude is divided by what a perfect model leaves of
the noise in its segment (:func:`ttsim_jax.diagnose.where.null_scale`): without it, a record
without spin, whose flights are fitted with three more parameters each, read "|error| depends on
since_contact (rho +0.32)" with no effect at all, the short segments' residuals being smaller. A
dependence is *significant* when |rho| >= :data:`MIN_RHO` and its two-sided p-value (t
approximation) is below :data:`MAX_P`.

Effects on the record are sized, not fitted as physics (:func:`record_sizes`):

* ``position_noise``: per axis, from second differences of equally spaced observations of one
  segment, sigma = 1.4826 MAD(p[i+1] - 2 p[i] + p[i-1]) / sqrt(6) (the flight's own curvature,
  g dt^2 = 0.25 mm at 200 Hz, is removed with the median);
* ``missing_frames``: the fraction of expected frames (at the median interval) missing inside
  segments;
* ``spin_noise``: what the data says of its spin estimates (share with confidence below 0.5);
  one estimate per segment carries no spread of its own;
* ``spin_check``: the measured spins against the spins the flights show
  (:func:`ttsim_jax.fit.spin_check.check_record_spin`: a sign flipped on some or all segments, an
  axis turned, a scale), over the flight segments flown with a measured spin, at least
  :data:`SPIN_CHECK_MIN` of them;
* ``racket_state_error``: the world-frame racket velocity bias b that best explains the
  racket-contact velocity residuals, r_i = (I - J_i) R_i^T b (J_i = d v+ / d v~ of the model's
  racket contact: an error b of the recorded racket velocity shifts both v~ and the observation),
  by least squares, with the spread of the per-contact solutions (an upper bound: the ball-state
  estimates' noise is in it) and the RMS velocity residual before and after removing the bias.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

#: Least |rho| of a significant dependence.
MIN_RHO = 0.3
#: Largest p-value of a significant dependence.
MAX_P = 1e-3
#: Least flight segments with a measured spin for the spin check.
SPIN_CHECK_MIN = 20


def _ranks(x):
    """Ranks with ties given their mean rank: ordinal ranks of tied values would follow the rows'
    order and correlate with anything stored in that order."""
    values, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    start = np.cumsum(counts) - counts
    return (start + (counts - 1) / 2.0)[inverse]


def spearman(x, y) -> tuple[float, float]:
    """(rho, two-sided p-value by the t approximation) of finite pairs."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    n = int(ok.sum())
    if n < 8:
        return math.nan, math.nan
    rx, ry = _ranks(x[ok]), _ranks(y[ok])
    if rx.std() == 0 or ry.std() == 0:
        return math.nan, math.nan
    rho = float(np.corrcoef(rx, ry)[0, 1])
    t = rho * math.sqrt((n - 2) / max(1e-12, 1.0 - rho * rho))
    return rho, float(math.erfc(abs(t) / math.sqrt(2.0)))


def dependence(item: dict, components=None, names=("x", "y", "z")) -> list:
    """Significant dependences of one phase's errors on its regime quantities, strongest first.

    Arguments:
        item: from :mod:`ttsim_jax.diagnose.where` (``error``, ``group``, ``regimes``).
        components: optional (M, k) signed error components, named by ``names``.

    Returns:
        [{"error", "quantity", "rho", "p"}] (only significant ones).
    """
    grp = np.asarray(item["group"])
    g = int(grp.max()) + 1 if len(grp) else 0
    cnt = np.maximum(np.bincount(grp, minlength=g), 1)
    mean = lambda v: np.bincount(grp, np.asarray(v, np.float64), minlength=g) / cnt  # noqa: E731
    # a flight residual's size under a perfect model depends on its segment's length (where.null_scale)
    targets = {"|error|": mean(np.asarray(item["error"]) / item.get("null_scale", 1.0))}
    if components is not None:
        comp = np.asarray(components, np.float64)
        for k in range(comp.shape[1]):
            targets[f"error {names[k]}"] = mean(comp[:, k])
    out = []
    for qname, values in item["regimes"].items():
        if qname == "spin_axis":
            continue
        q = mean(values)
        for tname, t in targets.items():
            rho, p = spearman(q, t)
            if math.isfinite(rho) and abs(rho) >= MIN_RHO and p < MAX_P:
                out.append(dict(error=tname, quantity=qname, rho=rho, p=p))
    return sorted(out, key=lambda d: -abs(d["rho"]))


# ---------------------------------------------------------------------------------------------- record effects
def position_noise(fl) -> dict:
    """Per-axis position noise [m] and the number of second differences used (see module docstring)."""
    d2 = []
    for row in range(fl.n):
        m = fl.mask[row] > 0
        t, p = fl.tau[row][m], fl.pos[row][m]
        if len(t) < 3:
            continue
        dt = np.diff(t)
        same = np.abs(dt[1:] - dt[:-1]) <= 1e-3 * np.maximum(dt[1:], 1e-9)
        d = p[2:] - 2.0 * p[1:-1] + p[:-2]
        d2.append(d[same])
    if not d2:
        return dict(sigma=[math.nan] * 3, n=0)
    d = np.concatenate(d2)
    mad = np.median(np.abs(d - np.median(d, 0)), 0)
    return dict(sigma=(1.4826 * mad / math.sqrt(6.0)).tolist(), n=int(len(d)))


def missing_frames(fl) -> dict:
    """Fraction of frames missing inside segments (at the median sampling interval)."""
    gaps = [np.diff(fl.tau[r][fl.mask[r] > 0]) for r in range(fl.n)]
    gaps = np.concatenate([g for g in gaps if len(g)]) if gaps else np.zeros(0)
    gaps = gaps[gaps > 0]
    if not len(gaps):
        return dict(fraction=math.nan, interval=math.nan)
    dt = float(np.median(gaps))
    missing = np.maximum(np.round(gaps / dt) - 1.0, 0.0).sum()
    return dict(fraction=float(missing / (missing + len(gaps))), interval=dt)


def racket_state_error(model, c) -> dict:
    """Racket velocity bias and spread that would explain the racket-contact residuals (module
    docstring); ``c``: the racket :class:`~ttsim_jax.diagnose.phases.ContactItems`."""
    from ttsim_jax.kernel.ball_step import ball_properties
    from ttsim_jax.physics.racket import base_response

    if c is None or len(c) < 3:
        return dict(n=0)
    radius, mass = ball_properties(model)
    x = jnp.asarray(c.x, jnp.float32)

    def out_v(v, w, d):
        return base_response(model.racket, v, w, d, radius, mass, model.effects)[0]

    jac = np.asarray(jax.jit(jax.vmap(jax.jacfwd(out_v)))(x[:, :3], x[:, 3:6], x[:, 6:8]), np.float64)
    pred = np.asarray(jax.jit(jax.vmap(out_v))(x[:, :3], x[:, 3:6], x[:, 6:8]), np.float64) + c.correction[:, :3]
    r = pred - c.y_obs[:, :3]  # (N, 3) racket frame
    a = (np.eye(3)[None] - jac) @ np.transpose(c.rot, (0, 2, 1))  # (N, 3, 3): world bias -> residual
    bias, *_ = np.linalg.lstsq(a.reshape(-1, 3), r.reshape(-1), rcond=None)
    each = np.stack([np.linalg.lstsq(ai, ri, rcond=None)[0] for ai, ri in zip(a, r)])
    after = r - a @ bias
    rms = lambda v: float(np.sqrt(np.mean(np.sum(v**2, axis=1))))  # noqa: E731
    return dict(n=int(len(r)), vel_bias=bias.tolist(), vel_bias_norm=float(np.linalg.norm(bias)),
                vel_spread=np.std(each - bias, axis=0).tolist(), rms_before=rms(r), rms_after=rms(after))


def spin_check(flights, model, seed: int = 0) -> dict:
    """The spin check (module docstring) of the flight segments flown with their measured spin, or
    ``{"skipped": why}``."""
    from ttsim_jax.fit.spin_check import check_record_spin

    rows = np.flatnonzero(flights.spin_source[: flights.n] == "measured") if flights.spin_source is not None else []
    if len(rows) < SPIN_CHECK_MIN:
        return dict(skipped=f"{len(rows)} flight segments with a measured spin (the check needs {SPIN_CHECK_MIN})")
    n = flights.mask[rows].sum(1).astype(int)
    times = [flights.tau[r, :k] for r, k in zip(rows, n)]
    positions = [flights.pos[r, :k] for r, k in zip(rows, n)]
    return check_record_spin(model, times, positions, flights.spin[rows], seed=seed)


def record_sizes(ds, phases, model, seed: int = 0, check_spin: bool = True, checked: dict | None = None) -> dict:
    """{effect name: size estimate} of the record effects of the catalogue, and the spin check
    (``check_spin``; module docstring; ``checked``: its result, run before)."""
    out = {}
    fl = phases.flights
    if fl is not None:
        out["position_noise"] = position_noise(fl)
        out["missing_frames"] = missing_frames(fl)
        if check_spin:
            out["spin_check"] = checked if checked is not None else spin_check(fl, model, seed)
    conf = np.asarray(ds.segments["spin_conf"], np.float64)
    if len(conf):  # a rig's contact states have no segments: nothing to size (and no NaN in the report)
        out["spin_noise"] = dict(segments=int(len(conf)), low_confidence_fraction=float(np.mean(conf < 0.5)),
                                 median_confidence=float(np.median(conf)))
    out["racket_state_error"] = racket_state_error(model, phases.racket)
    return out
