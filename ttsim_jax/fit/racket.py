"""Racket contact identification: the updated base model's five parameters by least squares.

On the racket-frame arrays of :func:`ttsim_jax.fit.racket_arrays.contact_arrays` (pre-contact
x = (v~, w~, d), observed post-contact y_obs = (v~+, w~+)), the parameters theta = (e0, e1, et0,
et1, e_s) of :func:`ttsim_jax.physics.racket.base_response` ("updated" kind: e_n = e0 + e1 |v_n|,
e_t = et0 + et1 |u_T|, normal spin factor e_s) minimise

    sum over contacts of |v+(theta) - v+_obs|^2 + (spin_scale |w+(theta) - w+_obs|)^2

(spin errors in surface-speed units, spin_scale = the ball radius by default), solved by one jitted
``jaxopt.LevenbergMarquardt``. Standard errors from the Gauss-Newton covariance
s^2 (J^T J)^-1 at the solution. What the fitted base model leaves unexplained is the racket
residual network's to learn (``ttsim train residual``; ``ttsim fit --stages ...,residual``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.physics import racket as racket_stage

PARAMETERS = ("e0", "e1", "et0", "et1", "e_s")
# Contacts are padded (with weight 0) to a multiple of this many rows.
PAD = 4096
UNITS = {"e0": "1", "e1": "s/m", "et0": "1", "et1": "s/m", "e_s": "1"}


def updated_params(base: racket_stage.RacketParams, theta) -> racket_stage.RacketParams:
    """The "updated" racket parameters theta = (e0, e1, et0, et1, e_s) over ``base`` (its kappa,
    e_max, k_p)."""
    theta = jnp.asarray(theta)
    dt = base.kappa.dtype
    return racket_stage.RacketParams(e0=theta[0].astype(dt), e1=theta[1].astype(dt), et0=theta[2].astype(dt),
                                     et1=theta[3].astype(dt), e_s=theta[4].astype(dt), k_p=base.k_p,
                                     kappa=base.kappa, e_max=base.e_max, kind="updated")


@jax.jit
def predict(params: racket_stage.RacketParams, x, radius, mass):
    """Base-model post-contact (v+ (N, 3), w+ (N, 3)) for racket-frame inputs x (N, 8)."""
    return jax.vmap(lambda xi: racket_stage.base_response(params, xi[:3], xi[3:6], xi[6:8], radius, mass))(x)


def _predict(theta, base, x, radius, mass):
    params = updated_params(base, theta)
    return jax.vmap(lambda xi: racket_stage.base_response(params, xi[:3], xi[3:6], xi[6:8], radius, mass))(x)


def _residuals(theta, fixed, held, base, x, y, real, radius, mass, spin_scale):
    v, w = _predict(jnp.where(fixed, held, theta), base, x, radius, mass)
    keep = real[:, None]
    return jnp.concatenate([(keep * (v - y[:, :3])).ravel(), (keep * spin_scale * (w - y[:, 3:])).ravel()])


@jax.jit
def _solve(theta0, fixed, held, base, x, y, real, radius, mass, spin_scale):
    """Least squares over theta with the ``fixed`` entries held at ``held`` (their Jacobian columns
    are zero, so they keep their start value and get no standard error)."""
    from jaxopt import LevenbergMarquardt

    solver = LevenbergMarquardt(residual_fun=_residuals, maxiter=100, tol=1e-10, xtol=1e-10, gtol=1e-10,
                                solver="cholesky", materialize_jac=True, implicit_diff=False)
    theta, state = solver.run(jnp.where(fixed, held, theta0), fixed, held, base, x, y, real, radius, mass, spin_scale)
    return jnp.where(fixed, held, theta), state.residual, state.jac  # of the last accepted step: the solution


def bounds() -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of :data:`PARAMETERS`: the physical ranges a model file allows
    (:data:`ttsim_jax.params.SCHEMA`; a restitution above 1 would create energy)."""
    from ttsim_jax.params import SCHEMA

    entries = [SCHEMA["racket"][k] for k in PARAMETERS]
    return np.array([e.lo for e in entries], np.float64), np.array([e.hi for e in entries], np.float64)


