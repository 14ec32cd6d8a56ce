"""The noise floor of each phase: the error a perfect model would reach on this record, and how much
of the model's error lies above it (the removable gap).

Measurement noise, from the record itself:

* *positions* (:func:`position_sigma`): per axis, from third differences of consecutive
  observations within each flight segment (:func:`third_differences`). At even spacing
  p[i+2] - 3 p[i+1] + 3 p[i] - p[i-1] has variance (1 + 9 + 9 + 1) sigma^2 = 20 sigma^2 of
  independent noise, while the flight contributes its jerk times dt^3 (drag: about 100 m/s^3,
  1e-5 m at 200 Hz, against sqrt(20) sigma = 4.5 mm at sigma = 1 mm), so the physics does not leak
  in as it does in a second difference (g dt^2 = 0.25 mm at 200 Hz). Measured logs are not evenly
  sampled (the TT3D tracks' intervals jitter between 3 and 6 ms), so the third *divided*
  difference is used, normalised to the noise's variance: the same at even spacing, and still
  blind to any quadratic in time. sigma = 1.4826 median(|d|): the Gaussian-equivalent sigma,
  robust to the few differences that straddle a missed contact or a tracker glitch (such outliers
  are counted as removable gap: a better record, not a better model, removes them).
* *spin* (:func:`spin_sigma`): a segment's spin is the confidence-weighted mean of its samples'
  estimates, so where the samples of a segment carry differing estimates their scatter about the
  segment's mean gives the per-sample noise s (robust, per axis), and the segment's spin has
  variance s^2 sum(c^2) / (sum c)^2 (c the samples' confidences). Where every sample carries its
  segment's value (one estimate per segment) the spin noise cannot be told from the record: it is
  left out of the floor, which is then a lower bound for the parts that involve measured spin, and
  the output says so.

Propagated into each phase's error, as :mod:`ttsim_jax.diagnose.candidates` measures it (RMS over
all items, every segment and contact, not only the held-out ones):

* *flight*: the RMS 3-D position residual of the flight flown from each segment's initial state,
  which is fitted (Gauss-Newton) to the same noisy observations. A perfect model leaves the noise
  minus its projection on the fit's 6 free parameters; the flight is close to separable per axis
  (each axis' positions depend mainly on its own initial position and velocity), so a segment of n
  samples leaves sum over axes of (n - 2) sigma_a^2 of squared residual: floor^2 =
  sum_a sigma_a^2 sum_s (n_s - k_s) / sum_s n_s, with k_s = 2, or 2 2/3 where the segment flies
  its latent spin, fitted to the same samples (:func:`flight_params_per_axis`). A measured spin
  is held in the fit; its noise is not propagated into the flight floor.
* *table* and *racket*: the contact-state estimates are linear in the positions: the velocity is
  the derivative at the contact time of a least-squares polynomial over the nearest samples
  (:func:`ttsim_jax.data.contact_states.fit_contact_state`), so its variance per axis is
  sigma_a^2 [(A^T A)^-1]_11 / s^2 with A the fit's design matrix in tau / s (:func:`velocity_variance`).
  The contact's error e = f(x) - y_obs (6-vector of velocity and radius x spin errors, in the
  frame of the phase) is linearised in the incoming state x (through the model's contact map) and
  in the observed outgoing state (:func:`error_jacobians`, one ``jax.jacfwd`` of the phase's own
  error function, so every mask of the error, the unknown incoming spin of a bounce, counts as it
  does there), and floor_i^2 = trace(G_in Cov_in G_in^T) + trace(G_out Cov_out G_out^T), with the
  covariances rotated into the racket frame for racket contacts. Not counted: the noise of the
  contact position (the event's position, which places the contact point on the racket face) and
  the bias of the polynomial estimator itself (a degree-2 window neglects the drag's jerk: a few
  cm/s on fast balls; it is in the error of a perfect model too, so it shows as removable gap).

Removable gap: sqrt(max(error^2 - floor^2, 0)). Noise independent of the model's own error adds to
it in the mean square (E |e|^2 = |model error|^2 + floor^2), so the difference of squares is the
RMS of the part a better model can remove; error - floor would understate it (an error twice the
floor holds a removable part of 0.87 times the error, not 0.5).

Intervals (95 %): group bootstrap (:mod:`ttsim_jax.diagnose.bootstrap`) over the items of the
phase (segments, contacts) for the error and the floor's per-item factors, and over the record's
segments for the noise estimates (independent draws: the noise comes from all segments, the
error from the phase's items); the removable gap's interval from the same draws.

Checked against the truth (``tests/diagnose/test_floor.py``): on generated data with the
generator's position noise, diagnosed with the true model, the floor is within a few per cent of
the true model's actual error in flight and on the table.
"""

