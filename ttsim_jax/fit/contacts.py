"""Measured racket contacts -> training arrays of the racket residual network.

For every racket contact of a :class:`~ttsim_jax.data.Dataset` that has a racket state, this
estimates the ball's state just before and just after the contact and converts both into the
racket frame exactly as the rally kernel does (:func:`ttsim_jax.physics.racket.racket_frame_state`),
so a network trained on the arrays corrects the simulator's own racket-frame prediction:

* ``x`` = (v~, w~, d) (8 inputs, conti2026) or (v~, w~) (6 inputs, durr2026): the ball's
  velocity relative to the face at the contact point (racket linear velocity plus, for racket
  kinds that use it, w_R x r), its spin relative to the racket's (the "nakashima" kind, used by
  durr2026, ignores the racket's angular velocity), and the contact position on the face.
* ``y_base`` = the base model's post-contact (v+, w+) for the model's racket parameters
  (:func:`ttsim_jax.physics.racket.base_response`).
* ``y_obs`` = the observed post-contact state in the same frame: R^T (v_out - v_surf),
  R^T (w_out - w_surf), with R, v_surf, w_surf those of the pre-contact state (the inverse of
  the paper's v+ = R v~+ + v_R + w_R x r, w+ = R w~+ + w_R).

How the contact states are estimated (:class:`ContactFit`):

* Velocity: a least-squares polynomial in time (degree 2 by default: constant acceleration, which
  absorbs gravity, drag and Magnus force over a short window) fitted per axis to the last
  ``n_samples`` observations of the incoming segment and to the first ``n_samples`` of the
  outgoing one, each within ``max_span`` seconds of the contact, and differentiated at the
  contact time. Over 50 ms at 20 m/s the neglected drag jerk biases the velocity by a few cm/s;
  position noise of sigma_p over n samples spanning T gives a velocity noise of roughly
  4 sigma_p / (T sqrt(n)) for degree 2 (about 0.2 m/s for 2 mm, 10 samples, 50 ms): choose the
  window to suit the data's rate and noise.
* Spin: the segments' spin (``segments.spin_*``, the confidence-weighted mean of the samples'
  spin), required to have ``spin_conf >= min_spin_conf`` before and after.
* Position: the racket event's ball position (``events.x, y, z``); the contact position d on the
  face is computed from it and the racket pose as in the simulator (``contact_point = "state"``)
  or taken from the rackets table (``"table"``).

Contacts lacking what is needed are skipped and counted by reason (:data:`SKIP_REASONS`).

:func:`synthetic_contact_dataset` makes a dataset of flights into known racket states with a known
post-contact law, for tests and for checking the pipeline end to end.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.physics import racket as racket_stage

SKIP_REASONS = {
    "no_racket_state": "racket event without a row in the rackets table",
    "no_incoming_segment": "no flight segment ends at the contact",
    "no_outgoing_segment": "no flight segment starts at the contact",
    "few_incoming_samples": "fewer than min_samples observations before the contact within max_span",
    "few_outgoing_samples": "fewer than min_samples observations after the contact within max_span",
    "low_spin_conf_in": "incoming segment's spin confidence below min_spin_conf",
    "low_spin_conf_out": "outgoing segment's spin confidence below min_spin_conf",
    "bad_fit": "polynomial fit RMSE above max_fit_rmse",
    "off_face": "ball centre farther than max_face_gap from the face plane (plus the ball radius)",
    "not_approaching": "ball not moving towards the face before the contact (v~_x >= 0)",
    "not_leaving": "ball not moving away from the face after the contact (v~+_x <= 0)",
    "non_finite": "a non-finite value in the contact's arrays",
}

# Default residual inputs per bundled model: the paper's 8-input network, Dürr's 6-input one.
MODEL_INPUTS = {"conti2026": 8, "durr2026": 6}


@dataclasses.dataclass(frozen=True)
class ContactFit:
    """How pre- and post-contact states are estimated from observations.

    Attributes:
        n_samples: observations used on each side of the contact (the nearest ones).
        max_span: only observations within this time of the contact are used [s].
        degree: degree of the per-axis polynomial in time (1: constant velocity, 2: constant
            acceleration).
        min_samples: fewer usable observations on a side skip the contact (>= degree + 2, so
            the fit has a residual).
        min_spin_conf: least spin confidence of the incoming and outgoing segments.
        max_fit_rmse: a side whose fit leaves a larger RMS position residual is skipped [m].
        max_face_gap: largest |distance of the ball centre from the face plane - radius| [m].
        contact_point: "state" (d from ball and racket positions, as the simulator) or "table"
            (the rackets table's d_y, d_z).
    """

    n_samples: int = 10
    max_span: float = 0.1
    degree: int = 2
    min_samples: int = 4
    min_spin_conf: float = 0.5
    max_fit_rmse: float = 0.01
    max_face_gap: float = 0.05
    contact_point: str = "state"

    def __post_init__(self):
        problems = []
        if self.degree not in (1, 2, 3):
            problems.append(f"degree = {self.degree!r}: must be 1, 2 or 3")
        if self.min_samples < self.degree + 2:
            problems.append(f"min_samples = {self.min_samples!r}: must be >= degree + 2 = {self.degree + 2}")
        if self.n_samples < self.min_samples:
            problems.append(f"n_samples = {self.n_samples!r}: must be >= min_samples = {self.min_samples}")
        if not self.max_span > 0:
            problems.append(f"max_span = {self.max_span!r}: must be > 0")
        if self.contact_point not in ("state", "table"):
            problems.append(f"contact_point = {self.contact_point!r}: must be 'state' or 'table'")
        if problems:
            raise ValueError("invalid ContactFit: " + "; ".join(problems))


@dataclasses.dataclass
class ContactArrays:
    """Training arrays of the racket residual network, one row per usable racket contact.

    Attributes:
        x: (N, n_inputs) racket-frame inputs (v~, w~[, d]).
        y_base: (N, 6) base-model post-contact (v+, w+), racket frame.
        y_obs: (N, 6) observed post-contact (v+, w+), racket frame.
        distance: (N,) contact distance |d| from the face centre [m].
        event_id, session_id: (N,) ids of the contacts.
        in_segment_id, out_segment_id: (N,) the segments the states were fitted on.
        world_in, world_out: (N, 6) fitted world-frame (velocity, spin) before / after.
        fit_rmse: (N, 2) RMS position residual of the incoming / outgoing fit [m].
        skipped: reason -> event ids of the skipped contacts (:data:`SKIP_REASONS`).
        n_contacts: racket events examined.
        model: name of the model whose racket parameters gave ``y_base``.
    """

    x: np.ndarray
    y_base: np.ndarray
    y_obs: np.ndarray
    distance: np.ndarray
    event_id: np.ndarray
    session_id: np.ndarray
    in_segment_id: np.ndarray
    out_segment_id: np.ndarray
    world_in: np.ndarray
    world_out: np.ndarray
    fit_rmse: np.ndarray
    skipped: dict
    n_contacts: int
    model: str = ""

    def __len__(self) -> int:
        return len(self.x)

    def counts(self) -> dict:
        """reason -> number of contacts skipped for it (only reasons that occurred)."""
        return {k: len(v) for k, v in self.skipped.items() if v}

    def summary(self) -> str:
        """One paragraph: how many racket contacts were used and why the others were not."""
        lines = [f"{len(self)} of {self.n_contacts} racket contacts usable"]
        for k, n in self.counts().items():
            lines.append(f"  skipped {n:5d}: {k} ({SKIP_REASONS[k]})")
        return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# Quaternions (w, x, y, z), racket frame -> world frame


def quat_to_matrix(q) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices (normalised first)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quat(m) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z), w >= 0."""
    m = np.asarray(m, np.float64)
    flat = m.reshape(-1, 3, 3)
    out = np.empty((len(flat), 4))
    for i, r in enumerate(flat):  # Shepperd's method: divide by the largest of the four terms
        tr = np.trace(r)
        cand = [tr, r[0, 0], r[1, 1], r[2, 2]]
        k = int(np.argmax(cand))
        if k == 0:
            s = 2.0 * math.sqrt(1.0 + tr)
            q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        elif k == 1:
            s = 2.0 * math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 1e-300))
            q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
        elif k == 2:
            s = 2.0 * math.sqrt(max(1.0 + r[1, 1] - r[0, 0] - r[2, 2], 1e-300))
            q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
        else:
            s = 2.0 * math.sqrt(max(1.0 + r[2, 2] - r[0, 0] - r[1, 1], 1e-300))
            q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
        q = np.asarray(q)
        out[i] = q / np.linalg.norm(q) * (1.0 if q[0] >= 0 else -1.0)
    return out.reshape(m.shape[:-2] + (4,))


