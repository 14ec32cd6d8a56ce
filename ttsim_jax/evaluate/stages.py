"""The paper's Results section on any dataset: models compared stage by stage (``ttsim evaluate``).

:func:`evaluate_models` computes, for each model, the four evaluations of the paper's Results
section on a :class:`~ttsim_jax.data.Dataset`; :mod:`ttsim_jax.evaluate.report` summarises them
and writes the figures (PNG), a Markdown report and every number.

1. *flight*: per flight segment (those with a measured spin, when the data has any), the 3-D
   position RMSE of the model's flight with the initial velocity fitted
   (:func:`ttsim_jax.fit.flight.flight_rmse`); median, 75th percentile and their reductions
   in % against the reference model (nakashima2011 when compared, else the first model), with
   paired bootstrap intervals.
2. *table*: per table bounce, the model's table contact (the rally kernel's
   :func:`~ttsim_jax.kernel.ball_step.respond`) applied to the measured pre-bounce state, minus the
   measured post-bounce state, per component (v_x, v_y, v_z, w_x, w_y, w_z; spin components only
   where both segments have a measured spin). An unmeasured pre-bounce spin enters as the
   incoming segment's latent spin, fitted under each model (``spin="auto"``, the default; see
   :class:`EvaluateSettings`), or as 0 (``"measured"``, ``"zero"``). States
   are estimated as for the racket residual's training data
   (:func:`ttsim_jax.data.contact_states.estimate_contact`: polynomial fits next to the contact, the
   segments' spins).
3. *racket*: per racket contact with a racket state, the model's racket contact (base model plus
   its residual network, if it carries one) minus the observation, in the racket frame
   (:func:`ttsim_jax.fit.racket_arrays.contact_arrays`), grouped by contact distance (0-5, 5-8,
   > 8 cm); every model is scored on the same contacts (those usable for all).
4. *landing*: from the state at the last observation before a racket contact (fitted on the
   incoming samples; the segment's spin, measured or latent as for the table stage) the model is rolled out (:func:`ttsim_jax.rollout`) with
   the data's racket state (moving at its measured velocity) until the ball reaches the table
   plane (z = one radius, whether or not it meets the table); the landing point is compared with
   the measured one (the next table event, or where the outgoing observations cross the plane).

A stage whose data the dataset lacks (no racket states, no bounces) is skipped, with the reason
in the report.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.data import racket_configs
from ttsim_jax.data.contact_states import SKIP_REASONS, ContactFit, fit_contact_state
from ttsim_jax.data.tables import id_index, rows_of
from ttsim_jax.files.programs import stored_jit
from ttsim_jax.fit.network_evaluation import contact_errors
from ttsim_jax.fit.racket_arrays import contact_arrays

from ttsim_jax.results import Skipped

from .result import STAGES, Evaluation, LandingStage, RacketStage, TableStage
from .spins import incoming_spins
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
    "low_spin_conf_in": "incoming segment's spin confidence below min_spin_conf (with spin = \"measured\")",
    "bad_fit": "polynomial fit RMSE above max_fit_rmse",
    "no_outgoing_segment": "no flight segment starts at the racket contact",
    "no_measured_landing": "the outgoing flight neither ends on the table nor crosses the table plane",
}


@dataclasses.dataclass(frozen=True)
class EvaluateSettings:
    """How the evaluation selects and estimates.

    Attributes:
        fit: state estimation next to contacts (:class:`~ttsim_jax.data.contact_states.ContactFit`).
        min_samples: flight segments with fewer observations are left out.
        dt: integration step of the landing rollouts [s].
        horizon: longest landing rollout [s]; a ball not reaching the table plane by then has no
            landing point.
        chunk: most racket contacts per compiled landing rollout (fewer contacts: the power of two
            above their number; the last chunk is padded).
        sessions: evaluate only these session ids (None: all).
        float64: load the models (names and TOML files) in float64; by default float32, the
            simulator's usual type, whatever JAX's default float is.
        spin: where a flight segment's spin comes from (``"auto"``: the measured one where there is
            one, the latent spin fitted from the segment's samples elsewhere; ``"measured"``,
            ``"latent"``, ``"zero"``: see :func:`ttsim_jax.fit.flight.segment_rmse`), in every
            stage: the table and landing stages take the incoming segment's spin the same way
            (with ``"measured"``, a bounce without a measured spin enters with spin 0 and a racket
            contact without one is skipped).
    """

    fit: ContactFit = ContactFit()
    min_samples: int = 5
    dt: float = 1e-3
    horizon: float = 1.5
    chunk: int = 256
    sessions: tuple | None = None
    float64: bool = False
    spin: str = "auto"

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
    from ttsim_jax.params import ConfigError, Model, load_model, resolve_model_path, split_model_name

    out = []
    for spec in models:
        if isinstance(spec, Model):
            name, model = spec.name, spec
        else:
            base, racket = split_model_name(spec)
            path = resolve_model_path(base)
            model = load_model(spec, dtype=dtype)
            name = str(spec) if path != Path(str(base)) or racket else path.stem
        if any(name == n for n, _ in out):
            raise ConfigError(f"models: two models are named {name!r} ({spec!r}); rename the .toml file")
        out.append((name, model))
    if not out:
        raise ConfigError("models: none given")
    return out


def reference_name(names: Sequence[str]) -> str:
    """The model reductions are measured against: nakashima2011 if compared, else the first."""
    return REFERENCE if REFERENCE in names else names[0]


# ---------------------------------------------------------------------------------------------- flight
def flight_stage(ds, models: list, settings: EvaluateSettings, tick: Callable = lambda: None):
    """Flight-segment 3-D position RMSE per model (see the module docstring): the segments of
    ``settings.sessions`` with at least ``settings.min_samples`` observations, those with a spin
    confidence >= ``settings.fit.min_spin_conf`` when the data has any.

    Returns:
        What :func:`ttsim_jax.fit.flight.segment_rmse` returns: a
        :class:`~ttsim_jax.fit.flight.FlightStage` or :class:`~ttsim_jax.results.Skipped`.
    """
    from ttsim_jax.fit.flight import segment_rmse

    return segment_rmse(ds, models, min_samples=settings.min_samples, min_spin_conf=settings.fit.min_spin_conf,
                        sessions=settings.sessions, spin=settings.spin, tick=tick)


# ---------------------------------------------------------------------------------------------- table
@jax.jit
def _table_response(model, pos, vel, spin):
    from ttsim_jax.kernel.ball_step import respond
    from ttsim_jax.physics.events import TABLE
    from ttsim_jax.state import Ball

    def one(p, v, w):
        post, _, _ = respond(model, Ball(p, v, w), TABLE, None)
        return post.vel, post.spin

    return jax.vmap(one)(pos, vel, spin)


def table_stage(ds, models: list, settings: EvaluateSettings, tick: Callable = lambda: None) -> TableStage | Skipped:
    """Table-contact errors per model (see the module docstring).

    Returns:
        A :class:`~ttsim_jax.evaluate.result.TableStage`, or :class:`~ttsim_jax.results.Skipped`
        without a usable table bounce.
    """
    ev = ds.events
    rows = np.flatnonzero((np.asarray(ev["kind"]).astype(str) == "table") & settings.keep(ev["session_id"]))
    if not len(rows):
        for _ in models:
            tick()
        return Skipped("no table bounce (event kind 'table') in the dataset")
    ids = np.asarray(ev["event_id"], np.int64)[rows]
    c = ds.contacts(settings.fit)
    at = c.rows(ids)
    reasons = c.skip_reasons(need_spin=False)[at]
    reasons[(reasons == None) & (c.vel_in[at, 2] >= 0.0)] = "not_falling"  # noqa: E711 (an object array)
    reasons[(reasons == None) & (c.vel_out[at, 2] <= 0.0)] = "not_rising"  # noqa: E711
    counts = {k: int(np.sum(reasons == k)) for k in TABLE_SKIP_REASONS}
    skip_counts = {k: v for k, v in counts.items() if v}
    good = np.flatnonzero(reasons == None)  # noqa: E711
    if not len(good):
        for _ in models:
            tick()
        return Skipped(f"none of the {len(rows)} table bounces is usable ({counts_text(skip_counts, TABLE_SKIP_REASONS)})")
    g = at[good]
    spin_known = c.spin_known[g]
    p_c = c.pos[at]
    pre = np.concatenate([c.vel_in[g], np.where(spin_known[:, :1], c.spin_in[g], 0.0)], 1)
    post = np.concatenate([c.vel_out[g], c.spin_out[g]], 1)
    spin_in, source, _ = incoming_spins(ds, models, c.in_row[g], spin_known[:, 0], c.spin_in[g], settings.spin)
    error = {}
    for name, model in models:
        dtype = model.ball.radius.dtype
        vel, spin = _table_response(model.replace(name=""), jnp.asarray(p_c[good], dtype), jnp.asarray(pre[:, :3], dtype),
                                    jnp.asarray(spin_in[name], dtype))
        e = np.concatenate([np.asarray(vel, np.float64), np.asarray(spin, np.float64)], 1) - post
        e[~spin_known.all(1), 3:] = np.nan
        error[name] = e
        tick()
    return TableStage(event_id=ids[good], spin_known=spin_known, pre=pre, post=post, spin_in=spin_in, spin_source=source,
                      error=error, skip_counts=skip_counts, n_bounces=len(rows))


def counts_text(counts: dict, reasons: dict) -> str:
    """'2 bad_fit: polynomial fit RMSE above max_fit_rmse; ...': skip counts with their reasons."""
    return "; ".join(f"{n} {k}: {reasons.get(k, k)}" for k, n in counts.items()) or "none skipped"


#: Why a stage that needs racket states has none.
NO_RACKET_STATES = "no racket states (the dataset's rackets table is empty)"


def no_usable_contacts(n_contacts: int, counts: dict, reasons: dict = SKIP_REASONS) -> Skipped:
    """The reason a stage skips when none of ``n_contacts`` racket contacts is usable, with the
    counts of what left each out (``reasons``: their descriptions)."""
    return Skipped(f"none of the {n_contacts} racket contacts is usable ({counts_text(counts, reasons)})")


# ---------------------------------------------------------------------------------------------- racket
def racket_stage(ds, models: list, settings: EvaluateSettings, tick: Callable = lambda: None) -> RacketStage | Skipped:
    """Racket-contact errors per model, in the racket frame, on the contacts usable for every model.

    Returns:
        A :class:`~ttsim_jax.evaluate.result.RacketStage`, or :class:`~ttsim_jax.results.Skipped`
        without racket states or a contact usable for every model.
    """
    from ttsim_jax.fit.network_evaluation import predict

    n_states = len(ds.rackets["event_id"])
    if n_states == 0:
        for _ in models:
            tick()
        return Skipped(NO_RACKET_STATES)
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
        return no_usable_contacts(first.n_contacts, first.counts())
    event_ids = np.array(sorted(common), np.int64)
    error, predicted, x, y_obs = {}, {}, None, None
    for name, _ in models:
        a, _, y = arrays[name]
        rows = rows_of(id_index(a.event_id), event_ids)
        error[name] = contact_errors(y[rows], a.y_obs[rows])
        predicted[name] = np.asarray(y[rows], np.float64)
        if x is None:
            x, y_obs = np.asarray(a.x[rows], np.float64), np.asarray(a.y_obs[rows], np.float64)
        tick()
    config, rubber_type, tilt = racket_configs.of_events(ds, event_ids)
    return RacketStage(event_id=event_ids, distance=np.linalg.norm(x[:, 6:8], axis=1), x=x, error=error,
                       predicted=predicted, y_obs=y_obs, config=config, rubber_type=rubber_type, tilt=tilt,
                       skip_counts=first.counts(), n_contacts=first.n_contacts)


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
        dict with ``event_id`` (N,), ``in_row`` (N,) the incoming segment's row, ``spin_known``
        (N,) whether its spin is measured, ``t0`` (N,) time of the last observation before the
        contact, ``ball`` (N, 9) fitted (position, velocity) there and the incoming segment's
        measured spin (zeros without one: :func:`landing_stage` sets each model's), ``t_contact``
        (N,), ``racket`` (N, 18) (position, rotation matrix (9), velocity, angular velocity), ``measured``
        (N, 2) landing point, ``skip_counts``, ``n_contacts``.
    """
    from ttsim_jax.physics.rotations import quat_to_matrix

    fit = settings.fit
    rk, ev = ds.rackets, ds.events
    ids = np.asarray(rk["event_id"], np.int64)
    rows = ds.event_rows(ids)
    sel = settings.keep(np.asarray(ev["session_id"])[rows]) if len(rows) else np.zeros(0, bool)
    in_rows, out_rows = ds.segments_around(ids)
    kinds = np.asarray(ev["kind"]).astype(str)
    index = ds.observation_index()
    seg = ds.segments
    counts = {k: 0 for k in LANDING_SKIP_REASONS}
    out = dict(event_id=[], in_row=[], spin_known=[], t0=[], ball=[], t_contact=[], racket=[], measured=[])
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
        if conf < fit.min_spin_conf and settings.spin == "measured":
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
        end_row = int(ds.event_rows([end])[0]) if end >= 0 else -1
        if end_row >= 0 and kinds[end_row] == "table":
            measured = np.array([ev["x"][end_row], ev["y"][end_row]], np.float64)
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
        out["in_row"].append(int(in_rows[i]))
        out["spin_known"].append(conf >= fit.min_spin_conf)
        out["t0"].append(float(t[-1]))
        out["ball"].append(np.concatenate([p0, v0, spin]))
        out["t_contact"].append(t_c)
        out["racket"].append(racket)
        out["measured"].append(measured)
    res = {k: np.asarray(v, np.float64).reshape((len(v),) + ((9,) if k == "ball" else (18,) if k == "racket" else
                                                              (2,) if k == "measured" else ())) for k, v in out.items()}
    res["event_id"] = res["event_id"].astype(np.int64)
    res["in_row"] = res["in_row"].astype(np.int64)
    res["spin_known"] = res["spin_known"].astype(bool)
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