from __future__ import annotations

import math

import jax
import numpy as np

from ttsim_jax.diagnose.bootstrap import DRAWS, group_weights
from ttsim_jax.files.programs import stored_jit

#: Standard deviation of a Gaussian over its median absolute value.
MAD_SCALE = 1.4826
#: Parameters per axis of a flight segment's fit (initial position and velocity).
FLIGHT_PARAMS_PER_AXIS = 2
#: Parameters per axis that a latent spin adds (:func:`flight_params_per_axis`).
LATENT_PARAMS_PER_AXIS = 2.0 / 3.0
#: Fewest third differences for a noise estimate, and fewest items of a phase with a floor.
MIN_DIFFERENCES = 30
MIN_ITEMS = 2
#: Longest span of the 4 samples of a third difference, in median sampling intervals of the segment
#: (3 at even spacing; a missing frame or jittered times allowed).
MAX_SPAN = 4.5
#: Draws of the bootstrap processed at once (bounds the memory of the weighted medians).
CHUNK = 50


def flight_params_per_axis(spin_source) -> np.ndarray:
    """Parameters per axis that each flight segment's fit takes out of its samples' noise:
    :data:`FLIGHT_PARAMS_PER_AXIS`, and where the segment flies its latent spin, fitted to the same
    samples, 2/3 more: its two components across the flight, over the three axes (the one along it
    is held by its prior; what the positions show of it adds up to a further 1/3 on long
    segments: 2.6 measured on 16 samples, tests/fit/test_latent_spin.py, and 2.8 on 45).
    ``spin_source``: (S,) as :attr:`~ttsim_jax.diagnose.phases.Flights.spin_source`."""
    return FLIGHT_PARAMS_PER_AXIS + LATENT_PARAMS_PER_AXIS * (np.asarray(spin_source) == "latent")


# ---------------------------------------------------------------------------------------------- noise
def _segments(ds):
    """[(times (n,), positions (n, 3), spins (n, 3), confidences (n,))] of the record's segments in
    time order (observations outside segments left out)."""
    obs = ds.observations
    sid = np.asarray(obs["segment_id"])
    order = np.argsort(sid, kind="stable")
    bounds = np.flatnonzero(np.diff(sid[order])) + 1
    pos, t = ds.positions, np.asarray(obs["t"], np.float64)
    spin = np.stack([np.asarray(obs[k], np.float64) for k in ("spin_x", "spin_y", "spin_z")], -1)
    conf = np.asarray(obs["spin_conf"], np.float64)
    out = []
    for rows in np.split(order, bounds):
        if len(rows) and sid[rows[0]] >= 0:
            rows = rows[np.argsort(t[rows], kind="stable")]
            out.append((t[rows], np.asarray(pos[rows], np.float64), spin[rows], conf[rows]))
    return out


def third_differences(segments) -> tuple[np.ndarray, np.ndarray]:
    """Normalised third divided differences of positions within segments (module docstring).

    Of every 4 consecutive samples spanning at most :data:`MAX_SPAN` median sampling intervals of
    their segment, sum_j c_j p_j / sqrt(sum_j c_j^2) with c_j = 1 / prod_(k != j) (t_j - t_k): zero
    for any quadratic in time, of variance sigma^2 for independent noise of variance sigma^2 (at even
    spacing, the third difference over sqrt(20)).

    Arguments:
        segments: [(times (n,) [s], positions (n, 3) [m], ...)] per segment.

    Returns:
        (d (M, 3) [m], group (M,) the segment's index of each difference).
    """
    ds_, groups = [], []
    for g, (t, p, *_) in enumerate(segments):
        if len(t) < 4:
            continue
        t, p = np.asarray(t, np.float64), np.asarray(p, np.float64)
        k = np.arange(len(t) - 3)[:, None] + np.arange(4)
        tw = t[k]  # (m, 4)
        diff = tw[:, :, None] - tw[:, None, :] + np.eye(4)  # the diagonal made 1: left out of the product
        with np.errstate(divide="ignore", invalid="ignore"):
            c = 1.0 / np.prod(diff, axis=2)
            d = np.einsum("mj,mja->ma", c, p[k]) / np.sqrt(np.sum(c**2, 1, keepdims=True))
        dt = np.median(np.diff(t))
        # a long quadruple lets the flight's jerk in (it grows as the span cubed)
        ok = (tw[:, 3] - tw[:, 0] <= MAX_SPAN * dt) & np.all(np.diff(tw, axis=1) > 0, 1) & np.isfinite(d).all(1)
        ds_.append(d[ok])
        groups.append(np.full(int(ok.sum()), g))
    if not ds_:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(ds_), np.concatenate(groups)


