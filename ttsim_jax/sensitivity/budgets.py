"""Error budgets: input uncertainties propagated to a shot's target, linearly and by Monte Carlo.

A source is a Gaussian uncertainty of some input columns (:class:`Source`). Defaults
(:func:`default_sources`): the racket-state deviations the paper measured against an optical
tracker (about 8 mm in position, 0.2 m/s in velocity and 0.7 degrees in orientation; read as the
RMS length of the 3-D deviation, so each axis has that divided by sqrt(3)), and spin-estimate
noise of 5 % of the spin plus 10 rad/s per axis (the dataset generator's ``spin_noise`` effect at
its defaults). A fitted parameter covariance is a further source (:func:`parameter_source`).

The linear budget of a shot is J_s C_s J_s^T per source s (J: the Jacobian's columns of that
source); sources are independent, so they add, and each source's share is its part of the trace
(the landing point's variance). :func:`monte_carlo` samples the same sources through the simulator,
keeping the samples whose event sequence is the nominal one.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ttsim_jax.sensitivity.jacobians import Jacobian, outcomes

RACKET_POS_STD = 0.008  # m, RMS length of the racket position deviation (paper, Sec. VI)
RACKET_VEL_STD = 0.2  # m/s
RACKET_ROT_STD_DEG = 0.7  # degrees
SPIN_REL_STD = 0.05  # relative spin-estimate noise (effects.record.SpinNoise defaults)
SPIN_ABS_STD = 10.0  # rad/s per axis


@dataclass
class Source:
    """A Gaussian uncertainty of some inputs.

    Attributes:
        name: label in reports.
        columns: (n,) names of the input columns it acts on (``Jacobian.columns``).
        cov: (n, n) covariance shared by all shots, or None when ``relative`` is given.
        relative: for spin-like sources: (rel, abs): covariance rel^2 x x^T + abs^2 I around each
            shot's own nominal x.
    """

    name: str
    columns: tuple
    cov: np.ndarray | None = None
    relative: tuple | None = None

    def covariance(self, jac: Jacobian) -> tuple[np.ndarray, np.ndarray]:
        """(column indices (n,), per-shot covariance (B, n, n))."""
        index = np.array([jac.columns.index(c) for c in self.columns])
        b = len(jac.values)
        if self.relative is None:
            return index, np.broadcast_to(self.cov, (b,) + self.cov.shape)
        rel, absolute = self.relative
        x = jac.nominal[:, index]
        return index, rel**2 * x[:, :, None] * x[:, None, :] + absolute**2 * np.eye(len(index))


def _axes(group):
    return tuple(f"{group}[{i}]" for i in range(3))


def default_sources(racket_pos: float = RACKET_POS_STD, racket_vel: float = RACKET_VEL_STD,
                    racket_rot_deg: float = RACKET_ROT_STD_DEG, spin_rel: float = SPIN_REL_STD,
                    spin_abs: float = SPIN_ABS_STD) -> list[Source]:
    """The default sources; racket values are RMS lengths of 3-D deviations (isotropic), a value
    of 0 leaves that source out."""
    out = []
    for name, group, std in (("racket position", "racket.pos", racket_pos),
                             ("racket orientation", "racket.rot", math.radians(racket_rot_deg)),
                             ("racket velocity", "racket.vel", racket_vel)):
        if std > 0:
            out.append(Source(name, _axes(group), cov=np.eye(3) * std**2 / 3.0))
    if spin_rel > 0 or spin_abs > 0:
        out.append(Source("spin estimate", _axes("ball.spin"), relative=(spin_rel, spin_abs)))
    return out


def parameter_source(path, columns) -> Source:
    """A fitted parameter covariance from a JSON file ``{"parameters": [names], "covariance": [[...]]}``
    (names as ``Jacobian.columns``: ``"table.e0"``, ``"aero.drag.cd[1,2]"``).

    Errors name the file, the key and the value: an unknown parameter, a covariance of the wrong
    shape, not symmetric, not positive semi-definite or not finite.
    """
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a JSON file ({e})") from None
    if not isinstance(raw, dict) or "parameters" not in raw or "covariance" not in raw:
        raise ValueError(f"{path}: expected an object with keys 'parameters' and 'covariance'")
    names = raw["parameters"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{path}: key 'parameters' must be a list of parameter names, got {names!r}")
    unknown = [n for n in names if n not in columns]
    if unknown:
        raise ValueError(f"{path}: key 'parameters': unknown parameter {unknown[0]!r} (e.g. 'table.e0', "
                         "'aero.drag.cd[1,2]')")
    try:
        cov = np.asarray(raw["covariance"], np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: key 'covariance' must be a square array of numbers") from None
    n = len(names)
    if cov.shape != (n, n):
        raise ValueError(f"{path}: key 'covariance' has shape {cov.shape}, expected ({n}, {n}) for {n} parameters")
    if not np.all(np.isfinite(cov)):
        raise ValueError(f"{path}: key 'covariance' has a value that is not finite")
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-300):
        raise ValueError(f"{path}: key 'covariance' is not symmetric")
    low = float(np.linalg.eigvalsh(cov).min())
    if low < -1e-12 * max(float(np.abs(cov).max()), 1e-300):
        raise ValueError(f"{path}: key 'covariance' is not positive semi-definite (eigenvalue {low:g})")
    return Source("model parameters", tuple(names), cov=cov)


@dataclass
class Budget:
    """A linear error budget.

    Attributes:
        sources: source names.
        cov: (B, k, k) total covariance of the target per shot.
        parts: (S, B, k, k) each source's covariance.
        share: (S, B) each source's share of the variance (trace), nan where the total is 0.
        groups: the input groups the sources act on (whose gradients the budget relies on).
    """

    sources: list
    cov: np.ndarray
    parts: np.ndarray
    share: np.ndarray
    groups: list = field(default_factory=list)

    @property
    def std(self) -> np.ndarray:
        """(B, k) standard deviation of each component."""
        return np.sqrt(np.einsum("bkk->bk", self.cov))


def linear_budget(jac: Jacobian, sources: list[Source]) -> Budget:
    """Linear propagation J C J^T of each source to the target, per shot."""
    parts, groups = [], []
    for s in sources:
        index, cov = s.covariance(jac)
        groups += [str(g) for g in np.asarray(jac.groups)[np.asarray(index)]]
        j = jac.jac[:, :, index]
        parts.append(np.einsum("bki,bij,blj->bkl", j, cov, j))
    parts = np.stack(parts)
    total = parts.sum(0)
    tr = np.einsum("sbkk->sb", parts)
    ttot = tr.sum(0)
    share = np.where(ttot > 0, tr / np.where(ttot > 0, ttot, 1.0), np.nan)
    return Budget(sources=[s.name for s in sources], cov=total, parts=parts, share=share,
                  groups=list(dict.fromkeys(groups)))


def sample_inputs(jac: Jacobian, sources: list[Source], n: int, rng: np.random.Generator) -> np.ndarray:
    """(B, n, C) inputs drawn from every source at once around each shot's nominal inputs."""
    b, c = jac.nominal.shape
    x = np.repeat(jac.nominal[:, None], n, 1)
    for s in sources:
        index, cov = s.covariance(jac)
        w, v = np.linalg.eigh(cov)  # (B, m), (B, m, m); semi-definite covariances have no Cholesky
        root = v * np.sqrt(np.clip(w, 0.0, None))[:, None, :]
        x[:, :, index] += np.einsum("bij,bnj->bni", root, rng.standard_normal((b, n, len(index))))
    return x


