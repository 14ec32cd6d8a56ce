"""The bump scan of the ``table_unevenness`` candidate (:mod:`ttsim_jax.diagnose.bumps`).

* the scan, on errors made linear in the surface's slope with a random Jacobian: it finds two
  separated bumps (centre, width, height) in noisy errors, and none in noise alone;
* the slope Jacobian of the table contacts' errors equals central finite differences of the errors
  under a tilted table (the small generated buckling dataset's bounces; tests/diagnose/data).
"""

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.data import load
from ttsim_jax.diagnose import bumps as B
from ttsim_jax.diagnose import candidates as C
from ttsim_jax.diagnose import stages as S
from ttsim_jax.diagnose.phases import collect

DATA = Path(__file__).parent / "data" / "buckling"
# (x, y, width, height): a bump and a dip where balls land, on grid centres and scanned widths
TRUE = np.array([[0.8, 0.3375, 0.25, 0.005], [-0.9, -0.2125, 0.35, -0.004]])
NOISE = 0.1  # m/s per error component


def _linear_errors(seed: int, bumps=TRUE):
    rng = np.random.default_rng(seed)
    n = 1000
    xy = rng.uniform(-1.0, 1.0, (n, 2)) * np.array([1.3, 0.7])
    # a bounce's error moves by metres per second per unit slope, in velocity and spin components
    jac = rng.normal(0.0, 10.0, (n, 6, 2))
    resid = rng.normal(0.0, NOISE, (n, 6))
    for x, y, w, h in bumps:
        g = B._gaussian_gradient(xy, np.array([[x, y]]), np.array([w]))[0]
        resid -= h * np.einsum("nij,nj->ni", jac, g)  # errors of a model that lacks the bump
    return xy, jac, resid


@pytest.mark.parametrize("seed", [0, 1])
def test_scan_finds_separated_bumps_in_linearised_errors(seed):
    centers, widths, heights, falls = B.scan(*_linear_errors(seed), n_bumps=6)
    assert 2 <= len(heights) <= 3, (centers, heights, falls)
    for x, y, w, h in TRUE:
        k = int(np.argmin(np.linalg.norm(centers - [x, y], axis=1)))
        assert np.linalg.norm(centers[k] - [x, y]) <= 1.5 * B.STEP, (centers, x, y)
        assert widths[k] == w
        assert abs(heights[k] - h) < 0.25 * abs(h), (heights[k], h)


def test_scan_finds_no_bump_in_noise():
    centers, widths, heights, falls = B.scan(*_linear_errors(2, bumps=()), n_bumps=6)
    assert len(heights) == 0, (centers, heights, falls)


@pytest.fixture(scope="module")
def table():
    model = load_model("conti2026", dtype=jnp.float32)
    ph = collect(load(DATA), model, phases=("table",))
    pb = C.problem(ph, model)
    return model, pb.data["table"], len(ph.table)


def test_slope_jacobian_equals_finite_differences(table):
    model, c, n = table
    jac = np.asarray(B._jacobian(model.replace(name=""), c), np.float64)[:n]
    spec, const = B.tilt_candidate()
    h = 2e-3

    def errors(slope):
        u = ({"slope": jnp.asarray(slope, jnp.float32)[None]},)
        return np.asarray(S.table_errors(model, (spec,), (const,), u, c), np.float64)[:n]

    for axis in range(2):
        step = np.eye(2)[axis] * h
        fd = (errors(step) - errors(-step)) / (2 * h)
        scale = np.abs(fd).max()
        assert scale > 0.5  # a slope moves the bounce
        np.testing.assert_allclose(jac[..., axis], fd, atol=0.02 * scale)