# ----------------------------------------------------------------------------------------------
# State estimation


def fit_contact_state(t, pos, t_contact, degree: int = 2):
    """Least-squares polynomial fit of a short flight, evaluated at the contact time.

    Arguments:
        t: (n,) observation times [s] (n > degree).
        pos: (n, 3) positions [m].
        t_contact: the contact time [s].
        degree: polynomial degree per axis.

    Returns:
        (position (3,), velocity (3,), rmse [m]) at ``t_contact``; rmse is the RMS of the 3-D
        position residuals.
    """
    tau = np.asarray(t, np.float64) - float(t_contact)
    pos = np.asarray(pos, np.float64)
    scale = max(float(np.max(np.abs(tau))), 1e-9)  # conditioning: powers of tau / scale
    a = np.stack([(tau / scale) ** k for k in range(degree + 1)], 1)
    coef, *_ = np.linalg.lstsq(a, pos, rcond=None)
    resid = pos - a @ coef
    rmse = float(np.sqrt(np.mean(np.sum(resid**2, axis=1))))
    return coef[0], coef[1] / scale, rmse


class ObservationIndex:
    """A dataset's observations grouped by flight segment, to look up the samples of a segment
    next to a contact.

    Attributes:
        segments: the dataset's segments table; segment_ids: (S,) its ids.
        t: (N,) observation times [s] (float64); pos: (N, 3) positions [m].
    """

    def __init__(self, ds):
        obs = ds.observations
        self.segments = ds.segments
        self.segment_ids = np.asarray(self.segments["segment_id"], np.int64)
        self._order = np.argsort(obs["segment_id"], kind="stable")  # keeps time order within a segment
        self._sorted = np.asarray(obs["segment_id"])[self._order]
        self.t = np.asarray(obs["t"], np.float64)
        self.pos = ds.positions

    def rows(self, seg_row: int) -> np.ndarray:
        """Observation rows of the segment in row ``seg_row`` of the segments table, in time order."""
        sid = int(self.segment_ids[seg_row])
        lo, hi = np.searchsorted(self._sorted, [sid, sid + 1])
        return self._order[lo:hi]

    def near(self, seg_row: int, t_contact: float, before: bool, fit: ContactFit):
        """(times (n,), positions (n, 3)): the ``fit.n_samples`` samples of a segment nearest to a
        contact, within ``fit.max_span`` of it, on one side (``before`` or after)."""
        idx = self.rows(seg_row)
        t = self.t[idx]
        tc = float(t_contact)
        keep = (t < tc) & (t >= tc - fit.max_span) if before else (t > tc) & (t <= tc + fit.max_span)
        idx = idx[keep]
        idx = idx[-fit.n_samples:] if before else idx[:fit.n_samples]
        return self.t[idx], self.pos[idx]

    def spin(self, seg_row: int) -> tuple[np.ndarray, float]:
        """(spin (3,) [rad/s], confidence) of the segment in row ``seg_row``."""
        seg = self.segments
        return (np.array([seg[k][seg_row] for k in ("spin_x", "spin_y", "spin_z")], np.float64),
                float(seg["spin_conf"][seg_row]))


