"""The ball's state just before and just after a contact, estimated from the observations alone.

No model enters: the racket residual's training arrays (:mod:`ttsim_jax.fit.racket_arrays`), the
table fit's bounces (:mod:`ttsim_jax.fit.table_bounces`), the evaluation and the gap diagnosis all
start from these estimates.

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
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

#: Why a contact is not used: the estimation's reasons here, and those of the checks the racket
#: arrays make on the estimates in the racket frame (no_racket_state, off_face, not_approaching,
#: not_leaving, non_finite).
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

    Shared by the racket (:func:`ttsim_jax.fit.racket_arrays.contact_arrays`) and table
    (:func:`ttsim_jax.fit.table_bounces.table_bounces`) contacts: :func:`estimate_contact` for every contact (see the module docstring).

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