def _weighted_median_draws(values, group, weights) -> np.ndarray:
    """(B,) median of ``values`` (M,) in each bootstrap draw, each value counted as often as its
    group is drawn (``weights`` (B, G))."""
    order = np.argsort(values)
    v, g = values[order], group[order]
    out = np.empty(len(weights))
    for lo in range(0, len(weights), CHUNK):
        c = np.cumsum(weights[lo:lo + CHUNK][:, g], axis=1)
        idx = np.sum(c < 0.5 * c[:, -1:], axis=1)
        out[lo:lo + CHUNK] = v[np.minimum(idx, len(v) - 1)]
    return out


def position_sigma(segments, n_boot: int = DRAWS, seed: int = 0) -> dict:
    """Per-axis position noise of a record from its segments' third differences (module docstring).

    Arguments:
        segments: [(times (n,) [s], positions (n, 3) [m], ...)] per flight segment.
        n_boot, seed: bootstrap draws over segments and their seed.

    Returns:
        dict: ``sigma`` (3,) [m], ``draws`` (n_boot, 3) bootstrap draws of it, ``n`` the number of
        third differences; or ``reason`` (a string) when fewer than :data:`MIN_DIFFERENCES`.
    """
    d, group = third_differences(segments)
    if len(d) < MIN_DIFFERENCES:
        return dict(reason=f"{len(d)} third differences of positions within flight segments "
                           f"(at least {MIN_DIFFERENCES} are needed to estimate the position noise)")
    sigma = MAD_SCALE * np.median(np.abs(d), axis=0)
    w = group_weights(len(segments), n_boot, seed)
    draws = np.stack([MAD_SCALE * _weighted_median_draws(np.abs(d[:, a]), group, w) for a in range(3)], 1)
    return dict(sigma=sigma, draws=draws, n=int(len(d)))


def spin_sigma(segments) -> dict:
    """Per-sample spin noise [rad/s] per axis from the scatter of the samples' spin estimates about
    their segment's confidence-weighted mean (module docstring).

    Arguments:
        segments: [(times, positions, spins (n, 3) [rad/s], confidences (n,))] per segment.

    Returns:
        dict: ``sigma`` (3,) [rad/s] and ``n`` the deviations used; or ``reason`` when no segment
        has two samples with differing estimates.
    """
    dev, measured = [], False
    for _, _, w, c in segments:
        used = c > 0
        measured |= bool(used.any())
        if used.sum() < 2:
            continue
        mean = np.sum(w[used] * c[used, None], 0) / np.sum(c[used])
        dev.append(w[used] - mean)
    d = np.concatenate(dev) if dev else np.zeros((0, 3))
    if not measured:
        return dict(reason="no spin is measured")
    if not len(d) or not np.any(np.abs(d) > 1e-9 * max(1.0, float(np.abs(d).max(initial=0.0)))):
        return dict(reason="every sample carries its segment's spin (one estimate per segment): its noise cannot be "
                           "told from the record and is left out of the floor")
    return dict(sigma=MAD_SCALE * np.median(np.abs(d - np.median(d, 0)), 0), n=int(len(d)))


def mean_spin_variance_factor(c) -> float:
    """sum(c^2) / (sum c)^2: the variance of a confidence-weighted mean of samples with confidences
    ``c``, in units of one sample's variance (0 without a weighted sample)."""
    c = np.asarray(c, np.float64)
    c = c[c > 0]
    return float(np.sum(c**2) / np.sum(c) ** 2) if len(c) else 0.0


# ---------------------------------------------------------------------------------------------- contacts
def velocity_variance(t, t_contact: float, degree: int) -> float:
    """Variance of the velocity estimate of :func:`~ttsim_jax.data.contact_states.fit_contact_state` per
    axis, in units of the position noise variance [1/s^2]: [(A^T A)^-1]_11 / s^2.

    Arguments:
        t: (n,) sample times [s]; t_contact: the contact time [s]; degree: the polynomial's.
    """
    tau = np.asarray(t, np.float64) - float(t_contact)
    scale = max(float(np.max(np.abs(tau))), 1e-9)
    a = np.stack([(tau / scale) ** k for k in range(degree + 1)], 1)
    return float(np.linalg.inv(a.T @ a)[1, 1] / scale**2)


