"""Jacobians of a shot's target with respect to every input, through the rally kernel.

Every input of a shot is one column of a flat (B, C) array (:class:`Layout`): the ball's state at
the start, a few steps before the contact (position, velocity, spin), the racket's at the contact (position, a small rotation
vector applied to its orientation in the world frame, velocity, angular velocity) and every float
parameter of the model, each shot with its own copy (the kernel's per-ball parameters), so one
reverse-mode pass gives every shot its own gradient. Columns carry a group name
(:func:`group_of`): ``ball.pos`` ... ``racket.ang_vel`` for the state, ``aero.drag``,
``aero.magnus``, ``table.restitution``, ``table.residual``, ``racket.params``,
``residual.network`` (the whole network as one group) ... for the model.

:func:`jacobian` uses ``jax.jacrev`` (two backward passes, as many as the widest target has
components, so that every target shares one compiled program; any number of columns) or forward
mode (``jax.jvp`` with one tangent column per copy of a shot on the kernel's batch axis). A
forward run of every shot first finds the shots that land and how many steps each outcome needs;
only those are differentiated, sorted by that need (:func:`horizon_plan`). Each shot stops at its
landing and the kernel skips steps where every shot of a chunk has stopped
(``targets.program_outcome``), so a chunk of early landings costs little more than its flights,
forward and backward, through the one compiled horizon; ``buckets`` > 1 also compiles shorter
horizons (each a compilation of minutes for a few per cent of the run time).
:func:`finite_differences` gives central differences along directions, batched the same way;
:func:`local_flags` marks shots whose gradient holds only very locally (the event
sequence flips within the probe, or differences at two step sizes disagree).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.physics.numerics import rotation_matrix
from ttsim_jax.sensitivity.cases import WINDOW, ShotSet
from ttsim_jax.sensitivity.targets import (COLUMNS, TARGETS, Outcome, check_target, columns_of, for_target,
                                          program_outcome)
from ttsim_jax.state import Ball, Racket

STATE_GROUPS = ("ball.pos", "ball.vel", "ball.spin", "racket.pos", "racket.rot", "racket.vel", "racket.ang_vel")
STATE_UNITS = {"ball.pos": "m", "ball.vel": "m/s", "ball.spin": "rad/s", "racket.pos": "m", "racket.rot": "rad",
               "racket.vel": "m/s", "racket.ang_vel": "rad/s"}
_MODEL_GROUPS = (  # (path prefix, group), first match wins
    ("aero.drag", "aero.drag"), ("aero.magnus", "aero.magnus"), ("aero.rho_air", "aero.air"), ("aero.nu", "aero.air"),
    ("aero", "constants"), ("table.residual", "table.residual"),
    ("table.length", "table.geometry"), ("table.width", "table.geometry"), ("table.net", "table.geometry"),
    ("table.floor", "table.geometry"), ("table", "table.restitution"), ("racket", "racket.params"),
    ("residual", "residual.network"), ("ball", "ball.properties"), ("effects", "effects"),
)


def group_of(name: str) -> str:
    """The group of a model parameter's dotted path (``"table.e0"`` -> ``"table.restitution"``)."""
    for prefix, group in _MODEL_GROUPS:
        if name == prefix or name.startswith(prefix + ".") or name.startswith(prefix + "[") or (
                prefix.endswith("net") and name.startswith(prefix)):
            return group
    return "other"


def _path_name(path) -> str:
    parts = []
    for p in path:
        if isinstance(p, jax.tree_util.GetAttrKey):
            parts.append(p.name)
        elif isinstance(p, jax.tree_util.DictKey):
            parts.append(str(p.key))
        elif isinstance(p, jax.tree_util.SequenceKey):
            parts.append(str(p.idx))
        else:
            parts.append(str(p))
    return ".".join(parts)


