"""Starts of the ``buckling`` candidate: from which impact speed, and how steeply, restitution drops.

The loss starts at an onset speed and grows over a width: ``depth (1 - exp(-((v_n - onset) /
width)^2))`` for ``v_n`` above the onset, zero below. Descent from the catalogue's typical onsets
(5 m/s on the table, 15 m/s on the racket: competition speeds) has no gradient where the data's
impacts are slower: every contact then lies below the onset, and the depth's derivative is zero.
In one generated case the first descent ended at a table onset of 4.8 m/s with a slightly negative
depth while the true loss began at 2 m/s, and the candidate was rejected for making the table
errors (insignificantly) worse.

So after the first descent (:func:`onset_stage`, the candidate's
:data:`~ttsim_jax.diagnose.candidates.REFINE` stage), each contact kind's onset and width are
scanned on a grid (:data:`GRID`): for each pair the errors are linear in the depth (restitution
enters the response linearly), so two evaluations give the best depth in [0, :data:`DEPTH_MAX`] and
the fall of the training split's squared error in closed form. The best pair starts a second descent that frees
onset, width and depth of both kinds.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.diagnose import stages
from ttsim_jax.files.programs import stored_jit

#: Scanned (onsets, widths) [m/s] per contact kind: table impacts of rallies are about 1-8 m/s
#: normal to the table, racket impacts about 2-25 m/s normal to the face.
GRID = {
    "table": (np.arange(0.5, 8.01, 0.5), (0.5, 1.0, 2.0, 4.0)),
    "racket": (np.arange(1.0, 20.01, 1.0), (1.0, 2.0, 4.0, 8.0, 16.0)),
}
#: Depth of the probe evaluation (any value works where the errors are linear in the depth).
PROBE = 0.1
#: Largest depth of a start [1]: twice the catalogue's largest loss. Unbounded, the closed form can
#: fit a handful of fast training bounces with a loss above the restitution itself (1.4 on one
#: public dataset: the held-out table error tripled).
DEPTH_MAX = 0.3
#: Step scales of the second descent, per parameter [m/s, m/s, 1].
SCALES = {"table_onset": 0.5, "table_width": 0.5, "table_depth": 0.03,
          "racket_onset": 1.5, "racket_width": 2.0, "racket_depth": 0.05}


@stored_jit(static_argnames=("sp", "phase"))
def _grid_errors(model, sp, const, c, phase, values):
    """(G, N, 6) errors of the contacts ``c`` for each of G parameter sets ``values`` {param: (G,)}."""
    def one(v):
        cst = dict(start={**const["start"], **v}, scale=const["scale"])
        return stages.ERRORS[phase](model, (sp,), (cst,), ({},), c)

    return jax.vmap(one)(values)


def best_onset(errors0, probe, weight, depth_probe: float = PROBE, depth_max: float = DEPTH_MAX):
    """The grid point whose best depth in [0, ``depth_max``] lowers the weighted squared error most.

    Arguments:
        errors0: (N, 6) errors without the loss; probe: (G, N, 6) errors with depth ``depth_probe``
            at each grid point; weight: (N,) weights of the rows (the training split).

    Returns:
        (index of the best grid point, its depth, its fall of the weighted squared error).
    """
    e0 = np.asarray(errors0, np.float64)
    jac = (np.asarray(probe, np.float64) - e0[None]) / depth_probe  # error change per unit depth
    w = np.asarray(weight, np.float64)[None, :, None]
    jr = np.sum(w * jac * e0[None], axis=(1, 2))
    jj = np.maximum(np.sum(w * jac * jac, axis=(1, 2)), 1e-30)
    depth = np.clip(-jr / jj, 0.0, depth_max)
    fall = -(2.0 * depth * jr + depth**2 * jj)
    k = int(np.argmax(fall))
    return k, float(depth[k]), float(fall[k])


def onset_stage(pb, model, specs, consts, u, x, i):
    """The second descent of the ``buckling`` candidate ``specs[i]``: (spec with onsets, widths and
    depths free, consts starting at the grid's best per contact kind), or None when no contact kind
    has data.

    Used by :func:`ttsim_jax.diagnose.candidates.fit` through its ``REFINE`` table."""
    sp, const = specs[i], consts[i]
    start = {k: np.asarray(v, np.float64).copy() for k, v in const["start"].items()}
    scanned = False
    m = model.replace(name="")
    neutral = dataclasses.replace(sp, free=())  # every parameter at its start: the grid's values
    c32 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), const)
    for phase, (onsets, widths) in GRID.items():
        keys = (f"{phase}_onset", f"{phase}_width", f"{phase}_depth")
        if phase not in pb.data or not set(keys) <= set(sp.cls.PARAMS):
            continue
        o, w = (a.ravel() for a in np.meshgrid(onsets, widths, indexing="ij"))
        values = {keys[0]: jnp.asarray(o, jnp.float32), keys[1]: jnp.asarray(w, jnp.float32),
                  keys[2]: jnp.full(o.shape, PROBE, jnp.float32)}
        probe = _grid_errors(m, neutral, c32, pb.data[phase], phase, values)
        k, depth, _ = best_onset(pb.base[phase], probe, pb.data[phase]["train"])
        start[keys[0]], start[keys[1]], start[keys[2]] = np.float64(o[k]), np.float64(w[k]), np.float64(depth)
        scanned = True
    if not scanned:
        return None
    return stages.second_descent(sp, start, SCALES)