@dataclasses.dataclass
class RacketFit:
    """What :func:`fit_racket` found.

    Attributes:
        values, stderr: parameter name -> fitted value / standard error.
        n_used: contacts in the fit.
        errors: 'base' / 'fitted' -> {'velocity' [m/s], 'spin' [rad/s]}: median norm of the error of
            the model given to :func:`fit_racket` and of the fitted base model.
        bounds: the parameters held at a bound of their physical range (:func:`bounds`), one
            description each (with the free fit's value); empty when the free fit is within them.
    """

    values: dict
    stderr: dict
    n_used: int
    errors: dict
    bounds: list = dataclasses.field(default_factory=list)

    def params(self, base: racket_stage.RacketParams) -> racket_stage.RacketParams:
        return updated_params(base, [self.values[k] for k in PARAMETERS])

    def summary(self) -> str:
        vals = ", ".join(f"{k} = {self.values[k]:.4f} +- {self.stderr[k]:.4f}" for k in PARAMETERS)
        b, f = self.errors["base"], self.errors["fitted"]
        held = f"\nheld at a physical bound: {'; '.join(self.bounds)}" if self.bounds else ""
        return (f"{vals} ({self.n_used} contacts){held}\nmedian |error| base -> fitted: velocity {b['velocity']:.3f} "
                f"-> {f['velocity']:.3f} m/s, spin {b['spin']:.1f} -> {f['spin']:.1f} rad/s")

    def to_dict(self) -> dict:
        return dict(values=self.values, stderr=self.stderr, n_used=self.n_used, errors=self.errors, bounds=self.bounds)


def _median_errors(v, w, y) -> dict:
    return dict(velocity=float(np.median(np.linalg.norm(np.asarray(v) - y[:, :3], axis=1))),
                spin=float(np.median(np.linalg.norm(np.asarray(w) - y[:, 3:], axis=1))))


