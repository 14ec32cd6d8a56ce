"""The spin check: a record's measured spin against the spin its flights show.

A spin estimator that reads a sign wrong on some throws, a spin axis turned by a calibration error,
or a sign convention flipped between a tracker and the simulator would otherwise be taken for
physics by the table, the air or the ball. :func:`check_spin` compares, segment by segment, the
measured spin's part across the direction of flight with the latent spin's
(:mod:`ttsim_jax.fit.latent_spin`: the part the positions show) and reports:

* **opposite**: the share of segments bent the opposite way to their measured spin (the angle
  between the two parts above :data:`OPPOSITE_DEG`), with a 95 % interval (Wilson's): a sign flipped
  on every segment reads about 1, on some of them its share;
* **rotation**: the rotation that best turns the measured parts onto the latent ones over the
  segments that are not opposite (the orthogonal Procrustes solution on unit vectors: the
  correction of the record), its angle and the axis it turns right-handed about, with a bootstrap
  95 % interval of the angle: an axis turned by a frame error reads its
  angle, a consistent record a few degrees (the noise's own);
* **angle**: the median angle between the parts over those segments, before and after that
  rotation;
* **where the opposite ones gather**: an estimator that fails at large spins (a rotation per frame
  past half a turn reads backwards, motion blur hides the pattern) flips the sign of the largest
  readings only, so the check asks whether the segments bent opposite gather above some size of
  the measured spin: the size whose segments above it most exceed the rest's opposite share (two
  proportions' z, over the sizes of the opposite segments with :data:`MIN_ABOVE` or more above),
  named when a permutation of the opposite flags beats it in under :data:`GATHER_P` of
  :data:`PERMUTATIONS` (the scan over sizes included). On SpinDOE the 3 compared segments measured
  above 800 rad/s (2,224-2,362 rad/s, beyond what a launcher or a player puts on a ball) are all
  bent opposite, against 15 % of the others (``docs/measurements/spin.md``).

The spin's size is not compared segment by segment: under the paper's C_M the Magnus force hardly
grows with the spin above a few hundred rad/s, so a flight shows the spin's direction far better than
its size (``docs/measurements/spin.md``). :func:`spin_scale` reads the size over all segments at
once instead: the one factor on every measured spin that lets the model fly the segments best
(pooled, the segments whose spin is small enough for the Magnus force to grow with it carry it),
with a bootstrap interval over the segments.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: Two parts further apart than this are "opposite" [deg].
OPPOSITE_DEG = 120.0
#: Least size of the measured spin's part across the flight to be compared [rad/s] (a smaller one
#: has no direction to speak of).
MIN_ACROSS = 50.0
#: Bootstrap resamples of the rotation's angle and of the scale.
BOOTSTRAP = 200
#: Where the opposite segments gather: the least segments above a size, the permutations, and the
#: permutation p below which the size is named.
MIN_ABOVE, PERMUTATIONS, GATHER_P = 3, 2000, 0.01
#: Factors on the measured spin that :func:`spin_scale` tries (refined between grid points).
SCALES = tuple(np.round(np.linspace(0.5, 1.5, 21), 3))
#: Widest interval of the factor :func:`spin_scale` finds that is read as a size [1].
MAX_SCALE_WIDTH = 0.5
#: A record's spin is reported off when its interval leaves these out: a share bent opposite above
#: this, a rotation above this [deg], a scale outside 1 +- this.
FINDING_OPPOSITE, FINDING_ROTATION_DEG, FINDING_SCALE = 0.05, 5.0, 0.05


def _angles(a, b) -> np.ndarray:
    c = np.sum(a * b, 1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _rotation(src, dst) -> np.ndarray:
    """The rotation R minimising sum |R src_i - dst_i|^2 over unit vectors (Kabsch)."""
    u = src / np.linalg.norm(src, axis=1, keepdims=True)
    v = dst / np.linalg.norm(dst, axis=1, keepdims=True)
    a, _, bt = np.linalg.svd(v.T @ u)
    d = np.sign(np.linalg.det(a @ bt))
    return a @ np.diag([1.0, 1.0, d]) @ bt


def _rotation_angle(r) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def _rotation_axis(r) -> np.ndarray:
    """The unit axis about which ``r`` turns right-handed by its angle (from its skew part; for a
    turn too small to have one, the eigenvector of eigenvalue 1)."""
    skew = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if np.linalg.norm(skew) > 1e-9:
        return skew / np.linalg.norm(skew)
    w, v = np.linalg.eig(r)
    return np.real(v[:, np.argmin(np.abs(w - 1.0))])


def _two_proportions_z(flags, order, min_above):
    """(P, K) z of the opposite share above each size against below, the segments sorted by size
    (``order``), for flags (P, N) of P permutations; -inf where fewer than ``min_above`` lie above."""
    f = flags[:, order].astype(np.float64)
    n = f.shape[1]
    above_n = np.arange(n, 0, -1, dtype=np.float64)  # segments at or above the k-th smallest
    above_k = np.cumsum(f[:, ::-1], axis=1)[:, ::-1]
    below_n = n - above_n
    below_k = f.sum(1, keepdims=True) - above_k
    pooled = f.mean(1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        se = np.sqrt(pooled * (1 - pooled) * (1 / above_n + 1 / np.maximum(below_n, 1)))
        z = (above_k / above_n - below_k / np.maximum(below_n, 1)) / se
    z[:, (above_n < min_above) | (below_n < 1)] = -np.inf
    return np.where(np.isfinite(z), z, -np.inf)


def opposite_gather(sizes, opposite, *, min_above: int = MIN_ABOVE, permutations: int = PERMUTATIONS,
                    seed: int = 0) -> dict | None:
    """Whether the segments bent opposite gather above a size of the measured spin (module
    docstring): None when none do; else ``size`` (the least measured size of the group above
    [rad/s]), ``n`` and ``opposite`` (segments above it and those of them opposite), ``rest_share``
    (the opposite share of the others) and ``p`` (the permutation p, the scan over sizes included).

    Arguments:
        sizes: (N,) sizes of the compared segments' measured spins [rad/s]; opposite: (N,) bools.
    """
    sizes, opposite = np.asarray(sizes, np.float64), np.asarray(opposite, bool)
    if opposite.sum() == 0 or opposite.all() or len(sizes) < min_above + 1:
        return None
    order = np.argsort(sizes, kind="stable")
    z = _two_proportions_z(opposite[None], order, min_above)[0]
    # only sizes at an opposite segment: a group above that starts with an agreeing one is beaten by the next
    at_opposite = opposite[order]
    z = np.where(at_opposite, z, -np.inf)
    if not np.isfinite(z).any():
        return None
    k = int(np.argmax(z))
    rng = np.random.default_rng(seed)
    perm = np.stack([rng.permutation(opposite) for _ in range(permutations)])
    zp = _two_proportions_z(perm, order, min_above)
    zp = np.where(perm[:, order], zp, -np.inf).max(1)
    p = float((np.sum(zp >= z[k]) + 1) / (permutations + 1))
    if p >= GATHER_P:
        return None
    above = order[k:]
    rest = order[:k]
    return dict(size=float(sizes[order[k]]), n=int(len(above)), opposite=int(opposite[above].sum()),
                rest_share=float(opposite[rest].mean()) if len(rest) else 0.0, p=p)


def _wilson(k: int, n: int) -> tuple[float, float]:
    if n == 0:
        return 0.0, 1.0
    p, z = k / n, 1.96
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


@dataclasses.dataclass
class SpinCheck:
    """What :func:`check_spin` found (see the module docstring).

    Attributes:
        n: segments compared; opposite: (share, (low, high)) of those bent opposite to their
            measured spin; opposite_rows: their rows among the segments given;
        rotation_deg: (angle, (low, high)) of the best rotation over the others; rotation_axis: (3,);
        angle_deg: median angle between the parts over the others; angle_after_deg: the same after
            the rotation;
        opposite_above: where the opposite ones gather above a size of the measured spin
            (:func:`opposite_gather`), or None.
    """

    n: int
    opposite: tuple
    opposite_rows: np.ndarray
    rotation_deg: tuple
    rotation_axis: np.ndarray
    angle_deg: float
    angle_after_deg: float
    opposite_above: dict | None = None

    def summary(self) -> str:
        """One line a reader can act on."""
        if self.n == 0:
            return "spin check: no segment with both a measured and a latent spin across the flight"
        share, (lo, hi) = self.opposite
        angle, (alo, ahi) = self.rotation_deg
        parts = [f"spin check over {self.n} segments: {100 * share:.0f} % (95 % {100 * lo:.0f}-{100 * hi:.0f} %) bent "
                 f"opposite to their measured spin",
                 f"the others' measured spin {self.angle_deg:.0f} deg (median) from what the flights show, "
                 f"best turned by {angle:.0f} deg (95 % {alo:.0f}-{ahi:.0f}) about {np.round(self.rotation_axis, 2).tolist()}"
                 f" to {self.angle_after_deg:.0f} deg"]
        g = self.opposite_above
        if g:
            parts.insert(1, f"they gather at measured spins of {g['size']:.0f} rad/s and more ({g['opposite']} of "
                            f"{g['n']}; {100 * g['rest_share']:.0f} % of the rest; permutation p {g['p']:.3f}): the "
                            f"spin estimator's reading of large spins")
        return "; ".join(parts)

    def to_json(self) -> dict:
        return dict(n=self.n, opposite=self.opposite[0], opposite_interval=list(self.opposite[1]),
                    opposite_rows=self.opposite_rows.tolist(), rotation_deg=self.rotation_deg[0],
                    rotation_interval_deg=list(self.rotation_deg[1]), rotation_axis=self.rotation_axis.tolist(),
                    angle_deg=self.angle_deg, angle_after_deg=self.angle_after_deg, opposite_above=self.opposite_above)


def check_spin(measured, latent, *, min_across: float = MIN_ACROSS, seed: int = 0) -> SpinCheck:
    """Compares measured spins with latent ones (see the module docstring).

    Arguments:
        measured: (S, 3) measured spins [rad/s] of the segments ``latent`` was fitted on.
        latent: their :class:`~ttsim_jax.fit.latent_spin.LatentSpin`.
        min_across: least size of both parts across the flight [rad/s]; the latent one must also
            exceed twice its standard error.
        seed: of the bootstrap.

    Returns:
        :class:`SpinCheck`.
    """
    measured = np.asarray(measured, np.float64)
    if measured.shape != (len(latent), 3):
        raise ValueError(f"measured spins have shape {measured.shape}; the latent spins are of {len(latent)} "
                         f"segments: give ({len(latent)}, 3), the same segments in the same order")
    along = latent.along
    m = measured - np.sum(measured * along, 1, keepdims=True) * along
    est = latent.observed
    size_m, size_e = np.linalg.norm(m, axis=1), np.linalg.norm(est, axis=1)
    use = latent.ok & (size_m >= min_across) & (size_e >= min_across) & (size_e >= 2.0 * latent.stderr_observed)
    rows = np.flatnonzero(use)
    empty = SpinCheck(0, (0.0, (0.0, 1.0)), np.zeros(0, int), (0.0, (0.0, 180.0)), np.zeros(3), float("nan"),
                      float("nan"))
    if not len(rows):
        return empty
    ang = _angles(m[rows], est[rows])
    opp = ang > OPPOSITE_DEG
    same = rows[~opp]
    k, n = int(opp.sum()), len(rows)
    gather = opposite_gather(np.linalg.norm(measured[rows], axis=1), opp, seed=seed)
    if len(same) < 3:
        return dataclasses.replace(empty, n=n, opposite=(k / n, _wilson(k, n)), opposite_rows=rows[opp],
                                   opposite_above=gather)
    r = _rotation(m[same], est[same])
    rng = np.random.default_rng(seed)
    boot = [_rotation_angle(_rotation(m[b], est[b])) for b in (rng.choice(same, len(same)) for _ in range(BOOTSTRAP))]
    axis = _rotation_axis(r)
    return SpinCheck(n=n, opposite=(k / n, _wilson(k, n)), opposite_rows=rows[opp],
                     rotation_deg=(_rotation_angle(r), tuple(float(x) for x in np.percentile(boot, [2.5, 97.5]))),
                     rotation_axis=axis, angle_deg=float(np.median(ang[~opp])),
                     angle_after_deg=float(np.median(_angles(m[same] @ r.T, est[same]))), opposite_above=gather)


def _grid_min(scales, cost) -> float:
    """The minimum of ``cost`` over ``scales``, refined by the parabola through the lowest grid
    point and its neighbours (the grid's end where the lowest is there)."""
    k = int(np.argmin(cost))
    if k == 0 or k == len(scales) - 1:
        return float(scales[k])
    x, y = np.asarray(scales[k - 1:k + 2], np.float64), np.asarray(cost[k - 1:k + 2], np.float64)
    a, b, _ = np.polyfit(x, y, 2)
    return float(np.clip(-b / (2 * a), x[0], x[2])) if a > 0 else float(x[1])


def spin_scale(model, times, positions, spins, *, scales=SCALES, seed: int = 0) -> dict:
    """The factor on every measured spin that the flights favour (see the module docstring).

    Per segment and factor s, the model flies the segment with spin s w (initial position and
    velocity fitted, :func:`ttsim_jax.fit.flight.flight_rmse`); the costs (samples x RMSE^2) are
    summed over the segments and the factor of the least sum kept; the interval is that of a
    bootstrap over the segments.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model`; times, positions: the segments' samples (lists of
            (T_i,) and (T_i, 3)); spins: (S, 3) their measured spins [rad/s].
        scales: the factors tried; seed: of the bootstrap.

    Returns:
        dict: ``scale``, ``interval`` (95 %), ``n`` segments, ``scales`` and ``cost`` (summed cost
        per factor [m^2]).
    """
    from ttsim_jax.fit.flight import flight_rmse

    spins = np.asarray(spins, np.float64)
    scales = np.asarray(scales, np.float64)
    counts = np.array([len(t) for t in times], np.float64)
    n, g = len(times), len(scales)
    # every (factor, segment) pair in one call: the batches fill, and the compiled shapes are few
    rmse = flight_rmse(model, list(times) * g, list(positions) * g, (scales[:, None, None] * spins).reshape(-1, 3),
                       fit_position=True)
    cost = counts[:, None] * rmse.reshape(g, n).T ** 2
    good = np.isfinite(cost).all(1)
    cost = cost[good]
    if not len(cost):
        return dict(scale=float("nan"), interval=[float("nan")] * 2, n=0, scales=scales.tolist(), cost=[])
    rng = np.random.default_rng(seed)
    boot = [_grid_min(scales, cost[rng.integers(0, len(cost), len(cost))].sum(0)) for _ in range(BOOTSTRAP)]
    total = cost.sum(0)
    return dict(scale=_grid_min(scales, total), interval=[float(x) for x in np.percentile(boot, [2.5, 97.5])],
                n=int(len(cost)), scales=scales.tolist(), cost=total.tolist())


def check_record_spin(model, times, positions, spins, *, seed: int = 0, latent=None) -> dict:
    """The whole spin check of segments with a measured spin: their latent spins fitted under
    ``model`` (:func:`ttsim_jax.fit.latent_spin.fit_latent_spin`), compared with the measured ones
    (:func:`check_spin`), and the scale the flights favour (:func:`spin_scale`).

    ``latent``: that fit of these segments under ``model``, when already made (it does not depend
    on the record's spins, so checks of several spin records of the same flights share it).

    Returns:
        dict (JSON-able): the :meth:`SpinCheck.to_json` entries; ``scale`` and ``scale_interval``
        (the factor the flights favour, over the segments not bent opposite: ``scale_segments``;
        None without any), ``reads`` and ``reads_interval`` (its inverse: the measured spin reads
        that many times the flights'), ``scale_resolved`` (the least cost inside the factors tried,
        its interval at most :data:`MAX_SCALE_WIDTH` wide: only then is a scale named),
        ``segments`` (given), ``findings`` (short phrases of what is off, empty when the record's
        spin agrees with its flights: :func:`findings`) and ``summary`` (one line).
    """
    from ttsim_jax.fit.latent_spin import fit_latent_spin

    spins = np.asarray(spins, np.float64)
    latent = fit_latent_spin(times, positions, model) if latent is None else latent
    check = check_spin(spins, latent, seed=seed)
    rest = np.setdiff1d(np.arange(len(times)), check.opposite_rows)  # a flipped spin has no size to read
    scale = spin_scale(model, [times[i] for i in rest], [positions[i] for i in rest], spins[rest], seed=seed)
    lo, hi = scale["interval"]
    # the size is read where the least cost lies inside the factors tried and its interval is narrow
    resolved = bool(scale["n"]) and min(scale["scales"]) < scale["scale"] < max(scale["scales"]) \
        and hi - lo <= MAX_SCALE_WIDTH
    out = dict(check.to_json(), segments=len(times), scale_segments=scale["n"], scale_resolved=resolved,
               scale=scale["scale"] if scale["n"] else None, scale_interval=scale["interval"] if scale["n"] else None,
               reads=1.0 / scale["scale"] if scale["n"] else None,
               reads_interval=[1.0 / hi, 1.0 / lo] if scale["n"] else None)
    out["findings"] = findings(out)
    if resolved:
        size = (f"over {scale['n']} segments the measured spin reads {out['reads']:.2f} (95 % "
                f"{out['reads_interval'][0]:.2f}-{out['reads_interval'][1]:.2f}) times what the flights show")
    elif scale["n"]:
        size = (f"the spin's size is not resolved by the flights (over {scale['n']} segments the measured spin reads "
                f"{out['reads_interval'][0]:.2f}-{out['reads_interval'][1]:.2f} times theirs, 95 %)")
    else:
        size = "no segment left to read the spin's size on"
    text = check.summary() + "; " + size
    out["summary"] = text + ("; " + ", ".join(out["findings"]) if out["findings"] else "; consistent")
    return out


def _off(check: dict) -> dict:
    """What a check (:func:`check_record_spin`'s dict) shows off: ``flip`` (None, ``"all"`` or
    ``"some"``), ``rotate`` and ``scale`` (bools), each outside its interval's allowance."""
    n = check.get("n", 0)
    flip = None
    if n and check["opposite_interval"][0] > FINDING_OPPOSITE:
        flip = "all" if check["opposite"] > 0.9 else "some"
    lo, hi = check.get("reads_interval") or (np.nan, np.nan)
    return dict(flip=flip, rotate=bool(n and check["rotation_interval_deg"][0] > FINDING_ROTATION_DEG),
                scale=bool(check.get("scale_resolved", True) and np.isfinite(lo)
                           and (lo > 1.0 + FINDING_SCALE or hi < 1.0 - FINDING_SCALE)))


def findings(check: dict) -> list:
    """Short phrases naming what is off with a record's spin (:func:`check_record_spin`'s dict):
    a sign flipped (on all or some segments), an axis turned, a scale; [] when none is shown."""
    off, out = _off(check), []
    if off["flip"]:
        out.append("sign flipped on every segment" if off["flip"] == "all"
                   else f"sign flipped on {100 * check['opposite']:.0f} % of segments")
    if off["rotate"]:
        out.append(f"axis turned by {check['rotation_deg']:.0f} deg (turned back right-handed about "
                   f"{np.round(check['rotation_axis'], 2).tolist()})")
    if off["scale"]:
        out.append(f"spin reads {abs(100 * (check['reads'] - 1.0)):.0f} % {'high' if check['reads'] > 1 else 'low'}")
    return out


def _turn(axis, angle_deg) -> np.ndarray:
    """The rotation by ``angle_deg`` right-handed about the unit ``axis`` (Rodrigues)."""
    k = np.asarray(axis, np.float64) / max(np.linalg.norm(axis), 1e-12)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    a = np.radians(angle_deg)
    return np.eye(3) + np.sin(a) * cross + (1.0 - np.cos(a)) * cross @ cross


def corrected_spins(spins, check: dict) -> tuple[np.ndarray, list]:
    """The measured spins with what the check found off undone, in the order the check was run on
    (:func:`check_record_spin`'s dict): a sign flipped on every segment negated on all, one flipped
    on some negated on the segments bent opposite, a turned axis turned back by the check's
    rotation (not after a sign flipped on every segment: that rotation was read off the few
    segments left), a scale multiplied by the factor the flights favour.

    Returns:
        (corrected (S, 3) [rad/s], phrases of what was undone; [] when the check found nothing).
    """
    w = np.array(spins, np.float64)
    off, done = _off(check), []
    if off["flip"] == "all":
        w, done = -w, ["sign flipped back on every segment"]
    elif off["flip"] == "some":
        rows = np.asarray(check["opposite_rows"], int)
        w[rows] = -w[rows]
        done.append(f"sign flipped back on the {len(rows)} segments bent opposite")
    if off["rotate"] and off["flip"] != "all":
        w = w @ _turn(check["rotation_axis"], check["rotation_deg"]).T
        done.append(f"axis turned back by {check['rotation_deg']:.0f} deg")
    if off["scale"]:
        w = w * check["scale"]
        done.append(f"size multiplied by {check['scale']:.2f}")
    return w, done
