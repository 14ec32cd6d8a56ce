"""Starts of the ``table_unevenness`` candidate: where on the table the bounces say the bumps are.

Descent alone cannot move a bump from where it starts to where the data has one: a bump of the
first descent that lies away from the true ones has no gradient towards them, and the error surface
in a centre is as wide as the bump. So the bumps' centres, widths and heights are found first by a
scan, and the candidate descends again from there (:func:`bump_stage`, the candidate's
:data:`~ttsim_jax.diagnose.candidates.REFINE` stage), as the gusts of ``air_flow`` are found by a
periodogram.

The scan linearises the table-contact errors in the surface's local slope: near a bounce a bump is
a tilt of the surface (its height, millimetres, moves the contact by less than the estimates
resolve), so a bump of height A, centre c and width w changes contact i's error by A J_i g_i, with
J_i = d e_i / d slope (6 x 2, by forward differentiation of the contact response) and g_i the
gradient of the unit Gaussian at the contact. For every centre of a grid over the playing surface
and every width of :data:`WIDTHS`, the best height and its fall of the training split's squared
error follow in closed form (one-dimensional least squares); the best bump is taken, the residuals
updated, and so on (matching pursuit) while a bump lowers the squared error by more than
:data:`KEEP` times the noise variance of one error component: with thousands of centres and
widths scanned, noise alone lowers it by about 2 ln(thousands) ~ 17 variances at the best one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.diagnose import stages
from ttsim_jax.diagnose.specs import spec
from ttsim_jax.files.programs import stored_jit
from ttsim_jax.physics.dimensions import TABLE_HALF_LENGTH, TABLE_HALF_WIDTH

#: Grid step of the scanned centres [m] and the scanned widths [m].
STEP = 0.05
WIDTHS = (0.15, 0.25, 0.35)
#: Least fall of the training squared error of a kept bump, in noise variances of one component.
KEEP = 25.0
#: Typical bump height [m]: a Gaussian prior on each height, so that a tall bump is not fitted to
#: the noise of the few contacts near the net or a corner.
PRIOR = 0.005
#: Step scales of the second descent (amplitude, centre, width) [m].
SCALES = {"amplitude": 0.0015, "center": 0.1, "width": 0.05}
#: Scanned bumps per chunk (memory: CHUNK x contacts x 2 floats).
CHUNK = 512


def tilt_candidate():
    """(spec, consts) of the ``table_tilt`` candidate with its slope in plain units (scale 1): the
    local slope that :func:`scan` differentiates in."""
    sp, const = spec("table_tilt")
    return sp, dict(const, scale=dict(const["scale"], slope=np.float64(1.0)))


def _slope_jacobian(model, c: dict):
    """(N, 6, 2) derivative of each table contact's error in the surface's slope at zero slope."""
    sp, const = tilt_candidate()
    const = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), const)

    def errors(slope):
        return stages.table_errors(model, (sp,), (const,), ({"slope": slope[None]},), c)

    return jax.jacfwd(errors)(jnp.zeros(2, jnp.float32))


_jacobian = stored_jit(_slope_jacobian)


def _gaussian_gradient(xy, center, width):
    """(K, N, 2) gradient at the points ``xy`` (N, 2) of unit Gaussians with centres (K, 2), widths (K,)."""
    rel = xy[None, :, :] - center[:, None, :]
    g = np.exp(-np.sum(rel * rel, axis=-1) / (2.0 * width[:, None] ** 2))
    return -(g / width[:, None] ** 2)[..., None] * rel


def scan(xy, jac, resid, n_bumps: int, keep: float = KEEP):
    """Matching pursuit of Gaussian bumps in linearised table errors (module docstring).

    Arguments:
        xy: (N, 2) contact positions on the table; jac: (N, 6, 2) error derivative in the slope;
        resid: (N, 6) errors without bumps.
        n_bumps: most bumps taken; keep: least fall of the squared error of a taken bump, in noise
            variances of one error component.

    Returns:
        (centres (M, 2), widths (M,), heights (M,), falls (M,) in noise variances), M <= n_bumps.
    """
    xy, jac, r = (np.asarray(a, np.float64) for a in (xy, jac, resid))
    used = np.abs(jac).sum(axis=2) > 0  # error components a slope moves
    sigma2 = max(float(np.sum(r[used] ** 2) / max(used.sum(), 1)), 1e-30)
    gx = np.arange(-TABLE_HALF_LENGTH, TABLE_HALF_LENGTH + 1e-9, STEP)
    gy = np.arange(-TABLE_HALF_WIDTH, TABLE_HALF_WIDTH + 1e-9, STEP)
    grid = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    centers = np.concatenate([grid] * len(WIDTHS))
    widths = np.repeat(np.asarray(WIDTHS, np.float64), len(grid))
    # a bump's error change per metre of height is a_kn = J_n g_kn; its products with the residuals
    # and itself go through J^T r (N, 2) and J^T J (N, 2, 2), in chunks of bumps, so that memory
    # stays O(chunk x N) on a dataset of tens of thousands of bounces
    jtj = np.einsum("nij,nil->njl", jac, jac)
    chunks = [slice(k, k + CHUNK) for k in range(0, len(widths), CHUNK)]

    def gradients(sl):
        return _gaussian_gradient(xy, centers[sl], widths[sl])

    aa = np.concatenate([np.einsum("knj,njl,knl->k", g, jtj, g) for g in map(gradients, chunks)])
    aa = aa + sigma2 / PRIOR**2
    out = []
    for _ in range(n_bumps):
        jtr = np.einsum("nij,ni->nj", jac, r)
        ra = np.concatenate([np.einsum("knj,nj->k", gradients(sl), jtr) for sl in chunks])
        fall = ra**2 / aa
        k = int(np.argmax(fall))
        if fall[k] < keep * sigma2:
            break
        height = -ra[k] / aa[k]
        r = r + height * np.einsum("nij,nj->ni", jac, gradients(slice(k, k + 1))[0])
        out.append((centers[k], widths[k], height, fall[k] / sigma2))
    if not out:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0)
    c, w, h, f = zip(*out)
    return np.array(c), np.array(w), np.array(h), np.array(f)


def bump_stage(pb, model, specs, consts, u, x, i):
    """The second descent of the ``table_unevenness`` candidate ``specs[i]``: (spec with heights,
    centres and widths free, consts starting at the bumps :func:`scan` finds in the training
    split), or None when it finds none (then the first descent's result stands).

    Used by :func:`ttsim_jax.diagnose.candidates.fit` through its ``REFINE`` table."""
    sp, const = specs[i], consts[i]
    if "table" not in pb.data or not {"center", "amplitude", "width"} <= set(sp.cls.PARAMS):
        return None
    c = pb.data["table"]
    rows = np.asarray(c["train"]) > 0
    jac = np.asarray(_jacobian(model.replace(name=""), c), np.float64)[rows]
    resid = np.asarray(pb.base["table"], np.float64)[rows]
    n = sp.cls.PARAMS["amplitude"].shape[0]
    centers, widths, heights, _ = scan(np.asarray(c["pos"])[rows, :2], jac, resid, n)
    if not len(heights):
        return None
    start = {k: np.broadcast_to(np.asarray(const["start"][k], np.float64), p.shape).copy()
             for k, p in sp.cls.PARAMS.items()}
    m = len(heights)  # the other bumps keep their neutral (flat) start
    start["center"][:m], start["width"][:m], start["amplitude"][:m] = centers, widths, heights
    return stages.second_descent(sp, start, SCALES)