@stored_jit(static_argnames=("n_steps",))
def _landing_rollout(model, ball, schedule, dt, n_steps: int) -> dict:
    """The rollouts of :func:`simulate_landing` from ``ball``: their event logs and trajectories. A
    program kept on disk (:func:`~ttsim_jax.files.programs.stored_jit`): tracing the rally kernel
    with its racket takes seconds, once per process otherwise."""
    from ttsim_jax import Execution, Record, init_state, rollout

    state = init_state(ball, jnp.zeros((), ball.pos.dtype))
    _, out = rollout(model, state, n_steps, dt, schedule, record=Record(max_events=4, every=1),
                     execution=Execution(remat=False))
    return dict(kind=out.events.kind, time=out.events.time, pre_pos=out.events.pre.pos, trajectory=out.trajectory.pos,
                times=out.times)


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
    from ttsim_jax.kernel.ball_step import ball_properties
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
        schedule = _schedule(rel, n_steps, settings.dt, dtype)
        out = _landing_rollout(model, ball, schedule, jnp.asarray(settings.dt, dtype), n_steps=n_steps)
        kind = np.asarray(out["kind"])
        etime = np.asarray(out["time"], np.float64)
        epos = np.asarray(out["pre_pos"], np.float64)
        traj = np.asarray(out["trajectory"], np.float64)
        times = np.asarray(out["times"], np.float64)
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