@dataclasses.dataclass
class ContactEstimate:
    """The ball's estimated state just before and just after a contact (world frame).

    Attributes:
        vel_in, vel_out: (3,) velocity at the contact time [m/s], from the incoming / outgoing fit.
        spin_in, spin_out: (3,) the incoming / outgoing segment's spin [rad/s].
        spin_known: (2,) bool, the incoming / outgoing spin has a confidence of at least
            ``min_spin_conf``.
        rmse: (2,) RMS position residual of the incoming / outgoing fit [m].
    """

    vel_in: np.ndarray
    vel_out: np.ndarray
    spin_in: np.ndarray
    spin_out: np.ndarray
    spin_known: np.ndarray
    rmse: np.ndarray


def estimate_contact(index: ObservationIndex, in_row: int, out_row: int, t_contact: float, fit: ContactFit,
                     need_spin: bool = True) -> tuple[str | None, ContactEstimate | None]:
    """Estimates the ball's state on both sides of a contact (see the module docstring).

    Arguments:
        index: the dataset's :class:`ObservationIndex`.
        in_row, out_row: rows of the incoming and outgoing segments in the segments table (-1: none).
        t_contact: the contact time [s].
        fit: how states are estimated (:class:`ContactFit`).
        need_spin: skip a contact whose segments' spin confidence is below ``fit.min_spin_conf``;
            False keeps it, with ``spin_known`` saying which spin is measured.

    Returns:
        (reason, estimate): a key of :data:`SKIP_REASONS` and None for a contact that cannot be
        used, else None and the :class:`ContactEstimate`.
    """
    if in_row < 0:
        return "no_incoming_segment", None
    if out_row < 0:
        return "no_outgoing_segment", None
    ti, pi = index.near(in_row, t_contact, True, fit)
    if len(ti) < fit.min_samples:
        return "few_incoming_samples", None
    to, po = index.near(out_row, t_contact, False, fit)
    if len(to) < fit.min_samples:
        return "few_outgoing_samples", None
    spin_in, conf_in = index.spin(in_row)
    spin_out, conf_out = index.spin(out_row)
    if need_spin and conf_in < fit.min_spin_conf:
        return "low_spin_conf_in", None
    if need_spin and conf_out < fit.min_spin_conf:
        return "low_spin_conf_out", None
    _, v_in, r_in = fit_contact_state(ti, pi, t_contact, fit.degree)
    _, v_out, r_out = fit_contact_state(to, po, t_contact, fit.degree)
    if max(r_in, r_out) > fit.max_fit_rmse:
        return "bad_fit", None
    return None, ContactEstimate(vel_in=v_in, vel_out=v_out, spin_in=spin_in, spin_out=spin_out,
                                 spin_known=np.array([conf_in, conf_out]) >= fit.min_spin_conf,
                                 rmse=np.array([r_in, r_out]))


