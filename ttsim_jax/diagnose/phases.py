"""The measured items of each phase, gathered once for the diagnosis, with their regime quantities.

* *flight*: every flight segment with at least ``min_samples`` observations (only those with a
  measured spin when the data has any), padded to one capacity: absolute sample times, positions,
  mask, the segment's spin and session. The items of the "where" analysis are the observations.
* *table*: every usable table bounce, estimated as in ``ttsim evaluate``
  (:func:`ttsim_jax.evaluate.stages.table_stage`): contact point, pre- and post-bounce velocity
  and spin (the pre-bounce spin 0 where it is not measured: such a bounce is compared in its
  normal velocity only).
* *racket*: every usable racket contact with a racket state, in the racket frame
  (:func:`ttsim_jax.fit.racket_arrays.contact_arrays`): inputs x = (v~, w~, d), the observation, the
  racket's rotation (for racket-state error sizes).

Nothing here reads the generator's truth files: any dataset in the format works.

Regime quantities (:data:`REGIMES`) are computed from measured quantities only: speed [m/s],
spin magnitude [rad/s], spin ratio r|w|/|v|, spin axis (the dominant component of the spin
relative to the velocity: topspin, backspin, sidespin or gyro), impact angle [deg] (below the
surface for table contacts, from the face normal for racket contacts), contact distance on the
racket face [m], position on the table x and y [m], time since the last contact [s].
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ttsim_jax.data.contact_states import ContactFit
from ttsim_jax.diagnose.defaults import MAX_SEGMENTS

#: Regime quantities: name -> (label, unit).
REGIMES = {
    "speed": ("speed", "m/s"),
    "spin": ("spin magnitude", "rad/s"),
    "spin_ratio": ("spin ratio r|w|/|v|", "1"),
    "spin_axis": ("spin axis", ""),
    "impact_angle": ("impact angle", "deg"),
    "distance": ("contact distance on the face", "m"),
    "x": ("position along the table x", "m"),
    "y": ("position across the table y", "m"),
    "since_contact": ("time since the last contact", "s"),
}
#: Categories of the spin axis (:func:`spin_axis`).
AXES = ("topspin", "backspin", "sidespin", "gyro")
#: Observations kept per flight segment (its first ones): the padded length bounds the cost of every
#: flight evaluation, and 128 samples at 200 Hz (0.64 s) hold most of a flight's deviation.
MAX_SAMPLES = 128
#: Padded lengths of the flight arrays (samples).
CAPACITIES = (64, 128, 256, 512, 1024, 4096)


@dataclasses.dataclass
class Flights:
    """Flight segments padded to one shape (S_pad, T).

    Attributes:
        t0: (S,) absolute time of the first sample [s]; tau: (S, T) times from t0, padding repeats
            the last; pos: (S, T, 3); mask: (S, T) 1 for real samples; spin: (S, 3) the spin flown
            (measured, latent or 0: ``spin_source``);
            session: (S,) session index (0..n_sessions-1); segment_id: (S,); n: number of real
            segments (rows beyond are padding with mask 0); spin_source: (S,) where each segment's
            spin came from (``"measured"``, ``"latent"``, ``"zero"``; ``""`` on padding).
    """

    t0: np.ndarray
    tau: np.ndarray
    pos: np.ndarray
    mask: np.ndarray
    spin: np.ndarray
    session: np.ndarray
    segment_id: np.ndarray
    n: int
    spin_source: np.ndarray | None = None


@dataclasses.dataclass
class ContactItems:
    """The contacts of one kind (table or racket) as the diagnosis compares them, one row each
    (from :meth:`ttsim_jax.data.Dataset.contacts`, through the evaluation's and the racket fit's checks).

    Attributes:
        event_id: (N,); session: (N,) session index; pos: (N, 3) contact point (world);
        x: (N, 8) table: (v_in, w_in, 0, 0) world frame; racket: (v~, w~, d) racket frame;
        y_obs: (N, 6) observed post-contact (v, w) in the same frame; spin_known: (N,) whether
        the post-contact spin is measured (and the pre-contact one); spin_in_known: (N,) whether the
        pre-contact spin is measured (without it a table bounce's tangential velocity, which the
        spin drives, is not compared); correction: (N, 6) the model's
        residual network's correction (zeros without one); rot: (N, 3, 3) racket frame (identity
        for the table); world_in, world_out: (N, 6) world-frame pre- and post-contact (v, w) as
        estimated; since: (N,) time since the previous contact [s]; t: (N,) contact time [s];
        spin_dt: (N, 2) from the incoming segment's mean sample time to the contact and from the
        contact to the outgoing segment's [s] (:func:`contact_times`).
    """

    event_id: np.ndarray
    session: np.ndarray
    pos: np.ndarray
    x: np.ndarray
    y_obs: np.ndarray
    spin_known: np.ndarray
    spin_in_known: np.ndarray
    correction: np.ndarray
    rot: np.ndarray
    world_in: np.ndarray
    world_out: np.ndarray
    since: np.ndarray
    t: np.ndarray
    spin_dt: np.ndarray

    def __len__(self) -> int:
        return len(self.event_id)


@dataclasses.dataclass
class Phases:
    """What the diagnosis works on; a phase the data cannot support is None with a reason in
    ``skipped``. ``sessions``: the dataset's session ids in index order."""

    flights: Flights | None
    table: ContactItems | None
    racket: ContactItems | None
    sessions: np.ndarray
    skipped: dict
    left_out: dict = dataclasses.field(default_factory=dict)


