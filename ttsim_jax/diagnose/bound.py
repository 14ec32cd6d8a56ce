"""How far the gap could shrink at all: a model-free correction per phase, fitted on the training
split and scored on the held-out split exactly as a candidate effect is
(:func:`ttsim_jax.diagnose.candidates.score`: held-out RMS reduction and its 95 % interval).

The catalogue's candidates are physical effects with few parameters; when the true cause is not
among them, none explains the errors, and the question is whether anything could. The correction
here is a flexible linear map from physically named variables to the model's errors, so its
held-out reduction measures how much of the error is a reproducible function of those variables
(what a missing effect acting through them could remove), and its strongest terms point at the
variables that carry the gap. A reduction that is not significant says that no such function of
these variables generalises: what remains is noise, or depends on something not measured here.

* *table* and *racket* contacts (:func:`contact_bound`): the 6-vector error of
  :mod:`~ttsim_jax.diagnose.stages` (velocity and radius x spin errors; world frame for the table,
  racket frame for the racket) regressed on features of the pre-contact state
  (:func:`contact_features`): the incoming velocity (normal and tangential), the slip of the
  contact point v + w x (-r n) (tangential), r w about the normal (with the slip and the velocity,
  the whole incoming spin), speed, impact angle, normal speed x slip, normal speed squared, and
  the contact position (on the table; on the racket face with its distance |d| from the face's
  origin and the normal speed x |d|), hinges of the normal speed at its quantiles (a loss that
  sets in above an impact speed) and, on the racket, a step and a ramp of the normal speed and a
  step of the slip in |d| at its quantiles (a region of the face that starts somewhere, a rim or
  a logo, changing the restitution and the grip there), plus a constant. Where the contacts carry
  their spin times, the incoming r w times the time from the incoming segment's mean sample to the
  contact and the model's post-contact r w times the time from the contact to the outgoing
  segment's: the spins compared are the segments' means, so a spin that changes in flight
  shows in the contacts in proportion to those times. On a racket-rim case (outside suite, 227
  contacts) the steps of the slip raised the bound from 19.0 % of the held-out error to 57.8 %,
  against the oracle's 65.3 %. Each error component is fitted on the rows where it is
  compared (a bounce with unknown incoming spin compares only its normal velocity; spin errors
  only where both spins are measured), and the corrected errors e' = e - mask * Phi beta are
  scored.
* *flight* (:func:`flight_bound`): a missing acceleration, linear in its coefficients: B phi(v, w)
  with phi = (1, |v|, v, |v| v, w x v, |v| (w x v)) (14 scalars, one row of B per axis), a steady
  wind's change of drag and Magnus force (:func:`_fields`), and, where the candidates fit
  per-session parameters (not ``pb.pooled``), a constant acceleration and a steady wind per
  session (air flow differs between sessions: one B for all would miss winds of opposite
  directions). Linearised: a small extra acceleration moves the observed positions by its double
  integral along the path, and the segment's initial-state refit takes away what is constant and
  linear in time per axis. So the negated position residual (observation - model) of each
  segment is regressed on the double integrals of the fields along it, with the constant and
  linear parts per axis projected out (per segment, over its samples). The velocity along the
  path is the finite difference of the model's own flight at the samples (observation +
  residual): noise-free, unlike a difference of the observations, and no simulation is run. The
  spin is the segment's measured spin, held. A segment's rows are weighted as the candidates'
  robust flight loss weighs it (:data:`~ttsim_jax.diagnose.candidates.ROBUST`), so that a few
  mis-cut segments do not steer the fit; the score is the plain one, as for the candidates.
  Air that changes in gusts (periods of 1-20 s, against a training segment every ~10 s of a
  session) is no function of the state, nor one that the segments sample finely enough to
  interpolate: on a one-way air-flow case the true steady wind alone, gusts off, closes 17 % of the
  held-out error against the whole effect's 29 %. Gusts are periodic, though: each training
  segment's own steady wind (linear, from the wind columns) is laid against its session time, and
  the periodogram that the ``air_flow`` candidate's search uses
  (:func:`~ttsim_jax.diagnose.gusts.periodogram_gusts`) picks the frequencies that stand above
  noise (:func:`gust_components`); a wind at each of them, in sine and cosine of the session
  time, joins the columns (:func:`flight_basis`), so a held-out segment between training ones is
  predicted from the phase of the gust.

Fit (:mod:`~ttsim_jax.diagnose.ridge`): ridge regression on features scaled by their RMS (not
centred; the constant unpenalised), per error component for contacts and jointly over the axes in
flight, the regularisation chosen by cross-validation over the training items only (contacts;
whole segments in flight): for contacts
the largest weight within one standard error of the best, for flight the best. In flight the terms
per session and the gusts each get a weight of their own, a factor of 1, 10, 100 or 10^8 (left
out) times the common terms', chosen by the same cross-validation
(:func:`~ttsim_jax.diagnose.ridge.ridge_cv_groups`): 14 sessions of about 5 training segments give
126 columns of terms per session (9 a session) that few segments inform, and one weight for all
either overfits them or shrinks the common terms with them.

A linear correction fitted on a few dozen items is no upper limit: a physical candidate with a
few parameters can do better on the same data (it needs less of them), so the bound is a measured
lower limit of what is reducible through these variables, to be read beside the best candidate's.

Strongest terms (:func:`~ttsim_jax.diagnose.ridge.attribute`): the held-out fall of the squared error,
sum e^2 - sum (e - c)^2 = sum c (2 e - c), is split exactly into the parts c_m (2 e - c) of the
correction's named parts c_m (sum_m c_m = c): for contacts one part per (error component,
feature); in flight per physically named group (:func:`flight_parts`: the isotropic part of each
3 x 3 block of B, tr(M) / 3 times the identity, and the rest: drag-like along v, lift along
w x v, ...; the constant column split into vertical and horizontal; the winds). A term's share is
its part over the sum of the parts that lower the error; the terms are listed only where the
correction lowers the held-out error as a whole.
"""