@dataclass(frozen=True, eq=False)
class Layout:
    """Where each input sits in a shot's flat vector of C inputs (hashable: a static argument).

    Attributes:
        leaves: ((name, group, shape), ...) of the state fields then the model's float leaves.
        model_def: the model's tree structure; model_const: its non-float leaves (by position).
        float_index: positions of the float leaves among the model's leaves.
    """

    leaves: tuple
    model_def: object
    model_const: tuple
    float_index: tuple

    def _key(self):
        consts = tuple(None if c is None else (c.dtype.str, c.shape, c.tobytes()) for c in self.model_const)
        return (self.leaves, self.model_def, consts, self.float_index)

    def __hash__(self):
        return hash(self._key())

    def __eq__(self, other):
        return isinstance(other, Layout) and self._key() == other._key()

    @property
    def sizes(self) -> tuple:
        return tuple(int(np.prod(s)) for _, _, s in self.leaves)

    @property
    def n_columns(self) -> int:
        return sum(self.sizes)

    def columns(self) -> list[str]:
        """Every column's name: ``"racket.vel[2]"``, ``"aero.drag.cd[1,4]"``, ``"table.e0"``."""
        out = []
        for (name, _, shape), size in zip(self.leaves, self.sizes):
            if not shape:
                out.append(name)
                continue
            for idx in np.ndindex(*shape):
                out.append(f"{name}[{','.join(map(str, idx))}]")
        return out

    def groups(self) -> np.ndarray:
        """(C,) each column's group name."""
        return np.concatenate([np.full(size, g, dtype=object) for (_, g, _), size in zip(self.leaves, self.sizes)])

    def unflatten(self, flat):
        """(B, C) -> (model with (B, ...) leaves, ball, racket position, rotation vector, velocity,
        angular velocity)."""
        parts, start = [], 0
        for (_, _, shape), size in zip(self.leaves, self.sizes):
            parts.append(flat[:, start:start + size].reshape((flat.shape[0],) + tuple(shape)))
            start += size
        state, floats = parts[:7], parts[7:]
        leaves = list(self.model_const)
        for i, leaf in zip(self.float_index, floats):
            leaves[i] = leaf
        const = [(i, c) for i, c in enumerate(self.model_const) if i not in self.float_index]
        for i, c in const:
            leaves[i] = jnp.broadcast_to(c, (flat.shape[0],) + np.shape(c))
        model = jax.tree_util.tree_unflatten(self.model_def, leaves)
        return model, Ball(state[0], state[1], state[2]), state[3], state[4], state[5], state[6]


def layout_of(model) -> Layout:
    """The :class:`Layout` of a shot's inputs under ``model`` (its float leaves are the parameters)."""
    flat, treedef = jax.tree_util.tree_flatten_with_path(model)
    leaves = [(g, g, (3,)) for g in STATE_GROUPS]
    const, float_index = [], []
    for i, (path, leaf) in enumerate(flat):
        arr = np.asarray(leaf)
        if np.issubdtype(arr.dtype, np.floating):
            name = _path_name(path)
            leaves.append((name, group_of(name), tuple(arr.shape)))
            float_index.append(i)
            const.append(None)
        else:
            const.append(arr)
    return Layout(tuple(leaves), treedef, tuple(const), tuple(float_index))


def flatten_inputs(model, shots: ShotSet, layout: Layout) -> np.ndarray:
    """(B, C) nominal inputs of ``shots`` under ``model`` (rotation vectors 0)."""
    b = len(shots)
    cols = [shots.ball.pos, shots.ball.vel, shots.ball.spin, shots.racket.pos, np.zeros((b, 3)),
            shots.racket.vel, shots.racket.ang_vel]
    cols = [np.asarray(c, np.float64).reshape(b, -1) for c in cols]
    leaves = jax.tree.leaves(model)
    for i in layout.float_index:
        cols.append(np.broadcast_to(np.asarray(leaves[i], np.float64).reshape(1, -1), (b, np.size(leaves[i]))))
    return np.concatenate(cols, 1)