def contact_states(ds, event_ids, t_c, in_row, out_row, fit: ContactFit, skipped: dict,
                   progress: Callable | None = None):
    """The ball's world-frame (velocity, spin) just before and just after each contact.

    Shared by the racket (:func:`contact_arrays`) and table (:mod:`ttsim_jax.fit.table`)
    contacts: :func:`estimate_contact` for every contact (see the module docstring).

    Arguments:
        ds: the dataset.
        event_ids, t_c: (n,) the contacts' event ids and times [s] (float64).
        in_row, out_row: (n,) rows in ``ds.segments`` of the incoming / outgoing segment (-1: none).
        fit: how the states are estimated.
        skipped: reason -> list of event ids; contacts lacking what is needed are appended here
            (reasons ``no_incoming_segment`` ... ``bad_fit`` of :data:`SKIP_REASONS`).
        progress: optional ``progress(done, total)``, called every 100 contacts and at the end.

    Returns:
        (vel_in, spin_in, vel_out, spin_out (n, 3), rmse (n, 2), good) with ``good`` the int64
        indices of the contacts whose states were estimated (other rows are zero).
    """
    n = len(event_ids)
    index = ObservationIndex(ds)
    good = []
    vin, win, vout, wout, rmse = (np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)),
                                  np.zeros((n, 2)))
    for i in range(n):
        if progress is not None and (i % 100 == 0):
            progress(i, n)
        reason, est = estimate_contact(index, int(in_row[i]), int(out_row[i]), float(t_c[i]), fit)
        if reason is not None:
            skipped[reason].append(int(event_ids[i]))
            continue
        vin[i], win[i], vout[i], wout[i], rmse[i] = est.vel_in, est.spin_in, est.vel_out, est.spin_out, est.rmse
        good.append(i)
    if progress is not None:
        progress(n, n)
    return vin, win, vout, wout, rmse, np.asarray(good, np.int64)