from __future__ import annotations

import math

import numpy as np

from ttsim_jax.diagnose import candidates
from ttsim_jax.diagnose import gusts as gust_search
from ttsim_jax.diagnose.ridge import attribute, folds, ridge_cv, ridge_cv_groups, scaled

#: Least training items (contacts; segments in flight) of a phase with a bound, and of an error
#: component with a fitted correction.
MIN_TRAIN = 10
#: Least held-out items of a phase with a bound.
MIN_TEST = 3
#: Gust components sought per session (as many as the ``air_flow`` effect has).
GUST_COMPONENTS = 3
#: Terms reported per phase.
TOP_TERMS = 3
#: Labels of the contact error components (the 6-vector of :mod:`~ttsim_jax.diagnose.stages`).
OUTPUTS = {
    "table": ("post-bounce tangential velocity x", "post-bounce tangential velocity y", "post-bounce normal velocity",
              "post-bounce r·ω x", "post-bounce r·ω y", "post-bounce r·ω z"),
    "racket": ("post-contact normal velocity", "post-contact tangential velocity y",
               "post-contact tangential velocity z", "post-contact r·ω x (about the face normal)",
               "post-contact r·ω y", "post-contact r·ω z"),
}
#: Contact frames: (normal axis, tangential axes, their names).
FRAMES = {"table": (2, (0, 1), ("x", "y")), "racket": (0, (1, 2), ("y", "z"))}
#: Names of the axes of each contact frame (x, y, z of the world; the racket's x is the face normal).
AXES = {"table": ("x", "y", "z"), "racket": ("x (about the face normal)", "y", "z")}
#: Flight features phi, in the order of the columns of B.
FLIGHT_FEATURES = ("1", "|v|", "v_x", "v_y", "v_z", "|v|v_x", "|v|v_y", "|v|v_z", "(ω×v)_x", "(ω×v)_y", "(ω×v)_z",
                   "|v|(ω×v)_x", "|v|(ω×v)_y", "|v|(ω×v)_z")
#: Columns of the flight correction that every session shares (:func:`flight_basis`): B, then a
#: steady wind's 6; each session with terms of its own then has 9 (a constant acceleration, a wind).
COMMON = 3 * len(FLIGHT_FEATURES) + 6
PER_SESSION = 9
#: Name of the steady wind's terms (:func:`_fields`).
WIND = "a steady wind: the change of drag and Magnus force by air moving at w, |v| w + (v̂·w) v and |v| ω̂×w"
#: The 3 x 3 blocks of B (first column of the block) and the names of their isotropic part
#: (positive, negative coefficient) and of the rest.
FLIGHT_BLOCKS = (
    (2, ("linear drag: acceleration along +v in proportion to |v| (less drag than the model)",
         "linear drag: acceleration along −v in proportion to |v| (more drag than the model)"),
     "acceleration in proportion to v, direction-dependent (anisotropic linear drag, rotation of the frame)"),
    (5, ("drag-like: acceleration along +v in proportion to |v|² (less drag than the model)",
         "drag-like: acceleration along −v in proportion to |v|² (more drag than the model)"),
     "acceleration in proportion to |v| v, direction-dependent (anisotropic drag, a wind)"),
    (8, ("lift along ω×v in proportion to |ω||v| (more Magnus lift than the model)",
         "lift along −ω×v in proportion to |ω||v| (less Magnus lift than the model)"),
     "acceleration in proportion to ω×v, direction-dependent"),
    (11, ("lift along ω×v in proportion to |ω||v|² (more lift at speed than the model)",
          "lift along −ω×v in proportion to |ω||v|² (less lift at speed than the model)"),
     "acceleration in proportion to |v| ω×v, direction-dependent"),
)