def landing_stage(ds, models: list, settings: EvaluateSettings, tick: Callable = lambda: None) -> LandingStage | Skipped:
    """Landing-position errors per model (see the module docstring).

    Returns:
        A :class:`~ttsim_jax.evaluate.result.LandingStage`, or :class:`~ttsim_jax.results.Skipped`
        without racket states or a usable contact.
    """
    from ttsim_jax.kernel.ball_step import ball_properties

    if len(ds.rackets["event_id"]) == 0:
        for _ in models:
            tick()
        return Skipped(f"{NO_RACKET_STATES}: the rollouts need the racket")
    cases = landing_cases(ds, settings, float(ball_properties(models[0][1])[0]))
    if not len(cases["t0"]):
        for _ in models:
            tick()
        return no_usable_contacts(cases["n_contacts"], cases["skip_counts"], LANDING_SKIP_REASONS)
    spins, source, bounce = incoming_spins(ds, models, cases["in_row"], cases["spin_known"], cases["ball"][:, 6:],
                                           settings.spin, through_bounce=True)
    landing, hit, error = {}, {}, {}
    for name, model in models:
        ball = cases["ball"].copy()
        ball[:, 6:] = spins[name]
        landing[name], hit[name] = simulate_landing(model, dict(cases, ball=ball), settings)
        error[name] = np.linalg.norm(landing[name] - cases["measured"], axis=1)
        tick()
    return LandingStage(event_id=cases["event_id"], measured=cases["measured"], landing=landing, error=error, hit=hit,
                        spin_source=source, through_bounce=bounce, skip_counts=cases["skip_counts"],
                        n_contacts=cases["n_contacts"])