def window_factors(ds, contacts, fit) -> np.ndarray:
    """(N, 4): per contact, the incoming and outgoing velocity estimates' variance factors
    (:func:`velocity_variance`, [1/s^2]) and the incoming and outgoing spins' (:func:`mean_spin_variance_factor`),
    from the samples the estimation used (:meth:`~ttsim_jax.data.contact_states.ObservationIndex.near`)."""
    index = ds.observation_index()
    conf = np.asarray(ds.observations["spin_conf"], np.float64)
    in_rows, out_rows = ds.segments_around(contacts.event_id)
    out = np.zeros((len(contacts), 4))
    for i, (r_in, r_out, tc) in enumerate(zip(in_rows, out_rows, contacts.t)):
        for k, (row, before) in enumerate(((r_in, True), (r_out, False))):
            t, _ = index.near(int(row), float(tc), before, fit)
            out[i, k] = velocity_variance(t, tc, fit.degree)
            out[i, 2 + k] = mean_spin_variance_factor(conf[index.rows(int(row))])
    return out


def _jacobians_impl(model, c, phase):
    from ttsim_jax.diagnose.stages import ERRORS

    def one(row):
        def e(x, y):
            return ERRORS[phase](model, (), (), (), {k: v[None] for k, v in dict(row, x=x, y_obs=y).items()})[0]

        return jax.jacfwd(e, argnums=(0, 1))(row["x"], row["y_obs"])

    return jax.vmap(one)(c)


_jacobians = stored_jit(_jacobians_impl, static_argnames=("phase",))


def error_jacobians(model, data: dict, phase: str) -> tuple[np.ndarray, np.ndarray]:
    """(d e / d x (N, 6, 8), d e / d y_obs (N, 6, 6)) of every (padded) contact row of a phase's
    arrays (:attr:`~ttsim_jax.diagnose.candidates.Problem.data`), e its error of
    :mod:`~ttsim_jax.diagnose.stages` under ``model`` (no candidate effect)."""
    keys = ("pos", "x", "y_obs", "known", "known_in", "correction", "session", "world_in", "world_out", "rot", "t",
            "spin_dt")
    gx, gy = _jacobians(model.replace(name=""), {k: data[k] for k in keys}, phase)
    return np.asarray(gx, np.float64), np.asarray(gy, np.float64)


def contact_factors(gx, gy, rot, window, spin_var=None) -> np.ndarray:
    """Per contact, the floor's squared error: per unit position noise variance of each world axis a
    (the sum over the two sides of the velocity variance factor times |G R^T e_a|^2), and that of
    the spin noise.

    Arguments:
        gx, gy: (N, 6, 8), (N, 6, 6) from :func:`error_jacobians` (real rows).
        rot: (N, 3, 3) frame of the contact's x and y_obs (world from frame).
        window: (N, 4) from :func:`window_factors`.
        spin_var: (3,) per-sample spin noise variance [rad^2/s^2], or None.

    Returns:
        (position factors (N, 3) [(m/s)^2 per m^2 of noise variance], spin part (N,) [(m/s)^2]).
    """
    rt = np.transpose(rot, (0, 2, 1))  # world -> frame: a world axis a is column a of R^T
    v_in = np.einsum("nij,njk->nik", gx[:, :, :3], rt)  # (N, 6, 3): error per unit world velocity error
    v_out = np.einsum("nij,njk->nik", gy[:, :, :3], rt)
    pos = window[:, :1] * np.sum(v_in**2, 1) + window[:, 1:2] * np.sum(v_out**2, 1)
    spin = np.zeros(len(gx))
    if spin_var is not None:
        w_in = np.einsum("nij,njk->nik", gx[:, :, 3:6], rt)
        w_out = np.einsum("nij,njk->nik", gy[:, :, 3:6], rt)
        spin = window[:, 2] * (np.sum(w_in**2, 1) @ spin_var) + window[:, 3] * (np.sum(w_out**2, 1) @ spin_var)
    return pos, spin


# ---------------------------------------------------------------------------------------------- summary
def _ci(draws) -> list:
    d = np.asarray(draws, np.float64)
    d = d[np.isfinite(d)]
    return [float(np.percentile(d, 2.5)), float(np.percentile(d, 97.5))] if len(d) > 1 else [0.0, 0.0]