def _capacity(n: int) -> int:
    for c in CAPACITIES:
        if n <= c:
            return c
    raise ValueError(f"a flight segment of {n} samples is longer than {CAPACITIES[-1]}")


def pad_rows(n: int, multiple: int = 32) -> int:
    """Rows of a padded batch of n items: a multiple of ``multiple`` (one compiled shape for
    similar sizes)."""
    return max(multiple, -(-n // multiple) * multiple)


def flights(ds, session_index: dict, min_samples: int = 5, min_spin_conf: float = 0.5,
            max_samples: int = MAX_SAMPLES, max_segments: int | None = MAX_SEGMENTS, seed: int = 0, *, model=None,
            spin: str = "measured", exclude=()) -> Flights | None:
    """The dataset's flight segments padded to one shape (see :class:`Flights`); None without any.
    Segments longer than ``max_samples`` keep their first ``max_samples`` observations; of more
    than ``max_segments`` segments (None: no limit) a seeded random subset is kept.

    ``spin`` says where a segment's spin comes from, as :func:`ttsim_jax.fit.flight.segment_rmse`'s:
    ``"measured"`` (the segments with a measured spin of confidence >= ``min_spin_conf`` when the
    data has any; else every segment, with spin 0), ``"auto"`` (every segment: the measured spin
    where there is one, elsewhere the latent spin of :mod:`ttsim_jax.fit.latent_spin` fitted under
    ``model`` from the samples kept), ``"latent"`` (the latent spin everywhere) or ``"zero"``.
    A segment too short for a latent spin flies with spin 0; :attr:`Flights.spin_source` says which.
    The segments of ``exclude`` (ids) are left out."""
    from ttsim_jax.fit.segment_batches import dataset_segments
    from ttsim_jax.fit.choices import SPIN_SOURCES
    from ttsim_jax.fit.choices import LATENT_MIN_SAMPLES

    if spin not in SPIN_SOURCES:
        raise ValueError(f"spin = {spin!r}: must be one of {SPIN_SOURCES}")
    if spin in ("auto", "latent") and model is None:
        raise ValueError(f"spin = {spin!r} needs the model the latent spin is fitted under")
    ids, times, positions, spins, conf = dataset_segments(ds, min_samples)
    times = [t[:max_samples] for t in times]
    positions = [p[:max_samples] for p in positions]
    if not len(ids):
        return None
    known = conf >= min_spin_conf
    keep = known.copy() if spin == "measured" and known.any() else np.ones(len(ids), bool)
    keep &= ~np.isin(ids, np.asarray(exclude, np.int64))
    if not keep.any():
        return None
    idx = np.flatnonzero(keep)
    if max_segments is not None and len(idx) > max_segments:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_segments, replace=False))
    source = np.where(known[idx] & (spin in ("auto", "measured")), "measured", "zero").astype("U8")
    flown = np.where((source == "measured")[:, None], spins[idx], 0.0)
    fittable = np.array([len(times[i]) >= LATENT_MIN_SAMPLES for i in idx], bool)
    latent = fittable & ((source != "measured") if spin == "auto" else (spin == "latent"))
    if latent.any():
        from ttsim_jax.fit.latent_spin import fit_latent_spin

        rows = np.flatnonzero(latent)
        ls = fit_latent_spin([times[idx[r]] for r in rows], [positions[idx[r]] for r in rows], model,
                             min_samples=LATENT_MIN_SAMPLES)
        flown[rows] = np.where(ls.ok[:, None], ls.spin, 0.0)
        source[rows] = np.where(ls.ok, "latent", "zero")
    session_of = dict(zip(np.asarray(ds.segments["segment_id"]).tolist(), np.asarray(ds.segments["session_id"]).tolist()))
    s, t = pad_rows(len(idx)), _capacity(max(len(times[i]) for i in idx))
    out = Flights(t0=np.zeros(s), tau=np.zeros((s, t)), pos=np.zeros((s, t, 3)), mask=np.zeros((s, t)),
                  spin=np.zeros((s, 3)), session=np.zeros(s, np.int64), segment_id=np.full(s, -1, np.int64), n=len(idx),
                  spin_source=np.full(s, "", "U8"))
    out.spin_source[: len(idx)] = source
    for row, i in enumerate(idx):
        ti = np.asarray(times[i], np.float64)
        k = len(ti)
        out.t0[row] = ti[0]
        out.tau[row, :k] = ti - ti[0]
        out.tau[row, k:] = ti[-1] - ti[0]
        out.pos[row, :k] = positions[i]
        out.pos[row, k:] = positions[i][-1]
        out.mask[row, :k] = 1.0
        out.spin[row] = flown[row]
        out.session[row] = session_index[session_of[int(ids[i])]]
        out.segment_id[row] = ids[i]
    return out