def model_and_name(model):
    """(Model, name) from a bundled model name, a TOML path or a Model."""
    from ttsim_jax.params import Model, load_model

    if isinstance(model, Model):
        return model, model.name
    return load_model(model), str(model)


def default_inputs(model) -> int:
    """Residual inputs for a model: 8 (conti2026), 6 (durr2026); otherwise 6 for the
    "nakashima" racket kind, 8 for the others, unless the model carries a residual network."""
    return _default_inputs(*model_and_name(model))


def _default_inputs(m, name) -> int:
    if m.residual is not None:
        return m.residual.config.n_inputs
    if name in MODEL_INPUTS:
        return MODEL_INPUTS[name]
    return 6 if m.racket.kind == "nakashima" else 8


@jax.jit
def _frames(racket_params, radius, mass, rpos, rrot, rvel, rang, pos, vel_in, spin_in, vel_out, spin_out, d_table,
            use_table_d):
    from ttsim_jax.state import Racket

    def one(rp, rr, rv, rw, p, vi, wi, vo, wo, dt):
        racket = Racket(pos=rp, rot=rr, vel=rv, ang_vel=rw, face=jnp.zeros(2, rp.dtype))
        st = racket_stage.racket_frame_state(racket_params, racket, radius, p, vi, wi)
        d = jnp.where(use_table_d, dt, st["d"])
        vb, wb = racket_stage.base_response(racket_params, st["v"], st["w"], d, radius, mass)
        rot = st["rot"]
        v_obs = rot.T @ (vo - st["v_surf"])
        w_obs = rot.T @ (wo - st["w_surf"])
        gap = jnp.dot(rot[:, 0], p - rp) - radius
        return (jnp.concatenate([st["v"], st["w"], d]), jnp.concatenate([vb, wb]),
                jnp.concatenate([v_obs, w_obs]), gap)

    return jax.vmap(one)(rpos, rrot, rvel, rang, pos, vel_in, spin_in, vel_out, spin_out, d_table)