def monte_carlo(model, shots, jac: Jacobian, sources: list[Source], n: int = 1000, *, dt: float, n_steps: int,
                seed: int = 0, batch: int | None = None) -> dict:
    """Monte Carlo through the simulator with the sources of :func:`linear_budget`.

    Returns:
        dict with ``cov`` (B, k, k) sample covariance of the target over the samples that kept the
        nominal event sequence, ``kept`` (B,) their fraction, ``std`` (B, k).
    """
    rng = np.random.default_rng(seed)
    x = sample_inputs(jac, sources, n, rng)
    b, _, c = x.shape
    out = outcomes(model, shots, x.reshape(b * n, c), target=jac.target, dt=dt, n_steps=n_steps, batch=batch,
                   shot_index=np.repeat(np.arange(b), n))
    vals = out.values.reshape(b, n, -1)
    same = np.all(out.sequence.reshape(b, n, 2) == jac.sequence[:, None], -1) & out.valid.reshape(b, n)
    cov = np.zeros((b, vals.shape[-1], vals.shape[-1]))
    for i in range(b):
        v = vals[i][same[i]]
        if len(v) > 1:
            cov[i] = np.atleast_2d(np.cov(v.T))
    return dict(cov=cov, kept=same.mean(1), std=np.sqrt(np.einsum("bkk->bk", cov)))