def contact_times(ds, event_ids) -> dict:
    """Times around each contact [s]: ``t`` (N,) the contact's; ``since`` (N,) from the start of the
    incoming segment (NaN without one); ``spin_dt`` (N, 2) from the incoming segment's mean sample
    time to the contact and from the contact to the outgoing segment's (0 without one): a segment's
    spin is the mean of its samples' estimates, the spin at its mean sample time when it changes
    linearly in flight."""
    in_rows, out_rows = ds.segments_around(event_ids)
    t_c = np.asarray(ds.events["t"], np.float64)[ds.event_rows(event_ids)]
    t_obs = np.asarray(ds.observations["t"], np.float64)
    seg_ids = np.asarray(ds.segments["segment_id"])
    order, sorted_ids = ds.observations_by_segment()
    lo = np.searchsorted(sorted_ids, seg_ids)
    hi = np.searchsorted(sorted_ids, seg_ids, side="right")
    first = np.array([t_obs[order[a]] if b > a else np.nan for a, b in zip(lo, hi)])
    mean = np.array([t_obs[order[a:b]].mean() if b > a else np.nan for a, b in zip(lo, hi)])
    # NaN for a contact without the segment (as every contact of a rig that measured states, not flights)
    at = lambda values, rows: np.append(values, np.nan)[np.where(rows >= 0, rows, len(values))]  # noqa: E731
    spin_dt = np.nan_to_num(np.stack([t_c - at(mean, in_rows), at(mean, out_rows) - t_c], 1))
    return dict(t=t_c, since=t_c - at(first, in_rows), spin_dt=spin_dt)