def contact_arrays(ds, model="conti2026", n_inputs: int | None = None, fit: ContactFit = ContactFit(),
                   validate: bool = True) -> ContactArrays:
    """Training arrays of the racket residual network from a dataset's racket contacts.

    Arguments:
        ds: a :class:`~ttsim_jax.data.Dataset` with racket events, racket states and segments.
        model: bundled model name, TOML path or :class:`~ttsim_jax.params.Model`; its racket
            parameters give the racket frame convention (racket spin used or not) and ``y_base``,
            its ball the radius and mass.
        n_inputs: 8 (v~, w~, d) or 6 (v~, w~); default :func:`default_inputs`.
        fit: how the contact states are estimated (:class:`ContactFit`).
        validate: validate ``ds`` first.

    Returns:
        :class:`ContactArrays` (float32 ``x``, ``y_base``, ``y_obs``; float64 diagnostics).
    """
    from ttsim_jax.data.batch import racket_contact_batch
    from ttsim_jax.kernel.step import ball_properties

    m, name = model_and_name(model)
    n_inputs = _default_inputs(m, name) if n_inputs is None else int(n_inputs)
    if n_inputs not in (6, 8):
        raise ValueError(f"contact_arrays: n_inputs = {n_inputs!r}, must be 8 or 6")
    radius, mass = (float(v) for v in ball_properties(m))

    batch = racket_contact_batch(ds, validate=validate)  # the join: event <-> racket state <-> segments
    n = int(np.sum(np.asarray(batch.mask)))
    in_row = np.asarray(batch.in_segment)[:n]
    out_row = np.asarray(batch.out_segment)[:n]
    event_ids = np.asarray(ds.rackets["event_id"], np.int64)[:n]
    # Float values come from the tables in float64 (batch arrays follow JAX's default float,
    # float32, which cannot hold absolute times to the sub-millisecond).
    ev = ds.events
    ev_row = {int(e): i for i, e in enumerate(ev["event_id"])}
    rows = np.array([ev_row[int(e)] for e in event_ids], np.int64)
    t_c = np.asarray(ev["t"], np.float64)[rows] if n else np.zeros(0)
    p_c = np.stack([np.asarray(ev[k], np.float64)[rows] for k in "xyz"], -1) if n else np.zeros((0, 3))
    sess = np.asarray(ev["session_id"], np.int64)[rows] if n else np.zeros(0, np.int64)
    rk = ds.rackets
    col = lambda *ks: np.stack([np.asarray(rk[k], np.float64)[:n] for k in ks], -1)  # noqa: E731
    r_pos, r_vel, r_ang = col("x", "y", "z"), col("vx", "vy", "vz"), col("wx", "wy", "wz")
    r_rot = quat_to_matrix(col("qw", "qx", "qy", "qz")) if n else np.zeros((0, 3, 3))
    d_table = col("d_y", "d_z")

    skipped = {k: [] for k in SKIP_REASONS}
    kinds = np.asarray(ev["kind"]).astype(str)
    stateless = np.setdiff1d(np.asarray(ev["event_id"], np.int64)[kinds == "racket"], event_ids)
    skipped["no_racket_state"] = [int(e) for e in stateless]

    vin, win, vout, wout, rmse, good = contact_states(ds, event_ids, t_c, in_row, out_row, fit, skipped)
    seg_ids = np.asarray(ds.segments["segment_id"], np.int64)
    if len(good):
        j = lambda a: jnp.asarray(a[good])  # noqa: E731
        x8, y_base, y_obs, gap = (np.asarray(a, np.float64) for a in _frames(
            m.racket, jnp.asarray(radius), jnp.asarray(mass), j(r_pos), j(r_rot), j(r_vel), j(r_ang), j(p_c), j(vin),
            j(win), j(vout), j(wout), j(d_table), jnp.asarray(fit.contact_point == "table")))
    else:
        x8, y_base, y_obs, gap = np.zeros((0, 8)), np.zeros((0, 6)), np.zeros((0, 6)), np.zeros(0)
    keep = np.ones(len(good), bool)
    checks = (("non_finite", ~(np.isfinite(x8).all(1) & np.isfinite(y_base).all(1) & np.isfinite(y_obs).all(1))),
              ("off_face", np.abs(gap) > fit.max_face_gap),
              ("not_approaching", x8[:, 0] >= 0.0),
              ("not_leaving", y_obs[:, 0] <= 0.0))
    for reason, bad in checks:
        bad = bad & keep
        skipped[reason].extend(int(event_ids[good[k]]) for k in np.flatnonzero(bad))
        keep &= ~bad
    g = good[keep]
    x8, y_base, y_obs = x8[keep], y_base[keep], y_obs[keep]
    f32 = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
    return ContactArrays(
        x=f32(x8[:, :n_inputs]), y_base=f32(y_base), y_obs=f32(y_obs),
        distance=np.linalg.norm(x8[:, 6:8], axis=1), event_id=event_ids[g], session_id=sess[g],
        in_segment_id=seg_ids[in_row[g]] if len(g) else np.zeros(0, np.int64),
        out_segment_id=seg_ids[out_row[g]] if len(g) else np.zeros(0, np.int64),
        world_in=np.concatenate([vin[g], win[g]], 1), world_out=np.concatenate([vout[g], wout[g]], 1),
        fit_rmse=rmse[g], skipped=skipped, n_contacts=n + len(stateless), model=name,
    )


# ----------------------------------------------------------------------------------------------
# A synthetic dataset with known contacts


def _flight(p, v, w, times, kd, km, substeps=20):
    """Positions at ``times`` (n, T) (signed, from the contact) of flights starting at the contact
    state p, v (n, 3) with constant spin w (n, 3): dv/dt = g - kd |v| v + km (w x v), RK4."""
    g = np.array([0.0, 0.0, -9.81])

    def acc(v_):
        return g - kd * np.linalg.norm(v_, axis=1, keepdims=True) * v_ + km * np.cross(w, v_)

    out = np.zeros(times.shape + (3,))
    prev = np.zeros(len(p))
    for k in range(times.shape[1]):
        h = (times[:, k] - prev)[:, None] / substeps
        for _ in range(substeps):
            k1p, k1v = v, acc(v)
            k2p, k2v = v + 0.5 * h * k1v, acc(v + 0.5 * h * k1v)
            k3p, k3v = v + 0.5 * h * k2v, acc(v + 0.5 * h * k2v)
            k4p, k4v = v + h * k3v, acc(v + h * k3v)
            p = p + h / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
            v = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        out[:, k] = p
        prev = times[:, k]
    return out


