"""The paper's Results section on any dataset: models compared stage by stage (``ttsim evaluate``).

:func:`evaluate_models` computes, for each model, the four evaluations of the paper's Results
section on a :class:`~ttsim_jax.data.Dataset`; :func:`write_report` writes the figures (PNG), a
Markdown report and every number (``metrics.json``; per-item values in ``samples.npz``).

1. *flight*: per flight segment (those with a measured spin, when the data has any), the 3-D
   position RMSE of the model's flight with the initial velocity fitted
   (:func:`ttsim_jax.evaluate.flight.flight_rmse`); median, 75th percentile and their reductions
   in % against the reference model (nakashima2011 when compared, else the first model), with
   paired bootstrap intervals.
2. *table*: per table bounce, the model's table contact (the rally kernel's
   :func:`~ttsim_jax.kernel.step.respond`) applied to the measured pre-bounce state, minus the
   measured post-bounce state, per component (v_x, v_y, v_z, w_x, w_y, w_z; spin components only
   where both segments have a measured spin; an unmeasured pre-bounce spin enters as 0). States
   are estimated as for the racket residual's training data
   (:func:`ttsim_jax.fit.contacts.estimate_contact`: polynomial fits next to the contact, the
   segments' spins).
3. *racket*: per racket contact with a racket state, the model's racket contact (base model plus
   its residual network, if it carries one) minus the observation, in the racket frame
   (:func:`ttsim_jax.fit.contacts.contact_arrays`), grouped by contact distance (0-5, 5-8,
   > 8 cm); every model is scored on the same contacts (those usable for all).
4. *landing*: from the state at the last observation before a racket contact (fitted on the
   incoming samples; the segment's spin) the model is rolled out (:func:`ttsim_jax.rollout`) with
   the data's racket state (moving at its measured velocity) until the ball reaches the table
   plane (z = one radius, whether or not it meets the table); the landing point is compared with
   the measured one (the next table event, or where the outgoing observations cross the plane).

A stage whose data the dataset lacks (no racket states, no bounces) is skipped, with the reason
in the report.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit.contacts import ContactFit, ObservationIndex, contact_arrays, estimate_contact, fit_contact_state
from ttsim_jax.fit.residual import COMPONENTS, DISTANCE_BANDS, ERROR_NAMES, contact_errors, distance_bands

STAGES = ("flight", "table", "racket", "landing")
REFERENCE = "nakashima2011"
#: Face semi-axes [m] of the racket in the landing rollouts: larger than any real blade, so that a
#: measured contact is never lost to an outline the data does not give.
LANDING_FACE = (0.2, 0.2)
#: After the measured contact time plus this [s] the racket is withdrawn (its face shrunk to
#: nothing), so that a racket moving on at constant velocity cannot meet the ball again.
RACKET_WITHDRAW = 0.03

TABLE_SKIP_REASONS = {
    "no_incoming_segment": "no flight segment ends at the bounce",
    "no_outgoing_segment": "no flight segment starts at the bounce",
    "few_incoming_samples": "fewer than min_samples observations before the bounce within max_span",
    "few_outgoing_samples": "fewer than min_samples observations after the bounce within max_span",
    "bad_fit": "polynomial fit RMSE above max_fit_rmse",
    "not_falling": "estimated pre-bounce v_z >= 0",
    "not_rising": "estimated post-bounce v_z <= 0",
}
LANDING_SKIP_REASONS = {
    "no_incoming_segment": "no flight segment ends at the racket contact",
    "few_incoming_samples": "fewer than min_samples observations before the contact within max_span",
    "low_spin_conf_in": "incoming segment's spin confidence below min_spin_conf",
    "bad_fit": "polynomial fit RMSE above max_fit_rmse",
    "no_outgoing_segment": "no flight segment starts at the racket contact",
    "no_measured_landing": "the outgoing flight neither ends on the table nor crosses the table plane",
}


@dataclasses.dataclass(frozen=True)
class EvaluateSettings:
    """How the evaluation selects and estimates.

    Attributes:
        fit: state estimation next to contacts (:class:`~ttsim_jax.fit.contacts.ContactFit`).
        min_samples: flight segments with fewer observations are left out.
        dt: integration step of the landing rollouts [s].
        horizon: longest landing rollout [s]; a ball not reaching the table plane by then has no
            landing point.
        chunk: most racket contacts per compiled landing rollout (fewer contacts: the power of two
            above their number; the last chunk is padded).
        sessions: evaluate only these session ids (None: all).
        float64: load the models (names and TOML files) in float64; by default float32, the
            simulator's usual type, whatever JAX's default float is.
    """

    fit: ContactFit = ContactFit()
    min_samples: int = 5
    dt: float = 1e-3
    horizon: float = 1.5
    chunk: int = 256
    sessions: tuple | None = None
    float64: bool = False

    def keep(self, session_ids) -> np.ndarray:
        """(N,) bool: rows whose session is evaluated."""
        s = np.asarray(session_ids)
        return np.ones(s.shape, bool) if self.sessions is None else np.isin(s, np.asarray(self.sessions))


def resolve_models(models: Sequence, dtype=None) -> list:
    """[(name, Model)] from bundled names, TOML paths or :class:`~ttsim_jax.params.Model` objects.

    A bundled model is named as given, a TOML file by its stem (``runs/fitted.toml``: ``fitted``),
    a Model object by its ``name``. Names and files are loaded with float type ``dtype`` (default:
    JAX's default float); Model objects are used as they are.

    Raises:
        ConfigError: an unknown name, an unreadable file, or two models of the same name (the
        message names them).
    """
    from ttsim_jax.params import ConfigError, Model, load_model, resolve_model_path

    out = []
    for spec in models:
        if isinstance(spec, Model):
            name, model = spec.name, spec
        else:
            path = resolve_model_path(spec)
            model = load_model(path, dtype=dtype)
            name = str(spec) if path != Path(str(spec)) else path.stem
        if any(name == n for n, _ in out):
            raise ConfigError(f"models: two models are named {name!r} ({spec!r}); rename the .toml file")
        out.append((name, model))
    if not out:
        raise ConfigError("models: none given")
    return out


def reference_name(names: Sequence[str]) -> str:
    """The model reductions are measured against: nakashima2011 if compared, else the first."""
    return REFERENCE if REFERENCE in names else names[0]


def reduction(ref: float, value: float) -> float:
    """Reduction of ``value`` against ``ref`` in % (positive: smaller than the reference)."""
    return float(100.0 * (ref - value) / ref) if ref and math.isfinite(ref) and math.isfinite(value) else math.nan


BOOTSTRAP = 1000


def reduction_ci(ref_values, values, q: float, n_boot: int = BOOTSTRAP, seed: int = 0) -> list:
    """95 % interval of the reduction [%] of the ``q``-th percentile of ``values`` against that of
    ``ref_values``: a paired bootstrap over the items (those finite in both), ``n_boot`` draws.

    Returns:
        [low, high] (NaN with fewer than two items).
    """
    x, y = np.asarray(ref_values, np.float64), np.asarray(values, np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 2:
        return [math.nan, math.nan]
    rng = np.random.default_rng(seed)
    draws = []
    for lo in range(0, n_boot, 100):  # 100 resamples at a time bounds the memory
        idx = rng.integers(0, len(x), (min(100, n_boot - lo), len(x)))
        a, b = np.percentile(x[idx], q, axis=1), np.percentile(y[idx], q, axis=1)
        draws.append(100.0 * (a - b) / np.where(a > 0, a, np.nan))
    r = np.concatenate(draws)
    r = r[np.isfinite(r)]
    return [float(np.percentile(r, 2.5)), float(np.percentile(r, 97.5))] if len(r) else [math.nan, math.nan]


def _headline(values: dict, names: list, ref: str) -> dict:
    """Per model: :func:`_stats` of its values and the reductions of the median and the 75th
    percentile against the reference, with their bootstrap intervals."""
    per = {n: _stats(values[n]) for n in names}
    for n in names:
        for key, q in (("median", 50), ("p75", 75)):
            per[n][f"reduction_{key}_pct"] = reduction(per[ref][key], per[n][key])
            per[n][f"reduction_{key}_ci95"] = reduction_ci(values[ref], values[n], q)
    return per


def _stats(x) -> dict:
    """n, median, 75th percentile, mean of the finite values of ``x``."""
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    if not len(x):
        return dict(n=0, median=math.nan, p75=math.nan, mean=math.nan)
    return dict(n=int(len(x)), median=float(np.median(x)), p75=float(np.percentile(x, 75)), mean=float(np.mean(x)))


# ---------------------------------------------------------------------------------------------- flight
def flight_stage(ds, models: list, settings: EvaluateSettings, tick: Callable = lambda: None) -> dict:
    """Flight-segment 3-D position RMSE per model (see the module docstring).

    Segments with a measured spin (confidence >= ``fit.min_spin_conf``) are used when the data has
    any; otherwise every segment is, flown with spin 0.

    Returns:
        dict: ``skipped`` (a reason) or ``segment_id`` (S,), ``spin_measured`` (whether the
        segments have a measured spin), ``n_without_spin`` (segments left out for want of one) and
        ``rmse`` {name: (S,) [m]}.
    """
    from ttsim_jax.evaluate.flight import flight_rmse
    from ttsim_jax.fit import aero as A

    ids, times, positions, spins, conf = A.dataset_segments(ds, settings.min_samples)
    session_of = dict(zip(np.asarray(ds.segments["segment_id"]).tolist(), np.asarray(ds.segments["session_id"]).tolist()))
    keep = settings.keep([session_of[i] for i in ids.tolist()]) if len(ids) else np.zeros(0, bool)
    n_keep = int(keep.sum())
    if not n_keep:
        for _ in models:
            tick()
        return dict(skipped=f"no flight segment with at least {settings.min_samples} observations")
    spin_known = conf >= settings.fit.min_spin_conf
    with_spin = bool((keep & spin_known).any())
    if with_spin:  # a flight flown with spin 0 for want of a measurement says little about a model
        keep &= spin_known
    times = [t for t, k in zip(times, keep) if k]
    positions = [p for p, k in zip(positions, keep) if k]
    rmse = {}
    for name, model in models:
        rmse[name] = flight_rmse(model, times, positions, spins[keep])
        tick()
    return dict(segment_id=ids[keep], spin_measured=with_spin, n_without_spin=int(n_keep - keep.sum()), rmse=rmse)


# ---------------------------------------------------------------------------------------------- table
@jax.jit
def _table_response(model, pos, vel, spin):
    from ttsim_jax.kernel.step import respond
    from ttsim_jax.physics.events import TABLE
    from ttsim_jax.state import Ball

    def one(p, v, w):
        post, _, _ = respond(model, Ball(p, v, w), TABLE, None)
        return post.vel, post.spin

    return jax.vmap(one)(pos, vel, spin)


def table_stage(ds, models: list, settings: EvaluateSettings, tick: Callable = lambda: None) -> dict:
    """Table-contact errors per model (see the module docstring).

    Returns:
        dict: ``skipped`` (a reason) or ``event_id`` (N,), ``spin_known`` (N, 2) bool (before,
        after), ``pre``, ``post`` (N, 6) estimated world-frame (v, w) before / after (the pre-bounce
        spin 0 where not measured), ``error`` {name: (N, 6) predicted minus measured, NaN spin
        unless both spins are measured}, ``skip_counts`` {reason: n}.
    """
    from ttsim_jax.data.batch import segments_around

    ev = ds.events
    rows = np.flatnonzero((np.asarray(ev["kind"]).astype(str) == "table") & settings.keep(ev["session_id"]))
    if not len(rows):
        for _ in models:
            tick()
        return dict(skipped="no table bounce (event kind 'table') in the dataset")
    ids = np.asarray(ev["event_id"], np.int64)[rows]
    in_rows, out_rows = segments_around(ds, ids)
    t_c = np.asarray(ev["t"], np.float64)[rows]
    p_c = np.stack([np.asarray(ev[k], np.float64)[rows] for k in "xyz"], -1)
    index = ObservationIndex(ds)
    counts = {k: 0 for k in TABLE_SKIP_REASONS}
    good, pre, post, spin_known = [], [], [], []
    for i in range(len(rows)):
        reason, est = estimate_contact(index, in_rows[i], out_rows[i], t_c[i], settings.fit, need_spin=False)
        if reason is None and est.vel_in[2] >= 0.0:
            reason = "not_falling"
        if reason is None and est.vel_out[2] <= 0.0:
            reason = "not_rising"
        if reason is not None:
            counts[reason] += 1
            continue
        good.append(i)
        pre.append(np.concatenate([est.vel_in, est.spin_in if est.spin_known[0] else np.zeros(3)]))
        post.append(np.concatenate([est.vel_out, est.spin_out]))
        spin_known.append(est.spin_known)
    skip_counts = {k: v for k, v in counts.items() if v}
    if not good:
        for _ in models:
            tick()
        return dict(skipped=f"none of the {len(rows)} table bounces is usable ({_counts_text(skip_counts, TABLE_SKIP_REASONS)})")
    good = np.asarray(good)
    pre, post, spin_known = np.asarray(pre), np.asarray(post), np.asarray(spin_known)
    error = {}
    for name, model in models:
        dtype = model.ball.radius.dtype
        vel, spin = _table_response(model.replace(name=""), jnp.asarray(p_c[good], dtype), jnp.asarray(pre[:, :3], dtype),
                                    jnp.asarray(pre[:, 3:], dtype))
        e = np.concatenate([np.asarray(vel, np.float64), np.asarray(spin, np.float64)], 1) - post
        e[~spin_known.all(1), 3:] = np.nan
        error[name] = e
        tick()
    return dict(event_id=ids[good], spin_known=spin_known, pre=pre, post=post, error=error, skip_counts=skip_counts,
                n_bounces=len(rows))


def _counts_text(counts: dict, reasons: dict) -> str:
    return "; ".join(f"{n} {k}: {reasons.get(k, k)}" for k, n in counts.items()) or "none skipped"


# ---------------------------------------------------------------------------------------------- racket
def racket_stage(ds, models: list, settings: EvaluateSettings, tick: Callable = lambda: None) -> dict:
    """Racket-contact errors per model, in the racket frame, on the contacts usable for every model.

    Returns:
        dict: ``skipped`` (a reason) or ``event_id`` (N,), ``distance`` (N,) [m], ``x`` (N, 8)
        the pre-contact racket-frame state (v~, w~, d) of the first model's frame, ``error``
        {name: (N, 8) signed errors (:data:`~ttsim_jax.fit.residual.ERROR_NAMES`)},
        ``skip_counts`` {reason: n} (of the first model's conversion), ``n_contacts``.
    """
    from ttsim_jax.fit.residual import predict

    n_states = len(ds.rackets["event_id"])
    if n_states == 0:
        for _ in models:
            tick()
        return dict(skipped="no racket states (the dataset's rackets table is empty)")
    arrays = {}
    for name, model in models:
        a = contact_arrays(ds, model, n_inputs=8, fit=settings.fit, validate=False)
        keep = settings.keep(a.session_id)
        y = a.y_base
        if model.residual is not None:
            y, _, _ = predict(model.residual, a.x[:, :model.residual.config.n_inputs], a.y_base)
        arrays[name] = (a, keep, y)
    common = None
    for a, keep, _ in arrays.values():
        ids = set(a.event_id[keep].tolist())
        common = ids if common is None else common & ids
    first = arrays[models[0][0]][0]
    if not common:
        for _ in models:
            tick()
        return dict(skipped=f"none of the {first.n_contacts} racket contacts is usable "
                    f"({_counts_text(first.counts(), _skip_reasons())})")
    event_ids = np.array(sorted(common), np.int64)
    error, x = {}, None
    for name, _ in models:
        a, _, y = arrays[name]
        row_of = {int(e): k for k, e in enumerate(a.event_id)}
        rows = np.array([row_of[int(e)] for e in event_ids], np.int64)
        error[name] = contact_errors(y[rows], a.y_obs[rows])
        if x is None:
            x = np.asarray(a.x[rows], np.float64)
        tick()
    return dict(event_id=event_ids, distance=np.linalg.norm(x[:, 6:8], axis=1), x=x, error=error,
                skip_counts=first.counts(), n_contacts=first.n_contacts)


def _skip_reasons() -> dict:
    from ttsim_jax.fit.contacts import SKIP_REASONS

    return SKIP_REASONS


# ---------------------------------------------------------------------------------------------- landing
def crossing(t, pos, height: float):
    """First downward crossing of z = ``height`` in a sampled path, linearly interpolated.

    Arguments:
        t: (n,) times; pos: (n, 3) positions in time order; height: the plane's z [m].

    Returns:
        ((x, y) (2,), time) of the crossing, or None when the path does not cross downward.
    """
    t, pos = np.asarray(t, np.float64), np.asarray(pos, np.float64)
    z = pos[:, 2] - height
    k = np.flatnonzero((z[:-1] > 0.0) & (z[1:] <= 0.0))
    if not len(k):
        return None
    k = int(k[0])
    f = z[k] / (z[k] - z[k + 1])
    return (1.0 - f) * pos[k, :2] + f * pos[k + 1, :2], (1.0 - f) * t[k] + f * t[k + 1]


def landing_cases(ds, settings: EvaluateSettings, radius: float) -> dict:
    """The racket contacts of a dataset set up for the landing evaluation.

    Returns:
        dict with ``event_id`` (N,), ``t0`` (N,) time of the last observation before the contact,
        ``ball`` (N, 9) fitted (position, velocity) there and the incoming spin, ``t_contact``
        (N,), ``racket`` (N, 18) (position, rotation matrix (9), velocity, angular velocity), ``measured``
        (N, 2) landing point, ``skip_counts``, ``n_contacts``.
    """
    from ttsim_jax.data.batch import segments_around
    from ttsim_jax.fit.contacts import quat_to_matrix

    fit = settings.fit
    rk, ev = ds.rackets, ds.events
    ev_row = {int(e): i for i, e in enumerate(ev["event_id"])}
    ids = np.asarray(rk["event_id"], np.int64)
    rows = np.array([ev_row[int(e)] for e in ids], np.int64)
    sel = settings.keep(np.asarray(ev["session_id"])[rows]) if len(rows) else np.zeros(0, bool)
    in_rows, out_rows = segments_around(ds, ids)
    kinds = np.asarray(ev["kind"]).astype(str)
    index = ObservationIndex(ds)
    seg = ds.segments
    counts = {k: 0 for k in LANDING_SKIP_REASONS}
    out = dict(event_id=[], t0=[], ball=[], t_contact=[], racket=[], measured=[])
    for i in np.flatnonzero(sel):
        t_c = float(ev["t"][rows[i]])
        if in_rows[i] < 0:
            counts["no_incoming_segment"] += 1
            continue
        t, p = index.near(in_rows[i], t_c, True, fit)
        if len(t) < fit.min_samples:
            counts["few_incoming_samples"] += 1
            continue
        spin, conf = index.spin(in_rows[i])
        if conf < fit.min_spin_conf:
            counts["low_spin_conf_in"] += 1
            continue
        p0, v0, r = fit_contact_state(t, p, t[-1], fit.degree)
        if r > fit.max_fit_rmse:
            counts["bad_fit"] += 1
            continue
        if out_rows[i] < 0:
            counts["no_outgoing_segment"] += 1
            continue
        end = int(seg["end_event_id"][out_rows[i]])
        if end >= 0 and kinds[ev_row[end]] == "table":
            measured = np.array([ev["x"][ev_row[end]], ev["y"][ev_row[end]]], np.float64)
        else:
            o = index.rows(out_rows[i])
            cross = crossing(index.t[o], index.pos[o], radius)
            measured = None if cross is None else cross[0]
        if measured is None:
            counts["no_measured_landing"] += 1
            continue
        q = np.array([rk[k][i] for k in ("qw", "qx", "qy", "qz")], np.float64)
        racket = np.concatenate([[rk[k][i] for k in ("x", "y", "z")], quat_to_matrix(q).ravel(),
                                 [rk[k][i] for k in ("vx", "vy", "vz")], [rk[k][i] for k in ("wx", "wy", "wz")]])
        out["event_id"].append(int(ids[i]))
        out["t0"].append(float(t[-1]))
        out["ball"].append(np.concatenate([p0, v0, spin]))
        out["t_contact"].append(t_c)
        out["racket"].append(racket)
        out["measured"].append(measured)
    res = {k: np.asarray(v, np.float64).reshape((len(v),) + ((9,) if k == "ball" else (18,) if k == "racket" else
                                                              (2,) if k == "measured" else ())) for k, v in out.items()}
    res["event_id"] = res["event_id"].astype(np.int64)
    res["skip_counts"] = {k: v for k, v in counts.items() if v}
    res["n_contacts"] = int(sel.sum())
    return res


def _schedule(cases: dict, n_steps: int, dt: float, dtype):
    """Per-ball racket schedules (B, T, 1, ...): the measured racket moving at its velocity, withdrawn
    (face shrunk to nothing) after the contact time plus :data:`RACKET_WITHDRAW`."""
    from ttsim_jax.state import Racket

    r = cases["racket"]
    b = len(r)
    t = cases["t0"][:, None] + dt * np.arange(n_steps)[None, :]  # (B, T) step start times
    rel = t - cases["t_contact"][:, None]
    pos = r[:, None, 0:3] + rel[..., None] * r[:, None, 12:15]
    rot = np.broadcast_to(r[:, None, 3:12].reshape(b, 1, 3, 3), (b, n_steps, 3, 3))
    vel = np.broadcast_to(r[:, None, 12:15], (b, n_steps, 3))
    ang = np.broadcast_to(r[:, None, 15:18], (b, n_steps, 3))
    face = np.where((rel <= RACKET_WITHDRAW)[..., None], np.asarray(LANDING_FACE), 0.0)
    as_j = lambda a: jnp.asarray(np.asarray(a)[:, :, None], dtype)  # noqa: E731
    return Racket(pos=as_j(pos), rot=as_j(rot), vel=as_j(vel), ang_vel=as_j(ang), face=as_j(face))


def simulate_landing(model, cases: dict, settings: EvaluateSettings) -> tuple[np.ndarray, np.ndarray]:
    """Rolls the model out from each case's pre-contact state and finds where it reaches the table plane.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model`.
        cases: from :func:`landing_cases`.
        settings: ``dt``, ``horizon``, ``chunk``.

    Returns:
        (landing (N, 2) [m], NaN where the ball was not hit or did not reach the plane within the
        horizon; hit (N,) bool, whether the simulated ball met the racket).
    """
    from ttsim_jax import init_state, rollout
    from ttsim_jax.kernel.step import ball_properties
    from ttsim_jax.physics.events import RACKET, TABLE
    from ttsim_jax.state import Ball

    n = len(cases["t0"])
    model = model.replace(name="")  # the name is static: models differing only in values share a compilation
    dtype = model.ball.radius.dtype
    radius = float(ball_properties(model)[0])
    n_steps = int(math.ceil(settings.horizon / settings.dt))
    landing, hit = np.full((n, 2), np.nan), np.zeros(n, bool)
    b = min(settings.chunk, max(8, 1 << (n - 1).bit_length()))
    for lo in range(0, n, b):
        idx = np.minimum(np.arange(lo, lo + b), n - 1)  # the last chunk repeats its last case
        sub = {k: v[idx] for k, v in cases.items() if isinstance(v, np.ndarray)}
        # Times relative to each case's start keep float32 clocks exact; the racket schedule is
        # built on the same relative clock.
        rel = dict(sub, t_contact=sub["t_contact"] - sub["t0"], t0=np.zeros(b))
        ball = Ball(*(jnp.asarray(sub["ball"][:, k:k + 3], dtype) for k in (0, 3, 6)))
        state = init_state(ball, jnp.zeros((), dtype))
        _, out = rollout(model, state, n_steps, settings.dt, _schedule(rel, n_steps, settings.dt, dtype),
                         max_events=4, record_every=1, remat=False)
        kind = np.asarray(out.events.kind)
        etime = np.asarray(out.events.time, np.float64)
        epos = np.asarray(out.events.pre.pos, np.float64)
        traj = np.asarray(out.trajectory.pos, np.float64)
        times = np.asarray(out.times, np.float64)
        for j in range(min(b, n - lo)):
            r = np.flatnonzero(kind[j] == RACKET)
            if not len(r):
                continue
            hit[lo + j] = True
            t_hit = etime[j, r[0]]
            table = np.flatnonzero((kind[j] == TABLE) & (etime[j] > t_hit))
            after = times > t_hit
            path = crossing(times[after], traj[j, after], radius)
            if len(table) and (path is None or etime[j, table[0]] <= path[1]):
                landing[lo + j] = epos[j, table[0], :2]
            elif path is not None:
                landing[lo + j] = path[0]
    return landing, hit


def landing_stage(ds, models: list, settings: EvaluateSettings, tick: Callable = lambda: None) -> dict:
    """Landing-position errors per model (see the module docstring).

    Returns:
        dict: ``skipped`` (a reason) or ``event_id`` (N,), ``measured`` (N, 2), ``landing``
        {name: (N, 2)}, ``error`` {name: (N,) distance [m], NaN where the simulated ball was not
        hit or did not land}, ``hit`` {name: (N,) bool}, ``skip_counts``, ``n_contacts``.
    """
    from ttsim_jax.kernel.step import ball_properties

    if len(ds.rackets["event_id"]) == 0:
        for _ in models:
            tick()
        return dict(skipped="no racket states (the dataset's rackets table is empty): the rollouts need the racket")
    cases = landing_cases(ds, settings, float(ball_properties(models[0][1])[0]))
    if not len(cases["t0"]):
        for _ in models:
            tick()
        return dict(skipped=f"none of the {cases['n_contacts']} racket contacts is usable "
                    f"({_counts_text(cases['skip_counts'], LANDING_SKIP_REASONS)})")
    landing, hit, error = {}, {}, {}
    for name, model in models:
        landing[name], hit[name] = simulate_landing(model, cases, settings)
        error[name] = np.linalg.norm(landing[name] - cases["measured"], axis=1)
        tick()
    return dict(event_id=cases["event_id"], measured=cases["measured"], landing=landing, error=error, hit=hit,
                skip_counts=cases["skip_counts"], n_contacts=cases["n_contacts"])


# ---------------------------------------------------------------------------------------------- all
def evaluate_models(ds, models: Sequence, settings: EvaluateSettings = EvaluateSettings(), *,
                    stages: Sequence[str] = STAGES, progress: bool = False) -> dict:
    """Every stage of the evaluation for every model.

    Arguments:
        ds: a validated :class:`~ttsim_jax.data.Dataset`.
        models: bundled names, TOML paths or :class:`~ttsim_jax.params.Model` objects.
        settings: :class:`EvaluateSettings`.
        stages: which of :data:`STAGES` to run.
        progress: show a progress bar over stages x models.

    Returns:
        dict: ``models`` (names), ``reference`` (name), ``settings``, and per stage the dict of
        its ``*_stage`` function.
    """
    from tqdm import tqdm

    unknown = set(stages) - set(STAGES)
    if unknown:
        raise ValueError(f"stages: unknown {sorted(unknown)}; known: {list(STAGES)}")
    resolved = resolve_models(models, jnp.float64 if settings.float64 else jnp.float32)
    names = [n for n, _ in resolved]
    result = dict(models=names, reference=reference_name(names),
                  settings=dict(dataclasses.asdict(settings), fit=dataclasses.asdict(settings.fit)))
    run = dict(flight=flight_stage, table=table_stage, racket=racket_stage, landing=landing_stage)
    with tqdm(total=len(stages) * len(resolved), desc="evaluate", unit="model", disable=not progress) as bar:
        for stage in stages:
            bar.set_postfix_str(stage)
            result[stage] = run[stage](ds, resolved, settings, bar.update)
    return result


# ---------------------------------------------------------------------------------------------- summary
def summarise(result: dict) -> dict:
    """The numbers of the report (JSON-ready): per stage and model, medians, 75th percentiles,
    means and reductions in % against the reference model."""
    names, ref = result["models"], result["reference"]
    out = dict(models=names, reference=ref, settings=result["settings"])
    clean = lambda v: None if isinstance(v, float) and not math.isfinite(v) else v  # noqa: E731

    def tidy(d):
        if isinstance(d, dict):
            return {k: tidy(v) for k, v in d.items()}
        if isinstance(d, list):
            return [tidy(v) for v in d]
        return clean(d)

    if "flight" in result:
        f = result["flight"]
        if "skipped" in f:
            out["flight"] = dict(skipped=f["skipped"])
        else:
            per = _headline(f["rmse"], names, ref)
            out["flight"] = dict(n_segments=len(f["segment_id"]), spin_measured=f["spin_measured"],
                                 n_without_spin=f["n_without_spin"], unit="m", models=per)
    if "table" in result:
        t = result["table"]
        if "skipped" in t:
            out["table"] = dict(skipped=t["skipped"])
        else:
            per = {}
            for n in names:
                e = t["error"][n]
                per[n] = {c: dict(_stats(np.abs(e[:, k])), bias=_stats(e[:, k])["median"]) for k, c in enumerate(COMPONENTS)}
            for n in names:
                for c in COMPONENTS:
                    per[n][c]["reduction_median_pct"] = reduction(per[ref][c]["median"], per[n][c]["median"])
            out["table"] = dict(n_bounces=t["n_bounces"], n_used=len(t["event_id"]),
                                n_with_spin_in=int(np.sum(t["spin_known"][:, 0])),
                                n_with_spin=int(np.sum(t["spin_known"].all(1))), skip_counts=t["skip_counts"],
                                units=dict(velocity="m/s", spin="rad/s"), models=per)
    if "racket" in result:
        r = result["racket"]
        if "skipped" in r:
            out["racket"] = dict(skipped=r["skipped"])
        else:
            bands = [(label, sel) for label, _, _, sel in distance_bands(r["distance"], DISTANCE_BANDS)]
            bands.append(("all", np.ones(len(r["distance"]), bool)))
            per = {}
            for n in names:
                e = r["error"][n]
                per[n] = {label: dict(n=int(sel.sum()), **{c: dict(_stats(np.abs(e[sel, k])), bias=_stats(e[sel, k])["median"])
                                                             for k, c in enumerate(ERROR_NAMES)})
                          for label, sel in bands}
            for n in names:
                for label, _ in bands:
                    for c in ERROR_NAMES:
                        cell = per[n][label][c]
                        cell["reduction_median_pct"] = reduction(per[ref][label][c]["median"], cell["median"])
            out["racket"] = dict(n_contacts=r["n_contacts"], n_used=len(r["event_id"]), skip_counts=r["skip_counts"],
                                 frame="racket (x = face normal)", units=dict(velocity="m/s", spin="rad/s"),
                                 bands=[label for label, _ in bands], models=per)
    if "landing" in result:
        g = result["landing"]
        if "skipped" in g:
            out["landing"] = dict(skipped=g["skipped"])
        else:
            per = _headline(g["error"], names, ref)
            for n in names:
                per[n].update(not_hit=int(np.sum(~g["hit"][n])),
                              no_landing=int(np.sum(g["hit"][n] & ~np.isfinite(g["error"][n]))))
            out["landing"] = dict(n_contacts=g["n_contacts"], n_used=len(g["event_id"]), skip_counts=g["skip_counts"],
                                  unit="m", models=per)
    return tidy(out)


# ---------------------------------------------------------------------------------------------- files
FIGURES = dict(flight="flight_rmse.png", table="table_errors.png", racket="racket_errors.png",
               landing_hist="landing_hist.png", landing_xy="landing_xy.png")


def _num(v, fmt) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def _cell(stat: dict, velocity: bool) -> str:
    """'median (bias)' of a summary cell, 3 decimals for velocities [m/s], 1 for spins [rad/s]."""
    fmt = ".3f" if velocity else ".1f"
    return f"{_num(stat['median'], fmt)} ({_num(stat['bias'], '+' + fmt)})"


def _reduction(m: dict, key: str) -> str:
    """'26 [18, 33]': a reduction [%] and its bootstrap interval."""
    lo, hi = m[f"reduction_{key}_ci95"]
    return f"{_num(m[f'reduction_{key}_pct'], '.0f')} [{_num(lo, '.0f')}, {_num(hi, '.0f')}]"


def _table_md(head: list, rows: list) -> list:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]


SECTIONS = dict(flight="Flight segments: 3-D position RMSE", table="Table contacts: post-bounce errors",
                racket="Racket contacts: errors by contact distance", landing="Landing position")


def _flight_md(f: dict, names: list, figures: dict) -> list:
    mm = lambda v: _num(None if v is None else 1e3 * v, ".1f")  # noqa: E731
    rows = [[n, str(m["n"]), mm(m["median"]), mm(m["p75"]), _reduction(m, "median"), _reduction(m, "p75")]
            for n, m in f["models"].items()]
    spin = (f"segments with a measured spin ({f['n_without_spin']} without one left out)" if f["spin_measured"] else
            "segments, none with a measured spin: every model flies with spin 0")
    return ([f"{f['n_segments']} {spin}; initial position the first observation, initial velocity fitted per "
             "segment.", ""]
            + _table_md(["model", "n", "median [mm]", "75th pct [mm]", "median reduction [%] [95 % CI]",
                         "75th pct reduction [%] [95 % CI]"], rows)
            + ["", f"![flight RMSE]({figures['flight']})", ""])


def _table_contacts_md(t: dict, names: list, figures: dict) -> list:
    head = ["model"] + list(COMPONENTS)
    rows = [[n] + [_cell(per[c], c[0] == "v") for c in COMPONENTS] for n, per in t["models"].items()]
    reductions = [[n] + [_num(per[c]["reduction_median_pct"], ".0f") for c in COMPONENTS]
                  for n, per in t["models"].items()]
    return ([f"{t['n_used']} of {t['n_bounces']} bounces used; {t['n_with_spin_in']} with a measured pre-bounce spin "
             "(the others enter the models with spin 0), spin errors for the "
             f"{t['n_with_spin']} with measured spins on both sides. Skipped: "
             f"{_counts_text(t['skip_counts'], TABLE_SKIP_REASONS)}.",
             "Median |error| (bias: median signed error), velocity in m/s, spin in rad/s; world frame.", ""]
            + _table_md(head, rows) + ["", "Reduction of the median |error| [%]:", ""] + _table_md(head, reductions)
            + ["", f"![table contact errors]({figures['table']})", ""])


def _racket_md(r: dict, names: list, figures: dict) -> list:
    head = ["model"] + [f"{b} (n={r['models'][names[0]][b]['n']})" for b in r["bands"]]
    rows = [[f"{n} {q}"] + [_cell(per[b][q], q == "|v|") for b in r["bands"]]
            for q in ("|v|", "|w|") for n, per in r["models"].items()]
    components = [[n] + [_num(per["all"][c]["median"], ".3f" if c[0] == "v" else ".1f") for c in COMPONENTS]
                  for n, per in r["models"].items()]
    return ([f"{r['n_used']} of {r['n_contacts']} racket contacts used (usable for every model). Skipped: "
             f"{_counts_text(r['skip_counts'], _skip_reasons())}.",
             "Median |error| of the speed |v| [m/s] and spin magnitude |w| [rad/s] after the contact (bias in "
             "brackets), per band of contact distance from the face centre; racket frame.", ""]
            + _table_md(head, rows) + ["", "All bands, median |error| per component (racket frame):", ""]
            + _table_md(["model"] + list(COMPONENTS), components)
            + ["", f"![racket contact errors]({figures['racket']})", ""])


def _landing_md(g: dict, names: list, figures: dict) -> list:
    rows = [[n, str(m["n"]), _num(m["median"], ".3f"), _num(m["p75"], ".3f"), _reduction(m, "median"),
             _reduction(m, "p75"), str(m["not_hit"]), str(m["no_landing"])] for n, m in g["models"].items()]
    return ([f"{g['n_used']} of {g['n_contacts']} racket contacts used. Skipped: "
             f"{_counts_text(g['skip_counts'], LANDING_SKIP_REASONS)}. Simulated from the last observation before the "
             "contact with the measured racket state until the table plane.", ""]
            + _table_md(["model", "n", "median [m]", "75th pct [m]", "median reduction [%] [95 % CI]",
                         "75th pct reduction [%] [95 % CI]", "racket missed", "no landing"], rows)
            + ["", f"![landing error histogram]({figures['landing_hist']})",
               f"![landing points]({figures['landing_xy']})", ""])


def markdown(summary: dict, figures: dict, data: str = "") -> str:
    """The report: one section per stage, tables of the summary's numbers and links to the figures
    (a skipped stage: its reason)."""
    names, ref = summary["models"], summary["reference"]
    lines = [f"# Model evaluation{f' on {data}' if data else ''}", "",
             f"Models: {', '.join(names)}. Reductions are relative to **{ref}** (positive: smaller error); "
             f"95 % intervals from a paired bootstrap over the items ({BOOTSTRAP} draws).", ""]
    body = dict(flight=_flight_md, table=_table_contacts_md, racket=_racket_md, landing=_landing_md)
    for stage in STAGES:
        if stage not in summary:
            continue
        part = summary[stage]
        lines += [f"## {SECTIONS[stage]}", ""]
        lines += [f"Skipped: {part['skipped']}.", ""] if "skipped" in part else body[stage](part, names, figures)
    lines += ["Every number: `metrics.json`; per-item values: `samples.npz`.", ""]
    return "\n".join(lines)


def _samples(result: dict) -> dict:
    """Flat per-item arrays for ``samples.npz`` (stage/quantity[/model])."""
    out = {}
    for stage in STAGES:
        r = result.get(stage)
        if not r or "skipped" in r:
            continue
        for key, value in r.items():
            if isinstance(value, dict):
                if key == "skip_counts":
                    continue
                for name, arr in value.items():
                    out[f"{stage}/{key}/{name}"] = np.asarray(arr)
            elif isinstance(value, np.ndarray):
                out[f"{stage}/{key}"] = value
    return out


def write_report(result: dict, out_dir, data: str = "") -> dict:
    """Writes ``report.md``, ``metrics.json``, ``samples.npz`` and the figures to ``out_dir``.

    Arguments:
        result: from :func:`evaluate_models`.
        out_dir: output directory (created).
        data: the dataset's name or path, for the report's title.

    Returns:
        {what: path} of the files written.
    """
    from ttsim_jax import plots

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = result["models"]
    summary = summarise(result)
    paths = {}
    if "flight" in result and "skipped" not in result["flight"]:
        paths["flight"] = plots.plot_violins({"": {n: 1e3 * result["flight"]["rmse"][n] for n in names}},
                                             out / FIGURES["flight"], ylabel="3-D position RMSE [mm]",
                                             title="flight segments: position RMSE per model")
    if "table" in result and "skipped" not in result["table"]:
        e = result["table"]["error"]
        paths["table"] = plots.plot_violins({c: {n: e[n][:, k] for n in names} for k, c in enumerate(COMPONENTS)},
                                            out / FIGURES["table"], ylabel="predicted - measured (m/s | rad/s)",
                                            title="table contact: post-bounce errors per component",
                                            panels=(COMPONENTS[:3], COMPONENTS[3:]))
    if "racket" in result and "skipped" not in result["racket"]:
        r = result["racket"]
        bands = distance_bands(r["distance"], DISTANCE_BANDS)
        groups = {}
        for k, q in ((6, "|v| [m/s]"), (7, "|w| [rad/s]")):
            for label, _, _, sel in bands:
                groups[f"{q} {label}"] = {n: r["error"][n][sel, k] for n in names}
        keys = list(groups)
        paths["racket"] = plots.plot_violins(groups, out / FIGURES["racket"], ylabel="magnitude error (predicted - measured)",
                                             title="racket contact: speed and spin magnitude errors by contact distance",
                                             panels=(keys[:len(bands)], keys[len(bands):]))
    if "landing" in result and "skipped" not in result["landing"]:
        g = result["landing"]
        paths["landing_hist"], paths["landing_xy"] = plots.plot_landing(
            g["error"], g["landing"], g["measured"], out / FIGURES["landing_hist"], out / FIGURES["landing_xy"])
    (out / "metrics.json").write_text(json.dumps(summary, indent=1, allow_nan=False) + "\n")
    paths["metrics"] = out / "metrics.json"
    np.savez_compressed(out / "samples.npz", **_samples(result))
    paths["samples"] = out / "samples.npz"
    (out / "report.md").write_text(markdown(summary, FIGURES, data))
    paths["report"] = out / "report.md"
    return paths