def _outcome(flat, rot0, face, dt, layout: Layout, n_steps: int, buffering: str | None = None) -> Outcome:
    model, ball, rpos, rvec, rvel, rang = layout.unflatten(flat)
    racket = Racket(pos=rpos, rot=rotation_matrix(rvec) @ rot0, vel=rvel, ang_vel=rang, face=face)
    return program_outcome(model, ball, racket, dt, n_steps=n_steps, buffering=buffering)


@partial(jax.jit, static_argnames=("layout", "n_steps"))
def evaluate(flat, rot0, face, dt, *, layout: Layout, n_steps: int) -> Outcome:
    """Outcomes (every column of :data:`~ttsim_jax.sensitivity.targets.COLUMNS`) of B shots given as
    flat inputs (B, C), with their racket orientations ``rot0`` (B, 3, 3) and face sizes (B, 2); jitted."""
    return _outcome(flat, rot0, face, dt, layout, n_steps)


@partial(jax.jit, static_argnames=("layout", "n_steps"))
def _jac_rev(flat, rot0, face, dt, weights, *, layout, n_steps):
    """(B, K, C) d (columns @ weights.T) / d inputs: K = ``weights``' rows (traced, so that every
    target shares this compilation; a row of zeros costs a backward pass too)."""
    def total(x):
        out = _outcome(x, rot0, face, dt, layout, n_steps, buffering="single")
        return (out.values @ weights.T).sum(0), out  # shots are independent: row b of the gradient is shot b's

    jac, out = jax.jacrev(total, has_aux=True)(flat)
    return jnp.moveaxis(jac, 0, 1), out


@partial(jax.jit, static_argnames=("layout", "n_steps"))
def evaluate_jvp(flat, tangent, rot0, face, dt, *, layout: Layout, n_steps: int):
    """(outcome, d values along ``tangent``) of every column of
    :data:`~ttsim_jax.sensitivity.targets.COLUMNS`: forward mode, each shot (row) with its own
    tangent (B, C)."""
    def values(x):
        out = _outcome(x, rot0, face, dt, layout, n_steps)
        return out.values, out

    _, tan, out = jax.jvp(values, (flat,), (tangent,), has_aux=True)
    return out, tan


@dataclass
class Jacobian:
    """A target's Jacobian for a batch of shots.

    Attributes:
        target: the target's name; components: its component names.
        values: (B, k) the target at the nominal inputs; valid: (B,); sequence: (B, 2) events.
        jac: (B, k, C) d target / d input (0 for invalid shots).
        nominal: (B, C) the inputs.
        columns: (C,) input names; groups: (C,) their groups.
        horizon: (B,) flight steps each shot was differentiated through (0: not differentiated, it
            does not land), or None.
    """

    target: str
    components: tuple
    values: np.ndarray
    valid: np.ndarray
    sequence: np.ndarray
    jac: np.ndarray
    nominal: np.ndarray
    columns: list
    groups: np.ndarray
    horizon: np.ndarray | None = None

    def group(self, name: str) -> np.ndarray:
        """(B, k, n) the columns of one group."""
        return self.jac[:, :, self.groups == name]

    def take(self, index) -> "Jacobian":
        """The shots at ``index`` (any numpy index)."""
        return Jacobian(self.target, self.components, self.values[index], self.valid[index], self.sequence[index],
                        self.jac[index], self.nominal[index], self.columns, self.groups,
                        None if self.horizon is None else self.horizon[index])


def _chunks(n: int, chunk: int | None):
    """(compiled size, [(lo, hi), ...]): ``chunk`` rows per call (the last padded), or all at once."""
    size = chunk or n
    return size, [(lo, min(lo + size, n)) for lo in range(0, n, size)]


def _pad(a, size):
    a = np.asarray(a)
    if len(a) == size:
        return a
    return np.concatenate([a, np.repeat(a[-1:], size - len(a), 0)], 0)