def _small_rotations(rng, n, max_angle):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = rng.uniform(0.0, max_angle, n)
    k = np.zeros((n, 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - np.swapaxes(k, 1, 2)
    s, c = np.sin(ang)[:, None, None], np.cos(ang)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def draw_contact_states(rng: np.random.Generator, n: int, max_speed: float = 15.0, max_spin: float = 600.0):
    """Random racket-frame pre-contact states: (v~ (n, 3), w~ (n, 3), d (n, 2)).

    Speed 1..max_speed m/s within 60 degrees of the face normal (v~_x < 0), spin up to ``max_spin``
    rad/s in a uniform direction, d uniform over a 7.5 cm disc.
    """
    rad = 0.075 * np.sqrt(rng.uniform(0.0, 1.0, n))
    phi = rng.uniform(0.0, 2 * math.pi, n)
    d = np.stack([rad * np.cos(phi), rad * np.sin(phi)], 1)
    speed = rng.uniform(1.0, max_speed, n)
    cos_t = rng.uniform(0.5, 1.0, n)
    sin_t = np.sqrt(1.0 - cos_t**2)
    psi = rng.uniform(0.0, 2 * math.pi, n)
    v_t = speed[:, None] * np.stack([-cos_t, sin_t * np.cos(psi), sin_t * np.sin(psi)], 1)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    w_t = rng.uniform(0.0, max_spin, n)[:, None] * direction
    return v_t, w_t, d


def synthetic_contact_dataset(n: int, seed: int = 0, model="conti2026", residual_fn: Callable | None = None,
                              rate: float = 200.0, span: float = 0.06, noise: float = 0.0, max_speed: float = 15.0,
                              max_spin: float = 600.0, kd: float = 0.11, km: float = 1e-3):
    """A dataset of ``n`` racket contacts with known pre- and post-contact states.

    Each contact is its own session: a flight of ``span`` seconds into a racket (random pose
    facing -x near x = 1.4 m, random linear and angular velocity), one ``racket`` event with the
    racket state, and a flight of ``span`` seconds out. The racket-frame pre-contact state
    (v~, w~, d) is drawn (speed 1..max_speed m/s within 60 degrees of the normal, spin up to
    ``max_spin`` rad/s, d within 7.5 cm), the post-contact state is the model's base response plus
    ``residual_fn(x8)`` (none by default), and both are turned into the world frame with the
    model's racket frame convention. Flights: gravity, drag ``kd`` |v| v and Magnus ``km`` w x v,
    sampled at ``rate`` Hz (the sampling phase is random per contact), optional Gaussian position
    noise ``noise`` [m]. Spin is given to every sample with confidence 1.

    Arguments:
        n: number of contacts.
        seed: NumPy seed.
        model: the model name / path / :class:`~ttsim_jax.params.Model` (racket parameters).
        residual_fn: fn(x (N, 8)) -> (N, 6) racket-frame residual added to the base response, or
            None.
        rate, span, noise, max_speed, max_spin, kd, km: see above.

    Returns:
        (dataset, truth) with ``truth`` a dict of float64 arrays: ``x`` (n, 8), ``y_base``,
        ``y_obs`` (n, 6) in the racket frame, ``distance`` (n,), ``event_id`` (n,), and the
        world-frame ``vel_in``, ``spin_in``, ``vel_out``, ``spin_out`` (n, 3).
    """
    from ttsim_jax.data import Dataset, Metadata
    from ttsim_jax.kernel.step import ball_properties

    m, name = model_and_name(model)
    radius, mass = (float(v) for v in ball_properties(m))
    rng = np.random.default_rng(seed)
    base_rot = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])  # normal along -x
    rot = _small_rotations(rng, n, math.radians(30.0)) @ base_rot
    # heights spread over 0.8 m: the validator reads z reversals clustered at one height as a
    # misplaced table surface
    r_pos = np.stack([rng.uniform(1.3, 1.5, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0.1, 0.9, n)], 1)
    r_vel = np.stack([rng.uniform(-6.0, 0.0, n), rng.uniform(-1.0, 1.0, n), rng.uniform(0.0, 3.0, n)], 1)
    r_ang = rng.uniform(-10.0, 10.0, (n, 3))
    v_t, w_t, d = draw_contact_states(rng, n, max_speed, max_spin)

    # ball centre at the contact: one radius in front of the face at d
    local = np.concatenate([np.full((n, 1), radius), d], 1)
    p_c = r_pos + np.einsum("nij,nj->ni", rot, local)
    offset = p_c - radius * rot[:, :, 0] - r_pos
    w_surf = r_ang if racket_stage.uses_racket_spin(m.racket) else np.zeros_like(r_ang)
    v_surf = r_vel + np.cross(w_surf, offset)
    vel_in = np.einsum("nij,nj->ni", rot, v_t) + v_surf
    spin_in = np.einsum("nij,nj->ni", rot, w_t) + w_surf

    x8 = np.concatenate([v_t, w_t, d], 1)

    def base(v, w, dd):
        return racket_stage.base_response(m.racket, v, w, dd, radius, mass)

    vb, wb = jax.vmap(base)(jnp.asarray(v_t), jnp.asarray(w_t), jnp.asarray(d))
    y_base = np.concatenate([np.asarray(vb), np.asarray(wb)], 1).astype(np.float64)
    y_obs = y_base + (0.0 if residual_fn is None else np.asarray(residual_fn(x8), np.float64))
    vel_out = np.einsum("nij,nj->ni", rot, y_obs[:, :3]) + v_surf
    spin_out = np.einsum("nij,nj->ni", rot, y_obs[:, 3:]) + w_surf

    k = int(math.floor(span * rate))
    phase = rng.uniform(0.05, 0.95, (n, 2)) / rate
    steps = np.arange(k) / rate
    t_in = -(phase[:, :1] + steps[None, :])  # (n, k), descending from the contact
    t_out = phase[:, 1:] + steps[None, :]
    p_in = _flight(p_c, vel_in, spin_in, t_in, kd, km)[:, ::-1]
    p_out = _flight(p_c, vel_out, spin_out, t_out, kd, km)
    t_in = t_in[:, ::-1]
    # Gravity is uniform, so lifting a whole contact changes nothing but keeps steep flights above
    # the floor (validation refuses balls below it).
    lift = np.maximum(-0.5 - np.minimum(p_in[..., 2].min(1), p_out[..., 2].min(1)), 0.0)
    for a in (p_in, p_out):
        a[..., 2] += lift[:, None]
    p_c[:, 2] += lift
    r_pos[:, 2] += lift
    t_c = 1.0
    times = np.concatenate([t_in, t_out], 1) + t_c
    pos = np.concatenate([p_in, p_out], 1)
    if noise:
        pos = pos + rng.normal(0.0, noise, pos.shape)
    spins = np.concatenate([np.repeat(spin_in[:, None], k, 1), np.repeat(spin_out[:, None], k, 1)], 1)
    ds = Dataset.from_arrays(
        np.repeat(np.arange(n), 2 * k), times.reshape(-1), pos.reshape(-1, 3), spin=spins.reshape(-1, 3),
        events=dict(session_id=np.arange(n), t=np.full(n, t_c), kind=np.full(n, "racket", object), pos=p_c),
        rackets=dict(pos=r_pos, quat=matrix_to_quat(rot), vel=r_vel, ang_vel=r_ang, contact=d),
        metadata=Metadata(source=f"ttsim_jax.fit.contacts.synthetic_contact_dataset(n={n}, seed={seed}, "
                                 f"model={name!r})", notes="synthetic racket contacts with known states"),
    )
    truth = dict(x=x8, y_base=y_base, y_obs=y_obs, distance=np.linalg.norm(d, axis=1), event_id=np.arange(n),
                 vel_in=vel_in, spin_in=spin_in, vel_out=vel_out, spin_out=spin_out)
    return ds, truth