def table_contacts(ds, model, session_index: dict, fit: ContactFit) -> tuple[ContactItems | None, str]:
    """The usable table bounces (see :class:`ContactItems`), or (None, reason)."""
    from ttsim_jax.evaluate.stages import EvaluateSettings, table_stage
    from ttsim_jax.results import Skipped

    res = table_stage(ds, [("model", model)], EvaluateSettings(fit=fit))
    if isinstance(res, Skipped):
        return None, res.reason
    ids = res.event_id
    ev = ds.events
    rows = ds.event_rows(ids)
    pos = np.stack([np.asarray(ev[k], np.float64)[rows] for k in "xyz"], -1)
    sess = np.array([session_index[int(s)] for s in np.asarray(ev["session_id"])[rows]], np.int64)
    n = len(ids)
    x = np.concatenate([res.pre, np.zeros((n, 2))], 1)
    times = contact_times(ds, ids)
    return ContactItems(event_id=ids, session=sess, pos=pos, x=x, y_obs=res.post, spin_known=res.spin_known.all(1),
                    spin_in_known=res.spin_known[:, 0], correction=np.zeros((n, 6)),
                    rot=np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), world_in=res.pre, world_out=res.post,
                    since=times["since"], t=times["t"], spin_dt=times["spin_dt"]), ""


def racket_contacts(ds, model, session_index: dict, fit: ContactFit) -> tuple[ContactItems | None, str]:
    """The usable racket contacts in the racket frame (see :class:`ContactItems`), or (None, reason)."""
    from ttsim_jax.evaluate.stages import NO_RACKET_STATES, no_usable_contacts
    from ttsim_jax.fit.network_evaluation import predict
    from ttsim_jax.fit.racket_arrays import contact_arrays
    from ttsim_jax.physics.rotations import quat_to_matrix

    if len(ds.rackets["event_id"]) == 0:
        return None, NO_RACKET_STATES
    a = contact_arrays(ds, model, n_inputs=8, fit=fit, validate=False)
    if not len(a):
        return None, no_usable_contacts(a.n_contacts, a.counts()).reason
    corr = np.zeros((len(a), 6))
    if model.residual is not None:
        y, _, _ = predict(model.residual, a.x[:, :model.residual.config.n_inputs], a.y_base)
        corr = y - np.asarray(a.y_base, np.float64)
    rk, ev = ds.rackets, ds.events
    rrows, rows = ds.racket_rows(a.event_id), ds.event_rows(a.event_id)
    q = np.stack([np.asarray(rk[k], np.float64)[rrows] for k in ("qw", "qx", "qy", "qz")], -1).reshape(-1, 4)
    pos = np.stack([np.asarray(ev[k], np.float64)[rows] for k in "xyz"], -1).reshape(-1, 3)
    sess = np.array([session_index[int(s)] for s in a.session_id], np.int64)
    times = contact_times(ds, a.event_id)
    return ContactItems(event_id=a.event_id, session=sess, pos=pos, x=np.asarray(a.x, np.float64),
                    y_obs=np.asarray(a.y_obs, np.float64), spin_known=np.ones(len(a), bool),
                    spin_in_known=np.ones(len(a), bool), correction=corr, rot=quat_to_matrix(q),
                    world_in=a.world_in, world_out=a.world_out, since=times["since"], t=times["t"],
                    spin_dt=times["spin_dt"]), ""