def _racket_arrays(shots: ShotSet, dtype):
    return np.asarray(shots.racket.rot, dtype), np.asarray(shots.racket.face, dtype)


def horizons(n_steps: int, buckets: int) -> tuple:
    """The flight horizons a Jacobian is compiled for: ``n_steps * j / buckets`` steps rounded up,
    j = 1 ... ``buckets`` (each one compilation)."""
    return tuple(sorted({-(-n_steps * j // buckets) for j in range(1, max(1, buckets) + 1)}))


def horizon_plan(steps, valid, n_steps: int, size: int, buckets: int, margin: int = 2) -> list:
    """Which shots go together through which horizon: only the shots ``valid`` for the target (the
    others have no gradient), sorted by the steps their outcome needs, ``size`` at a time, each
    group through the shortest of :func:`horizons` that holds the longest of its shots.

    Arguments:
        steps: (B,) the rollout steps each shot's outcome needs (:class:`Outcome` ``steps``, racket
            window included); ``margin`` more are run (the landing step is read from a float time).
        valid: (B,) shots to differentiate. n_steps: the full flight horizon.
        size: shots per group (the compiled batch). buckets: as :func:`horizons`.

    Returns:
        [(rows, horizon), ...]: the shots' indices (at most ``size``) and the flight steps to run.
    """
    need = np.asarray(steps) - WINDOW + margin
    rows = np.flatnonzero(valid)
    rows = rows[np.argsort(need[rows], kind="stable")]
    sizes = horizons(n_steps, buckets)
    plan = []
    for lo in range(0, len(rows), size):
        part = rows[lo:lo + size]
        plan.append((part, next((h for h in sizes if h >= need[part].max()), n_steps)))
    return plan


def jacobian(model, shots: ShotSet, *, target: str = "landing", dt: float = 1e-3, n_steps: int = 1500,
             mode: str = "rev", chunk: int | None = None, buckets: int = 1, progress: bool = False) -> Jacobian:
    """d target / d every input for each shot, through the rally kernel.

    A forward run of every shot at the full horizon first gives each its outcome and the steps
    that outcome depends on (the landing, the net crossing); only the shots that land are then
    differentiated, grouped by those steps (:func:`horizon_plan`), so that a group's steps after its
    last landing are skipped.

    Arguments:
        model: a :class:`~ttsim_jax.params.Model` (its float dtype is the computation's).
        shots: a :class:`~ttsim_jax.sensitivity.cases.ShotSet` made for this ``dt``.
        target: a key of :data:`~ttsim_jax.sensitivity.targets.TARGETS`.
        dt: step [s]; n_steps: flight horizon in steps.
        mode: ``"rev"`` (``jax.jacrev``, cost ~ two backward passes, the components of the widest
            target: every target shares one compilation) or ``"fwd"`` (forward mode, one tangent
            column per copy of a shot: cost ~ C forward passes; for few columns or checks).
        chunk: shots per compiled call (the last chunk is padded); default all at once.
        buckets: how many horizons (fractions of ``n_steps``, :func:`horizons`) the differentiated
            shots may be run through, each one compilation of the Jacobian; 1 (default): the full
            horizon only (the steps after a chunk's last landing are skipped anyway).
        progress: show a tqdm bar over the chunks.

    Returns:
        A :class:`Jacobian`.
    """
    components = check_target(target)
    if mode not in ("rev", "fwd"):
        raise ValueError(f"mode must be 'rev' or 'fwd', got {mode!r}")
    if buckets < 1:
        raise ValueError(f"buckets must be at least 1, got {buckets!r}")
    dtype = np.dtype(model.ball.radius.dtype)
    layout = layout_of(model)
    nominal = flatten_inputs(model, shots, layout)
    rot0, face = _racket_arrays(shots, dtype)
    c = layout.n_columns
    cols = columns_of(target)
    # reverse mode: one row of weights per component, as many rows as the widest target has (every
    # target then shares one compilation)
    weights = np.zeros((max(map(len, TARGETS.values())), len(COLUMNS)), dtype)
    weights[np.arange(len(cols)), cols] = 1.0
    size, _ = _chunks(len(shots), min(chunk, len(shots)) if chunk else None)
    first = outcomes(model, shots, nominal, target=target, dt=dt, n_steps=n_steps, batch=size)
    values, valid, sequence = np.array(first.values), np.array(first.valid), np.array(first.sequence)
    jac = np.zeros((len(shots), len(cols), c), dtype)
    run = np.zeros(len(shots), np.int64)
    plan = horizon_plan(first.steps, valid, n_steps, size, buckets)
    bar = plan
    if progress:
        from tqdm import tqdm
        bar = tqdm(plan, desc=f"jacobian ({mode}) of {target}", unit="chunk")
    for rows, horizon in bar:
        x, r, f = (_pad(a[rows], size) for a in (nominal, rot0, face))
        if mode == "rev":
            j, out = _jac_rev(jnp.asarray(x, dtype), jnp.asarray(r), jnp.asarray(f), dt, jnp.asarray(weights),
                              layout=layout, n_steps=horizon)
            j = np.asarray(j)[:, :len(cols)]
        else:
            # each shot repeated C times on the batch axis, copy i with tangent e_i
            xs = np.repeat(x, c, 0)
            tan = np.tile(np.eye(c, dtype=dtype), (size, 1))
            out, t = evaluate_jvp(jnp.asarray(xs, dtype), jnp.asarray(tan), jnp.asarray(np.repeat(r, c, 0)),
                                  jnp.asarray(np.repeat(f, c, 0)), dt, layout=layout, n_steps=horizon)
            j = np.asarray(t)[:, list(cols)].reshape(size, c, len(cols)).transpose(0, 2, 1)
            out = jax.tree.map(lambda a: a[::c], out)
        n = len(rows)
        out = for_target(jax.tree.map(lambda a: np.asarray(a)[:n], out), target)
        jac[rows], run[rows] = j[:n], horizon
        values[rows], valid[rows], sequence[rows] = out.values, out.valid, out.sequence
    jac = np.where(valid[:, None, None], jac, 0.0)
    return Jacobian(target=target, components=components, values=values, valid=valid, sequence=sequence, jac=jac,
                    nominal=nominal, columns=layout.columns(), groups=layout.groups(), horizon=run)


def outcomes(model, shots: ShotSet, flat: np.ndarray, *, target: str, dt: float, n_steps: int,
             batch: int | None = None, shot_index=None) -> Outcome:
    """Outcomes at given inputs ``flat`` (N, C): row i is shot ``shot_index[i]`` (default i) with
    those inputs. ``batch`` fixes the compiled batch size (rows are padded), so calls of any N reuse
    one compiled shape."""
    dtype = np.dtype(model.ball.radius.dtype)
    layout = layout_of(model)
    check_target(target)
    rot0, face = _racket_arrays(shots, dtype)
    idx = np.arange(len(flat)) if shot_index is None else np.asarray(shot_index)
    size, spans = _chunks(len(flat), batch)
    parts = []
    for lo, hi in spans:
        x, r, f = (_pad(a, size) for a in (flat[lo:hi], rot0[idx[lo:hi]], face[idx[lo:hi]]))
        out = evaluate(jnp.asarray(x, dtype), jnp.asarray(r), jnp.asarray(f), dt, layout=layout, n_steps=n_steps)
        parts.append(jax.tree.map(lambda a: np.asarray(a)[:hi - lo], out))
    return for_target(jax.tree.map(lambda *a: np.concatenate(a), *parts), target)


def group_directions(jac: Jacobian, rng: np.random.Generator, scale: np.ndarray) -> dict:
    """One random direction per input group for each shot: group -> (B, C) with unit-RMS entries
    times ``scale`` (C,) on that group's columns and 0 elsewhere (groups with no column are left out)."""
    out = {}
    b, c = jac.nominal.shape
    for g in dict.fromkeys(jac.groups):
        mask = jac.groups == g
        u = rng.standard_normal((b, c)) * mask
        u /= np.sqrt(np.mean(u[:, mask] ** 2, 1, keepdims=True))
        out[g] = u * scale
    return out


def finite_differences(model, shots: ShotSet, nominal: np.ndarray, directions: np.ndarray, steps, *, target: str,
                       dt: float, n_steps: int, batch: int | None = None):
    """Central differences of the target along per-shot directions, at several step sizes, batched.

    Arguments:
        nominal: (B, C) inputs; directions: (D, B, C) directions; steps: step sizes (multiples of
            each direction).

    Returns:
        (fd (S, D, B, k) central differences for each step, same (S, D, B) whether the event
        sequence at both ends equals the nominal's, nominal :class:`Outcome`).
    """
    steps = np.asarray(steps, np.float64)
    d, b, c = directions.shape
    plus = nominal[None, None] + steps[:, None, None, None] * directions[None]
    minus = nominal[None, None] - steps[:, None, None, None] * directions[None]
    rows = np.concatenate([nominal, plus.reshape(-1, c), minus.reshape(-1, c)])
    shot = np.concatenate([np.arange(b), np.tile(np.arange(b), 2 * len(steps) * d)])
    out = outcomes(model, shots, rows, target=target, dt=dt, n_steps=n_steps, batch=batch, shot_index=shot)
    nom = jax.tree.map(lambda a: a[:b], out)
    s = len(steps)
    vp = out.values[b:b + s * d * b].reshape(s, d, b, -1)
    vm = out.values[b + s * d * b:].reshape(s, d, b, -1)
    fd = (vp - vm) / (2 * steps[:, None, None, None])
    sp = out.sequence[b:b + s * d * b].reshape(s, d, b, 2)
    sm = out.sequence[b + s * d * b:].reshape(s, d, b, 2)
    same = np.all(sp == nom.sequence[None, None], -1) & np.all(sm == nom.sequence[None, None], -1)
    return fd, same, nom


def local_flags(model, shots: ShotSet, jac: Jacobian, probe: dict, *, dt: float, n_steps: int, rtol: float = 0.05,
                ratio: float = 8.0, seed: int = 0, batch: int | None = None) -> dict:
    """Which shots' gradients are only local: along a random direction in each group, of size
    ``probe[group]`` (C,) per column, the event sequence flips within the probe, or central
    differences at that step and at a ``ratio`` times smaller one disagree by more than ``rtol``
    (relative to the larger, plus an absolute floor of 1e-9).

    Returns:
        dict with ``flag`` (B,) bool, ``flip`` (B,) bool (the sequence changed), ``groups``
        (group -> (B,) bool flagged by that group), ``disagreement`` (group -> (B,) relative gap).
    """
    rng = np.random.default_rng(seed)
    groups = [g for g in probe if np.any(jac.groups == g)]
    dirs = group_directions(jac, rng, np.ones(jac.nominal.shape[1]))
    dirs = np.stack([dirs[g] * probe[g] for g in groups])
    fd, same, _ = finite_differences(model, shots, jac.nominal, dirs, [1.0, 1.0 / ratio], target=jac.target, dt=dt,
                                     n_steps=n_steps, batch=batch)
    big, small = fd[0], fd[1]  # (D, B, k)
    gap = np.max(np.abs(big - small), -1) / (np.maximum(np.max(np.abs(big), -1), np.max(np.abs(small), -1)) + 1e-9)
    flip = ~np.all(same, (0, 1))
    per = (gap > rtol) | ~np.all(same, 0)
    return dict(flag=np.any(per, 0) | flip | ~jac.valid, flip=flip,
                groups={g: per[i] for i, g in enumerate(groups)},
                disagreement={g: gap[i] for i, g in enumerate(groups)})