def _heldout(pb, phase: str, corrected, seed: int) -> dict:
    h = candidates.score(pb, {phase: corrected}, seed=seed)[phase]
    return dict(h, significant=candidates.significant(phase, h) if _finite(h) else False)


def _finite(obj) -> bool:
    """Whether every number in ``obj`` (nested dicts and lists) is finite."""
    if isinstance(obj, dict):
        return all(_finite(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return all(_finite(v) for v in obj)
    if isinstance(obj, (float, np.floating)):
        return math.isfinite(obj)
    return True


def _terms(names: list, parts: np.ndarray, coefs: list) -> list:
    """The strongest :data:`TOP_TERMS` parts that lower the held-out error, as [{"name", "share",
    "coef"}], share: of the sum of such parts (parts that raise it are left out: their sum can be
    near the lowering ones', and shares of a small difference mean nothing); none where the
    correction does not lower the held-out error as a whole."""
    gain = np.maximum(parts, 0.0)
    if not parts.sum() > 0:
        return []
    order = [i for i in np.argsort(-parts) if parts[i] > 0][:TOP_TERMS]
    return [dict(name=names[i], share=float(gain[i] / gain.sum()), coef=float(coefs[i])) for i in order]


def _text(phase: str, what: str, h: dict, terms: list) -> str:
    head = (f"{phase}: a model-free correction ({what}) lowers the held-out RMS error by {h['pct']:.1f} % "
            f"(95 % interval {h['ci95'][0]:.1f} to {h['ci95'][1]:.1f} %, {h['n']} held-out items)")
    if not h["significant"]:
        return head + ("; not significant: no linear function of these variables explains the error that is held "
                       "out, so what remains is noise or depends on something not measured here.")
    lead = "; ".join(f"{t['name']} ({100 * t['share']:.0f} %)" for t in terms)
    return head + ". Strongest terms: " + lead + "."


# ---------------------------------------------------------------------------------------------- contacts
def contact_features(x, pos, kind: str, radius: float, spin_dt=None, spin_out=None) -> tuple[np.ndarray, list]:
    """Features of the pre-contact state of each contact (see the module docstring).

    Arguments:
        x: (N, 8) the phase's inputs (:class:`~ttsim_jax.diagnose.phases.ContactItems`: table
            (v_in, w_in, 0, 0) world frame; racket (v~, w~, d) racket frame); pos: (N, 3) contact
            point (world); kind: "table" or "racket"; radius: ball radius [m]; spin_dt: optional
            (N, 2) times from the incoming segment's mean sample to the contact and from the
            contact to the outgoing segment's [s]; spin_out: optional (N, 3) the model's
            post-contact r ω [m/s] (0 where the spin is not compared), with ``spin_dt``.

    Returns:
        ((N, K) features, K names); the first is the constant.
    """
    x = np.asarray(x, np.float64)
    v, w = x[:, :3], x[:, 3:6]
    normal, tang, axes = FRAMES[kind]
    n = np.zeros(3)
    n[normal] = 1.0
    slip = v + np.cross(w, -radius * n)  # velocity of the ball's point touching the surface
    vn = v[:, normal]
    vt = np.linalg.norm(v[:, list(tang)], axis=1)
    speed = np.linalg.norm(v, axis=1)
    angle = np.degrees(np.arctan2(-vn, vt) if kind == "table" else np.arctan2(vt, -vn))
    # r w about the tangential axes is (v_t - slip) turned by 90 deg: left out, so that no feature is
    # an exact combination of others (the attribution would split among them arbitrarily)
    cols = [np.ones(len(x)), vn] + [v[:, a] for a in tang] + [slip[:, a] for a in tang] + [radius * w[:, normal]] + \
        [speed, angle] + [np.abs(vn) * slip[:, a] for a in tang] + [vn**2]
    names = ["constant", "incoming normal velocity"] + [f"incoming tangential velocity {a}" for a in axes] + \
        [f"contact-point slip {a}" for a in axes] + ["incoming r·ω about the normal"] + \
        ["incoming speed", "impact angle"] + [f"normal speed × slip {a}" for a in axes] + ["normal speed squared"]
    # Hinges at the quantiles of the normal speed (and, on the racket, of the contact distance): a
    # loss that sets in above an impact speed or towards the rim is no straight line in them
    an = np.abs(vn)
    for k in _knots(an):
        cols.append(an * np.maximum(an - k, 0.0))
        names.append(f"normal speed × its excess over {k:.2g} m/s")
    if kind == "table":
        p = np.asarray(pos, np.float64)
        cols += [p[:, 0], p[:, 1]]
        names += ["contact position x on the table", "contact position y on the table"]
    else:
        d = x[:, 6:8]
        dist = np.linalg.norm(d, axis=1)
        cols += [d[:, 0], d[:, 1], dist, an * dist]
        names += ["contact point on the face y", "contact point on the face z", "distance |d| from the face origin",
                  "normal speed × |d|"]
        for k in _knots(dist):
            # a region of the face (a rim, a logo) changes the bounce where it starts: a step, and a
            # ramp, of the normal speed (restitution) and of the slip (grip) there
            beyond = dist > k
            cols += [an * beyond, an * np.maximum(dist - k, 0.0)] + [slip[:, a] * beyond for a in tang]
            names += [f"normal speed where |d| is beyond {100 * k:.2g} cm",
                      f"normal speed × |d| beyond {100 * k:.2g} cm"]
            names += [f"contact-point slip {a} where |d| is beyond {100 * k:.2g} cm" for a in axes]
    if spin_dt is not None:
        # a spin that changes in flight is measured off the contact: the spins compared are the
        # segments' means, dt before and after it
        dt = np.asarray(spin_dt, np.float64)
        r_in, r_out = radius * w, np.asarray(spin_out, np.float64)
        cols += [r_in[:, a] * dt[:, 0] for a in range(3)] + [r_out[:, a] * dt[:, 1] for a in range(3)]
        names += [f"incoming r·ω {a} × the time from the incoming segment's mean sample to the contact"
                  for a in AXES[kind]]
        names += [f"model's post-contact r·ω {a} × the time from the contact to the outgoing segment's mean sample"
                  for a in AXES[kind]]
    return np.stack(cols, 1), names


#: Quantiles of a variable where :func:`contact_features` puts hinges.
HINGES = (0.5, 0.75, 0.9)


def _knots(values) -> list:
    """Distinct knots at the :data:`HINGES` quantiles of ``values`` (none for fewer than 20 rows:
    too few to tell a hinge from noise)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if len(v) < 20 or not HINGES:
        return []
    return sorted(set(np.round(np.quantile(v, HINGES), 4).tolist()))


def contact_masks(d: dict, kind: str) -> np.ndarray:
    """(N, 6) where each error component is compared (:mod:`~ttsim_jax.diagnose.stages`): a
    bounce's tangential velocity where its incoming spin is measured, the spin errors where both
    spins are."""
    known = np.asarray(d["known"], np.float64)
    one = np.ones_like(known)
    tangential = np.asarray(d["known_in"], np.float64) if kind == "table" else one
    first = (tangential, tangential, one) if kind == "table" else (one, one, one)
    return np.stack(list(first) + [known] * 3, 1)


def contact_bound(pb, phase: str, radius: float, seed: int = 0) -> dict:
    """The model-free bound of a contact phase (see the module docstring).

    Arguments:
        pb: the :class:`~ttsim_jax.diagnose.candidates.Problem` (or any object with its ``data``
            and ``base``); phase: "table" or "racket"; radius: ball radius [m]; seed: of the
            folds and the bootstrap.

    Returns:
        {"heldout": as a candidate's, with "significant"; "terms": [{"name", "share", "coef"}];
        "text"; "features"; "lambda" (per error component); "n_train"} or {"reason"}.
    """
    d = pb.data[phase]
    e = np.asarray(pb.base[phase], np.float64)
    train, test = np.asarray(d["train"]) > 0, np.asarray(d["test"]) > 0
    if train.sum() < MIN_TRAIN or test.sum() < MIN_TEST:
        return dict(reason=f"{int(train.sum())} training and {int(test.sum())} held-out {phase} contacts: a bound "
                           f"needs at least {MIN_TRAIN} and {MIN_TEST}")
    mask = contact_masks(d, phase)
    spin_dt = spin_out = None
    if "spin_dt" in d and "y_obs" in d:
        spin_dt = d["spin_dt"]
        # the model's post-contact spin, e + observation: a function of the pre-contact state only
        spin_out = mask[:, 3:] * (radius * np.asarray(d["y_obs"], np.float64)[:, 3:6] + e[:, 3:])
    feats, names = contact_features(d["x"], d["pos"], phase, radius, spin_dt, spin_out)
    w = train[:, None] * mask
    # a component compared on too few training contacts is left uncorrected
    w[:, w.sum(0) < MIN_TRAIN] = 0.0
    z, scale = scaled(feats, train)
    penalty = np.ones(z.shape[1])
    penalty[0] = 0.0
    beta, lam = ridge_cv(z, e, w, folds(len(e), train, seed), penalty)
    corrected = e - mask * (z @ beta)
    h = _heldout(pb, phase, corrected, seed)
    if not _finite(h):
        return dict(reason=f"the held-out {phase} error is not defined (no held-out error to reduce)")
    k, j = beta.shape
    parts = np.zeros((k * j, k, j))
    labels, coefs = [], []
    for a in range(j):
        for b in range(k):
            parts[a * k + b, b, a] = beta[b, a]
            how = "a constant offset" if b == 0 else f"in proportion to the {names[b]}"
            labels.append(f"{OUTPUTS[phase][a]}, {how}")
            coefs.append(beta[b, a] / scale[b] if np.isfinite(scale[b]) else 0.0)
    fall = attribute(z, parts, e, test[:, None] * mask)
    terms = _terms(labels, fall, coefs)
    what = f"a ridge-regularised linear map from {len(names) - 1} variables of the incoming state"
    return dict(heldout=h, terms=terms, text=_text(phase, what, h, terms), features=names, **{"lambda": lam.tolist()},
                n_train=int(train.sum()))


# ---------------------------------------------------------------------------------------------- flight
def _double_integral(f, t) -> np.ndarray:
    """Cumulative double integral from t[0] of samples f (n, K) at times t (n,), trapezoids."""
    dt = np.diff(t)[:, None]
    first = np.concatenate([np.zeros((1, f.shape[1])), np.cumsum(0.5 * dt * (f[1:] + f[:-1]), 0)])
    return np.concatenate([np.zeros((1, f.shape[1])), np.cumsum(0.5 * dt * (first[1:] + first[:-1]), 0)])


def _fields(v, spin) -> np.ndarray:
    """(n, 3 K + 6, 3) the vector fields of one segment at its samples: the columns of B (each
    feature of :data:`FLIGHT_FEATURES` along each axis, feature-major), then those of a steady wind
    w (:data:`WIND`): |v| e_b + v v_b / |v| (the change of a quadratic drag by w along axis b) and
    |v| (ω̂ × e_b) (that of a Magnus force whose coefficient goes as |v| / |ω|), b = x, y, z."""
    speed = np.linalg.norm(v, axis=1, keepdims=True)
    wxv = np.cross(spin, v)
    phi = np.concatenate([np.ones_like(speed), speed, v, speed * v, wxv, speed * wxv], 1)
    per_axis = phi[:, :, None, None] * np.eye(3)[None, None]  # (n, K, axis of B, 3)
    drag = speed[:, :, None] * np.eye(3)[None] + v[:, None, :] * (v / np.maximum(speed, 1e-9))[:, :, None]
    axis = spin / max(float(np.linalg.norm(spin)), 1e-9)
    magnus = speed[:, :, None] * np.cross(axis, np.eye(3))[None]
    return np.concatenate([per_axis.reshape(len(v), -1, 3), drag, magnus], 1)


def flight_basis(d: dict, errors, per_session: bool, gusts=()) -> tuple[np.ndarray, int]:
    """(S, T, M, 3) position changes at the samples of each segment by a unit of each of the
    correction's M vector fields (its double integral along the segment with the constant and
    linear parts in time projected out; 0 at padding and in unusable segments), and the number of
    sessions with columns of their own.

    Columns: B (:data:`FLIGHT_FEATURES` x axes, feature-major), a steady wind's 6 (:func:`_fields`),
    and, with ``per_session``, for each session a constant acceleration and a steady wind of its
    own (a frame tilt and the hall's air of that session; 9 columns each); then, per gust
    component (session, frequency f) of ``gusts``, a steady wind's change of drag times
    sin(2 pi f t) and times cos(2 pi f t), t the session time (6 columns each).

    Arguments:
        d: the flight arrays (``tau``, ``pos``, ``mask``, ``spin``, optional ``session``);
        errors: (S, T, 3) the model's position residuals (model - observation) at the fitted
        initial states; per_session: whether sessions get columns of their own.
    """
    tau, pos = np.asarray(d["tau"], np.float64), np.asarray(d["pos"], np.float64)
    mask, spin = np.asarray(d["mask"]) > 0, np.asarray(d["spin"], np.float64)
    session = np.asarray(d.get("session", np.zeros(len(tau))), np.int64)
    sessions = int(session[mask.any(1)].max()) + 1 if per_session and mask.any() else 0
    sessions = sessions if sessions > 1 else 0
    path = pos + np.asarray(errors, np.float64)  # the model's own flight at the samples
    t0 = np.asarray(d.get("t0", np.zeros(len(tau))), np.float64)
    first_gust = COMMON + PER_SESSION * sessions
    out = np.zeros(tau.shape + (first_gust + 6 * len(gusts), 3))
    for s in range(len(tau)):
        m = mask[s]
        t = tau[s][m]
        if len(t) < 4 or np.any(np.diff(t) <= 0):
            continue
        v = np.gradient(path[s][m], t, axis=0, edge_order=2)
        f = _fields(v, spin[s])
        drag = f[:, COMMON - 6:COMMON - 3]
        if sessions:
            own = np.concatenate([f[:, 0:3], f[:, COMMON - 6:COMMON]], 1)  # constant, wind
            f = np.concatenate([f, np.zeros((len(t), PER_SESSION * sessions, 3))], 1)
            f[:, COMMON + PER_SESSION * session[s]:COMMON + PER_SESSION * (session[s] + 1)] = own
        if len(gusts):
            f = np.concatenate([f, np.zeros((len(t), 6 * len(gusts), 3))], 1)
            for k, (gs, freq) in enumerate(gusts):
                if gs == session[s]:
                    arg = 2.0 * np.pi * freq * (t0[s] + t)[:, None, None]
                    f[:, first_gust + 6 * k:first_gust + 6 * k + 6] = np.concatenate(
                        [drag * np.sin(arg), drag * np.cos(arg)], 1)
        g = _double_integral(f.reshape(len(t), -1), t)
        a = np.stack([np.ones_like(t), t - t.mean()], 1)
        g -= a @ np.linalg.lstsq(a, g, rcond=None)[0]  # what the initial-state refit absorbs
        out[s, m] = g.reshape(len(t), -1, 3)
    return out, sessions


def flight_parts(theta, sessions: int, gusts=()) -> tuple[np.ndarray, list, list]:
    """The named parts of the fitted flight correction (see the module docstring).

    Arguments:
        theta: (M,) coefficients of the columns of :func:`flight_basis`; sessions: sessions with
        columns of their own; gusts: its gust components (session, frequency).

    Returns:
        ((P, M) parts summing to theta, P names, P coefficients: the part's coefficient per unit
        of its feature, or the norm of its coefficients where it has several (per session: the
        largest session's)).
    """
    k = len(FLIGHT_FEATURES)
    parts, names, coefs = [], [], []

    def add(cells, name, coef):
        p = np.zeros_like(theta)
        p[cells] = theta[cells]
        parts.append(p)
        names.append(name)
        coefs.append(float(coef))

    b = theta[:3 * k].reshape(k, 3)
    add([2], "constant vertical acceleration: gravity or clock scale", b[0, 2])
    add([0, 1], "constant horizontal acceleration (a tilted frame or a steady push)", np.linalg.norm(b[0, :2]))
    add([3, 4, 5], "acceleration along a fixed direction in proportion to |v|", np.linalg.norm(b[1]))
    add(list(range(3 * k, COMMON)), f"{WIND}, the same in every session", np.linalg.norm(theta[3 * k:3 * k + 3]))
    for first, iso_names, rest_name in FLIGHT_BLOCKS:
        block = b[first:first + 3]
        iso = np.trace(block) / 3.0
        cells = [3 * (first + i) + j for i in range(3) for j in range(3)]
        # the isotropic part of the block and the rest: parts of the same cells, not a subset
        p = np.zeros_like(theta)
        p[[3 * (first + i) + i for i in range(3)]] = iso
        parts += [p, np.where(np.isin(np.arange(len(theta)), cells), theta, 0.0) - p]
        names += [iso_names[0] if iso >= 0 else iso_names[1], rest_name]
        coefs += [float(iso), float(np.linalg.norm(block - iso * np.eye(3)))]
    if sessions:
        own = theta[COMMON:COMMON + PER_SESSION * sessions].reshape(sessions, PER_SESSION)
        tilt = [COMMON + PER_SESSION * i + j for i in range(sessions) for j in range(3)]
        wind = [COMMON + PER_SESSION * i + j for i in range(sessions) for j in range(3, PER_SESSION)]
        add(tilt, "constant acceleration per session (a tilt of that session's frame)",
            np.linalg.norm(own[:, :3], axis=1).max())
        add(wind, f"{WIND}, one per session", np.linalg.norm(own[:, 3:6], axis=1).max())
    if len(gusts):
        first = COMMON + PER_SESSION * sessions
        amp = np.hypot(theta[first:].reshape(-1, 2, 3)[:, 0], theta[first:].reshape(-1, 2, 3)[:, 1])
        freqs = ", ".join(f"{f:.2g}" for f in sorted({round(float(f), 3) for _, f in gusts}))
        add(list(range(first, len(theta))), f"air moving in gusts: a wind varying in session time at {freqs} Hz "
            "(its change of drag)", np.linalg.norm(amp, axis=1).max())
    return np.stack(parts), names, coefs


def gust_components(d: dict, g, errors, train, sessions: int) -> list:
    """Gust components (session, frequency [Hz]) of the flights: per training segment its own
    steady wind (the least-squares coefficients of the drag-change columns of ``g``, :func:`flight_basis`,
    on the segment's residual, with their information), and per session the periodogram of those
    winds against the segments' mean times (:func:`ttsim_jax.diagnose.gusts.periodogram_gusts`),
    keeping the components it finds. Linear: no simulation, unlike the ``air_flow`` candidate's
    search (:func:`ttsim_jax.diagnose.gusts.gust_stage`), which refits each segment's state.

    Arguments:
        d: the flight arrays; g: (S, T, M, 3) :func:`flight_basis` without gusts; errors: (S, T, 3)
        the model's position residuals; train: (S,) training segments; sessions: as returned by
        :func:`flight_basis`.
    """
    if "t0" not in d:  # no session times: nothing to lay the winds against
        return []
    mask = np.asarray(d["mask"]) > 0
    col = 3 * len(FLIGHT_FEATURES)  # the steady wind's drag columns
    n = mask.sum(1)
    offsets, info, reduced = np.zeros((len(n), 3)), np.zeros((len(n), 3, 3)), np.full(len(n), np.inf)
    for s in np.flatnonzero(train & (n >= 6)):
        x = g[s][mask[s]][:, col:col + 3].transpose(0, 2, 1).reshape(-1, 3)
        y = -np.asarray(errors[s], np.float64)[mask[s]].reshape(-1)
        a = x.T @ x
        if not np.all(np.isfinite(a)) or np.linalg.matrix_rank(a) < 3:
            continue
        offsets[s] = np.linalg.solve(a, x.T @ y)
        info[s] = a
        reduced[s] = float(np.sum((y - x @ offsets[s]) ** 2)) / max(3.0 * n[s] - 9.0, 1.0)
    ok = np.isfinite(reduced)
    if not ok.any():
        return []
    ok, sigma2 = gust_search.typical_segments(reduced, ok)
    times = gust_search.mean_times(d)
    session = np.asarray(d.get("session", np.zeros(len(n))), np.int64)
    out = []
    for k in np.unique(session[ok]):
        rows = ok & (session == k)
        amp, freq, _, _ = gust_search.periodogram_gusts(times[rows], offsets[rows], info[rows] / sigma2,
                                                       components=GUST_COMPONENTS)
        out += [(int(k), float(f)) for a, f in zip(amp, freq) if np.linalg.norm(a) > 0]
    return out


def flight_bound(pb, seed: int = 0) -> dict:
    """The model-free bound of the flight phase (see the module docstring).

    Arguments:
        pb: the :class:`~ttsim_jax.diagnose.candidates.Problem` (or any object with its ``data``,
            ``base`` and optionally ``pooled``); seed: of the folds and the bootstrap.

    Returns:
        {"heldout": as a candidate's, with "significant"; "terms": [{"name", "share", "coef"}]
        (see :func:`flight_parts`); "text"; "features"; "lambda"; "group_factors" (the ridge
        weights of the terms per session and of the gusts relative to the common terms', where
        they exist); "sessions" (sessions with terms of their own); "n_train"} or {"reason"}.
    """
    d = pb.data["flight"]
    e = np.asarray(pb.base["flight"], np.float64)
    mask = np.asarray(d["mask"], np.float64)
    train, test = np.asarray(d["train"]) > 0, np.asarray(d["test"]) > 0
    if train.sum() < MIN_TRAIN or test.sum() < MIN_TEST:
        return dict(reason=f"{int(train.sum())} training and {int(test.sum())} held-out flight segments: a bound "
                           f"needs at least {MIN_TRAIN} and {MIN_TEST}")
    # per-session terms where the candidates fit per-session parameters
    g, sessions = flight_basis(d, e, not getattr(pb, "pooled", False))
    gusts = gust_components(d, g, e, train, sessions)
    if gusts:
        g, sessions = flight_basis(d, e, not getattr(pb, "pooled", False), gusts)
    s, t, m, _ = g.shape
    # the candidates' robust weight of each segment, from the model's errors (held fixed)
    sse, n = candidates.item_sums(pb, "flight", e)
    msq = sse / np.maximum(n, 1.0)
    used = train & (n > 0)
    c2 = max(candidates.ROBUST**2 * float(np.median(msq[used])) if used.any() else 0.0, 1e-20)
    robust = train / (1.0 + msq / c2)
    # one row per sample and axis
    x = g.transpose(0, 1, 3, 2).reshape(-1, m)
    z, scale = scaled(x, np.repeat((robust[:, None] * mask).reshape(-1), 3))
    y = -e.reshape(-1, 1)  # observation - model: the position change the missing acceleration makes
    w = np.repeat((robust[:, None] * mask).reshape(-1), 3)[:, None]
    fold = np.repeat(folds(s, train, seed), 3 * t)
    # thousands of rows per fold: the curve's minimum is well determined, and the one-standard-error
    # rule would shrink a strong drag term into its correlated neighbours. The terms per session
    # and the gusts are many columns that a few segments each inform: under the common terms'
    # weight they either overfit or, the weight raised for them, shrink the common terms; each
    # group's weight is chosen apart (on a one-way air-density case, 14 sessions of 5 training
    # segments, one weight for all held out 37.7 %, not significant, against the oracle's 73.7 %)
    first_gust = COMMON + PER_SESSION * sessions
    cols = np.arange(m)
    groups = [g for g in ((cols >= COMMON) & (cols < first_gust), cols >= first_gust) if g.any()]
    beta, lam, factors = ridge_cv_groups(z, y, w, fold, np.ones(m), groups, one_se=False)
    corrected = e + (z @ beta).reshape(s, t, 3) * mask[..., None]
    h = _heldout(pb, "flight", corrected, seed)
    if not _finite(h):
        return dict(reason="the held-out flight error is not defined (no held-out error to reduce)")
    unit = np.where(np.isfinite(scale), 1.0 / scale, 0.0)
    named, names, coefs = flight_parts(unit * beta[:, 0], sessions, gusts)
    parts = (named * np.where(np.isfinite(scale), scale, 0.0))[:, :, None]  # in the units of the scaled columns
    fall = attribute(z, parts, y, np.repeat((test[:, None] * mask).reshape(-1), 3)[:, None])
    terms = _terms(names, fall, coefs)
    what = ("a missing acceleration linear in 1, |v|, v, |v| v, ω×v and |v| ω×v per axis and a steady wind"
            + (f", and a frame tilt and a steady wind per session ({sessions} sessions)" if sessions else "")
            + (f", and {len(gusts)} gust components found in the segments' own winds" if gusts else ""))
    return dict(heldout=h, terms=terms, text=_text("flight", what, h, terms), features=list(FLIGHT_FEATURES),
                sessions=sessions, gusts=[dict(session=k, freq_hz=f) for k, f in gusts], n_train=int(train.sum()),
                group_factors=[float(f) for f in factors], **{"lambda": lam.tolist()})


# ---------------------------------------------------------------------------------------------- all phases
def bounds(pb, radius: float, seed: int = 0, skipped: dict | None = None) -> dict:
    """The model-free bound of every phase (see the module docstring).

    Arguments:
        pb: the :class:`~ttsim_jax.diagnose.candidates.Problem` with the model's errors and split;
        radius: ball radius [m]; seed: of the folds and the bootstraps; skipped: {phase: why it
        has no data} (from :class:`~ttsim_jax.diagnose.phases.Phases`).

    Returns:
        {phase: :func:`flight_bound` / :func:`contact_bound`, or {"reason"}} for each phase of
        :data:`~ttsim_jax.diagnose.candidates.PHASES`; no number in it is NaN.
    """
    out = {}
    for p in candidates.PHASES:
        if p not in pb.phases:
            out[p] = dict(reason=(skipped or {}).get(p, f"no {p} items in the data"))
            continue
        res = flight_bound(pb, seed) if p == "flight" else contact_bound(pb, p, radius, seed)
        out[p] = res if _finite(res) else dict(reason=f"the {p} bound is not defined on these data")
    return out