def racket_errors(params: racket_stage.RacketParams, x, y_obs, radius, mass) -> dict:
    """Median norm of the velocity [m/s] and spin [rad/s] error of the racket base model ``params``
    over racket-frame contacts ``x`` (N, 8) against ``y_obs`` (N, 6) (NaN with no contact)."""
    x, y = np.asarray(x, np.float64).reshape(-1, 8), np.asarray(y_obs, np.float64).reshape(-1, 6)
    n = len(x)
    if n == 0:
        return dict(velocity=float("nan"), spin=float("nan"))
    jx = jnp.asarray(np.concatenate([x, np.repeat(x[:1], -(-n // PAD) * PAD - n, 0)]), jnp.float32)
    return _median_errors(*(np.asarray(a)[:n] for a in predict(params, jx, radius, mass)), y)


def fit_racket(x, y_obs, model="conti2026", spin_scale: float | None = None) -> RacketFit:
    """Fits (e0, e1, et0, et1, e_s) of the updated racket base model.

    Arguments:
        x: (N, 8) racket-frame inputs (v~, w~, d) (:func:`ttsim_jax.fit.racket_arrays.contact_arrays`
            with ``n_inputs=8``).
        y_obs: (N, 6) observed post-contact (v~+, w~+).
        model: bundled name, TOML path or Model: the ball (radius, mass), the racket's kappa and
            e_max, and the starting point (its racket parameters if "updated", else a neutral one).
        spin_scale: weight of spin errors [m/rad] (default: the ball radius).

    Returns:
        :class:`RacketFit`.
    """
    from ttsim_jax.fit.racket_arrays import model_and_name
    from ttsim_jax.kernel.ball_step import ball_properties

    m, _ = model_and_name(model)
    radius, mass = ball_properties(m)
    x = np.asarray(x, np.float64)
    y = np.asarray(y_obs, np.float64)
    if x.ndim != 2 or x.shape[1] != 8 or y.shape != (len(x), 6):
        raise ValueError(f"fit_racket: x must be (N, 8) and y_obs (N, 6); got {x.shape} and {y.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        bad = np.flatnonzero(~(np.isfinite(x).all(1) & np.isfinite(y).all(1)))
        raise ValueError(f"fit_racket: non-finite values in rows {bad[:5].tolist()} of x / y_obs")
    if len(x) < 2 * len(PARAMETERS):
        raise ValueError(f"fit_racket: {len(x)} contacts; at least {2 * len(PARAMETERS)} are needed")
    base = m.racket
    if base.kind == "updated":
        theta0 = [float(getattr(base, k)) for k in PARAMETERS]
    else:
        theta0 = [0.85, 0.0, 0.8, 0.0, 1.0]
    start = updated_params(base, theta0)  # one static kind: one compiled solver for every base model
    scale = float(radius) if spin_scale is None else float(spin_scale)
    n = len(x)
    real = np.arange(-(-n // PAD) * PAD) < n  # padded rows (weight 0): one compiled solver for most datasets
    jx, jy = (jnp.asarray(np.concatenate([a, np.repeat(a[:1], len(real) - n, 0)]), jnp.float32) for a in (x, y))
    lo, hi = bounds()
    fixed, held, notes = np.zeros(len(PARAMETERS), bool), np.clip(theta0, lo, hi), []
    for _ in PARAMETERS:  # a parameter the fit puts outside its range is held at the bound, the others refitted
        theta, r, jac = (np.asarray(a, np.float64) for a in _solve(
            jnp.asarray(held, jnp.float32), jnp.asarray(fixed), jnp.asarray(held, jnp.float32), start, jx, jy,
            jnp.asarray(real, jnp.float32), radius, mass, jnp.asarray(scale, jnp.float32)))
        beyond = np.where(fixed, 0.0, np.maximum(lo - theta, theta - hi))
        if not np.any(beyond > 0):
            break
        k = int(np.argmax(beyond))
        fixed[k], held = True, np.where(fixed, held, theta)
        held[k] = np.clip(theta[k], lo[k], hi[k])
        notes.append(f"{PARAMETERS[k]} = {held[k]:g} (the free fit: {theta[k]:.4g})")
    s2 = float(np.sum(r**2)) / max(6 * n - int((~fixed).sum()), 1)
    cov = s2 * np.linalg.pinv(jac.T @ jac)  # the held parameters' columns are zero: no error
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    result = RacketFit(values={k: float(v) for k, v in zip(PARAMETERS, theta)},
                       stderr={k: float(v) for k, v in zip(PARAMETERS, se)}, n_used=len(x), errors={}, bounds=notes)
    fitted = (np.asarray(a)[:n] for a in predict(updated_params(base, theta), jx, radius, mass))
    base_pred = (np.asarray(a)[:n] for a in predict(base, jx, radius, mass))
    result.errors = dict(base=_median_errors(*base_pred, y), fitted=_median_errors(*fitted, y))
    return result


def racket_section(base: racket_stage.RacketParams, result: RacketFit) -> dict:
    """{"racket": TOML text} of the fitted updated base model (kappa, e_max from ``base``)."""
    f = lambda v: f"{float(v):.6g}"  # noqa: E731
    lines = ["[racket]                                        # fitted: updated base model (ttsim fit)",
             'kind = "updated"']
    lines += [f'{k} = {{ value = {f(result.values[k])}, unit = "{UNITS[k]}" }}' for k in PARAMETERS]
    lines += [f'kappa = {{ value = {f(base.kappa)}, unit = "1" }}',
              f'e_max = {{ value = {f(base.e_max)}, unit = "1" }}']
    return {"racket": "\n".join(lines) + "\n"}