def summary(sse, count, floor_pos, floor_spin, sigma: dict, n_boot: int = DRAWS, seed: int = 0) -> dict:
    """One phase's error, floor and removable gap with their intervals (module docstring).

    Arguments:
        sse: (G,) squared error summed per item group (segment, contact) [m^2 or (m/s)^2];
        count: (G,) items per group; floor_pos: (G, 3) squared floor per unit position noise
        variance of each axis, summed per group; floor_spin: (G,) the spin noise's squared floor
        per group; sigma: :func:`position_sigma`'s result; n_boot, seed: the groups' bootstrap.

    Returns:
        dict: ``error``, ``error_ci95``, ``floor``, ``floor_ci95``, ``removable``,
        ``removable_ci95`` (RMS, the phase's unit), ``sigma_m`` (3,), ``n`` (groups).
    """
    sse, count = np.asarray(sse, np.float64), np.asarray(count, np.float64)
    w = group_weights(len(sse), n_boot, seed)
    var = np.asarray(sigma["sigma"], np.float64) ** 2
    err2 = sse.sum() / count.sum()
    floor2 = (floor_pos.sum(0) @ var + floor_spin.sum()) / count.sum()
    n = w @ count
    err2_d = (w @ sse) / n
    floor2_d = (np.sum((w @ floor_pos) * sigma["draws"][:n_boot] ** 2, 1) + w @ floor_spin) / n
    rem_d = np.sqrt(np.maximum(err2_d - floor2_d, 0.0))
    return dict(error=math.sqrt(err2), error_ci95=_ci(np.sqrt(err2_d)), floor=math.sqrt(floor2),
                floor_ci95=_ci(np.sqrt(floor2_d)), removable=math.sqrt(max(err2 - floor2, 0.0)),
                removable_ci95=_ci(rem_d), sigma_m=[float(s) for s in sigma["sigma"]], n=int(len(sse)))


def floors(ds, ph, pb, model, fit, seed: int = 0, n_boot: int = DRAWS) -> dict:
    """{phase: summary or reason} of every phase of :data:`~ttsim_jax.diagnose.candidates.PHASES`:
    the model's RMS error on all items, the noise floor and the removable gap (module docstring).

    Arguments:
        ds: the dataset; ph: its :class:`~ttsim_jax.diagnose.phases.Phases`; pb: the
        :class:`~ttsim_jax.diagnose.candidates.Problem` (the model's errors ``pb.base``);
        model: the model; fit: the contact-state estimation (:class:`~ttsim_jax.data.contact_states.ContactFit`);
        seed, n_boot: bootstrap.

    Returns:
        {phase: :func:`summary`'s dict (plus ``spin_noise``: the spin's per-sample sigma [rad/s]
        or why it is left out), or a string saying why the phase has no floor}.
    """
    from ttsim_jax.diagnose.candidates import PHASES, item_sums

    segs = _segments(ds)
    sigma = position_sigma(segs, n_boot, seed)
    spin = spin_sigma(segs)
    out = {}
    for p in PHASES:
        if p not in pb.phases:
            out[p] = f"no data: {ph.skipped.get(p, 'no items')}"
            continue
        real = ph.flights.n if p == "flight" else len(getattr(ph, p))
        if real < MIN_ITEMS:
            out[p] = f"{real} {'segment' if p == 'flight' else 'contact'}(s): at least {MIN_ITEMS} are needed"
            continue
        if "reason" in sigma:
            out[p] = sigma["reason"]
            continue
        sse, count = (a[:real] for a in item_sums(pb, p, pb.base[p]))
        if p == "flight":
            source = ph.flights.spin_source[:real] if ph.flights.spin_source is not None else np.full(real, "")
            fpos = np.repeat(np.maximum(count - flight_params_per_axis(source), 0.0)[:, None], 3, 1)
            fspin = np.zeros(real)
        else:
            c = getattr(ph, p)
            gx, gy = error_jacobians(model, pb.data[p], p)
            fpos, fspin = contact_factors(gx[:real], gy[:real], c.rot, window_factors(ds, c, fit),
                                          None if "reason" in spin else np.asarray(spin["sigma"]) ** 2)
        bad = ~(np.isfinite(fpos).all(1) & np.isfinite(fspin) & np.isfinite(sse))
        if bad.all():
            out[p] = "no item with a finite error and floor"
            continue
        # an item whose error map is not differentiable where it was estimated has no floor: left out
        out[p] = summary(sse[~bad], count[~bad], fpos[~bad], fspin[~bad], sigma, n_boot, seed)
        if bad.any():
            out[p]["left_out"] = int(bad.sum())
        if p != "flight":
            out[p]["spin_noise"] = spin["reason"] if "reason" in spin else [float(s) for s in spin["sigma"]]
    return out
