"""Which effect: each simulator effect of the catalogue fitted by gradient descent on a training
split and scored by its error reduction on the held-out split.

For a candidate effect (:func:`spec`), the phases it can change follow from its hooks
(:func:`phases_of`): ``air_velocity`` and ``air_properties`` act in flight, ``table_surface``,
``table_restitution`` and ``table_friction`` on table contacts, ``racket_coefficients`` on racket
contacts, and ``ball_properties`` and ``spin_derivative`` on all three (a spin that changes in flight also moves the contacts' spin
estimates, each segment's mean, away from the spin at the contact:
:func:`ttsim_jax.diagnose.stages.contact_spin`). Its free parameters are written ``start + scale * u`` with ``u``
starting at 0 (the effect neutral, or at the typical values of its fixed shape parameters, e.g. the
bump centres of ``table_unevenness``), so Adam's step size means the same for every parameter.
Effects drawn per session (``SCOPE == "session"``: air flow, ball variation, worn ball) get one set
of parameters per session, unless the sessions are too thin to fit them (:func:`pooled`: fewer
than :data:`MIN_SESSION_ITEMS` training items in the median session, as when every recorded throw
is a session of its own); then one set is shared by all sessions, since a session's parameters
fitted on one throw could be scored only on that throw.

The effects of one compilation group (:func:`groups`) are all attached in one compiled program,
and a fit frees only its own (the others stay exactly neutral), so a group costs one compilation.
The loss is the sum over the effect's phases of the training split's mean squared error divided by
the model's own (so each phase counts equally), plus a small ridge on ``u``. A flight segment's
mean squared error counts robustly (:func:`_mse`): a few segments that the segmentation cut wrongly
err fifty times more than the rest and would otherwise pull every fit towards themselves. The whole descent
(``steps`` Adam steps, a cosine-decayed step size, one warm-started Gauss-Newton step of each
flight segment's initial state per step) is one ``lax.scan`` in one jitted call, the data padded to
one capacity per phase. The descent flies only the training segments (:func:`flight_split`); the
others' initial states are fitted once at the end (:data:`~ttsim_jax.diagnose.stages.GN_START`
Gauss-Newton steps from the model's), with the effects found. The states' Jacobian costs seven
flights (forward differences: :func:`~ttsim_jax.diagnose.stages.difference_jacobian`), so a fresh
one is taken only every
:data:`JACOBIAN_EVERY` steps and in the final ones; the steps between reuse it with the latest
residuals (chord steps, which reach the same optimum).

Held-out score (:func:`score`): per phase, the reduction of the held-out RMS error against the
model's, 100 (1 - RMS_after / RMS_before) [%], with a 95 % paired bootstrap interval over held-out
segments / contacts. A candidate is *significant* when in some phase the interval's lower end is
above :data:`MIN_REDUCTION` % and the RMS error falls by more than that phase's :data:`MIN_GAIN`,
and in no phase it acts in is the held-out error materially worse (by as much, :func:`explains`);
candidates are ranked by their largest held-out reduction, significant ones first.

An effect whose parameters descent cannot start near their optimum gets a second descent from
starts found otherwise (:data:`REFINE`): the gusts of ``air_flow`` from a periodogram of the
flights' wind offsets (:mod:`ttsim_jax.diagnose.gusts`), the bumps of ``table_unevenness`` from a
scan of the table contacts' errors (:mod:`ttsim_jax.diagnose.bumps`), the onsets of ``buckling``
from a grid (:mod:`ttsim_jax.diagnose.onsets`).

A user adds a candidate by registering an effect (:func:`ttsim_jax.effects.register`); which of
its parameters are fitted is inferred (those whose typical value differs from the neutral one, at
the scale of that difference) unless the effect's parameters declare otherwise (``fit_scale``).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ttsim_jax import effects as fx
from ttsim_jax.diagnose import bumps, gusts, onsets, stages
from ttsim_jax.diagnose.bootstrap import group_weights, rms_reduction
from ttsim_jax.diagnose.defaults import MIN_REDUCTION
from ttsim_jax.diagnose.phases import Phases, pad_rows
from ttsim_jax.diagnose.specs import (HOOK_PHASES, PHASES, Spec,  # noqa: F401 (public here too)
                                      phases_of, spec)
from ttsim_jax.files.programs import stored_jit

#: Effects fitted in two descents: after the first, a function of (problem, model, specs, consts, u,
#: flight states, index) gives the effect's spec and per-session starts for a second one (or None
#: to keep the first): the gusts' frequencies are found by a periodogram of the flights' wind
#: offsets, which descent cannot do (:mod:`ttsim_jax.diagnose.gusts`); the bumps' centres by a scan
#: of the table contacts' errors linearised in the surface's slope (:mod:`ttsim_jax.diagnose.bumps`);
#: the onsets and widths of buckling by a grid over them (:mod:`ttsim_jax.diagnose.onsets`).
REFINE = {"air_flow": gusts.gust_stage, "table_unevenness": bumps.bump_stage, "buckling": onsets.onset_stage}
#: Gauss-Newton steps of the flight states after the descent (from the states it ended with).
FINAL_GN = 3
#: Descent steps per fresh Jacobian of the flight states (the steps between reuse it: the states
#: move little from one step to the next).
JACOBIAN_EVERY = 10
#: Items per stratum of the split (sorted by the model's error).
STRATUM = 5
#: Least fall of the held-out RMS error of a significant candidate, per phase [m, m/s, m/s]: a
#: reduction below the resolution of the phase's measurement is not a physical effect (with a
#: perfect model, the contact states' polynomial estimates still err by millimetres per second).
MIN_GAIN = {"flight": 5e-5, "table": 0.01, "racket": 0.01}
#: Least training items (segments and contacts) of the median session for per-session parameters.
MIN_SESSION_ITEMS = 5
#: Scale of the robust flight loss, in units of the median training segment's RMS error under the
#: model being fitted (:func:`_mse`); the gust periodogram leaves out segments beyond the same
#: multiple.
ROBUST = gusts.OUTLIER


def initial_u(specs, n_sessions: int) -> tuple:
    """Zeros of every free parameter (leading axis: sessions, or 1)."""
    return tuple({k: jnp.zeros(((n_sessions if s.per_session else 1),) + s.cls.PARAMS[k].shape, jnp.float32)
                  for k in s.free} for s in specs)


def parameters(sp: Spec, const: dict, u: dict, sessions) -> dict:
    """The fitted values {param: value} (per session {session id: {...}} for per-session effects)."""
    def values(i):
        return {k: (np.asarray(stages.start_of(sp, const, k, i), np.float64) + const["scale"][k] *
                    np.asarray(u[k][i], np.float64)).tolist()
                if k in u else np.asarray(stages.start_of(sp, const, k, i)).tolist() for k in sp.cls.PARAMS}

    if sp.per_session:
        return {int(s): values(i) for i, s in enumerate(sessions)}
    return values(0)


# ---------------------------------------------------------------------------------------------- the problem
@dataclasses.dataclass
class Problem:
    """Padded JAX arrays of every phase, the split, and the model's own errors.

    Attributes:
        data: {phase: dict of arrays}, each with ``train`` and ``test`` weights per row (0 for
            padding); ``phases``: the phases present; ``n_sessions``; ``x0``: (S, 6) the flight
            segments' fitted initial states under the model; ``base``: {phase: per-row errors of
            the model}; ``norm``: {phase: the model's training mean squared error}; ``pooled``:
            per-session effects share one parameter set (:func:`pooled`).
    """

    data: dict
    phases: tuple
    n_sessions: int
    sessions: np.ndarray
    x0: jnp.ndarray | None = None
    base: dict = dataclasses.field(default_factory=dict)
    norm: dict = dataclasses.field(default_factory=dict)
    pooled: bool = False


def pooled(pb: Problem) -> bool:
    """Whether the median session (of those with items) holds fewer than :data:`MIN_SESSION_ITEMS`
    training segments and contacts, too few to fit per-session parameters."""
    count = np.zeros(pb.n_sessions)
    for d in pb.data.values():
        np.add.at(count, np.asarray(d["session"]), np.asarray(d["train"], np.float64))
    used = count[count > 0]
    return bool(len(used) and np.median(used) < MIN_SESSION_ITEMS)


def _split(score, n: int, rows: int, test_fraction: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """(train, test) weights (rows,): the first n rows split at random, stratified by ``score``.

    Rows sorted by ``score`` (the model's own error) are cut into blocks of :data:`STRATUM` and a
    share ``test_fraction`` of each block is held out, so that the rare large errors (an effect
    acting in a narrow regime) fall on both sides. The split depends on the model only, never on
    a candidate.
    """
    test = np.zeros(rows, np.float32)
    order = np.argsort(np.asarray(score, np.float64)[:n], kind="stable")
    for lo in range(0, n, STRATUM):
        block = order[lo:lo + STRATUM]
        k = rng.binomial(len(block), test_fraction) if len(block) < STRATUM else int(round(test_fraction * len(block)))
        test[rng.permutation(block)[:k]] = 1.0
    real = np.zeros(rows, np.float32)
    real[:n] = 1.0
    return real * (1.0 - test), test


def _pad_contacts(c):
    n = len(c)
    idx = np.minimum(np.arange(pad_rows(n)), n - 1)
    f = lambda a: jnp.asarray(np.asarray(a)[idx], jnp.float32)  # noqa: E731
    return dict(pos=f(c.pos), x=f(c.x), y_obs=f(c.y_obs), known=f(c.spin_known.astype(np.float32)),
                known_in=f(c.spin_in_known.astype(np.float32)), world_in=f(c.world_in), world_out=f(c.world_out),
                rot=f(c.rot), t=f(c.t), spin_dt=f(c.spin_dt),
                correction=f(c.correction), session=jnp.asarray(c.session[idx], jnp.int32))


def problem(ph: Phases, model, test_fraction: float = 0.4, seed: int = 0) -> Problem:
    """The padded arrays of ``ph``, the model's own errors on them (one compilation) and a seeded
    split of the segments / contacts stratified by those errors (:func:`_split`)."""
    rng = np.random.default_rng(seed)
    data, real = {}, {}
    if ph.flights is not None:
        fl = ph.flights
        f = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
        data["flight"] = dict(t0=f(fl.t0), tau=f(fl.tau), pos=f(fl.pos), mask=f(fl.mask), spin=f(fl.spin),
                              session=jnp.asarray(fl.session, jnp.int32))
        real["flight"] = fl.n
    for name in ("table", "racket"):
        c = getattr(ph, name)
        if c is not None:
            data[name] = _pad_contacts(c)
            real[name] = len(c)
    pb = Problem(data=data, phases=tuple(p for p in PHASES if p in data), n_sessions=len(ph.sessions), sessions=ph.sessions)
    if "flight" in data:
        d = data["flight"]
        pb.x0 = _initial(d["tau"], d["pos"], d["mask"])
    pb.base, pb.x0 = evaluate(model, (), (), (), pb, stages.GN_START)
    for p in pb.phases:
        sse, n = item_sums(pb, p, pb.base[p])
        train, test = _split(sse / np.maximum(n, 1.0), real[p], len(sse), test_fraction, rng)
        data[p]["train"], data[p]["test"] = jnp.asarray(train), jnp.asarray(test)
    for p in pb.phases:
        sse, n = item_sums(pb, p, pb.base[p])
        w = np.asarray(pb.data[p]["train"])
        pb.norm[p] = float(max(np.sum(w * sse) / max(np.sum(w * n), 1.0), 1e-20))
    pb.pooled = pooled(pb)
    return pb


_initial = jax.jit(stages.initial_state)


def item_sums(pb: Problem, phase: str, errors) -> tuple[np.ndarray, np.ndarray]:
    """Per row: (sum of squared error norms, number of items): flight, over the segment's samples
    (3-D position errors); contacts, one item (the 6-vector of :mod:`~ttsim_jax.diagnose.stages`)."""
    e = np.asarray(errors, np.float64)
    if phase == "flight":
        return np.sum(e**2, axis=(1, 2)), np.asarray(pb.data["flight"]["mask"], np.float64).sum(1)
    return np.sum(e**2, axis=1), np.ones(len(e))


# ---------------------------------------------------------------------------------------------- jitted
def _errors(model, specs, consts, u, data, x, phases, iterations):
    out = {}
    if "flight" in phases:
        if iterations:
            x = stages.flight_states(model, specs, consts, u, data["flight"], x, iterations)
        out["flight"] = stages.flight_errors(model, specs, consts, u, data["flight"], x)
    for p in ("table", "racket"):
        if p in phases:
            out[p] = stages.ERRORS[p](model, specs, consts, u, data[p])
    return out, x


def _mse(phase, e, d, w, robust=False):
    """Weighted mean squared error norm per item, as :func:`item_sums` counts them.

    ``robust`` (flight): a segment of n samples and mean squared error m counts as
    n c2 log(1 + m / c2) instead of n m, with c2 = ROBUST^2 times the median m of the weighted
    segments (held fixed in the gradient): about the same for a typical segment (m = c2 / 9 counts
    0.95 m), while a segment far above the scale weighs c2 / m of its plain weight in the gradient.
    The scale follows the errors of the model being fitted, so a segment that the effect explains
    regains its full weight, and where the model plus effect is right (all segments at the noise)
    the fit is that of the plain loss."""
    if phase == "flight":
        n = jnp.sum(d["mask"], 1)
        sse = jnp.sum(e**2, axis=(1, 2))
        if robust:
            m = sse / jnp.maximum(n, 1.0)
            used = (w > 0) & (n > 0)
            order = jnp.sort(jnp.where(used, m, jnp.inf))
            median = order[jnp.maximum(jnp.sum(used) - 1, 0) // 2]
            c2 = jax.lax.stop_gradient(jnp.maximum(ROBUST**2 * median, 1e-20))
            sse = n * c2 * jnp.log1p(m / c2)
        return jnp.sum(w * sse) / jnp.maximum(jnp.sum(w * n), 1.0)
    return jnp.sum(w[:, None] * e**2) / jnp.maximum(jnp.sum(w), 1.0)


def _evaluate_impl(model, consts, u, data, x, specs, phases, iterations):
    return _errors(model, specs, consts, u, data, x, phases, iterations)


_evaluate = stored_jit(_evaluate_impl, static_argnames=("specs", "phases", "iterations"))


def evaluate(model, specs, consts, u, pb: Problem, iterations: int = 2, phases=None):
    """Per-row errors {phase: array} of ``model`` plus the effects, and the flight states."""
    phases = tuple(phases or pb.phases)
    consts = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), consts)
    return _evaluate(model.replace(name=""), consts, u, pb.data, pb.x0, tuple(specs), phases, iterations)


def _fit_impl(model, consts, u0, data, x0, norm, lr, free, weight, split, specs, phases, steps, ridge):
    schedule = optax.cosine_decay_schedule(lr, steps, alpha=0.05)
    opt = optax.adam(schedule)
    if "flight" in phases:
        # the descent flies the training segments only (the others weigh nothing in the loss); the
        # held-out ones get their states at the end, fitted from the model's with the effects found
        train, valid, rest = split
        whole, x_whole = data["flight"], x0
        data = dict(data, flight=dict(jax.tree.map(lambda a: a[train], whole), train=whole["train"][train] * valid))
        x0 = x_whole[train]

    def loss(u, x):
        errs, _ = _errors(model, specs, consts, u, data, x, phases, 0)
        total = sum(weight[p] * _mse(p, errs[p], data[p], data[p]["train"], robust=True) / norm[p] for p in phases)
        return total + ridge * sum(jnp.sum(v**2) for uk in u for v in uk.values()), errs

    def body(carry, i):
        u, state, x, jac, errs = carry
        if "flight" in phases:
            # one Gauss-Newton step of the states per step keeps them at their optimum; the
            # Jacobian (seven flights: forward differences) is refreshed every JACOBIAN_EVERY steps
            # and in the final steps, and between refreshes the step uses the last residuals
            # (a chord step: the states lag the parameters by one step)
            fresh = (i % JACOBIAN_EVERY == 0) | (i >= steps)
            res, jac = jax.lax.cond(
                fresh, lambda: stages.flight_jacobians(model, specs, consts, u, data["flight"], x),
                lambda: (errs["flight"].reshape(jac.shape[:2]), jac))
            x = jax.vmap(stages.gauss_newton_update)(x, res, jac)
        (value, errs), g = jax.value_and_grad(loss, has_aux=True)(u, x)
        # effects not being fitted keep u = 0 (neutral); a non-finite gradient is skipped
        g = tuple({k: jnp.where(jnp.isfinite(a), a, 0.0) * f for k, a in gk.items()} for gk, f in zip(g, free))
        upd, state = opt.update(g, state, u)
        upd = jax.tree.map(lambda a: jnp.where(i < steps, a, 0.0), upd)  # the final steps only refit the states
        return (optax.apply_updates(u, upd), state, x, jac, errs), value

    # the errors' shapes from the data's (eval_shape would trace the whole loss once more)
    dtype = jnp.result_type(model.ball.radius, jnp.float32)
    zeros = {p: jnp.zeros(data[p]["pos"].shape if p == "flight" else (data[p]["x"].shape[0], 6), dtype)
             for p in phases}
    jac0 = None
    if "flight" in phases:
        segments, samples = data["flight"]["pos"].shape[:2]
        jac0 = jnp.zeros((segments, 3 * samples, x0.shape[1]), x0.dtype)
    n = steps + (FINAL_GN if "flight" in phases else 1)
    (u, _, x, _, errors), history = jax.lax.scan(body, (u0, opt.init(u0), x0, jac0, zeros), jnp.arange(n))
    if "flight" in phases:
        others = {"flight": jax.tree.map(lambda a: a[rest], whole)}
        e_rest, x_rest = _errors(model, specs, consts, u, others, x_whole[rest], ("flight",), stages.GN_START)
        # the others first: with no held-out segment, ``rest`` repeats a training row
        x = x_whole.at[rest].set(x_rest).at[train].set(x)
        errors = dict(errors, flight=jnp.zeros(whole["pos"].shape, dtype).at[rest].set(e_rest["flight"].astype(dtype))
                      .at[train].set(errors["flight"]))
    return u, history[:steps], errors, x


def flight_split(pb: Problem, multiple: int = 8) -> tuple | None:
    """(training rows, 1 for a real training row (0 for padding), the other rows) of the flight
    segments, each padded to a multiple of ``multiple`` by repeating its last row (a padded row is
    flown but weighs nothing; a repeated row ends with the same values as its original)."""
    if "flight" not in pb.data:
        return None
    is_train = np.asarray(pb.data["flight"]["train"]) > 0
    train, rest = np.flatnonzero(is_train), np.flatnonzero(~is_train)
    train = train if len(train) else np.zeros(1, np.int64)  # no training segment: one that weighs nothing
    valid = np.zeros(pad_rows(len(train), multiple), np.float32)
    valid[:len(train)] = is_train[train]
    pad = lambda rows: rows[np.minimum(np.arange(pad_rows(len(rows), multiple)), len(rows) - 1)]  # noqa: E731
    rest = rest if len(rest) else train[:1]
    return jnp.asarray(pad(train), jnp.int32), jnp.asarray(valid), jnp.asarray(pad(rest), jnp.int32)


_fit = stored_jit(_fit_impl, static_argnames=("specs", "phases", "steps", "ridge"))


# ---------------------------------------------------------------------------------------------- candidates
@dataclasses.dataclass
class Candidate:
    """A fitted candidate: its spec, fitted values, loss history, per-row errors and per-phase
    held-out reductions {phase: {"pct", "ci95", "before_rms", "after_rms", "n"}}."""

    spec: Spec
    consts: dict
    u: tuple
    history: np.ndarray
    errors: dict
    heldout: dict
    params: dict

    @property
    def best(self) -> float:
        vals = [h["pct"] for h in self.heldout.values() if math.isfinite(h["pct"])]
        return max(vals) if vals else math.nan

    @property
    def significant(self) -> bool:
        return explains(self.heldout)


def group_specs(pb: Problem, group) -> tuple[tuple, tuple]:
    """(specs, numpy constants) of the effects of one compiled group, as every fit attaches them."""
    built = [spec(n, pb.pooled) for n in group]
    specs = tuple(b[0] for b in built)
    return specs, tuple(stages.session_starts(s, b[1], pb.n_sessions) for s, b in zip(specs, built))


def fit(pb: Problem, names, model, *, group=None, steps: int = 150, lr: float = 0.1, ridge: float = 1e-4,
        name: str = "") -> Candidate:
    """Fits the effects ``names`` jointly on the training split (see the module docstring) and scores
    them on the held-out split, in the phases they act in.

    Arguments:
        pb: the :class:`Problem`; names: catalogue names of simulator effects; model: the model.
        group: the effects of the compiled program (default ``names``; must contain them): effects
            of the group that are not fitted stay neutral, so every fit of one group shares one
            compilation (:func:`groups`).
        steps, lr, ridge: Adam steps, initial step size (in units of each parameter's scale), ridge
            weight on ``u``.
        name: label of the result (default: the names joined by '+').

    Returns:
        :class:`Candidate` (its spec is that of the first effect when several are fitted jointly).
    """
    group = tuple(group or names)
    missing = set(names) - set(group)
    if missing:
        raise ValueError(f"fit: effects {sorted(missing)} are not in the group {list(group)}")
    specs, consts = group_specs(pb, group)
    fitted = [s for s in specs if s.name in names]
    phases = tuple(p for p in pb.phases if any(p in s.phases for s in specs))
    scored = tuple(p for p in phases if any(p in s.phases for s in fitted))
    if not scored:
        raise ValueError(f"effects {list(names)}: none of the phases they act in "
                         f"({sorted({p for s in fitted for p in s.phases})}) has data")
    norm = {p: jnp.asarray(pb.norm[p], jnp.float32) for p in phases}
    weight = {p: jnp.asarray(1.0 if p in scored else 0.0, jnp.float32) for p in phases}
    free = tuple(jnp.asarray(1.0 if s.name in names else 0.0, jnp.float32) for s in specs)
    split = flight_split(pb)

    def descend(specs, consts):
        c32 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), consts)
        return _fit(model.replace(name=""), c32, initial_u(specs, pb.n_sessions), pb.data, pb.x0, norm,
                    jnp.asarray(lr, jnp.float32), free, weight, split, specs, phases, steps, ridge)

    u, history, errors, x = descend(specs, consts)
    for i, s in enumerate(specs):
        refine = REFINE.get(s.name) if s.name in names else None
        if refine is None:
            continue
        second = refine(pb, model, specs, consts, u, x, i)
        if second is not None:  # a second descent from the starts the first one made possible
            specs = specs[:i] + (second[0],) + specs[i + 1:]
            consts = consts[:i] + (second[1],) + consts[i + 1:]
            fitted = [specs[i] if f.name == s.name else f for f in fitted]
            u, history2, errors, x = descend(specs, consts)
            history = jnp.concatenate([history, history2])
    heldout = score(pb, {p: errors[p] for p in scored})
    u_np = jax.tree.map(np.asarray, u)
    params = {s.name: parameters(s, c, uk, pb.sessions) for s, c, uk in zip(specs, consts, u_np) if s.name in names}
    sp = fitted[0] if len(fitted) == 1 else Spec(name or "+".join(names), fitted[0].cls, (), False)
    return Candidate(spec=sp, consts=consts, u=u_np, history=np.asarray(history), errors={p: errors[p] for p in scored},
                     heldout=heldout, params=params)


def groups(names, phases) -> list:
    """Candidates split into compilation groups, each one compiled program (empty groups left out):
    the flight effects that change the spin in flight (attached, even neutral, they make every
    flight fly twice: :func:`~ttsim_jax.diagnose.stages.changes_spin`), the other flight effects
    (the costly phase), and those acting on contacts only."""
    flight = [n for n in names if "flight" in phases_of(fx.effect_class(n))]
    spinning = tuple(n for n in flight if stages.changes_spin(fx.effect_class(n)))
    steady = tuple(n for n in flight if n not in spinning)
    other = tuple(n for n in names if n not in flight)
    return [g for g in (spinning, steady, other) if g]


def score(pb: Problem, errors: dict, seed: int = 0, base: dict | None = None) -> dict:
    """Held-out RMS reduction per phase of ``errors`` against the model's (see the module docstring),
    or against ``base`` {phase: per-row errors} where it has the phase (an effect on top of others)."""
    base = base or {}
    out = {}
    for p, e in errors.items():
        test = np.asarray(pb.data[p]["test"]) > 0
        before, n = item_sums(pb, p, base.get(p, pb.base[p]))
        after, _ = item_sums(pb, p, e)
        before, after, n = before[test], after[test], n[test]
        w = group_weights(len(n), seed=seed)
        pct, ci = rms_reduction(before, after, n, w)
        out[p] = dict(pct=pct, ci95=ci, before_rms=float(np.sqrt(before.sum() / max(n.sum(), 1))),
                      after_rms=float(np.sqrt(after.sum() / max(n.sum(), 1))), n=int(len(n)))
    return out


def significant(phase: str, h: dict) -> bool:
    """Whether a held-out score ``h`` of :func:`score` is significant (see the module docstring)."""
    return bool(h["ci95"][0] > MIN_REDUCTION and h["before_rms"] - h["after_rms"] > MIN_GAIN[phase])


def worse(phase: str, h: dict) -> bool:
    """Whether a held-out score ``h`` of :func:`score` is materially worse than the model's, the mirror
    of :func:`significant`: the whole 95 % interval of the reduction below -:data:`MIN_REDUCTION` %
    and the RMS error up by more than the phase's :data:`MIN_GAIN`. A loss below the phase's
    resolution is no evidence against an effect: a candidate acting on both contact kinds whose
    parameters for one kind stay near neutral (no data at the speeds where it acts) changes that
    kind's errors by a hair, consistently, and its interval then excludes zero."""
    return bool(h["ci95"][1] < -MIN_REDUCTION and h["after_rms"] - h["before_rms"] > MIN_GAIN[phase])


def explains(heldout: dict) -> bool:
    """Whether a candidate's held-out scores {phase: score} make it significant: significant in some
    phase and materially worse in none (:func:`worse`). An effect acting in several phases is fitted
    to all of them at once; one that buys a gain in one phase with a loss in another is fitting
    something else there (e.g. a bias of the contact state estimates), not a physical effect."""
    return any(significant(p, h) for p, h in heldout.items()) and not any(worse(p, h) for p, h in heldout.items())


def rank(cands: list) -> list:
    """Candidates ordered: significant ones first, then by their largest held-out reduction."""
    key = lambda c: (not c.significant, -(c.best if math.isfinite(c.best) else -1e9))  # noqa: E731
    return sorted(cands, key=key)


def candidate_names(which=None) -> list:
    """The simulator effects of the catalogue to try (``which``: names or a spec for
    :func:`ttsim_jax.effects.parse_names`; default all)."""
    chosen = fx.parse_names(which) if which is not None else fx.names("simulator")
    return [n for n in chosen if fx.effect_class(n).WHERE == "simulator"]