def collect(ds, model, fit: ContactFit = ContactFit(), min_samples: int = 5, phases=("flight", "table", "racket"),
            max_samples: int = MAX_SAMPLES, max_segments: int | None = MAX_SEGMENTS, seed: int = 0,
            spin: str = "measured") -> Phases:
    """Every phase's items of ``ds`` for ``model`` (its ball radius, its racket frame convention);
    see :func:`flights` for ``max_samples``, ``max_segments``, ``seed`` and ``spin``."""
    sessions = np.unique(np.asarray(ds.sessions["session_id"], np.int64)) if len(ds.sessions["session_id"]) else \
        np.unique(np.asarray(ds.segments["session_id"], np.int64))
    index = {int(s): k for k, s in enumerate(sessions)}
    skipped, left_out = {}, {}
    fl = None
    if "flight" in phases:
        from ttsim_jax.data.speeds import non_flights

        # a segment no free flight can give (a ball rolling or resting in it, a contact or a
        # tracking error) would be scored as the model's flight error: one such segment of
        # thousands can make the whole phase a gap
        bad = non_flights(ds)
        if bad.size:
            left_out["flight"] = {"no free flight (validation's acceleration check)": int(bad.size)}
        fl = flights(ds, index, min_samples, fit.min_spin_conf, max_samples, max_segments, seed, model=model,
                     spin=spin, exclude=bad)
    if fl is None and "flight" in phases:
        skipped["flight"] = f"no flight segment with at least {min_samples} observations"
    tb = rk = None
    if "table" in phases:
        tb, why = table_contacts(ds, model, index, fit)
        if tb is None:
            skipped["table"] = why
    if "racket" in phases:
        rk, why = racket_contacts(ds, model, index, fit)
        if rk is None:
            skipped["racket"] = why
    return Phases(flights=fl, table=tb, racket=rk, sessions=sessions, skipped=skipped, left_out=left_out)


# ---------------------------------------------------------------------------------------------- regimes
def spin_axis(vel, spin) -> np.ndarray:
    """(N,) index into :data:`AXES`: the dominant component of the spin relative to the velocity.

    Components: along z x v_h (top- or backspin, v_h the horizontal velocity's direction), along
    z (sidespin) and along v_h (gyro spin).
    """
    v, w = np.asarray(vel, np.float64).reshape(-1, 3), np.asarray(spin, np.float64).reshape(-1, 3)
    h = v * np.array([1.0, 1.0, 0.0])
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-9)
    top = np.cross(np.array([0.0, 0.0, 1.0]), h)
    c_top, c_side, c_gyro = np.sum(w * top, 1), w[:, 2], np.sum(w * h, 1)
    k = np.argmax(np.abs(np.stack([c_top, c_side, c_gyro], 1)), axis=1)
    return np.where(k == 0, np.where(c_top >= 0, 0, 1), k + 1).astype(np.float64)


def kinematic_regimes(vel, spin, radius: float) -> dict:
    """speed, spin, spin_ratio, spin_axis of (N, 3) velocities and spins."""
    v, w = np.linalg.norm(vel, axis=1), np.linalg.norm(spin, axis=1)
    return dict(speed=v, spin=w, spin_ratio=radius * w / np.maximum(v, 1e-9), spin_axis=spin_axis(vel, spin))


def contact_regimes(c: ContactItems, kind: str, radius: float) -> dict:
    """Regime quantities of contacts (see the module docstring)."""
    out = kinematic_regimes(c.world_in[:, :3], c.world_in[:, 3:], radius)
    if kind == "table":
        v = c.world_in[:, :3]
        out["impact_angle"] = np.degrees(np.arctan2(-v[:, 2], np.linalg.norm(v[:, :2], axis=1)))
    else:
        v = c.x[:, :3]
        out["impact_angle"] = np.degrees(np.arctan2(np.linalg.norm(v[:, 1:], axis=1), -v[:, 0]))
        out["distance"] = np.linalg.norm(c.x[:, 6:8], axis=1)
    out["x"], out["y"] = c.pos[:, 0], c.pos[:, 1]
    out["since_contact"] = c.since
    return out
