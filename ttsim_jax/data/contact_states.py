"""The ball's state just before and just after a contact, estimated from the observations alone,
or read where the dataset measured it directly (its ``contact_states`` table: a racket-bounce rig
such as tt_rackets, a tracker that writes states).

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

Contacts lacking what is needed are skipped and counted by reason (:data:`SKIP_REASONS`). A
contact with a row in ``contact_states`` takes its states from there, whatever its segments hold
(fit residual 0, the spins' confidences as given).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from .tables import id_index, rows_of

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
        self._order, self._sorted = ds.observations_by_segment()
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


#: Kinds of event whose states :class:`Contacts` estimates (with a racket state, any kind).
CONTACT_KINDS = ("table", "racket")
#: The reasons :meth:`Contacts.estimate` gives, in the order they are checked; the spin's
#: (``low_spin_conf_*``) come after the samples' and before ``bad_fit`` (:meth:`Contacts.skip_reasons`).
_SAMPLE_REASONS = ("no_incoming_segment", "no_outgoing_segment", "few_incoming_samples", "few_outgoing_samples")


@dataclasses.dataclass(frozen=True)
class Contacts:
    """A dataset's contacts with the ball's states on both sides estimated from the observations
    alone (see the module docstring), one row per table or racket event: built once per dataset and
    :class:`ContactFit` (:meth:`ttsim_jax.data.Dataset.contacts`) and read by the evaluation, the
    fits and the diagnosis, each applying its own checks.

    Attributes:
        fit: how the states were estimated.
        event_id, kind, session_id: (E,) the events'; t: (E,) contact time [s] (float64);
        pos: (E, 3) the event's ball position [m].
        in_row, out_row: (E,) rows of the incoming and outgoing segments in ``ds.segments`` (-1: none).
        vel_in, vel_out: (E, 3) world-frame velocity at the contact [m/s] from the polynomial fits
            (NaN where not estimated).
        spin_in, spin_out: (E, 3) the incoming / outgoing segment's spin [rad/s] (zeros without one);
        spin_conf: (E, 2) their confidences (0 without one).
        rmse: (E, 2) RMS position residual of each fit [m] (NaN where not fitted).
        reason: (E,) the :data:`SKIP_REASONS` key of a contact whose states are not estimated, spin
            aside (None where they are; :meth:`skip_reasons` adds the spin's).
        measured: (E,) bool, the states come from the dataset's ``contact_states`` table (not
            estimated from observations).
    """

    fit: ContactFit
    event_id: np.ndarray
    kind: np.ndarray
    session_id: np.ndarray
    t: np.ndarray
    pos: np.ndarray
    in_row: np.ndarray
    out_row: np.ndarray
    vel_in: np.ndarray
    vel_out: np.ndarray
    spin_in: np.ndarray
    spin_out: np.ndarray
    spin_conf: np.ndarray
    rmse: np.ndarray
    reason: np.ndarray
    measured: np.ndarray

    def __len__(self) -> int:
        return len(self.event_id)

    @property
    def spin_known(self) -> np.ndarray:
        """(E, 2) bool: the incoming / outgoing spin's confidence is at least ``fit.min_spin_conf``."""
        return self.spin_conf >= self.fit.min_spin_conf

    def rows(self, event_ids) -> np.ndarray:
        """(n,) int64 rows of ``event_ids`` here, -1 for an event that is not a contact."""
        return rows_of(id_index(self.event_id), event_ids)

    def skip_reasons(self, need_spin: bool = True) -> np.ndarray:
        """(E,) why each contact cannot be used (None: it can), with ``need_spin`` a spin confidence
        below ``fit.min_spin_conf`` on either side skipping it too (as :func:`estimate_contact`)."""
        out = self.reason.copy()
        if need_spin:
            known = self.spin_known
            open_ = np.array([r not in _SAMPLE_REASONS for r in self.reason], bool)
            out[open_ & ~known[:, 1]] = "low_spin_conf_out"
            out[open_ & ~known[:, 0]] = "low_spin_conf_in"
        return out

    def states(self, event_ids, skipped: dict, need_spin: bool = True):
        """The world-frame (velocity, spin) just before and just after the contacts ``event_ids``.

        Arguments:
            event_ids: (n,) contact event ids.
            skipped: reason -> list of event ids; the contacts that cannot be used are appended
                here (:meth:`skip_reasons`).
            need_spin: as for :meth:`skip_reasons`.

        Returns:
            (vel_in, spin_in, vel_out, spin_out (n, 3), rmse (n, 2), good) with ``good`` the int64
            indices of the contacts whose states were estimated (other rows are zero).
        """
        ids = np.asarray(event_ids, np.int64).reshape(-1)
        rows = self.rows(ids)
        if (rows < 0).any():
            raise ValueError(f"event {int(ids[rows < 0][0])} is not a contact (kinds {CONTACT_KINDS} or a racket state)")
        reasons = self.skip_reasons(need_spin)[rows]
        good = np.flatnonzero(np.array([r is None for r in reasons], bool))
        for e, r in zip(ids, reasons):
            if r is not None:
                skipped[r].append(int(e))
        zeros = lambda k: np.zeros((len(ids), k))  # noqa: E731
        vin, win, vout, wout, rmse = zeros(3), zeros(3), zeros(3), zeros(3), zeros(2)
        g = rows[good]
        vin[good], win[good], vout[good], wout[good] = self.vel_in[g], self.spin_in[g], self.vel_out[g], self.spin_out[g]
        rmse[good] = self.rmse[g]
        return vin, win, vout, wout, rmse, good.astype(np.int64)

    @classmethod
    def estimate(cls, ds, fit: ContactFit, progress: Callable | None = None) -> "Contacts":
        """Estimates every contact of ``ds`` (:func:`estimate_contact`, spin aside); ``progress``:
        optional ``progress(done, total)``, called every 100 contacts and at the end. Prefer
        :meth:`ttsim_jax.data.Dataset.contacts`, which estimates them once."""
        ev = ds.events
        kinds = np.asarray(ev["kind"]).astype(str)
        ids_all = np.asarray(ev["event_id"], np.int64)
        rows = np.flatnonzero(np.isin(kinds, CONTACT_KINDS) | (ds.racket_rows(ids_all) >= 0))
        ids = ids_all[rows]
        in_row, out_row = ds.segments_around(ids)
        t_c = np.asarray(ev["t"], np.float64)[rows]
        index = ds.observation_index()
        n = len(ids)
        nan = lambda k: np.full((n, k), np.nan)  # noqa: E731
        vin, vout, rmse = nan(3), nan(3), nan(2)
        win, wout, conf = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 2))
        reason = np.full(n, None, object)
        for i in range(n):
            if progress is not None and (i % 100 == 0):
                progress(i, n)
            if in_row[i] >= 0 and out_row[i] >= 0:
                (win[i], conf[i, 0]), (wout[i], conf[i, 1]) = index.spin(int(in_row[i])), index.spin(int(out_row[i]))
            why, est = estimate_contact(index, int(in_row[i]), int(out_row[i]), float(t_c[i]), fit, need_spin=False)
            reason[i] = why
            if est is not None:
                vin[i], vout[i], rmse[i] = est.vel_in, est.vel_out, est.rmse
        if progress is not None:
            progress(n, n)
        measured = _read_measured(ds, ids, vin, win, vout, wout, conf, rmse, reason)
        return cls(fit=fit, event_id=ids, kind=kinds[rows], session_id=np.asarray(ev["session_id"], np.int64)[rows],
                   t=t_c, pos=np.stack([np.asarray(ev[k], np.float64)[rows] for k in "xyz"], -1).reshape(n, 3),
                   in_row=in_row, out_row=out_row, vel_in=vin, vel_out=vout, spin_in=win, spin_out=wout,
                   spin_conf=conf, rmse=rmse, reason=reason, measured=measured)


def _read_measured(ds, ids, vin, win, vout, wout, conf, rmse, reason) -> np.ndarray:
    """Writes the ``contact_states`` rows of contacts ``ids`` over the estimates (in place);
    returns which contacts had one."""
    cs = ds.contact_states
    rows = rows_of(id_index(cs["event_id"]), ids)
    hit = np.flatnonzero(rows >= 0)
    if hit.size:
        r = rows[hit]
        col = lambda p: np.stack([np.asarray(cs[f"{p}{a}"], np.float64)[r] for a in "xyz"], -1)  # noqa: E731
        vin[hit], win[hit], vout[hit], wout[hit] = col("v_in_"), col("w_in_"), col("v_out_"), col("w_out_")
        conf[hit] = np.stack([np.asarray(cs["spin_conf_in"], np.float64)[r],
                              np.asarray(cs["spin_conf_out"], np.float64)[r]], -1)
        rmse[hit] = 0.0
        reason[hit] = None
    return rows >= 0