# ---------------------------------------------------------------------------------------------- all
def evaluate_models(ds, models: Sequence, settings: EvaluateSettings = EvaluateSettings(), *,
                    stages: Sequence[str] = STAGES, progress: bool = False) -> Evaluation:
    """Every stage of the evaluation for every model.

    Arguments:
        ds: a validated :class:`~ttsim_jax.data.Dataset`.
        models: bundled names, TOML paths or :class:`~ttsim_jax.params.Model` objects.
        settings: :class:`EvaluateSettings`.
        stages: which of :data:`STAGES` to run.
        progress: show a progress bar over stages x models.

    Returns:
        An :class:`~ttsim_jax.evaluate.result.Evaluation`: per stage asked for, what its
        ``*_stage`` function returned.
    """
    from tqdm import tqdm

    unknown = set(stages) - set(STAGES)
    if unknown:
        raise ValueError(f"stages: unknown {sorted(unknown)}; known: {list(STAGES)}")
    resolved = resolve_models(models, jnp.float64 if settings.float64 else jnp.float32)
    names = [n for n, _ in resolved]
    run = dict(flight=flight_stage, table=table_stage, racket=racket_stage, landing=landing_stage)
    done = {}
    with tqdm(total=len(stages) * len(resolved), desc="evaluate", unit="model", disable=not progress) as bar:
        for stage in stages:
            bar.set_postfix_str(stage)
            done[stage] = run[stage](ds, resolved, settings, bar.update)
    return Evaluation(models=names, reference=reference_name(names),
                      settings=dataclasses.asdict(settings), **done)
